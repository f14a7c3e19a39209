"""``hybridctl fit``: a spec and the classical controller from a URDF alone."""

import json
import math

import numpy as np
import pytest

from hybridctl.cli import main
from hybridctl.experiments import fit as fit_module
from hybridctl.experiments.fit import FitSettings, fit
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


SMALL = FitSettings(screen_samples=300, gate_samples=500)
"""Fewer starts: the same stages, a test's time."""


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit")
    model = write_model(root / "model")
    result = fit(model, root / "out", progress=False, learner=None, settings=SMALL)
    return model, result


def test_fit_writes_a_spec_whose_goal_is_the_upright(fitted):
    model, result = fitted
    assert result.computed == ["model", "lqr", "integrator", "gate", "reward"]
    system = load(str(result.system_file))
    np.testing.assert_allclose(system.goal, [math.pi, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(system.initial_state.nominal, [0, 0, 0, 0], atol=1e-12)
    assert system.action_limit == 6.0
    assert system.spec.sources["state.goal"].startswith("fit: model stage, highest-potential equilibrium")
    assert system.spec.sources["control.period"].startswith("fit: lqr stage")
    assert "among 6 tried" in system.spec.sources["lqr.Q"]
    assert system.spec.sources["gate.cost_scale"].startswith("fit: gate stage")
    assert system.gate.cost_scale > 0 and system.control_period >= system.dt
    assert system.spec.sources["integrator.dt"].startswith("fit: integrator stage, the cheapest")
    assert abs(round(system.control_period / system.dt) * system.dt - system.control_period) < 1e-12
    integrator = result.stages["integrator"]
    kept = next(t for t in integrator["tried"] if (t["method"], t["dt"]) == (integrator["method"], integrator["dt"]))
    assert kept["max_position_error"] <= SMALL.step_tolerance
    system.lqr()                                    # an equilibrium: Drake's LQR about it solves
    report = json.loads((result.out / "report.json").read_text())
    assert [s["name"] for s in report["stages"]] == ["model", "lqr", "integrator", "gate", "reward"]
    for stage in report["stages"]:
        assert stage["seconds"] >= 0 and "tried" in stage and "kept" in stage and "why" in stage
    assert report["not_yet_built"]


def test_resume_skips_finished_stages(fitted):
    model, result = fitted
    stamps = {n: json.loads((result.out / "stages" / f"{n}.json").read_text())["finished_at"] for n in fit_module.CLASSICAL}
    again = fit(model, result.out, resume=True, progress=False, learner=None, settings=SMALL)
    assert again.computed == []
    assert all(s["cached"] for s in again.report["stages"])
    assert stamps == {n: json.loads((result.out / "stages" / f"{n}.json").read_text())["finished_at"]
                      for n in fit_module.CLASSICAL}
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


@pytest.mark.parametrize("flags, says", [(["--address", "127.0.0.1:6379"], "--address"),
                                         (["--backend", "processes", "--task-cpus", "2"], "--task-cpus"),
                                         (["--device", "nosuch"], "device"),
                                         (["--workers", "999"], "--workers")])
def test_resource_flags_are_checked_before_any_work(tmp_path, capsys, flags, says):
    model = write_model(tmp_path / "m")
    assert says in refused(capsys, model, "--out", tmp_path / "out", *flags)
    assert not (tmp_path / "out").exists()


def test_out_beside_the_model_is_refused(tmp_path, capsys):
    model = write_model(tmp_path / "m")
    refused(capsys, model, "--out", tmp_path / "m")


# ------------------------------------------------------------------ the learned stages, on a tiny budget
TINY_SSAC = {"gate_warm_samples": 500, "gate_warm_fit_steps": 50, "num_envs": 8, "exploration_steps": 200,
             "replay_batch_size": 128, "minibatch_size": 64, "steps_per_update": 200, "updates_per_round": 1,
             "buffer_size": 20000, "needle_buffer_size": 5000, "checkpoint_every": 400, "log_every": 400,
             "tensorboard": False, "gate_refit_every": 400, "gate_refit_steps": 20, "gate_relabel_per_refit": 64}
"""A learner run of a test's size: every stage runs as in a real fit, with no time to learn."""
TINY = FitSettings(screen_samples=300, gate_samples=500, learned_gate_samples=2000, learned_gate_fit_steps=200,
                   learner_max_steps=800, eval_episodes=2, learner_settings=TINY_SSAC, verify_grid=2,
                   verify_duration=1.0, swingup_knots=11, track_samples=16,
                   clone_settings={"rollouts": 16, "steps": 50, "dagger_rounds": 1},
                   clone_start_min=0.0)   # SSAC starts from the tiny clone, whatever it balances: the --init path runs


@pytest.fixture(scope="module")
def fitted_learned(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit-learned")
    model = write_model(root / "model")
    # the Drake maps on the serial backend: where work runs is no cached input (the resumed fits below give none)
    return model, fit(model, root / "out", progress=False, settings=TINY, budget_minutes=30, backend="serial")


def test_every_stage_runs_and_the_fitted_controller_is_a_named_controller(fitted_learned, capsys):
    model, result = fitted_learned
    assert result.computed == list(fit_module.STAGES)
    report = json.loads((result.out / "report.json").read_text())
    assert [s["name"] for s in report["stages"]] == list(fit_module.STAGES)
    system = load(str(result.system_file))
    sources = system.spec.sources
    for key in ("reward.kind", "model.tip_point", "control.swingup_period", "episode.duration", "gate.warm_near"):
        assert sources[key].startswith("fit: "), key
    assert system.spec.values["reward.kind"] == "tip_height"        # link2 rises most; no prismatic joint
    swingup = result.stages["swingup"]
    assert swingup["found"] and 1.0 <= swingup["duration_s"] <= 8.0
    assert abs(round(1.0 / system.swingup_period) * system.swingup_period - 1.0) < 1e-9   # divides the episode
    learner = result.stages["learner"]
    assert learner["steps"] == 800 and (result.out / "learner" / "final" / "model.pt").is_file()
    # the clone's maps were measured before SSAC's first step, then each periodic checkpoint's (TINY_SSAC: every 400)
    assert [(c["checkpoint"], c["steps"]) for c in learner["map_checks"]] == [("clone", 0), ("checkpoint", 400),
                                                                              ("checkpoint", 800)]
    assert not learner["stopped_full"]
    # the tracked swing-up was measured at each decision period and cloned; SSAC started from the clone
    assert swingup["tracked"] and all(0.0 <= f <= 1.0 for f in swingup["tracked"].values())
    clone = result.stages["clone"]
    if swingup["tracking_table"]:
        assert clone["cloned"] and (result.out / "clone" / "model.pt").is_file()
        assert len(clone["rounds"]) == TINY.clone_settings["dagger_rounds"] + 1
        assert clone["fraction"] == max(r["fraction"] for r in clone["rounds"])
        assert clone["starts_ssac"] == (clone["fraction"] >= TINY.clone_start_min)
        assert learner["started_from"] == ("clone" if clone["starts_ssac"] else None)
    else:
        assert not clone["cloned"] and learner["started_from"] is None
    verify = result.stages["verify"]
    assert verify["gate"] in ("learned", "cost-to-go")
    maps = {f"{g}/{m}" for g in ("learned", "cost-to-go") for m in ("rest", "start_range")}
    assert set(verify["torch_maps"]) == maps | ({f"clone/{k}" for k in maps} if clone["cloned"] else set())
    assert verify["checkpoint"] in verify["candidates"] and report["controller"]["checkpoint"] == verify["checkpoint"]
    for name in ("rest", "start_range"):
        drake = verify["drake_maps"][name]
        assert drake["starts"] == 4 and 0 <= drake["balanced"] <= 4
        assert (result.out / drake["plot"]).is_file()
    assert report["controller"]["gate"] == verify["gate"]
    assert (result.out / "replay.html").is_file()
    # fitted:DIR is a controller like any other, on the fitted spec, from Python and from the CLI
    from hybridctl.experiments import build_named_diagram
    build_named_diagram(system, f"fitted:{result.out}")
    assert main(["simulate", str(result.system_file), "--controller", f"fitted:{result.out}", "--duration", "0.5",
                 "--no-html", "--out", str(result.out.parent / "sim")]) == 0


def test_a_resumed_fit_reuses_every_stage_and_the_learner_run(fitted_learned):
    model, result = fitted_learned
    again = fit(model, result.out, resume=True, progress=False, settings=TINY, budget_minutes=30)
    assert again.computed == []
    assert again.report["controller"] == result.report["controller"]


def test_a_learner_killed_mid_run_continues_its_checkpoint(tmp_path, fitted_learned):
    """The learner stage resumes SSAC on the fitted spec file (a robot no shipped name finds)."""
    from hybridctl.experiments.training import train_and_evaluate
    spec = fitted_learned[1].system_file
    run = tmp_path / "learner"
    train_and_evaluate("ssac", str(spec), out=run, settings={**TINY_SSAC, "total_steps": 400}, eval_episodes=1,
                       progress=False, report=None)
    resumed = train_and_evaluate("ssac", str(spec), out=run, settings={**TINY_SSAC, "total_steps": 800},
                                 resume=True, eval_episodes=1, progress=False, report=None)
    assert resumed.evaluation["env_steps"] == 800


def test_fitted_needs_a_verified_fit(tmp_path, fitted):
    from hybridctl.experiments.fit import fitted_controller
    with pytest.raises(ValueError, match="no report.json"):
        fitted_controller(tmp_path)
    _, classical = fitted
    with pytest.raises(ValueError, match="no verified controller"):
        fitted_controller(classical.out)


def test_the_cli_says_when_no_swing_up_was_found(fitted_learned, monkeypatch, capsys):
    """Exit 1 and one error line saying what to try when nothing balances; the report says what each stage
    reached. (The tiny learner's 800 steps rarely swing up; the exit code follows the report either way.)"""
    import functools

    from hybridctl.cli import fit as cli_fit
    model, result = fitted_learned
    monkeypatch.setattr(cli_fit, "fit", functools.partial(fit, settings=TINY))
    code = main(["fit", str(model), "--out", str(result.out), "--resume", "--budget", "30"])
    report = json.loads((result.out / "report.json").read_text())
    assert all(stage["cached"] for stage in report["stages"])
    err = capsys.readouterr().err
    if report["swingup_found"]:
        assert code == 0
    else:
        assert code == 1 and "--resume and a larger --budget" in err.strip().splitlines()[-1]
        assert "Traceback" not in err


def test_the_learner_stops_at_the_budget_and_keeps_its_checkpoint(fitted_learned, tmp_path, monkeypatch):
    """A learner whose step cap lies far beyond the budget stops when the budget (less the verification's
    estimate) is spent, writes final/ and says so; a resumed stage continues from there."""
    import dataclasses
    import time

    from hybridctl.experiments import fit_learn
    _, result = fitted_learned
    system = load(str(result.system_file))
    settings = dataclasses.replace(TINY, learner_max_steps=10 ** 7)
    # no verification time kept (its estimate times two maps, 21 s on a loaded machine): the deadline is the learner's
    monkeypatch.setattr(fit_learn, "_verify_estimate", lambda system, s, resources=None: ({"torch_map_s": 0.0, "drake_map_s": 0.0}, 0.0))
    # the checkpoints' map checks have tests of their own (below); here they would only eat the short deadlines
    monkeypatch.setattr(fit_learn, "checkpoint_maps", lambda system, path, s, resources=None: {"full": False})
    stage = functools_partial_stage(fit_learn.stage_learner, result, settings, system, tmp_path)
    # the callback checks the deadline after every vectorised step, so any deadline stops the run with steps done;
    # a short one keeps the test short
    first = stage(deadline=time.monotonic() + 2)
    assert first["stopped_by_budget"] and 0 < first["steps"] < 10 ** 7
    assert (tmp_path / "learner" / "final" / "model.pt").is_file()
    second = stage(deadline=time.monotonic() + 2)
    assert second["steps_before"] >= first["steps"] and second["steps"] > first["steps"]


def test_the_learner_stops_at_a_checkpoint_whose_maps_balance_every_start(fitted_learned, tmp_path, monkeypatch):
    """With learner_stop_full, each periodic checkpoint's torch maps (verify's two) are measured; the first that
    balances every start ends the run at the next vector step, well inside its budget, and the stage says why."""
    import dataclasses
    import time

    from hybridctl.experiments import fit_learn
    _, result = fitted_learned
    system = load(str(result.system_file))
    measured = []

    def maps(system, path, s, resources=None):
        measured.append(path.name)
        return {"rest": 1.0, "start_range": 1.0, "full": len(measured) >= 2, "seconds": 0.0}
    monkeypatch.setattr(fit_learn, "checkpoint_maps", maps)
    settings = dataclasses.replace(TINY, learner_max_steps=10 ** 7)
    stage = functools_partial_stage(fit_learn.stage_learner, result, settings, system, tmp_path)
    done = stage(deadline=time.monotonic() + 600)
    assert measured == ["checkpoint", "checkpoint"]           # every 400 steps (TINY_SSAC), never the final
    assert done["stopped_full"] and not done["stopped_by_budget"] and done["steps"] == 800 + TINY_SSAC["num_envs"]
    assert [c["steps"] for c in done["map_checks"]] == [400, 800] and "balance every start" in done["why"]


def test_a_clone_whose_maps_balance_every_start_is_kept_without_a_policy_step(fitted_learned, tmp_path, monkeypatch):
    """Started from a clone whose torch maps are full, the learner stops at its first vector step: no policy step
    (actor_delay), so its final actor is the clone's."""
    import shutil
    import time

    import torch

    from hybridctl.experiments import fit_learn
    _, result = fitted_learned
    system = load(str(result.system_file))
    shutil.copytree(result.out / "clone", tmp_path / "clone")
    monkeypatch.setattr(fit_learn, "checkpoint_maps", lambda system, path, s, resources=None: {
        "rest": 1.0, "start_range": 1.0, "full": path.name == "clone", "seconds": 0.0})
    stages = {**result.stages, "clone": {"cloned": True, "starts_ssac": True}}
    done = fit_learn.stage_learner(str(result.out), {"seed": 0}, stages, TINY, False, system=system, folder=tmp_path,
                                   spec_file=result.system_file, deadline=time.monotonic() + 600)
    assert done["stopped_full"] and done["steps"] == TINY_SSAC["num_envs"] and done["started_from"] == "clone"
    assert "no policy step" in done["why"]
    clone, final = (torch.load(tmp_path / d / "model.pt", weights_only=True) for d in ("clone", "learner/final"))
    assert clone["actor"] and all(torch.equal(value, final["actor"][name]) for name, value in clone["actor"].items())


def functools_partial_stage(function, result, settings, system, folder):
    """``function`` (a learned stage) on a fitted folder's records, writing into ``folder``."""
    stages = {**result.stages, "clone": {"cloned": False}}   # a new run in ``folder``, which holds no clone

    def run(deadline):
        return function(str(result.out), {"seed": 0}, stages, settings, False, system=system, folder=folder,
                        spec_file=result.system_file, deadline=deadline)
    return run


def test_a_cart_with_a_long_light_pole_fits_its_classical_stages(tmp_path):
    """A prismatic cart (fit_robots' made-up cart): the goal holds the pole up over the cart at 0, the reward is
    the pole's height minus the cart's distance (tip_height_centered), and the saturated LQR balances."""
    from hybridctl.reproduce.fit_robots import model_file
    model = model_file("cart_long_pole", tmp_path / "models")
    result = fit(model, tmp_path / "out", progress=False, learner=None, settings=SMALL)
    np.testing.assert_allclose(result.stages["model"]["goal"], [0, math.pi, 0, 0], atol=1e-12)
    reward = result.stages["reward"]
    assert reward["kind"] == "tip_height_centered" and reward["tip_body"] == "pole"
    assert reward["rises"]["pole"] == pytest.approx(1.5) and reward["rises"]["cart"] == pytest.approx(0.0)
    assert max(q["balanced"] for q in result.stages["lqr"]["qr"] if "balanced" in q) > 0


@pytest.mark.parametrize("robot", ["cartpole", "double_cartpole"])
def test_a_chain_robots_drake_model_has_the_specs_parameters_and_one_limited_slider(robot, tmp_path):
    """fit_robots' cart-pole models: the SDF template rendered with the spec's parameters, the slider the one
    actuator, its effort limit the spec's action limit (what `hybridctl fit` reads as the robot's)."""
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    from hybridctl.reproduce.fit_robots import model_file
    path = model_file(robot, tmp_path)
    assert path.suffix == ".sdf" and "${" not in path.read_text()
    plant = MultibodyPlant(0.0)
    Parser(plant).AddModels(str(path))
    plant.Finalize()
    actuators = [plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices()]
    assert [a.joint().name() for a in actuators] == ["cart_slider"]
    assert actuators[0].effort_limit() == load(robot).action_limit
    spec = load(robot).chain
    masses = [plant.GetBodyByName(name).default_mass() for name in ("cart", "pole1", "pole2")[:1 + spec.n_links]]
    np.testing.assert_allclose(masses, [spec.cart_mass, *spec.link_mass], rtol=1e-15)


def test_a_robot_named_like_a_shipped_system_loads_its_own_checkpoint(fitted_learned, tmp_path):
    """A user's spec whose name is a shipped system's (fit names a robot by its file: reaction_wheel.urdf):
    its checkpoint's learner is built on the user's spec, not on the shipped one of that name."""
    from hybridctl.experiments.training import train_and_evaluate
    from hybridctl.learn import load_controller
    text = fitted_learned[1].system_file.read_text()
    spec = tmp_path / "spec" / "system.toml"
    spec.parent.mkdir()
    spec.write_text(text.replace('name = "pendubot"', 'name = "acrobot"', 1))
    assert load(str(spec)).name == "acrobot"
    run = tmp_path / "run"
    train_and_evaluate("ssac", str(spec), out=run, settings={**TINY_SSAC, "total_steps": 400}, eval_episodes=1,
                       progress=False, report=None)
    controller = load_controller(run, load(str(spec)))
    assert controller.decision_period == pytest.approx(load(str(spec)).swingup_period)


def test_a_fit_on_other_inputs_sets_the_old_learner_aside(tmp_path):
    """A learner folder made on other earlier stages is not continued (its gamma may differ): it moves to stale/,
    kept; one made on the same inputs is continued (a killed run)."""
    from hybridctl.experiments.fit import _set_aside_stale_run
    out = tmp_path / "fit"
    (out / "stages").mkdir(parents=True)
    (out / "learner").mkdir()
    (out / "learner" / "mine.txt").write_text("kept")
    inputs = {"stage": "learner", "earlier": "a"}
    moved = _set_aside_stale_run(out, "learner", inputs, resume=True)       # no marker: made by another start
    assert moved and (out / moved / "mine.txt").read_text() == "kept" and not (out / "learner").exists()
    (out / "learner").mkdir()
    assert _set_aside_stale_run(out, "learner", inputs, resume=True) is None     # same inputs: continued
    assert (out / "learner").is_dir()
    assert _set_aside_stale_run(out, "learner", {**inputs, "earlier": "b"}, resume=True)   # other inputs
    (out / "learner").mkdir()
    assert _set_aside_stale_run(out, "learner", {**inputs, "earlier": "b"}, resume=False)  # not a resume
    assert len(list((out / "stale").iterdir())) == 3
