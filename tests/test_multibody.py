"""The multibody family: torch dynamics generated from Drake's symbolic plant (issue 30).

The generated code is checked against Drake's own MultibodyPlant (``CalcTimeDerivatives``) and
against the hand-folded chain family on the same robots; bad models get one clear error."""

from __future__ import annotations

import base64
import json
import re
import textwrap

import numpy as np
import pytest
import torch

from hybridctl import systems
from hybridctl.systems import ModelError, SpecError, multibody, symbolic
from hybridctl.systems.plants import render_model

DRAKE_MODELS = ["package://drake/examples/acrobot/Acrobot.urdf",
                "package://drake/examples/multibody/cart_pole/cart_pole.sdf"]
MULTIBODY_SPECS = [name for name in systems.known_systems() if systems.spec.read_spec(name).get("model.family")
                   == "multibody"]


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch):
    """Each test session's generated models go to a cache of its own, never the user's."""
    monkeypatch.setenv(symbolic.CACHE_ENV, str(tmp_path_factory.getbasetemp() / "cache"))


def _drake_reference(system, X, U):
    plant = system.drake_plant()
    context = system.drake_context(plant)
    return np.stack([system.drake_derivatives(plant, context, x, u) for x, u in zip(X, U)])


def _random(system, rng, n=1000):
    X = rng.uniform(-2 * np.pi, 2 * np.pi, size=(n, system.n_states))
    U = rng.uniform(-1, 1, size=(n, system.n_actions)) * min(system.action_limit, 50.0)
    return X, U


def _from_drake_file(source, n_states, n_actions=1, **kwargs):
    kwargs.setdefault("action_limit", 10.0)     # Drake's acrobot and cart-pole set no effort limit
    return systems.from_drake(source, goal=np.zeros(n_states), Q=np.eye(n_states), R=np.eye(n_actions), **kwargs)


@pytest.mark.parametrize("source", DRAKE_MODELS)
def test_generated_dynamics_equal_drakes_plant(source, rng):
    system = _from_drake_file(source, 4)
    X, U = _random(system, rng)
    ours = system.derivatives(torch.tensor(X), torch.tensor(U)).numpy()
    np.testing.assert_allclose(ours, _drake_reference(system, X, U), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", MULTIBODY_SPECS)
def test_shipped_multibody_systems_equal_drakes_plant(name, rng):
    system = systems.load(name)
    X, U = _random(system, rng)
    ours = system.derivatives(torch.tensor(X), torch.tensor(U)).numpy()
    np.testing.assert_allclose(ours, _drake_reference(system, X, U), rtol=1e-9, atol=1e-9)


def test_the_acrobot_urdf_equals_the_chain_family(rng):
    chain = systems.load("acrobot")
    model = systems.from_drake("acrobot.urdf", goal=[np.pi, 0, 0, 0], Q=chain.Q, R=chain.R, gravity=9.8)
    X, U = _random(chain, rng)
    offset = chain.drake_state_offset()                     # th1 from the horizontal vs from hanging down
    expected = chain.derivatives(torch.tensor(X), torch.tensor(U))
    got = model.derivatives(torch.tensor(X + offset), torch.tensor(U))
    np.testing.assert_allclose(got.numpy(), expected.numpy(), rtol=1e-9, atol=1e-9)
    K_chain, S_chain = chain.lqr()
    K_model, S_model = model.lqr()                          # Drake's LQR on the MultibodyPlant
    np.testing.assert_allclose(K_model, K_chain, rtol=1e-9)
    np.testing.assert_allclose(K_model.ravel(), [-1649.87, -460.16, -716.07, -278.15], atol=0.006)  # thesis
    np.testing.assert_allclose(model.energy(X + offset), chain.energy(X), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ["cartpole", "double_cartpole"])
def test_cart_models_equal_the_chain_family(name, rng, tmp_path):
    chain = systems.load(name)
    sdf = tmp_path / f"{name}.sdf"
    sdf.write_text(render_model(chain))                     # the chain spec's parameters in Drake's format
    n = chain.n_states
    model = systems.from_drake(str(sdf), goal=chain.goal, Q=chain.Q, R=chain.R, gravity=float(chain.params["gravity"]),
                               action_limit=chain.action_limit)
    assert model.model.n_q == n // 2 and model.angle_indices == chain.angle_indices
    X, U = _random(chain, rng)
    expected = chain.derivatives(torch.tensor(X), torch.tensor(U)).numpy()
    got = model.derivatives(torch.tensor(X), torch.tensor(U)).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)


def test_steps_float32_columns_floats_and_gradients(rng):
    system = systems.from_drake("acrobot.urdf", goal=[np.pi, 0, 0, 0], Q=np.eye(4), R=np.eye(1), gravity=9.8,
                                integrator__method="runge_kutta2")
    X, U = _random(system, rng, 64)
    x, u = torch.tensor(X), torch.tensor(U)
    step = system.step(x, u)
    # the plain-float path of one state, and column-major batches, give the same step
    for i in range(3):
        np.testing.assert_allclose(system.step_single(X[i], U[i]), step[i].numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(system.step_columns(x.T.contiguous(), u.T.contiguous()).T.numpy(), step.numpy())
    # float32 on the input's dtype
    step32 = system.step(x.float(), u.float())
    assert step32.dtype == torch.float32
    np.testing.assert_allclose(step32.numpy(), step.numpy(), rtol=1e-4, atol=1e-3)
    # differentiable: autograd equals central differences
    x0 = x[:4].clone().requires_grad_(True)
    system.step(x0, u[:4]).sum().backward()
    eps = 1e-6
    numeric = np.zeros((4, 4))
    for k in range(4):
        d = torch.zeros_like(x[:4])
        d[:, k] = eps
        numeric[:, k] = ((system.step(x[:4] + d, u[:4]) - system.step(x[:4] - d, u[:4])).sum(-1) / (2 * eps)).numpy()
    np.testing.assert_allclose(x0.grad.numpy(), numeric, rtol=1e-6, atol=1e-6)


def test_a_generated_model_is_cached_and_a_damaged_cache_is_derived_anew(tmp_path, monkeypatch):
    monkeypatch.setenv(symbolic.CACHE_ENV, str(tmp_path / "cache"))
    first = _from_drake_file(DRAKE_MODELS[1], 4)
    assert first.model.info["cached"] is False and first.model.info["generation_seconds"] > 0
    second = _from_drake_file(DRAKE_MODELS[1], 4)
    assert second.model.info["cached"] is True and second.model == first.model
    cache = tmp_path / "cache" / "multibody" / f"{first.model.info['key']}.json"
    doc = json.loads(cache.read_text())
    doc["mass"][0] = [[1.0, ["__import__('os').system('x')"]]]  # not numbers: data that fails its check
    cache.write_text(json.dumps(doc))
    with pytest.warns(UserWarning, match=r"model cache .*: the entry is damaged: a term of 'mass' must be .*; derived"):
        third = _from_drake_file(DRAKE_MODELS[1], 4)
    assert third.model.info["cached"] is False and third.model == first.model
    assert json.loads(cache.read_text())["mass"] == first.model.to_json()["mass"]    # replaced
    with pytest.raises(ModelError, match="is damaged: a term of 'mass' must be"):
        multibody.MultibodyModel.from_json(doc, where="x.json")


def test_a_changed_model_file_is_a_new_cache_entry(tmp_path):
    path = tmp_path / "pendulum.urdf"
    path.write_text(_pendulum_urdf(mass=1.0))
    light = _from_drake_file(str(path), 2)
    path.write_text(_pendulum_urdf(mass=2.0))
    heavy = _from_drake_file(str(path), 2)
    assert light.model.info["key"] != heavy.model.info["key"]
    x, u = torch.tensor([[0.5, 0.0]]), torch.tensor([[1.0]])
    assert not torch.equal(light.derivatives(x, u), heavy.derivatives(x, u))


def test_from_drake_fills_names_angles_limits_and_sources():
    system = systems.from_drake("package://drake/examples/acrobot/Acrobot.urdf", goal=[np.pi, 0, 0, 0],
                                Q=np.eye(4), R=np.eye(1), action_limit=10.0)
    assert system.state_names == ["shoulder", "elbow", "shoulder_dot", "elbow_dot"]
    assert system.action_names == ["elbow"] and system.angle_indices == [0, 1] and system.action_limit == 10.0
    assert system.spec.sources["state.names"].startswith("model file")
    assert system.spec.sources["integrator.dt"] == "hybridctl.systems.from_drake default"
    assert system.spec.sources["state.goal"] == "from_drake argument"
    assert system.family == "multibody" and system.chain is None
    # Drake's acrobot is damped (0.1 N m s/rad at each joint): the model file is the physics
    assert system.model.damping == (0.1, 0.1)


# ------------------------------------------------------------------------------------------ bad models
def _pendulum_urdf(mass=1.0, joint="continuous", weld=True, transmission=True, extra=""):
    return textwrap.dedent(f"""\
        <?xml version="1.0"?>
        <robot name="pendulum">
          <link name="base"/>
          <link name="arm">
            <inertial><origin xyz="0 0 -0.5"/><mass value="{mass}"/>
              <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
          </link>
          {'<joint name="weld" type="fixed"><parent link="world"/><child link="base"/></joint>' if weld else ''}
          <joint name="pivot" type="{joint}"><parent link="base"/><child link="arm"/><axis xyz="0 1 0"/>
            <limit effort="5" lower="-10" upper="10" velocity="100"/></joint>
          {'<transmission type="SimpleTransmission" name="t"><actuator name="m"/><joint name="pivot"/></transmission>'
           if transmission else ''}
          {extra}
        </robot>
        """)


BAD_MODELS = [
    # (case, urdf text or None for a special file, message)
    ("floating base", _pendulum_urdf(weld=False), "has a floating base or a quaternion joint .* weld the root link"),
    ("ball joint", _pendulum_urdf(extra='<link name="bob"><inertial><mass value="1"/><inertia ixx="0.01" ixy="0" '
                                        'ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link><drake:joint '
                                        'name="wrist" type="ball"><parent link="arm"/><child link="bob"/></drake:joint>'),
     "joint 'wrist' is of type 'ball_rpy'; the generated dynamics support revolute, prismatic, weld joints"),
    ("no actuators", _pendulum_urdf(transmission=False), "has no actuators; add a <transmission>"),
    ("broken XML", "<robot name='x'><link name='a'>", "does not parse: .*"),
]


@pytest.mark.parametrize("case, text, message", BAD_MODELS, ids=[c[0] for c in BAD_MODELS])
def test_a_bad_model_is_one_clear_error_naming_the_file(case, text, message, tmp_path):
    path = tmp_path / "robot.urdf"
    path.write_text(text)
    with pytest.raises(ModelError, match=message) as raised:
        _from_drake_file(str(path), 2)
    assert str(path) in str(raised.value) and "\n" not in str(raised.value)


def test_bad_references_are_named(tmp_path):
    with pytest.raises(SpecError, match="model.file.* no such file"):
        _from_drake_file(str(tmp_path / "missing.urdf"), 2)
    with pytest.raises(SpecError, match="only package://drake/ URLs"):
        _from_drake_file("package://drake_models/iiwa_description/urdf/iiwa14.urdf", 14)
    path = tmp_path / "robot.urdf"
    path.write_text(_pendulum_urdf())
    with pytest.raises(ModelError, match="actuated_joints names 'elbow', which has no actuator; joints with one: pivot"):
        _from_drake_file(str(path), 2, actuated_joints=["elbow"])
    with pytest.raises(ModelError, match="model.tip_body 'hand' is not a body of the model; its bodies: arm, base"):
        _from_drake_file(str(path), 2, tip_body="hand")
    with pytest.raises(SpecError, match="state.goal.* must be 2 finite numbers"):
        systems.from_drake(str(path), goal=[0.0, 0.0, 0.0, 0.0], Q=np.eye(4), R=np.eye(1))


def test_a_goal_that_is_no_equilibrium_and_a_model_too_large_are_refused(tmp_path, monkeypatch):
    path = tmp_path / "robot.urdf"
    path.write_text(_pendulum_urdf())
    tilted = systems.from_drake(str(path), goal=[0.5, 0.0], Q=np.eye(2), R=np.eye(1))
    with pytest.raises(ValueError, match=r"the goal \[0.5, 0.0\] is not an equilibrium with u = 0, nor near") as error:
        tilted.lqr()
    assert "\n" not in str(error.value)
    monkeypatch.setattr(symbolic, "MAX_TERMS", 3)
    with pytest.raises(ModelError, match="more than 3 terms .* too large to generate code for"):
        symbolic.derive(symbolic.ModelRequest(str(path)))
    monkeypatch.setattr(symbolic, "MAX_EXPRESSION_CHARS", 10)
    with pytest.raises(ModelError, match=r"symbolic equations have [\d,]+ characters, above the limit of 10"):
        symbolic.derive(symbolic.ModelRequest(str(path)))


def test_a_multibody_spec_refuses_chain_keys_and_chain_rewards(tmp_path):
    urdf = tmp_path / "robot.urdf"
    urdf.write_text(_pendulum_urdf())
    with pytest.raises(SpecError, match="params.link_mass' is not used by the multibody family"):
        _from_drake_file(str(urdf), 2, **{"params": None}) if False else systems.spec.spec_from_document(
            {"system": {"name": "x"}, "model": {"family": "multibody", "file": str(urdf)},
             "params": {"link_mass": [1.0]}}, urdf)
    with pytest.raises(SpecError, match="reward.kind.* must be one of .* for a multibody system"):
        _from_drake_file(str(urdf), 2, reward__kind="upright_centered")
    with pytest.raises(SpecError, match="'tip_height' needs a tip point"):
        _from_drake_file(str(urdf), 2, reward__kind="tip_height")
    tipped = _from_drake_file(str(urdf), 2, reward__kind="tip_height", tip_body="arm", tip_point=[0, 0, -1])
    np.testing.assert_allclose(tipped.reward(np.array([[0.0, 0.0], [np.pi, 0.0]])), [-1.0, 1.0], atol=1e-12)


# ------------------------------------------------------------------------------------ the user's paths
@pytest.mark.parametrize("name", MULTIBODY_SPECS)
def test_shipped_multibody_specs_balance_in_drake_with_their_own_geometry(name, tmp_path):
    """Drake's LQR on the MultibodyPlant, in the hybrid diagram with the plant's SceneGraph (the replay
    records the model's own geometry), balances from 0.05 rad off the goal."""
    from hybridctl.experiments.simulation import simulate_and_write

    system = systems.load(name)
    assert system.family == "multibody" and system.spec.sources["lqr.Q"]
    x0 = system.goal.copy()
    x0[system.angle_indices[0]] += 0.05
    summary = simulate_and_write(system, "lqr", out=tmp_path / "run", x0=x0)   # the spec's episode
    assert summary["balanced"] is True, summary
    html = (tmp_path / "run" / "replay.html").read_text()
    umsgpack = pytest.importorskip("umsgpack")
    blobs = re.findall(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", html)
    scene = repr([umsgpack.unpackb(base64.b64decode(blob)) for blob in blobs])
    for body in system.model.bodies:        # the model's links are in the recorded scene
        assert f"/{body}" in scene


def test_the_acrobot_urdf_swings_up_like_the_chain_acrobot_on_both_engines():
    """The energy swing-up + LQR on the Drake-model acrobot balances from the same starts as on the chain
    acrobot (its Drake coordinates are shifted by pi/2), in Drake and in batched torch."""
    from hybridctl.experiments.balance_map import balance_map

    maps = {}
    for name in ("acrobot", "acrobot_urdf"):
        for engine in ("torch", "drake"):
            maps[name, engine] = balance_map(name, "energy", grid=3, duration=10.0, engine=engine, progress=False,
                                             workers=1)
    verdicts = {key: np.asarray(m.balanced).tolist() for key, m in maps.items()}
    assert verdicts["acrobot_urdf", "torch"] == verdicts["acrobot", "torch"] == verdicts["acrobot_urdf", "drake"]
    assert any(v for row in verdicts["acrobot", "torch"] for v in np.ravel(row))


@pytest.mark.parametrize("name", MULTIBODY_SPECS)
def test_gymnasium_and_torch_envs_run_a_multibody_system(name):
    from hybridctl.envs import SwingupEnv, TorchVectorEnv

    env = SwingupEnv(name, render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    obs, reward, *_ = env.step(env.action_space.sample())
    assert np.all(np.isfinite(obs)) and np.isfinite(reward)
    frame = env.render()
    assert frame.shape == (256, 256, 3) and (frame != 255).any()     # the bodies are drawn
    venv = TorchVectorEnv(name, num_envs=4, seed=0)
    obs, _ = venv.reset()
    out = venv.step(torch.zeros(4, venv.system.n_actions, dtype=obs.dtype))
    assert torch.isfinite(out[0]).all()


def test_a_checkpoint_refuses_a_changed_model_file_unless_forced(tmp_path, monkeypatch):
    """config.json records the model file's sha256 with the spec values: a changed URDF is another plant."""
    from hybridctl.learn import SAC
    from hybridctl.learn.checkpoint import CheckpointError

    folder = tmp_path / "specs"
    folder.mkdir()
    (folder / "pendulum.urdf").write_text(_pendulum_urdf(mass=1.0))
    spec = (systems.spec.SPEC_DIR / "furuta.toml").read_text()
    spec = spec.replace('name = "furuta"', 'name = "my_pendulum"').replace('"furuta.urdf"', '"pendulum.urdf"')
    spec = spec.replace('actuated_joints = ["arm_joint"]', 'actuated_joints = ["pivot"]')
    spec = re.sub(r'tip_body = .*\ntip_point = .*\n', '', spec)
    for key, value in (("goal", '["pi", 0.0]'), ("nominal", "[0.0, 0.0]"), ("low", "[-0.1, 0.0]"),
                       ("high", "[0.1, 0.0]"), ("warm_near", "[0.5, 5.0]"), ("warm_far", '["pi", 10.0]')):
        spec = re.sub(rf"^{key}\s*= \{{ value = \[[^\]]*\]", f"{key} = {{ value = {value}", spec, flags=re.M)
    spec = re.sub(r"^Q = .*$", 'Q = { value = [[10, 0], [0, 1]], source = "test" }', spec, flags=re.M)
    (folder / "my_pendulum.toml").write_text(spec)
    monkeypatch.setenv("HYBRIDCTL_SYSTEMS", str(folder))
    agent = SAC("my_pendulum", num_envs=2, exploration_steps=100, hidden_size=8, seed=0)
    agent.learn(total=100, progress=False, out=tmp_path / "run")
    SAC.load(tmp_path / "run" / "final")                    # the same model: loads
    (folder / "pendulum.urdf").write_text(_pendulum_urdf(mass=2.0))
    with pytest.raises(CheckpointError, match="trained on my_pendulum with model.file_sha256="):
        SAC.load(tmp_path / "run" / "final")
    with pytest.warns(UserWarning, match="force: loading anyway.*model.file_sha256"):
        SAC.load(tmp_path / "run" / "final", force=True)


def test_overriding_the_physics_warns_which_tuned_values_were_kept(recwarn):
    with pytest.warns(UserWarning, match=r"acrobot: override link_mass=\[2, 1\] changes the physics, but the values "
                                         r"tuned for acrobot.toml were kept and may no longer fit: control.period=0.01, "
                                         r"gate.cost_scale=2500.0, swingup.k_energy=5.0, swingup.k_p=50.0, swingup.k_d=5.0"):
        systems.load("acrobot", link_mass=[2, 1])
    recwarn.clear()
    systems.load("acrobot", link_mass=[2, 1], control__period=0.02, gate__cost_scale=100.0, k_energy=1.0, k_p=1.0,
                 k_d=1.0)                                   # every tuned value retuned with it: nothing to say
    systems.load("acrobot", dt=0.005)                       # not the physics
    assert not [w for w in recwarn if "changes the physics" in str(w.message)]
    with pytest.warns(UserWarning, match=r"furuta: override gravity=3.7 changes the physics.*gate.cost_scale=113.4"):
        systems.load("furuta", gravity=3.7)


def test_an_optional_key_a_spec_leaves_out_can_be_overridden():
    """The Ch. 7 reward settings are optional (default 0): a spec without them takes them as overrides, as
    the APG learners set them (furuta.toml has no reward.alive_bonus)."""
    assert not systems.spec.read_spec("furuta").has("reward.alive_bonus")
    system = systems.load("furuta", reward__alive_bonus=10.0, velocity_penalty=0.01)
    assert system.reward_alive_bonus == 10.0 and system.reward_velocity_penalty == 0.01
    with pytest.raises(SpecError, match="override 'alive_bonuss' is not a key of this spec"):
        systems.load("furuta", alive_bonuss=1.0)


def test_the_command_line_trains_fine_tunes_and_simulates_a_multibody_system_by_name(tmp_path, capsys):
    """SSAC (learned swing-up + gate), PAPG and CE-APG with the LQR takeover, ARS, fine-tuning (of SSAC and ARS),
    simulate and both balance-map engines, by system name:
    tiny budgets, only that every path runs on generated dynamics and writes what it says."""
    from hybridctl.cli import main

    ssac = tmp_path / "ssac"
    assert main(["train", "ssac", "reaction_wheel", "--steps", "600", "--num-envs", "4", "--exploration-steps", "400",
                 "--minibatch-size", "32", "--buffer-size", "2000", "--gate-warm-samples", "200",
                 "--gate-warm-fit-steps", "10", "--eval-episodes", "2", "--out", str(ssac), "--quiet"]) == 0
    assert (ssac / "final" / "model.pt").is_file()
    papg = tmp_path / "papg"
    assert main(["train", "papg", "furuta", "--takeover", "lqr", "--policy", "mlp:8", "--population", "2",
                 "--elites", "1", "--batch", "2", "--horizon", "10", "--apg-iterations", "2", "--epochs", "1",
                 "--eval-episodes", "2", "--out", str(papg), "--quiet"]) == 0
    ceapg = tmp_path / "ce-apg"
    assert main(["train", "ce-apg", "reaction_wheel", "--takeover", "lqr", "--policy", "mlp:8", "--population", "2",
                 "--elites", "1", "--batch", "2", "--horizon", "10", "--apg-iterations", "1", "--epochs", "1",
                 "--eval-episodes", "2", "--out", str(ceapg), "--quiet"]) == 0
    ars = tmp_path / "ars"
    assert main(["train", "ars", "furuta", "--epochs", "1", "--n-directions", "2", "--top-directions", "1",
                 "--episode-steps", "20", "--transient-steps", "2", "--backend", "serial", "--eval-episodes", "1",
                 "--out", str(ars), "--quiet"]) == 0
    assert main(["finetune", "reaction_wheel", "--policy", f"ssac:{ssac / 'final'}", "--updates", "1",
                 "--directions", "2", "--eval-episodes", "2", "--out", str(tmp_path / "ft")]) == 0
    # the SSAC fine-tuning above starts worker processes (a generated system rebuilt in a worker); this one
    # runs in the test's process, which is all it needs to show and 4-5 s cheaper
    assert main(["finetune", "furuta", "--policy", f"ars:{ars / 'final'}", "--updates", "1", "--directions", "2",
                 "--eval-episodes", "2", "--backend", "serial", "--out", str(tmp_path / "ft-ars")]) == 0
    for name, policy in (("reaction_wheel", f"ssac:{ssac / 'final'}"), ("furuta", f"papg:{papg / 'final'}"),
                         ("reaction_wheel", f"ce-apg:{ceapg / 'final'}")):
        out = tmp_path / f"sim-{name}-{policy.partition(':')[0]}"
        assert main(["simulate", name, "--controller", policy, "--duration", "0.5", "--out", str(out)]) == 0
        assert (out / "replay.html").is_file()
    for engine in ("drake", "torch"):
        out = tmp_path / f"map-{engine}"
        assert main(["balance-map", "reaction_wheel", "--controller", f"ssac-costgate:{ssac / 'final'}", "--grid", "2",
                     "--duration", "0.5", "--engine", engine, "--workers", "1", "--out", str(out)]) == 0
        assert len(json.loads((out / "balance_map.json").read_text())["balanced"]) == 2
    capsys.readouterr()


def test_the_shipped_reaction_wheel_swing_up_balances_from_hanging_down_in_drake(tmp_path):
    """models/policies/ssac-reaction-wheel: the learned swing-up + the spec's cost-to-go gate + Drake's LQR
    (issue 30 item 4), loaded by system name, from hanging down (nudged), in the Drake diagram."""
    from hybridctl.experiments.simulation import simulate_and_write

    system = systems.load("reaction_wheel")
    summary = simulate_and_write(system, "ssac-costgate:models/policies/ssac-reaction-wheel", out=tmp_path / "run",
                                 html=False)
    assert summary["balanced"] is True and 0.5 < summary["first_balance_time"] < 4.5, summary


def test_the_shipped_furuta_swing_up_balances_from_hanging_down_in_drake(tmp_path):
    """models/policies/ssac-furuta: trained beside another gate scale and with 5 s episodes (both recorded as
    spec overrides), it loads by name as ``ssac-costgate:`` (only a learned gate reads the gate section) and,
    with the spec's cost-to-go gate and Drake's LQR, balances from hanging down within the spec's 10 s."""
    from hybridctl.experiments.simulation import simulate_and_write
    from hybridctl.learn import CheckpointError

    system = systems.load("furuta")
    shipped = "models/policies/ssac-furuta"
    summary = simulate_and_write(system, f"ssac-costgate:{shipped}", out=tmp_path / "run", html=False)
    assert summary["balanced"] is True and 1.0 < summary["first_balance_time"] < 6.0, summary
    with pytest.raises(CheckpointError, match="gate.cost_scale"):   # its own learned gate reads the scale
        simulate_and_write(system, f"ssac:{shipped}", out=tmp_path / "learned-gate", html=False)


def test_a_robot_from_its_file_pickles_and_refuses_a_changed_file(rng, tmp_path):
    import pickle
    chain = systems.load("cartpole")
    sdf = tmp_path / "cartpole.sdf"
    sdf.write_text(render_model(chain))
    model = systems.from_drake(str(sdf), goal=chain.goal, Q=chain.Q, R=chain.R, gravity=9.81,
                               action_limit=chain.action_limit)
    data = pickle.dumps(model)
    X, U = _random(model, rng)
    again = pickle.loads(data)
    np.testing.assert_array_equal(again.derivatives(torch.tensor(X), torch.tensor(U)).numpy(),
                                  model.derivatives(torch.tensor(X), torch.tensor(U)).numpy())
    with pytest.warns(UserWarning, match="changes the physics"):
        heavier = systems.load("cartpole", cart_mass=2.0)
    sdf.write_text(render_model(heavier))                   # another plant in the same file
    with pytest.raises(ValueError, match="changed since the system was pickled"):
        pickle.loads(data)


# ------------------------------------------------------------------ issue 47: no cache changes the physics
def _pendubot_urdf(effort=2.5):
    """Drake's acrobot with the motor at the shoulder (a pendubot) and an effort limit."""
    inertial = ('<inertial><origin xyz="0 0 -{c}"/><mass value="{m}"/>'
                '<inertia ixx="{i}" ixy="0" ixz="0" iyy="{i}" iyz="0" izz="0.01"/></inertial>')
    return textwrap.dedent(f"""\
        <?xml version="1.0"?>
        <robot name="pendubot">
          <link name="base"/>
          <link name="upper_link">{inertial.format(c=0.5, m=1.0, i=0.083)}</link>
          <link name="lower_link">{inertial.format(c=1.0, m=1.0, i=0.33)}</link>
          <joint name="weld" type="fixed"><parent link="world"/><child link="base"/></joint>
          <joint name="shoulder" type="continuous"><parent link="base"/><child link="upper_link"/>
            <axis xyz="0 1 0"/><limit effort="{effort}" velocity="100"/><dynamics damping="0.1"/></joint>
          <joint name="elbow" type="continuous"><parent link="upper_link"/><child link="lower_link"/>
            <origin xyz="0 0 -1"/><axis xyz="0 1 0"/><dynamics damping="0.1"/></joint>
          <transmission type="SimpleTransmission" name="t"><actuator name="m"/><joint name="shoulder"/></transmission>
        </robot>
        """)


def _pendubot(tmp_path, effort=2.5, **kwargs):
    path = tmp_path / "pendubot.urdf"
    if not path.is_file():
        path.write_text(_pendubot_urdf(effort))
    kwargs.setdefault("action_limit", 10.0)                 # four times the effort limit
    return systems.from_drake(str(path), goal=[np.pi, 0, 0, 0], Q=np.eye(4), R=np.eye(1), **kwargs)


def _beyond_the_limits(system, rng, n=200):
    """Random states, and inputs up to 4x the largest of the action and effort limits (inputs that Drake clamps)."""
    efforts = [e for e in system.model.info["effort_limits"] if e is not None]
    scale = 4.0 * max([system.action_limit, *efforts])
    X = rng.uniform(-2 * np.pi, 2 * np.pi, size=(n, system.n_states))
    X[:, system.n_states // 2:] = rng.uniform(-5, 5, size=(n, system.n_states // 2))
    U = rng.uniform(-scale, scale, size=(n, system.n_actions))
    U[:4] = np.array([1, -1, 4, -4])[:, None] * scale / 4   # at the limit and far beyond it
    return X, U


def _drake_step(system, plant, context, x, u):
    """One step of the spec's integrator on Drake's plant (its derivatives, the input held)."""
    k1 = system.drake_derivatives(plant, context, x, u)
    if system.integrator == "euler":
        return x + system.dt * k1
    k2 = system.drake_derivatives(plant, context, x + system.dt * k1, u)
    return x + 0.5 * system.dt * (k1 + k2)


def _assert_every_step_path_equals_drake(system, rng):
    X, U = _beyond_the_limits(system, rng)
    plant = system.drake_plant()
    context = system.drake_context(plant)
    derivatives = np.stack([system.drake_derivatives(plant, context, x, u) for x, u in zip(X, U)])
    steps = np.stack([_drake_step(system, plant, context, x, u) for x, u in zip(X, U)])
    x, u = torch.tensor(X), torch.tensor(U)
    np.testing.assert_allclose(system.derivatives(x, u).numpy(), derivatives, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(system.step(x, u).numpy(), steps, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(system.step(x.float(), u.float()).numpy(), steps, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(system.step_columns(x.T.contiguous(), u.T.contiguous()).T.numpy(), steps,
                               rtol=1e-9, atol=1e-9)
    for i in range(8):                                      # one float64 state: the plain-float path
        np.testing.assert_allclose(system.step(x[i], u[i]).numpy(), steps[i], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(system.step_single(X[i], U[i]), steps[i], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", MULTIBODY_SPECS)
def test_every_step_path_equals_drake_beyond_the_limits_on_shipped_specs(name, rng):
    _assert_every_step_path_equals_drake(systems.load(name), rng)


@pytest.mark.parametrize("integrator", ["euler", "runge_kutta2"])
def test_an_action_limit_above_the_effort_limit_is_clamped_as_drake_does(integrator, rng, tmp_path):
    """Drake's MultibodyPlant clamps each actuator's input to [-effort, effort] (measured: pydrake 1.51 at
    u = 10 with effort 2.5 gives the accelerations of u = 2.5); the generated dynamics do the same."""
    system = _pendubot(tmp_path, integrator__method=integrator)
    assert system.action_limit == 10.0 and system.model.info["effort_limits"] == [2.5]
    _assert_every_step_path_equals_drake(system, rng)
    x = torch.zeros(1, 4, dtype=torch.float64)
    np.testing.assert_array_equal(system.derivatives(x, torch.tensor([[10.0]])).numpy(),
                                  system.derivatives(x, torch.tensor([[2.5]])).numpy())
    # beyond the limit the input has no effect, inside it its gradient is Drake's B
    u = torch.tensor([[10.0], [1.0]], dtype=torch.float64, requires_grad=True)
    system.derivatives(torch.zeros(2, 4, dtype=torch.float64), u)[:, 2].sum().backward()
    assert u.grad[0, 0] == 0.0 and u.grad[1, 0] > 0.0


def test_an_absurd_effort_limit_goes_through_the_specs_range_check(tmp_path):
    with pytest.raises(SpecError, match=r"action.limit.* must lie in \[1e-06, 1e\+06\].*1e\+300"):
        _pendubot(tmp_path, effort=1e300, action_limit=None)
    ok = tmp_path / "ok"
    ok.mkdir()
    assert _pendubot(ok, action_limit=None).action_limit == 2.5     # a plausible one is the default


def _flip_gravity(doc):
    doc["gravity"] = [[[-c, e] for c, e in p] for p in doc["gravity"]]


def _big_int(doc):
    doc["mass"][0][0][0] = 10 ** 400


def _deep(doc):
    doc["info"]["deep"] = "DEEP"


def _zero_mass(doc):
    doc["mass"][0] = []


def _huge_shape(doc):
    doc["bodies"] = [f"b{i}" for i in range(100_000)]
    doc["body_parents"] = [-1] * 100_000
    doc["body_origins"] = [[]] * 300_000


def _long_name(doc):
    doc["positions"][0] = "x" * 1_000_000


def _absurd_effort(doc):
    doc["info"]["effort_limits"] = [1e300]


def _hidden_fast_term(doc):
    doc["bias"][0].append([1e-30, [0, 0, 0, 0, 0, 0, 16, 0]])    # 1e-30 v0^16: nothing at the states a check
                                                                 # may draw, 1e2 at v0 = 100 rad/s


TAMPERED = [("gravity signs flipped", _flip_gravity), ("integer too large for a float", _big_int),
            ("nesting past the recursion limit", _deep), ("zero mass term", _zero_mass),
            ("huge claimed shape", _huge_shape), ("long string", _long_name), ("effort limit 1e300", _absurd_effort),
            ("tiny term of high degree in v", _hidden_fast_term)]


@pytest.mark.parametrize("case, tamper", TAMPERED, ids=[c[0] for c in TAMPERED])
def test_a_tampered_cache_entry_is_derived_anew_with_one_warning(case, tamper, rng, tmp_path, monkeypatch):
    monkeypatch.setenv(symbolic.CACHE_ENV, str(tmp_path / "cache"))
    fresh = _pendubot(tmp_path)
    cache = tmp_path / "cache" / "multibody" / f"{fresh.model.info['key']}.json"
    doc = json.loads(cache.read_text())
    tamper(doc)
    cache.write_text(json.dumps(doc).replace('"DEEP"', "[" * 100_000 + "]" * 100_000))
    with pytest.warns(UserWarning) as caught:
        again = _pendubot(tmp_path)
    messages = [str(w.message) for w in caught if "model cache" in str(w.message)]
    assert len(messages) == 1 and "\n" not in messages[0] and str(cache) in messages[0], messages
    assert "derived anew" in messages[0]
    assert again.model.info["cached"] is False and again.model == fresh.model
    assert again.model.info["effort_limits"] == [2.5]
    _assert_every_step_path_equals_drake(again, rng)
    written = json.loads(cache.read_text())                     # replaced: the physics as derived
    assert written.pop("info")["effort_limits"] == [2.5]
    assert written == {k: v for k, v in json.loads(json.dumps(fresh.model.to_json())).items() if k != "info"}
    assert _pendubot(tmp_path).model.info["cached"] is True     # the replaced entry passes its check


def test_a_cache_entry_under_the_key_of_a_request_that_cannot_be_derived_is_not_used(tmp_path, monkeypatch):
    """An entry written under the key of a request derive refuses (a tip body the model lacks) is checked like
    any other: derived anew, which gives the request's own one-line error, never a traceback or that entry."""
    monkeypatch.setenv(symbolic.CACHE_ENV, str(tmp_path / "cache"))
    system = _pendubot(tmp_path)
    bad = symbolic.ModelRequest(system.model_request.source, tip_body="hand", tip_point=(0.0, 0.0, 1.0))
    doc = system.model.to_json()
    doc["tip"] = [[[1.0, [0] * 8]]] * 3
    doc["info"] = {"effort_limits": [2.5]}
    (tmp_path / "cache" / "multibody" / f"{symbolic.cache_key(bad)}.json").write_text(json.dumps(doc))
    with pytest.warns(UserWarning, match="model cache .*: its tip body 'hand' is not a body of the model; derived"):
        with pytest.raises(ModelError, match="model.tip_body 'hand' is not a body of the model"):
            symbolic.load_model(bad)


# ------------------------------------------------------------- issue 49: a built system saved as a spec file
def test_save_spec_writes_a_spec_that_loads_to_the_same_dynamics_and_lqr_bit_for_bit(rng, tmp_path):
    (tmp_path / "pendubot.urdf").write_text(_pendubot_urdf())
    with pytest.warns(UserWarning, match="moved .* to the nearest equilibrium"):
        robot = systems.from_drake(str(tmp_path / "pendubot.urdf"), goal=[3.1416, 0, 0, 0], Q=np.diag([10, 5, 1, 1]),
                                   R=[[2.0]], gravity=9.80665, tip_body="lower_link", tip_point=[0, 0, -1.0],
                                   dt=0.005, gate__cost_scale=7.5)
    path = robot.save_spec(tmp_path / "pendubot.toml")
    text = path.read_text()
    assert 'family = "multibody"' in text and 'file = { value = "pendubot.urdf"' in text   # next to the spec
    assert re.search(r"source = \"from_drake argument: \[3.1416, 0.0, 0.0, 0.0\] moved 7.3\d*e-06 to the nearest "
                     r"equilibrium", text) and 'source = "user override"' in text and "file_sha256" not in text
    import tomllib
    doc = tomllib.loads(text)
    bare = {"system.name", "system.description", "model.family"}
    assert all("source" in entry for section, table in doc.items() for key, entry in table.items()
               if f"{section}.{key}" not in bare)
    again = systems.load(str(path))
    assert again.goal.tolist() == robot.goal.tolist() and again.dt == 0.005 and again.action_limit == robot.action_limit
    X = torch.as_tensor(rng.uniform(-4, 4, (64, 4)))
    U = torch.as_tensor(rng.uniform(-3, 3, (64, 1)))
    assert torch.equal(again.derivatives(X, U), robot.derivatives(X, U))
    assert torch.equal(again.step(X, U), robot.step(X, U))
    for a, b in zip(again.lqr(), robot.lqr()):
        assert np.array_equal(a, b)
    with pytest.raises(FileExistsError, match=r"pendubot.toml exists; pass overwrite=True to replace it") as error:
        robot.save_spec(path)
    assert "\n" not in str(error.value)
    robot.save_spec(path, overwrite=True)
    # a model outside the spec's folder keeps its absolute path; a shipped spec round-trips too
    (tmp_path / "elsewhere").mkdir()
    assert f'file = {{ value = "{tmp_path / "pendubot.urdf"}"' in robot.save_spec(tmp_path / "elsewhere/p.toml").read_text()
    furuta = systems.load("furuta")
    copy = systems.load(str(furuta.save_spec(tmp_path / "elsewhere/furuta.toml")))
    assert torch.equal(copy.derivatives(X, U[:, :1]), furuta.derivatives(X, U[:, :1]))
