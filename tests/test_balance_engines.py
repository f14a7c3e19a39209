"""The fast Drake loop (issue 15) and the two balance-map engines.

The Drake diagram keeps Python out of the continuous hot path (C++ switch, LQR and saturation;
Python only in periodic updates) and must give the runs it gave before; the torch engine runs the
same switched controller for a whole grid as one batch and must reach the same verdicts.
"""

import json

import numpy as np
import pytest
import torch

pytest.importorskip("pydrake")

from pydrake.systems.analysis import Simulator  # noqa: E402
from pydrake.systems.framework import Diagram  # noqa: E402

from hybridctl import drake, systems  # noqa: E402
from hybridctl.drake import HeldLQR, LQRController  # noqa: E402
from hybridctl.experiments import build_named_diagram  # noqa: E402
from hybridctl.experiments.balance_map import (balance_map, compare_engines, divergence_time,  # noqa: E402
                                               torch_rollouts)

SSAC = "ssac:models/policies/ssac-acrobot"
PAPG = "papg:models/policies/papg-cartpole"


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def test_default_diagram_runs_no_python_between_periodic_updates():
    """Every Python block of the diagram is a periodic zero-order hold: no direct feedthrough, no
    continuous state, so Drake never calls Python at a derivative evaluation."""
    system = systems.load("acrobot")
    diagram = build_named_diagram(system, SSAC)
    from pydrake.examples import AcrobotPlant

    from hybridctl.systems.plants import SpecAcrobotPlant

    # Drake's C++ AcrobotPlant, subclassed in Python only for CreateDefaultContext (which C++ never calls)
    assert {name for cls in SpecAcrobotPlant.__mro__[:2] for name in vars(cls) if not name.startswith("__")} \
        == {"CreateDefaultContext"}
    python_blocks = [s for s in diagram.GetSystems() if type(s).__module__.startswith("hybridctl")
                     and not isinstance(s, (Diagram, AcrobotPlant))]
    assert {s.get_name() for s in python_blocks} == {"swingup", "gate"}
    assert all(type(s).__module__.startswith("pydrake") for s in diagram.balance.GetSystems())
    for block in python_blocks:
        assert not block.HasAnyDirectFeedthrough(), block.get_name()
        assert block.CreateDefaultContext().num_continuous_states() == 0
    assert type(diagram.switch).__name__ == "PortSwitch" and isinstance(diagram.balance, HeldLQR)
    legacy = build_named_diagram(system, SSAC, switch="python")
    assert type(legacy.switch).__name__ == "ModeSwitch" and legacy.switch.HasAnyDirectFeedthrough()


@pytest.mark.parametrize("name, controller, duration", [("acrobot", "energy", 12.0), ("acrobot", SSAC, 6.0),
                                                        ("cartpole", PAPG, 4.0)])
def test_drake_switch_equals_the_python_switch(name, controller, duration):
    """The C++ loop (PortSwitch, HeldLQR) gives the run of the pre-issue-15 Python loop (ModeSwitch,
    LQR in a Python HeldController): same modes, states to rounding."""
    system = systems.load(name)
    x0 = system.nudged_nominal_state()
    fast = drake.simulate(build_named_diagram(system, controller), x0, duration)
    slow = drake.simulate(build_named_diagram(system, controller, switch="python"), x0, duration)
    np.testing.assert_array_equal(fast.gate, slow.gate)
    assert 0 < fast.gate.mean() < 1            # both controllers acted
    np.testing.assert_allclose(fast.x, slow.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.u, slow.u, rtol=0, atol=1e-7)


def test_held_lqr_is_the_lqr_law():
    system = systems.load("acrobot")
    K = system.lqr()[0]
    block, law = HeldLQR(system, K, 0.01, limit=system.action_limit), LQRController(system)
    rng = np.random.default_rng(0)
    for x in system.goal + rng.uniform(-1, 1, size=(30, 4)) * [7.0, 7.0, 3.0, 3.0]:
        context = block.CreateDefaultContext()
        block.get_input_port(0).FixValue(context, x)
        Simulator(block, context).AdvanceTo(0.005)      # the hold samples its input at t = 0
        expected = np.clip(law(x), -system.action_limit, system.action_limit)
        np.testing.assert_allclose(block.get_output_port(0).Eval(context), expected, rtol=1e-12, atol=1e-9)
    with pytest.raises(ValueError, match="K must have shape"):
        HeldLQR(system, np.ones((2, 4)), 0.01)


def test_simulate_reuses_its_simulator_without_memory_of_the_last_run():
    system = systems.load("acrobot")
    diagram = build_named_diagram(system, SSAC)
    a, b = system.nudged_nominal_state(), np.array([0.5, -1.0, 0.0, 0.0])
    first = drake.simulate(diagram, a, 4.0)
    drake.simulate(diagram, b, 2.0)
    again = drake.simulate(diagram, a, 4.0)
    fresh = drake.simulate(build_named_diagram(system, SSAC), a, 4.0)
    for run in (again, fresh):
        np.testing.assert_array_equal(run.x, first.x)
        np.testing.assert_array_equal(run.u, first.u)
        np.testing.assert_array_equal(run.gate, first.gate)


def test_learned_gate_numpy_forward_is_its_torch_forward():
    from hybridctl.learn import load_controller

    system = systems.load("acrobot")
    gate = load_controller("models/policies/ssac-acrobot", system).gate.module
    rng = np.random.default_rng(1)
    x = system.goal + rng.uniform(-1, 1, size=(500, 4)) * [4.0, 4.0, 10.0, 20.0]
    with torch.no_grad():
        expected = gate(torch.as_tensor(x, dtype=torch.float32)).numpy()
    # float32 both; the cost-to-go feature sums with cancellation, so the two roundings differ by ~1e-5
    np.testing.assert_allclose(gate.numpy_forward(x), expected, rtol=0, atol=1e-4)
    np.testing.assert_allclose(gate.numpy_forward(x[0]), gate.numpy_forward(x[:1])[0], rtol=0, atol=1e-5)
    with torch.no_grad():
        gate.net[-1].bias.add_(3.0)                 # a refit changes the weights in place
        expected = gate(torch.as_tensor(x, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(gate.numpy_forward(x), expected, rtol=0, atol=1e-4)


# The PAPG policy is float32: Drake evaluates it in numpy on one state, the torch engine in torch on the batch,
# and the two roundings (~1e-6 of the 200 N action) move the cart-pole's states by ~1e-5 within a second.
@pytest.mark.parametrize("name, controller, seconds, tol", [("acrobot", SSAC, 6.0, 1e-6), ("acrobot", "energy", 3.0, 1e-6),
                                                            ("cartpole", PAPG, 4.0, 1e-3)])
def test_torch_rollouts_follow_the_drake_trajectory(name, controller, seconds, tol):
    """The torch engine's states at its decision times equal Drake's while the run is not chaotic."""
    system = systems.load(name)
    x0 = system.nudged_nominal_state()
    runs = torch_rollouts(system, controller, x0[None], duration=10.0)
    traj = drake.simulate(build_named_diagram(system, controller), x0, 10.0)
    stride = int(round((runs["times"][1] - runs["times"][0]) / system.dt))
    upto = int(round(seconds / (stride * system.dt))) + 1
    np.testing.assert_allclose(runs["states"][0, :upto], traj.x[::stride][:upto], rtol=0, atol=tol)
    assert bool(runs["balanced"][0]) == traj.balanced
    assert runs["returns"][0] == pytest.approx(traj.episode_return, abs=1e-3)


@pytest.mark.parametrize("name, controller, grid", [
    ("acrobot", SSAC, 5),
    pytest.param("acrobot", "energy", 5, marks=pytest.mark.slow),
    pytest.param("cartpole", PAPG, 5, marks=pytest.mark.slow),
])
def test_both_engines_agree_on_a_grid(name, controller, grid):
    """Issue 15: the engines agree on >= 99 % of the cells; every disagreement is listed with the
    time at which its two trajectories part."""
    result = compare_engines(name, controller, grid=grid)
    assert result["cells"] == grid * grid
    assert result["drake"].balanced.shape == result["torch"].balanced.shape == (grid, grid)
    assert result["agreement"] >= 0.99, result["disagreements"]
    assert len(result["disagreements"]) == round((1 - result["agreement"]) * grid * grid)
    for row in result["disagreements"]:
        assert row["drake_balanced"] != row["torch_balanced"] and "divergence_time" in row
    assert result["torch"].meta["engine"] == "torch" and result["drake"].meta["engine"] == "drake"


def test_divergence_time_is_the_first_sample_apart():
    times = np.arange(5) * 0.2
    a = np.zeros((5, 2))
    b = a.copy()
    assert divergence_time(times, a, b) is None
    b[3, 1] = 0.1
    assert divergence_time(times, a, b, tol=1e-3) == pytest.approx(0.6)
    b[1, 0] = np.nan
    assert divergence_time(times, a, b) == pytest.approx(0.2)


def test_torch_engine_balance_map_and_bad_engine():
    result = balance_map("pendulum", grid=3, engine="torch", progress=False)
    assert result.balanced.shape == (3, 3) and result.meta["engine"] == "torch"
    with pytest.raises(ValueError, match="engine must be one of"):
        balance_map("pendulum", grid=3, engine="jax")


def test_cli_balance_map_torch_engine(tmp_path):
    from hybridctl.cli import main

    out = tmp_path / "map"
    assert main(["balance-map", "pendulum", "--grid", "3", "--engine", "torch", "--quiet", "--out", str(out)]) == 0
    summary = json.loads((out / "balance_map.json").read_text())
    assert summary["engine"] == "torch" and np.array(summary["balanced"]).shape == (3, 3)


@pytest.mark.parametrize("kind, hidden", [("gru", ()), ("mlp", (8, 8))])
def test_policy_numpy_forward_is_its_torch_forward(kind, hidden):
    """The Drake RecurrentTorchPolicy runs APG policies through numpy_forward: the same numbers in float64."""
    from hybridctl.learn.apg import ClosedLoopPolicy
    from hybridctl.learn.policies import Policy

    system = systems.load("acrobot")
    policy = Policy.build(kind, 6, 1, 25.0, hidden=hidden, dtype=torch.float64, init_std=0.3)
    module = ClosedLoopPolicy(system, policy)
    rng = np.random.default_rng(0)
    x, h = rng.normal(size=(40, 4)) * 3, rng.normal(size=(40, policy.hidden_dim))
    with torch.no_grad():
        u, h_next = module(torch.as_tensor(x), torch.as_tensor(h))
    u_np, h_np = module.numpy_forward(x, h)
    np.testing.assert_allclose(u_np, u.numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(h_np, h_next.numpy(), rtol=1e-12, atol=1e-12)
    with torch.no_grad():
        policy.population.l0_bias.add_(0.5)          # parameters changed in place: the copies follow
        u = module(torch.as_tensor(x), torch.as_tensor(h))[0]
    np.testing.assert_allclose(module.numpy_forward(x, h)[0], u.numpy(), rtol=1e-12, atol=1e-12)


def test_a_saved_map_names_its_axes_with_units_and_titles_no_absolute_path(tmp_path, monkeypatch):
    """The cart-pole map varies the cart position and the pole angle: its axes say so, in m and rad (not "initial
    th1 / th2"); a checkpoint given by absolute path is shown relative to the working folder, unbroken."""
    import matplotlib.pyplot as plt

    from hybridctl.experiments.controllers import display_name
    from hybridctl.viz import plots

    shown = {}
    real = plots.plot_balance_map

    def spy(*args, **kwargs):
        fig = real(*args, **kwargs)
        shown.update(x=fig.axes[0].get_xlabel(), y=fig.axes[0].get_ylabel(), title=fig.axes[0].get_title())
        return fig

    import importlib
    monkeypatch.setattr(importlib.import_module("hybridctl.viz"), "plot_balance_map", spy)
    result = balance_map("cartpole", "lqr", grid=2, engine="torch", progress=False, duration=0.5)
    assert result.axes[0] == "x"
    result.save(tmp_path / "map")
    plt.close("all")
    assert shown["x"] == f"initial {result.axes[0]} [m]" and shown["y"] == f"initial {result.axes[1]} [rad]"
    monkeypatch.chdir(tmp_path)
    checkpoint = tmp_path / "runs" / "ssac-cartpole-with-a-long-name" / "final"
    assert display_name(f"ssac:{checkpoint}") == "ssac:runs/ssac-cartpole-with-a-long-name/final"
    assert display_name("ssac:/elsewhere/policies/ssac-cartpole/final") == "ssac:.../ssac-cartpole/final"
    assert display_name("energy") == "energy" and display_name("ssac:models/x") == "ssac:models/x"


@pytest.mark.xdist_group("ray")
def test_drake_balance_map_is_the_same_on_every_backend(local_ray, tmp_path):
    """Serial, local processes and Ray (the session's local instance): the same map, cell for cell, with a
    checkpoint's controller that each worker rebuilds from its name (the one Drake-engine pool of `make test`:
    the demo and the notebooks map in their own process there)."""
    from pathlib import Path

    from hybridctl.cli import main

    checkpoint = Path(__file__).resolve().parents[1] / "models" / "policies" / "ssac-acrobot"   # any worker's folder
    maps = {backend: balance_map("acrobot", f"ssac:{checkpoint}", grid=3, duration=1.0, backend=backend, workers=2,
                                 progress=False) for backend in ("serial", "processes", "ray")}
    for backend, bmap in maps.items():
        assert bmap.meta["backend"] == backend
        np.testing.assert_array_equal(bmap.balanced, maps["serial"].balanced)
        np.testing.assert_array_equal(bmap.returns, maps["serial"].returns)
    assert maps["serial"].meta["workers"] == 1 and maps["ray"].meta["workers"] == 2
    assert main(["balance-map", "acrobot", "--grid", "2", "--duration", "0.5", "--backend", "ray", "--quiet",
                 "--out", str(tmp_path / "map")]) == 0
    assert json.loads((tmp_path / "map" / "balance_map.json").read_text())["backend"] == "ray"
