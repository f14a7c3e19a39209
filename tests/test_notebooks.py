"""Execute every notebook in ``notebooks/`` headless and check its key outputs.

Notebooks are stored without outputs; this runs each one top to bottom in a fresh
kernel (the ``python3`` kernel, which jupyter_client resolves to the interpreter
running pytest, i.e. the project's venv) with the repository root as working
directory. The executed copy is written to ``runs/notebook/`` for inspection.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))

# Lines each notebook must print (checked on its stream outputs), by file name.
EXPECTED_LINES = {
    "01_hybrid_control.ipynb": [
        "K matches thesis: True",
        "balanced: True",              # the acrobot's swing-up + balance from hanging down
        "cartpole balanced: True",
        "swing-up block: TorchPolicy held for 0.2 s",
    ],
    "02_switched_sac.ipynb": [
        "save/load round trip: True",
        "swing-up block: TorchPolicy held for 0.2 s",
        "balanced: True",              # the pretrained SSAC from hanging down, in Drake
        "engines agree on >= 99 % of cells: True",   # the balance map's Drake and torch engines (issue 15)
        "second build (C++ wrapper, overlapped refits) (results/ch3/fast/):",   # the issue-15 record
        "cart-pole balanced: True",    # the shipped SSAC cart-pole from hanging down, in Drake (issue 16)
    ],
    "04_reachable_mesh_mfpt.ipynb": [
        "finest mesh inside the Monte Carlo 95 % interval: True",   # mesh MFPT vs the true map
        "hopper record: results/ch5/hopper.json",            # the shipped Ch. 5 hopper record is read
        "hopper error record: results/ch5/hopper_error.json",   # the mesh-error decomposition (issue 16)
        "Table 5.1 record: results/ch5/table51.json",         # four training regimes' mesh sizes (issue 16)
        "Ulam record: results/ch5/hopper_ulam.json",          # several samples per box (issue 16)
        "compass gait record: results/ch5/compass_gait/hip_pd.json",   # the compass gait's records are read
        "hip PD walks longer than the passive walker: True",          # by Monte Carlo, 95 % intervals apart
    ],
    "05_analytic_policy_gradients.ipynb": [
        "balanced: True",                 # the shipped PAPG cart-pole swing-up + gate + LQR in Drake
        "torch = Drake to 1e-9: True",    # the switched torch rollout it was trained on
        "Ch. 7 record: results/ch7/table71.json",
        "| learner | acrobot | cart-pole | double cart-pole |",   # the matrix, from results/matrix
        "double cart-pole balanced: True",   # the shipped short-horizon APG double cart-pole swing-up, in Drake
    ],
    "06_fine_tuning.ipynb": [
        "written back as an SB3 zip: True",   # the shipped SB3 PPO, read without unpickling, fine-tuned
        "payload ran while we read and wrote the zip: False",   # a planted pickle is data (issue 29)
        "payload kept in our output: False",
        "SB3's own load of our output ran the payload: False",
        "SB3's own load of the planted input ran the payload: True",   # ... and would have run under SB3
        "balanced: True",                     # the fine-tuned SSAC swing-up in the Drake diagram
        "fine-tuned GRU swing-up balanced: True",   # the fine-tuned CE-APG GRU swing-up (recurrent block) in Drake
        "Ch. 6 record: results/ch6/results.json",
    ],
    "07_your_robot.ipynb": [
        "generated = Drake to 1e-9: True",   # a URDF's generated torch dynamics against Drake's plant (issue 30)
        "balanced: True",                    # Drake's LQR on the MultibodyPlant in the hybrid diagram
        "furuta: swing-up balanced: True",   # the shipped SSAC Furuta swing-up + cost-to-go gate + LQR, in Drake
        "reaction_wheel: swing-up balanced: True",   # the same for the shipped reaction-wheel swing-up
        "gradients finite: True",            # a PAPG run through the generated dynamics
        "fit stages: model, lqr, integrator, gate, reward, swingup, learned_gate, clone, learner, verify",   # hybridctl fit, every stage
        "fitted controller builds a Drake diagram: True",   # fitted:DIR is a named controller
    ],
    "03_trajectory_dimension.ipynb": [
        "same curve: True",            # vectorised box count equals the thesis' dict of tuples
        "MuJoCo record: results/ch4/results.json",   # the shipped Table 4.1 / 4.4 record is read
        "Table 4.4 record: results/ch4/table44.json",   # the grid-searched failure rates (issue 16)
        "Walker2d seeds record: results/ch4/walker_seeds.json",   # the walker seeds for Table 4.4
        "Table 4.4 record: results/ch4/table44-walker2d.json",   # the walker's grid-searched failure rates
    ],
}


def _stream_text(nb) -> str:
    return "".join(out.get("text", "") for cell in nb.cells if cell.cell_type == "code"
                   for out in cell.get("outputs", []) if out.get("output_type") == "stream")


def _mime_types(nb) -> set[str]:
    return {mime for cell in nb.cells if cell.cell_type == "code" for out in cell.get("outputs", [])
            for mime in out.get("data", {})}


def test_notebooks_exist():
    assert NOTEBOOKS, "no notebooks in notebooks/"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_is_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    dirty = [i for i, cell in enumerate(nb.cells)
             if cell.cell_type == "code" and (cell.get("outputs") or cell.get("execution_count") is not None)]
    assert not dirty, f"{path.name}: clear the outputs of cells {dirty} before committing"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs_headless(path, monkeypatch):
    # Never start the paced live-meshcat run under test (the kernel inherits this env).
    monkeypatch.delenv("HYBRIDCTL_LIVE_MESHCAT", raising=False)
    # The notebooks at a test's size: notebook 07's `hybridctl fit` runs every stage small (the full fit is
    # 20 minutes); notebooks 01 and 02 map 3 x 3 in the kernel's process, not 7 x 7 on 2 spawned workers (the
    # test processes already fill the cores, and each worker would first import torch and Drake: about 10 s a
    # notebook; the map is the same on every backend, test_balance_engines runs the pool with a checkpoint);
    # notebook 03's mesh dimension takes 10 acrobot episodes, not 30.
    monkeypatch.setenv("HYBRIDCTL_NOTEBOOK_QUICK", "1")
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(ROOT)}})
    start = time.perf_counter()
    try:
        client.execute()  # raises CellExecutionError on the first failing cell
    finally:
        out_dir = ROOT / "runs" / "notebook"
        out_dir.mkdir(parents=True, exist_ok=True)
        nbformat.write(nb, out_dir / f"{path.stem}.executed.ipynb")
    elapsed = time.perf_counter() - start
    print(f"{path.name}: executed in {elapsed:.1f} s")

    text = _stream_text(nb)
    lines = {line.strip() for line in text.splitlines()}
    for expected in EXPECTED_LINES.get(path.name, []):
        assert expected in lines, f"{path.name} did not print {expected!r}"
    if path.name == "01_hybrid_control.ipynb":
        mimes = _mime_types(nb)
        assert "image/png" in mimes, "no inline figure"
        assert "text/html" in mimes, "no inline meshcat replay"
        # The kernel ran in this interpreter's environment (the venv), not another python.
        prefix = [line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("python_prefix")]
        assert prefix == [sys.prefix], f"kernel ran in {prefix}, expected {sys.prefix}"
        for name in ("run_record.json", "acrobot/summary.json", "acrobot/replay.html", "cartpole/summary.json"):
            assert (ROOT / "runs" / "notebook" / name).is_file(), f"runs/notebook/{name} not written"
