"""``hybridctl mesh``'s Monte Carlo chunks and its extra mesh sizes run on the chosen backend, with the
same numbers as in this process (before: only the main mesh used --backend; Monte Carlo and the sizes
ran serially whatever the flags said)."""

import json

from hybridctl import parallel
from hybridctl.analysis import reachable
from hybridctl.cli import main
from hybridctl.experiments.mesh_report import mesh_report


def test_monte_carlo_and_sizes_use_the_backend_and_give_the_same_numbers(tmp_path, monkeypatch):
    made, used = [], []
    real, real_backend = reachable.make_backend, reachable._backend

    def counting(name, *args, **kwargs):
        made.append(name)
        return real(name, *args, **kwargs)

    def recording(*args):           # the backend each stage runs on
        used.append(real_backend(*args))
        return used[-1]

    settings = dict(box_size=0.05, monte_carlo=60, monte_carlo_chunks=3, sizes=[0.1], progress=False)
    serial = mesh_report("rimless-wheel", tmp_path / "serial", backend="serial", **settings)
    monkeypatch.setattr(reachable, "make_backend", counting)
    monkeypatch.setattr(reachable, "_backend", recording)
    # every mesh round goes out (the wheel's rounds are cheap enough to stay in process)
    monkeypatch.setattr(reachable, "SizedRounds", lambda make, below: parallel.SizedRounds(make, 0.0))
    pooled = mesh_report("rimless-wheel", tmp_path / "pooled", backend="processes", workers=2, **settings)
    # the meshes of the refined slope grid, two Monte Carlo estimates and two meshes of the sizes (0.05 and
    # 0.1): all on one pool, made once for the whole report (its workers start once, not once per stage)
    grids = len(pooled["disturbance"]["refinement"]["counts"])
    assert grids >= 2 and made == ["processes"] and len(used) == grids + 4
    assert len({id(pool) for pool in used}) == 1 and used[0].name == "processes"
    assert used[0]._pool is None                                   # closed at the end of the report
    def numbers(value):    # times left out
        if isinstance(value, dict):
            return {k: numbers(v) for k, v in value.items() if "wall_time" not in k and k != "seconds"}
        return [numbers(v) for v in value] if isinstance(value, list) else value
    for key in ("monte_carlo", "mesh_sizes", "mfpt", "disturbance"):
        assert json.dumps(numbers(pooled[key]), sort_keys=True) == json.dumps(numbers(serial[key]), sort_keys=True), key
    assert pooled["monte_carlo"]["continuous_disturbance"]["episodes"] == 60


def test_monte_carlo_chunks_flag_is_checked(tmp_path, capsys):
    import pytest
    with pytest.raises(SystemExit):
        main(["mesh", "rimless-wheel", "--monte-carlo", "4", "--monte-carlo-chunks", "5", "--out", str(tmp_path)])
    assert "--monte-carlo-chunks must be in [1, --monte-carlo=4], got 5" in capsys.readouterr().err
