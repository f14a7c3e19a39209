"""``hybridctl fit``: a spec and the classical controller from a URDF alone."""

import json
import math

import numpy as np
import pytest

from hybridctl.cli import main
from hybridctl.experiments import fit as fit_module
from hybridctl.experiments.fit import fit
from hybridctl.systems import load

PENDUBOT = """<?xml version="1.0"?>
<!-- A made-up pendubot: the shoulder actuated, 6 N m. -->
<robot name="pendubot">
  <link name="base"/>
  <link name="link1">
    <inertial><origin xyz="0 0 -0.2"/><mass value="0.8"/><inertia ixx="0.02" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="1e-6"/></inertial>
  </link>
  <link name="link2">
    <inertial><origin xyz="0 0 -0.25"/><mass value="0.5"/><inertia ixx="0.015" ixy="0" ixz="0" iyy="0.015" iyz="0" izz="1e-6"/></inertial>
  </link>
  <joint name="base_weld" type="fixed"><parent link="world"/><child link="base"/></joint>
  <joint name="shoulder" type="continuous"><parent link="base"/><child link="link1"/><axis xyz="0 -1 0"/>
    EFFORT</joint>
  <joint name="elbow" type="continuous"><parent link="link1"/><child link="link2"/><origin xyz="0 0 -0.4"/><axis xyz="0 -1 0"/></joint>
  TRANSMISSION
</robot>
"""
LIMIT = '<limit effort="6.0" velocity="100"/>'
TRANSMISSION = ('<transmission type="SimpleTransmission" name="t1"><actuator name="m1"/><joint name="shoulder"/>'
                '<mechanicalReduction>1</mechanicalReduction></transmission>')


def write_model(folder, name="pendubot.urdf", effort=LIMIT, transmission=TRANSMISSION):
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(PENDUBOT.replace("EFFORT", effort).replace("TRANSMISSION", transmission))
    return path


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit")
    model = write_model(root / "model")
    with pytest.MonkeyPatch.context() as mp:     # fewer starts: the same stages, a test's time
        mp.setattr(fit_module, "SCREEN_SAMPLES", 300)
        mp.setattr(fit_module, "GATE_SAMPLES", 500)
        result = fit(model, root / "out", progress=False)
    return model, result


def test_fit_writes_a_spec_whose_goal_is_the_upright(fitted):
    model, result = fitted
    assert result.computed == ["model", "lqr", "gate"]
    system = load(str(result.system_file))
    np.testing.assert_allclose(system.goal, [math.pi, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(system.initial_state.nominal, [0, 0, 0, 0], atol=1e-12)
    assert system.action_limit == 6.0
    assert system.spec.sources["state.goal"].startswith("fit: model stage, highest-potential equilibrium")
    assert system.spec.sources["control.period"].startswith("fit: lqr stage")
    assert "among 6 tried" in system.spec.sources["lqr.Q"]
    assert system.spec.sources["gate.cost_scale"].startswith("fit: gate stage")
    assert system.gate.cost_scale > 0 and system.control_period >= system.dt
    system.lqr()                                    # an equilibrium: Drake's LQR about it solves
    report = json.loads((result.out / "report.json").read_text())
    assert [s["name"] for s in report["stages"]] == ["model", "lqr", "gate"]
    for stage in report["stages"]:
        assert stage["seconds"] >= 0 and "tried" in stage and "kept" in stage and "why" in stage
    assert report["not_yet_built"]


def test_resume_skips_finished_stages(fitted):
    model, result = fitted
    stamps = {n: json.loads((result.out / "stages" / f"{n}.json").read_text())["finished_at"] for n in fit_module.STAGES}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fit_module, "SCREEN_SAMPLES", 300)
        mp.setattr(fit_module, "GATE_SAMPLES", 500)
        again = fit(model, result.out, resume=True, progress=False)
    assert again.computed == []
    assert all(s["cached"] for s in again.report["stages"])
    assert stamps == {n: json.loads((result.out / "stages" / f"{n}.json").read_text())["finished_at"]
                      for n in fit_module.STAGES}
    assert load(str(again.system_file)).spec.values["gate.cost_scale"] == result.system.gate.cost_scale


def refused(capsys, *args) -> str:
    with pytest.raises(SystemExit) as stop:
        main(["fit", *map(str, args)])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]            # after any progress bar: the one error line
    assert last.startswith("error: ")
    return last


def test_no_actuator_is_one_line(tmp_path, capsys):
    model = write_model(tmp_path / "m", transmission="")
    assert "no actuators" in refused(capsys, model, "--out", tmp_path / "out")


def test_no_effort_limit_asks_for_action_limit(tmp_path, capsys):
    model = write_model(tmp_path / "m", effort="")
    err = refused(capsys, model, "--out", tmp_path / "out")
    assert "--action-limit" in err
    report = json.loads((tmp_path / "out" / "report.json").read_text())     # what it had is kept
    assert report["stages"][0]["name"] == "model" and "--action-limit" in report["stages"][0]["error"]


def test_goal_that_is_no_equilibrium_is_one_line(tmp_path, capsys):
    model = write_model(tmp_path / "m")
    err = refused(capsys, model, "--out", tmp_path / "out", "--goal=1.0,0,0,0")
    assert "not an equilibrium" in err
    assert (tmp_path / "out" / "report.json").is_file()


def test_out_beside_the_model_is_refused(tmp_path, capsys):
    model = write_model(tmp_path / "m")
    refused(capsys, model, "--out", tmp_path / "m")
