"""Switched SAC: gate data, refits, needle episodes, checkpoints, Drake integration, CLI."""

import json
import math

import numpy as np
import pytest
import torch

from hybridctl import drake, experiments, systems
from hybridctl.cli import main as cli_main
from hybridctl.envs import SwitchedVectorEnv
from hybridctl.learn import (SAC, SSAC, CheckpointError, GateConfig, GateDataset, GateNet, SSACConfig,
                             load_controller, warm_start_gate)
from hybridctl.learn.gate import label_states

TINY = dict(num_envs=8, exploration_steps=400, steps_per_update=200, updates_per_round=1, replay_batch_size=128,
            minibatch_size=64, buffer_size=20_000, needle_buffer_size=5_000, log_every=400, checkpoint_every=800,
            tensorboard=False, gate_refit_every=800, gate_refit_steps=20, gate_batch_size=256)


@pytest.fixture(scope="module")
def warm():
    """One small warm-started gate (2000 LQR-labelled states) shared by the tests."""
    system = systems.load("acrobot")
    gate, states, labels, info = warm_start_gate(system, GateConfig(warm_samples=2000, warm_fit_steps=200))
    return gate, states, labels


def tiny_ssac(warm, system="acrobot", **overrides) -> SSAC:
    import copy

    gate, states, labels = warm
    return SSAC(system, gate=copy.deepcopy(gate), gate_data=(states, labels), **{**TINY, **overrides})


def near_top(duration=2.0):
    """The acrobot starting within 0.01 rad of upright (so the LQR balances it)."""
    return systems.load("acrobot", **{"initial_state.nominal": [math.pi / 2, 0, 0, 0],
                                      "initial_state.low": [-0.01, -0.01, 0, 0],
                                      "initial_state.high": [0.01, 0.01, 0, 0], "episode.duration": duration})


def always_lqr_gate(system) -> GateNet:
    gate = GateNet(system)
    with torch.no_grad():
        last = gate.net[-1]
        last.weight.zero_()
        last.bias.fill_(20.0)  # p = sigmoid(20) ~ 1 everywhere
    return gate


# ------------------------------------------------------------------------- config
def test_paper_and_author_variants():
    paper, author = SSACConfig.variant("paper"), SSACConfig.variant("author")
    assert (paper.polyak, paper.obs_transform, paper.gate_relabel_per_refit) == (0.995, "none", 0)
    assert (SSACConfig().polyak, SSACConfig().obs_transform) == (0.9, "angle_sincos")
    assert (paper.needle_prob, paper.gate_refit_every, paper.gamma, paper.updates_per_round, paper.reward) == \
        (0.5, 50_000, 0.95, 4, "tip_height")
    assert (author.needle_prob, author.gate_refit_every, author.gamma, author.updates_per_round, author.reward) == \
        (0.2, 25_000, 0.99, 16, "quadratic")
    assert SSACConfig.variant("author", gamma=0.9).gamma == 0.9
    with pytest.raises(ValueError, match="variant"):
        SSACConfig.variant("mine")


@pytest.mark.parametrize("field, value", [("gate_refit_every", 0), ("gate_lr", -1.0), ("reward", "height"),
                                          ("gate_positive_weight", 0.0), ("needle_prob", 1.5)])
def test_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        SSACConfig(**{field: value}).validate()


def test_reward_comes_from_the_spec_unless_the_config_names_one(warm):
    assert SSACConfig().reward is None
    gate, states, labels = warm
    default = SSAC("acrobot", gate=gate, gate_data=(states, labels), **TINY)
    assert default.system.reward_kind == default.config.reward == "tip_height"   # the spec's, recorded
    quadratic = systems.load("acrobot", **{"reward.kind": "quadratic"})
    agent = SSAC(quadratic, gate=GateNet(quadratic), **TINY)               # a System is used as it is
    assert agent.system is quadratic
    named = SSAC("acrobot", gate=GateNet(quadratic), reward="quadratic", **TINY)   # a name is loaded with it
    assert named.system.reward_kind == "quadratic"
    with pytest.raises(ValueError, match="reward.kind='quadratic'"):       # no silent reload of a System
        SSAC(quadratic, gate=GateNet(quadratic), reward="tip_height", **TINY)


def test_the_thread_count_is_set_before_the_gate_warm_start(monkeypatch):
    from hybridctl.learn import ssac as ssac_module
    threads = []

    def fake_warm_start(system, config, device="cpu"):
        threads.append(torch.get_num_threads())
        return GateNet(system), np.zeros((2, 4)), np.array([True, False]), {}

    monkeypatch.setattr(ssac_module, "warm_start_gate", fake_warm_start)
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        SSAC("acrobot", torch_threads=1, **TINY)
    finally:
        torch.set_num_threads(previous)
    assert threads == [1]


def test_gate_dataset_keeps_warm_rows_and_drops_oldest_episode_rows():
    data = GateDataset(2, capacity=7)
    data.add(np.zeros((3, 2)), [1, 0, 1], warm=True)
    data.add(np.ones((2, 2)), [1, 1])
    data.add(2 * np.ones((3, 2)), [0, 0, 0])
    assert len(data) == 7 and data.n_warm == 3
    np.testing.assert_array_equal(data.states[:3].numpy(), 0)
    np.testing.assert_array_equal(data.states[3:, 0].numpy(), [1, 2, 2, 2])  # the oldest episode row dropped


# ---------------------------------------------------------------- the algorithm
def test_gate_data_are_lqr_active_decisions_labelled_by_success(warm):
    system = near_top()
    env = SwitchedVectorEnv(system, 8, gate=always_lqr_gate(system), seed=0)
    agent = SSAC(env, gate_data=(np.zeros((4, 4)), [0, 0, 0, 1]), **TINY)
    agent.learn(total=8 * 10, progress=False)  # exactly one 10-decision episode per env
    wins = round(agent.success_rate * 8)
    assert agent.num_episodes == 8 and 0 < wins < 8  # random actions in the first 0.01 s: some fail
    # the first decision of each episode starts in swing-up mode, the other 9 under the LQR;
    # each episode's 9 rows carry that episode's success label
    assert len(agent.gate_data) == 4 + 8 * 9
    labels = agent.gate_data.labels[4:].reshape(8, 9)
    assert bool((labels == labels[:, :1]).all()) and int(labels[:, 0].sum()) == wins
    assert agent.num_needle_episodes == wins and agent.needle.size == 10 * wins


def test_failed_lqr_episodes_give_negative_gate_labels(warm):
    system = systems.load("acrobot", duration=2.0)  # random starts far from the top: the LQR fails
    env = SwitchedVectorEnv(system, 8, gate=always_lqr_gate(system), seed=0)
    agent = SSAC(env, gate_data=(np.zeros((4, 4)), [0, 0, 0, 1]), **TINY)
    agent.learn(total=8 * 10, progress=False)
    assert agent.success_rate == 0.0 and agent.needle.size == 0
    assert len(agent.gate_data) > 4 and not bool(agent.gate_data.labels[4:].any())


def test_rollout_labels_put_lqr_active_states_in_the_relabel_pool_not_in_gate_data():
    """gate_lqr_labels="rollout": the failed LQR episodes' states are not labelled 0 by the episode;
    they wait in the relabel pool and are labelled by LQR rollouts at the refit."""
    system = systems.load("acrobot", duration=2.0)  # random starts far from the top: the LQR fails
    env = SwitchedVectorEnv(system, 8, gate=always_lqr_gate(system), seed=0)
    agent = SSAC(env, gate_data=(np.zeros((4, 4)), [0, 0, 0, 1]), gate_lqr_labels="rollout",
                 gate_relabel_per_refit=50, **{**TINY, "gate_refit_every": 10_000})
    agent.learn(total=8 * 10, progress=False)
    assert agent.success_rate == 0.0 and len(agent.gate_data) == 4          # nothing labelled by the episodes
    pooled = len(agent._relabel_pool)
    assert pooled >= 8 * 9                                                   # 9 LQR-active decisions per episode
    info = agent.refit_gate(steps=2)
    assert info["relabelled"] == 50 and len(agent.gate_data) == 4 + 50
    expected = label_states(system, agent.gate_data.states[4:].double().numpy(), agent.config.gate_config())
    assert np.array_equal(agent.gate_data.labels[4:].numpy(), expected)
    with pytest.raises(ValueError, match="gate_lqr_labels"):
        SSACConfig(gate_lqr_labels="outcome").validate()
    with pytest.raises(ValueError, match="gate_relabel_per_refit"):
        SSACConfig(gate_lqr_labels="rollout", gate_relabel_per_refit=0).validate()


def test_gate_is_refit_on_schedule_and_env_uses_it(warm):
    agent = tiny_ssac(warm, gate_refit_every=400)
    before = [p.clone() for p in agent.gate.parameters()]
    agent.learn(total=1000, progress=False)
    assert agent.num_gate_refits == 2  # at 400 and 800 env steps
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.gate.parameters()))
    assert agent.env.gate is agent.gate
    assert agent.gate_info["last_refit"]["data"] == len(agent.gate_data)


def test_same_seed_repeats(warm):
    a, b = tiny_ssac(warm, seed=3, gate_refit_every=400), tiny_ssac(warm, seed=3, gate_refit_every=400)
    for agent in (a, b):
        agent.learn(total=800, progress=False)          # gradient steps and two gate refits (400, 800)
    for x, y in zip([*a.actor.parameters(), *a.gate.parameters()], [*b.actor.parameters(), *b.gate.parameters()]):
        assert torch.equal(x, y)
    assert a.recent_returns == b.recent_returns


def test_act_uses_the_lqr_where_the_gate_hands_over(warm):
    system = systems.load("acrobot")
    env = SwitchedVectorEnv(system, 2, gate=always_lqr_gate(system))
    agent = SSAC(env, gate_data=warm[1:], **TINY)
    x = torch.tensor([[math.pi / 2 + 0.01, 0.0, 0.0, 0.0]], dtype=torch.float64)
    np.testing.assert_allclose(agent.act(x).numpy(), env.lqr(x).clamp(-25, 25).numpy())
    agent.gate.net[-1].bias.data.fill_(-20.0)
    np.testing.assert_allclose(agent.act(x).numpy(), agent.predict(x).numpy())


# ------------------------------------------------------------- checkpoints
def test_save_load_keeps_policy_gate_and_resume_restores_gate_data(tmp_path, warm):
    agent = tiny_ssac(warm, gate_refit_every=400)
    agent.learn(total=800, progress=False, out=tmp_path)
    loaded = SSAC.load(tmp_path / "final")
    x = torch.as_tensor(systems.load("acrobot").sample_initial_states(16, np.random.default_rng(0)))
    assert torch.equal(loaded.act(x), agent.act(x))
    assert len(loaded.gate_data) == 0  # load() is for inference: no data
    resumed = tiny_ssac(warm, gate_refit_every=400)
    resumed.learn(total=1200, progress=False, out=tmp_path, resume=True)
    assert resumed.num_timesteps == 1200
    assert resumed.gate_data.n_warm == agent.gate_data.n_warm and len(resumed.gate_data) >= len(agent.gate_data)
    assert (agent.num_gate_refits, resumed.num_gate_refits) == (2, 3)  # at 400, 800; then 1200
    meta = json.loads((tmp_path / "final" / "config.json").read_text())
    assert meta["algorithm"] == "SSAC" and meta["gate"]["gate_on"] == 0.9 and meta["config"]["needle_prob"] == 0.5
    assert meta["gate"]["hidden"] == [32, 32] and {"torch", "hybridctl"} <= set(meta["versions"])
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    assert header[-3:] == ["gate_data", "gate_refits", "lqr_share"]
    assert (tmp_path / "final" / "gate_data.pt").is_file()


def test_config_json_is_written_once_with_the_gate(tmp_path, warm, monkeypatch):
    """SSAC adds its gate section through checkpoint_meta: config.json is written once, not rewritten."""
    from hybridctl.learn import run as run_module
    written = []
    original = run_module.ckpt.write_json
    monkeypatch.setattr(run_module.ckpt, "write_json",
                        lambda path, data: (written.append((path.name, "gate" in data)), original(path, data)))
    tiny_ssac(warm).save(tmp_path / "ck")
    assert [w for w in written if w[0] == "config.json"] == [("config.json", True)]


def test_load_errors(tmp_path, warm):
    agent = tiny_ssac(warm)
    agent.save(tmp_path / "ssac")
    with pytest.raises(CheckpointError, match="trained on system 'acrobot'.*'cartpole'"):
        load_controller(tmp_path / "ssac", systems.load("cartpole"))
    with pytest.raises(CheckpointError, match="trained on system 'acrobot'"):
        SSAC.load(tmp_path / "ssac", system="cartpole")
    (tmp_path / "ssac" / "model.pt").unlink()
    with pytest.raises(CheckpointError, match="model.pt"):
        SSAC.load(tmp_path / "ssac")
    with pytest.raises(CheckpointError, match="model.pt"):
        load_controller(tmp_path / "ssac", systems.load("acrobot"))
    SAC("acrobot", **{k: v for k, v in TINY.items() if not k.startswith("gate")}).save(tmp_path / "sac")
    with pytest.raises(CheckpointError, match="written by SAC"):
        SSAC.load(tmp_path / "sac")
    with pytest.raises(ValueError, match="without a learned gate"):
        experiments.build_named_diagram(systems.load("acrobot"), f"ssac:{tmp_path / 'sac'}")


def test_nan_loss_stops_and_keeps_the_last_checkpoint(tmp_path, warm):
    def poison(agent):
        if agent.num_timesteps >= 500:
            agent.replay.data["rewards"][:] = math.nan

    agent = tiny_ssac(warm, checkpoint_every=400)
    with pytest.raises(FloatingPointError, match="q_loss became nan"):
        agent.learn(total=2000, progress=False, out=tmp_path, callback=poison)
    good = SSAC.load(tmp_path / "checkpoint")
    assert good.num_timesteps == 400 and not (tmp_path / "final").exists()


# ------------------------------------------------------------ Drake integration
def test_drake_diagram_from_checkpoint_equals_the_switched_env(tmp_path, warm):
    """The checkpoint's swing-up and gate as TorchPolicy and Gate blocks behave as in training."""
    system = systems.load("acrobot")
    gate = warm[0]
    # a loose copy of the warm gate hands over somewhere along the run, so both modes are exercised
    with torch.no_grad():
        gate.net[-1].bias.add_(6.0)
    agent = SSAC(SwitchedVectorEnv(system, 1, gate=gate), gate_data=warm[1:], **TINY)
    agent.save(tmp_path / "ck")
    loaded = load_controller(tmp_path / "ck", system)
    policy, loaded_gate = loaded.swingup, loaded.gate.module
    diagram = experiments.build_named_diagram(system, f"ssac:{tmp_path / 'ck'}")
    x0 = np.array([1.2, -0.4, 0.5, -1.0])
    traj = drake.simulate(diagram, x0, duration=4.0)
    env = SwitchedVectorEnv(system, 1, gate=loaded_gate)
    obs, _ = env.reset(options={"state": x0})
    states = [obs[0].numpy()]
    for _ in range(20):
        obs, *_ = env.step(policy(obs))
        states.append(obs[0].numpy())
    np.testing.assert_allclose(np.array(states), traj.x[::env.substeps][:21], rtol=1e-6, atol=1e-6)
    assert 0 < traj.gate.mean() < 1  # both controllers acted


def test_cli_train_resume_simulate_and_balance_map(tmp_path):
    run = tmp_path / "run"
    common = ["train", "ssac", "acrobot", "--out", str(run), "--quiet", "--eval-episodes", "4",
              "--set", "gate_warm_samples=500", "--set", "gate_warm_fit_steps=50", "--set", "num_envs=8",
              "--set", "exploration_steps=400", "--set", "replay_batch_size=128", "--set", "checkpoint_every=400",
              "--set", "tensorboard=false"]
    assert cli_main([*common, "--steps", "400"]) == 0
    assert cli_main([*common, "--steps", "800", "--resume"]) == 0
    result = json.loads((run / "eval.json").read_text())
    assert result["env_steps"] == 800 and result["episodes"] == 4 and "--resume" in result["command"]
    assert (run / "training_curves.png").is_file() and (run / "progress.csv").is_file()
    assert cli_main(["simulate", "acrobot", "--controller", f"ssac:{run}", "--out", str(tmp_path / "sim"),
                     "--no-html"]) == 0
    assert cli_main(["balance-map", "acrobot", "--controller", f"ssac:{run}", "--grid", "2", "--workers", "1",
                     "--duration", "1", "--out", str(tmp_path / "map"), "--quiet"]) == 0
    with pytest.raises(SystemExit, match="not a SSACConfig field"):
        cli_main([*common, "--set", "gama=0.9"])


def test_the_shipped_checkpoint_evaluates_as_before():
    """models/policies/ssac-acrobot: 100 deterministic episodes, the numbers measured before the skeleton."""
    from pathlib import Path
    folder = Path(__file__).resolve().parents[1] / "models" / "policies" / "ssac-acrobot"
    result = SSAC.load(folder).evaluate(episodes=100)
    assert result["success_rate"] == 1.0 and result.episodes == 100
    # 91.98468007287164 on the development machine, before and after the training skeleton (bit-identical
    # there); float reductions differ in the last digits across CPUs / torch builds (91.98467998121106 was
    # measured elsewhere), hence 1e-6
    assert result["mean_return"] == pytest.approx(91.98468007287164, abs=1e-6)


@pytest.mark.parametrize("compile_mode", ["off", pytest.param("on", marks=pytest.mark.slow)])
def test_overlapped_gate_refit_gives_the_one_thread_numbers(warm, compile_mode):
    """gate_refit_overlap runs each due refit on a second thread during the round's gradient steps:
    the networks, the gate, D_g and the counters equal those of refitting after the steps."""
    agents = []
    for overlap in (False, True):
        agent = tiny_ssac(warm, gate_refit_overlap=overlap, updates_per_round=3, gate_refit_steps=60,
                          gate_relabel_per_refit=64, compile=compile_mode, gate_refit_every=400)
        agent.learn(1200, progress=False)             # refits at 400, 800, 1200, each during a round's updates
        agents.append(agent)
    one, two = agents
    assert one.num_gate_refits == two.num_gate_refits >= 2 and two._pending_refit is None
    assert one.num_gate_relabelled == two.num_gate_relabelled > 0
    for name in ("actor", "q1", "q2", "q1_target", "gate"):
        for a, b in zip(getattr(one, name).state_dict().values(), getattr(two, name).state_dict().values()):
            assert torch.equal(a, b), name
    assert torch.equal(one.gate_data.states, two.gate_data.states)
    assert one.gate_info["last_refit"] == two.gate_info["last_refit"]
    assert two.env.gate is two.gate


def test_a_failed_overlapped_refit_raises_in_training(warm, monkeypatch):
    agent = tiny_ssac(warm, gate_refit_steps=5, gate_refit_every=400)

    def broken(*args, **kwargs):
        raise FloatingPointError("gate loss is NaN (test)")
    monkeypatch.setattr(agent, "_fit_gate_on_data", broken)
    with pytest.raises(FloatingPointError, match="gate loss"):
        agent.learn(2400, progress=False)
    assert agent._pending_refit is None
