"""Analytic policy gradients (thesis Ch. 7): policies, batched population gradients, CEM, CE-APG, faults."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hybridctl import systems
from hybridctl.learn.apg import (APG, APGConfig, BatchedAdam, cem_update, lr_schedule, member_gradients,
                                 observe, population_returns)
from hybridctl.learn.policies import Policy, PolicyPopulation, gru_width


pytestmark = pytest.mark.usefixtures("one_torch_thread")   # tests/conftest.py


def small(method="ce-apg", **overrides) -> APGConfig:
    """A tiny float64 task: cart-pole, 12 policy steps, 3 members."""
    values = dict(method=method, horizon=12, batch=2, apg_iterations=2, population=3, elites=2, rank_window=1,
                  epochs=2, dtype="float64", lr_start=1e-2, lr_end=1e-3)
    if method == "apg":
        values.update(population=1, elites=1)
    values.update(overrides)
    return APGConfig(**values)


# ----------------------------------------------------------------------------- policies

def test_gru_policy_is_the_thesis_architecture_and_equals_torch_layers():
    pop = PolicyPopulation.gru(obs_dim=4, act_dim=1, action_limit=7.0, members=3,
                               generator=torch.Generator().manual_seed(0))
    assert gru_width(4) == 16 and gru_width(6) == 32 and gru_width(5) == 32
    assert [(l.kind, l.n_in, l.n_out, l.activation) for l in pop.layers] == [
        ("dense", 4, 16, "relu"), ("gru", 16, 4, "none"), ("dense", 4, 16, "relu"), ("dense", 16, 16, "relu"),
        ("dense", 16, 1, "tanh")]
    pop.set_normalization(torch.tensor([0.1, -0.2, 0.3, 0.0]), torch.tensor([1.0, 2.0, 0.5, 1.5]))
    obs = torch.randn(3, 5, 4, dtype=torch.float64)
    h = torch.randn(3, 5, 4, dtype=torch.float64)
    action, h_next = pop(obs, h)
    k = 2  # member k with torch's own layers
    dense = []
    for i in (0, 2, 3, 4):
        lin = torch.nn.Linear(*reversed(getattr(pop, f"l{i}_weight")[k].shape)).double()
        lin.weight.data.copy_(getattr(pop, f"l{i}_weight")[k])
        lin.bias.data.copy_(getattr(pop, f"l{i}_bias")[k])
        dense.append(lin)
    cell = torch.nn.GRUCell(16, 4).double()
    for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
        getattr(cell, name).data.copy_(getattr(pop, f"l1_{name}")[k])
    z = (obs[k] - pop.obs_mean) / pop.obs_std
    hk = cell(torch.relu(dense[0](z)), h[k])
    y = 7.0 * torch.tanh(dense[3](torch.relu(dense[2](torch.relu(dense[1](hk))))))
    assert torch.allclose(h_next[k], hk, atol=1e-12) and torch.allclose(action[k], y, atol=1e-12)
    assert action.abs().max() <= 7.0


def test_flat_parameters_round_trip_and_member_policy():
    pop = PolicyPopulation.build("mlp", 3, 2, 1.0, members=4, hidden=(8, 8))
    flat = torch.randn(4, pop.n_params, dtype=torch.float64)
    pop.from_flat(flat)
    assert torch.equal(pop.to_flat(), flat)
    one = pop.member(2)
    obs = torch.randn(5, 3, dtype=torch.float64)
    a, state = one(obs, one.initial_state(5))
    assert state.shape == (5, 0) and torch.allclose(a, pop(obs.expand(4, -1, -1), pop.initial_state(5))[0][2])
    assert torch.equal(one.to_flat(), flat[2])
    with pytest.raises(ValueError, match="flat parameters must be"):
        pop.from_flat(torch.zeros(3, pop.n_params))
    linear = Policy.build("linear", 3, 1, 2.0, init_std=0.0)
    assert linear.to_flat().abs().sum() == 0 and linear(torch.ones(3), linear.initial_state())[0].shape == (1,)


# ----------------------------------------------------------------------------- rewards

def test_ch7_rewards_from_upright_and_the_smooth_option():
    acrobot = systems.load("acrobot", reward__kind="angle_squared")
    x = acrobot.goal.copy()
    x[0] += 0.3
    x[1] -= 0.2
    assert acrobot.reward(acrobot.goal) == 0.0
    assert math.isclose(float(acrobot.reward(x)), -(0.3 ** 2 + 0.2 ** 2))
    smooth = systems.load("cartpole", reward__kind="angle_cosine")
    near, far = smooth.goal.copy(), smooth.goal.copy()
    near[1] += 1e-3
    far[1] += math.pi - 1e-6     # -theta^2 jumps at +-pi; 2 (1 - cos) does not
    far2 = smooth.goal.copy()
    far2[1] -= math.pi - 1e-6
    assert math.isclose(float(smooth.reward(near)), -1e-6, rel_tol=1e-5)
    assert abs(float(smooth.reward(far)) - float(smooth.reward(far2))) < 1e-9
    author = systems.load("double_cartpole", reward__kind="angle_squared", alive_bonus=10.0, velocity_penalty=0.01,
                          position_weight=1.0)
    y = author.goal.copy()
    y[0], y[4] = 0.5, 2.0
    assert math.isclose(float(author.reward(y)), 10 - 0.25 - 0.01 * 4)
    # the cart-speed term (hybridctl's): weight 0.5 on the cart's 2 m/s; the angle rates keep their own penalty
    resting = systems.load("double_cartpole", reward__kind="angle_squared", linear_velocity_weight=0.5)
    z = resting.goal.copy()
    z[3], z[4] = 2.0, 3.0
    assert math.isclose(float(resting.reward(z)), -0.5 * 4)
    assert math.isclose(float(resting.reward(torch.as_tensor(z))), -0.5 * 4)
    through_config = APG._system("double_cartpole", APGConfig(reward_kind="angle_cosine", linear_velocity_weight=0.5,
                                                              cost_to_go_weight=2.0))
    assert through_config.reward_linear_velocity_weight == 0.5 and through_config.reward_cost_to_go_weight == 2.0
    # the gate's measure: k log(1 + e' S e / scale), 0 at the goal, the same on numpy and torch (float32 too)
    shaped = systems.load("double_cartpole", reward__kind="angle_squared", cost_to_go_weight=2.0)
    S, scale = shaped.lqr()[1], shaped.gate.cost_scale
    w = shaped.goal.copy()
    w[0], w[3] = 0.3, 1.0
    e = shaped.state_error(w)
    expected = -2.0 * math.log1p(float(e @ S @ e) / scale)
    assert float(shaped.reward(shaped.goal)) == 0.0
    assert math.isclose(float(shaped.reward(w)), expected, rel_tol=1e-12)
    assert math.isclose(float(shaped.reward(torch.as_tensor(w))), expected, rel_tol=1e-12)
    assert math.isclose(float(shaped.reward(torch.as_tensor(w, dtype=torch.float32))), expected, rel_tol=1e-5)
    tip = systems.load("double_cartpole", reward__kind="tip_distance", alive_bonus=10.0)
    assert float(tip.reward(tip.goal)) == 10.0
    assert math.isclose(float(tip.reward(tip.initial_state.nominal)), 10 - (2 * 1.25) ** 2)
    t = torch.as_tensor(np.stack([y, tip.goal]))
    assert torch.allclose(tip.reward(t), torch.as_tensor(tip.reward(np.stack([y, tip.goal]))))
    with pytest.raises(systems.SpecError, match="must be one of"):
        systems.load("acrobot", reward__kind="nope")
    with pytest.raises(systems.SpecError, match="velocity_penalty.*>= 0"):
        systems.load("acrobot", velocity_penalty=-0.01)
    with pytest.raises(systems.SpecError, match="linear_velocity_weight.*>= 0"):
        systems.load("double_cartpole", linear_velocity_weight=-1.0)
    with pytest.raises(ValueError, match="cost_to_go_weight"):
        APGConfig(cost_to_go_weight=-1.0).validate()
    with pytest.raises(ValueError, match="APGConfig.reward_kind must be one of"):
        APGConfig(reward_kind="tip_height").validate()


# ----------------------------------------------------------------------------- gradients

def _rollout_loss(system, pop, x0, horizon, substeps):
    returns, *_ = population_returns(system, pop, x0, horizon, substeps)
    return -returns.mean(1)


def test_batched_population_gradients_equal_per_member_gradients():
    system = systems.load("cartpole", reward__kind="angle_squared")
    pop = PolicyPopulation.gru(5, 1, system.action_limit, members=3, dtype=torch.float64, init_std=0.3,
                               generator=torch.Generator().manual_seed(1))
    x0 = torch.as_tensor(system.initial_state.nominal + np.random.default_rng(0).uniform(-0.3, 0.3, (2, 4)))
    batched = member_gradients(pop, _rollout_loss(system, pop, x0, 15, 5))
    flat = pop.to_flat()
    for k in range(3):
        alone = pop.resized(1, flat[k:k + 1])
        single = member_gradients(alone, _rollout_loss(system, alone, x0, 15, 5))[0]
        assert torch.allclose(batched[k], single, rtol=0, atol=1e-10 * max(1.0, float(single.abs().max())))
    assert not torch.allclose(batched[0], batched[1])


def test_apg_gradient_matches_finite_differences():
    system = systems.load("cartpole", reward__kind="angle_cosine")
    pop = PolicyPopulation.gru(5, 1, system.action_limit, members=1, dtype=torch.float64, init_std=0.2,
                               generator=torch.Generator().manual_seed(2))
    x0 = torch.as_tensor(system.initial_state.nominal + np.array([[0.1, 0.2, 0.0, 0.0], [-0.1, -0.3, 0.0, 0.0]]))
    grad = member_gradients(pop, _rollout_loss(system, pop, x0, 8, 5))[0]
    theta = pop.to_flat()[0]
    direction = torch.randn(theta.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    eps = 1e-6
    with torch.no_grad():
        plus = float(_rollout_loss(system, pop.from_flat(theta + eps * direction), x0, 8, 5)[0])
        minus = float(_rollout_loss(system, pop.from_flat(theta - eps * direction), x0, 8, 5)[0])
    fd = (plus - minus) / (2 * eps)
    analytic = float(grad @ direction)
    assert abs(fd - analytic) <= 1e-6 * max(1.0, abs(analytic)), (fd, analytic)


def gru_case(members: int, seed: int):
    """(system, float64 GRU population, one start) on the cart-pole with the -theta^2 reward."""
    system = systems.load("cartpole", reward__kind="angle_squared")
    pop = PolicyPopulation.gru(5, 1, system.action_limit, members=members, dtype=torch.float64, init_std=0.2,
                               generator=torch.Generator().manual_seed(seed))
    return system, pop, torch.as_tensor(system.initial_state.nominal[None] + 0.1)


def test_truncation_cuts_the_graph():
    system, pop, x0 = gru_case(members=1, seed=4)
    full = member_gradients(pop, -population_returns(system, pop, x0, 10, 5)[0].mean(1))
    cut = member_gradients(pop, -population_returns(system, pop, x0, 10, 5, truncation=3)[0].mean(1))
    same = member_gradients(pop, -population_returns(system, pop, x0, 10, 5, truncation=10)[0].mean(1))
    assert torch.equal(full, same) and not torch.allclose(full, cut)


# ----------------------------------------------------------------------------- CEM and the learners

def test_cem_update_equations_on_a_toy_quadratic():
    mean = torch.tensor([1.0, -1.0])
    cands = torch.tensor([[0.0, 0.0], [2.0, 2.0], [1.0, 0.0], [3.0, -3.0]])
    scores = torch.tensor([1.0, -5.0, 2.0, float("-inf")])
    new_mean, new_std, elite = cem_update(mean, cands, scores, 2)
    assert elite.tolist() == [2, 0]
    assert torch.allclose(new_mean, torch.tensor([0.5, 0.0]))                             # eq. 7.11
    assert torch.allclose(new_std, torch.sqrt(torch.tensor([(0 + 1) / 2, (1 + 1) / 2])))  # eq. 7.13, old mean
    target = torch.tensor([0.7, -2.0, 1.5])
    gen = torch.Generator().manual_seed(0)
    m, s = torch.zeros(3), torch.ones(3)
    for _ in range(40):
        c = m + s * torch.randn(24, 3, generator=gen)
        m, s, _ = cem_update(m, c, -((c - target) ** 2).sum(1), 8)
    assert torch.allclose(m, target, atol=1e-2)


def test_lr_schedule_is_log_linear_over_epochs():
    cfg = APGConfig(epochs=4)
    assert [round(math.log10(lr_schedule(cfg, e)), 9) for e in range(4)] == [-3, -4, -5, -6]


def test_presets_name_their_differences():
    thesis = APGConfig.preset("thesis")
    assert (thesis.population, thesis.elites, thesis.apg_iterations, thesis.epochs, thesis.batch,
            thesis.horizon, thesis.init_std, thesis.lr_start, thesis.lr_end) == (24, 8, 100, 200, 4, 500, 0.05,
                                                                                 1e-3, 1e-6)
    short = APGConfig.preset("thesis", method="shapg")
    assert (short.short_horizon, short.clip, short.beta1, short.beta2) == (32, 1.0, 0.7, 0.95)
    reduced = APGConfig.preset("reduced")
    assert reduced.population < 24 and reduced.horizon < 500
    with pytest.raises(ValueError, match="known: thesis, reduced"):
        APGConfig.preset("fast")
    with pytest.raises(ValueError, match="APGConfig.policy must be"):
        APGConfig(policy="mlp:").validate()
    agent = APG("pendulum", APGConfig(policy="mlp:8,4", population=2, elites=1))
    assert [l.n_out for l in agent.pop.layers] == [8, 4, 1]


def test_papg_returns_the_best_member_not_the_initial_parameters():
    agent = APG("cartpole", small("papg", population=4, elites=2))
    initial = agent.members.clone()
    agent.learn(progress=False)
    scores = agent.last_scores
    top = int(torch.argmax(scores))
    assert torch.equal(agent.best, agent.members[top]) and agent.best_score == float(scores[top])
    assert not torch.equal(agent.best, initial[top])
    assert torch.equal(agent.policy().to_flat(), agent.best.to(torch.float64))


def test_ce_apg_improves_a_short_pendulum_swing_up():
    cfg = APGConfig(method="ce-apg", horizon=40, batch=2, apg_iterations=6, population=6, elites=2, epochs=3,
                    rank_window=2, dtype="float64", lr_start=3e-2, lr_end=1e-2, seed=0)
    agent = APG("pendulum", cfg)
    before = agent.evaluate(episodes=4)["mean_return"]
    agent.learn(progress=False)
    after = agent.evaluate(episodes=4)["mean_return"]
    assert after > before + 0.1 * abs(before), (before, after)
    assert agent.history[-1]["env_steps"] == 3 * 6 * 6 * 2 * 40   # K x N x T x iterations, honestly


def test_stabilisation_rate_counts_a_policy_that_holds_the_goal():
    """A start at the goal with zero parameters (zero force) stays there: stabilised; hanging down: not."""
    agent = APG("cartpole", small("papg", start_noise=None, horizon=40))
    agent.best = torch.zeros_like(agent.best)
    agent.system.initial_state.nominal[:] = agent.system.goal       # every held-out start at the goal
    agent.system.initial_state.low[:] = 0.0
    agent.system.initial_state.high[:] = 0.0
    held = agent.evaluate(episodes=2)
    assert held["success_rate"] == 1.0 and held["upright_rate"] == 1.0 and held["mean_return"] == 0.0
    hanging = APG("cartpole", small("papg", horizon=40))
    hanging.best = torch.zeros_like(hanging.best)
    out = hanging.evaluate(episodes=2)
    assert out["success_rate"] == 0.0 and out["upright_rate"] == 0.0


def test_bad_gradients_are_skipped_counted_and_isolated():
    agent = APG("cartpole", small("papg", population=3))
    theta = agent.members.clone()
    x0 = agent.starts(2, [0, 0])[None].repeat(3, 1, 1)
    poisoned = x0.clone()
    poisoned[1, 0, 1] = float("nan")           # member 1 diverges
    clean_adam, bad_adam = BatchedAdam(3, theta.shape[1]), BatchedAdam(3, theta.shape[1])
    clean, *_ = agent.apg_step(theta, x0, 1e-2, clean_adam)
    assert agent.nan_grads == 0
    new, scores, norms, ok, _, _ = agent.apg_step(theta, poisoned, 1e-2, bad_adam)
    assert agent.nan_grads == 1 and ok.tolist() == [True, False, True] and scores[1] == -math.inf
    assert torch.equal(new[1], theta[1]) and int(bad_adam.t[1]) == 0     # never applied
    assert torch.allclose(new[[0, 2]], clean[[0, 2]], atol=1e-12)        # the others are unaffected
    bounded = APG("cartpole", small("papg", population=3, grad_bound=1e-12))
    new, _, _, ok, _, _ = bounded.apg_step(theta, x0, 1e-2, BatchedAdam(3, theta.shape[1]))
    assert bounded.large_grads == 3 and not ok.any() and torch.equal(new, theta)


def test_nan_parameters_stop_training_and_keep_the_last_checkpoint(tmp_path, monkeypatch):
    agent = APG("cartpole", small("papg", epochs=3))
    agent.learn(total=1, out=tmp_path, progress=False)
    saved = agent.members.clone()

    def broken(self, theta, grad, mask, lr):
        return theta * float("nan")
    monkeypatch.setattr(BatchedAdam, "step", broken)
    with pytest.raises(FloatingPointError, match="APG parameters"):
        agent.learn(total=3, out=tmp_path, progress=False)
    again = APG.load(tmp_path / "final")
    assert again.epoch == 1 and torch.equal(again.members, saved)


@pytest.mark.parametrize("method", ["ce-apg", "papg", "shapg", "cem"])
def test_save_load_resume_reproduces(tmp_path, method):
    cfg = small(method, short_horizon=5)
    straight = APG("cartpole", cfg).learn(total=2, progress=False)
    first = APG("cartpole", cfg).learn(total=1, out=tmp_path, progress=False)
    assert first.epoch == 1
    resumed = APG("cartpole", cfg).learn(total=2, out=tmp_path, resume=True, progress=False)
    for name in ("mean", "std", "members", "best"):
        assert torch.equal(getattr(straight, name), getattr(resumed, name)), name
    assert torch.equal(straight.pop.obs_std, resumed.pop.obs_std)
    assert straight.env_steps == resumed.env_steps == 2 * cfg.batch * cfg.horizon * 3 * (
        1 if method == "cem" else cfg.apg_iterations)
    loaded = APG.load(tmp_path / "final")
    assert torch.equal(loaded.policy().to_flat(), resumed.policy().to_flat())


def test_observation_is_periodic_in_the_angles():
    system = systems.load("cartpole", reward__kind="angle_squared")
    x = torch.tensor([[0.3, 0.2, 1.0, -1.0]], dtype=torch.float64)
    y = x.clone()
    y[0, 1] += 2 * math.pi
    assert torch.allclose(observe(system, x), observe(system, y))
    assert observe(system, x).shape == (1, 5)


def test_benchmark_reports_ratios_and_batched_equals_loop(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "apg.json"
    proc = subprocess.run([sys.executable, str(root / "benchmarks" / "apg.py"), "--quick", "--horizon", "3",
                           "--repeats", "1", "--out", str(out)], cwd=root, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert report == json.loads(out.read_text())
    assert report["setting"]["population"] == 24 and report["setting"]["batch"] == 4
    assert report["setting"]["state_steps_per_iteration"] == 24 * 4 * 3
    assert all(v > 0 and math.isfinite(v) for v in report["ratios"].values())
    assert report["check"]["max_relative_difference_batched_vs_loop"] < 1e-4


@pytest.mark.parametrize("overrides, message", [
    ({"horizon": 1.5}, "APGConfig.horizon must be an integer"),
    ({"lr_start": float("nan")}, "APGConfig.lr_start must be a finite number"),
    ({"method": "ppo"}, "APGConfig.method must be one of"),
    ({"elites": 30}, r"APGConfig.elites \(30\) must be <= population"),
    ({"beta1": 1.0}, r"APGConfig.beta1 must be in \[0, 1\)"),
    ({"clip": 0.0}, "APGConfig.clip must be None or a finite number > 0"),
    ({"velocity_penalty": -1.0}, "APGConfig.velocity_penalty must be a finite number >= 0"),
    ({"control_period": 0.013}, "must be a whole multiple"),
])
def test_bad_settings_are_named(overrides, message):
    with pytest.raises(ValueError, match=message):
        APG("cartpole", APGConfig(**overrides))


@pytest.mark.slow   # CLI CE-APG training twice (~40-50 s); the library resume test of CE-APG stays
def test_cli_trains_and_resumes_ce_apg(tmp_path):
    import json
    import subprocess
    import sys

    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "run"
    base = [sys.executable, "-m", "hybridctl.cli", "train", "ce-apg", "pendulum", "--preset", "reduced",
            "--apg-iterations", "1", "--horizon", "5", "--population", "3", "--elites", "2", "--out", str(out),
            "--eval-episodes", "2", "--quiet"]
    first = subprocess.run(base + ["--epochs", "1"], capture_output=True, text=True, timeout=300, cwd=root)
    assert first.returncode == 0, first.stderr[-2000:]
    second = subprocess.run(base + ["--epochs", "2", "--resume"], capture_output=True, text=True, timeout=300,
                            cwd=root)
    assert second.returncode == 0 and "resuming" in second.stdout, second.stderr[-2000:]
    record = json.loads((out / "eval.json").read_text())
    assert record["epochs"] == 2 and record["env_steps"] == 2 * 3 * 4 * 5 and record["episodes"] == 2
    assert "stabilised" in second.stdout


def test_init_goes_on_from_another_runs_policy_under_another_reward_with_force(tmp_path, capsys):
    """``--init``: the first run's policy, normalisation, settings and counters go on (--epochs is the
    total; flags change settings); a changed reward is refused without --force; the best policy is
    chosen anew under the new reward (the first run's best score, with an alive bonus of 10 per step,
    would otherwise stay the best)."""
    import json

    from hybridctl.cli import main
    from hybridctl.learn.apg import APG as Loaded

    first, second = tmp_path / "first", tmp_path / "second"
    small = ["--preset", "reduced", "--apg-iterations", "1", "--horizon", "5", "--population", "3", "--elites", "2",
             "--eval-episodes", "1", "--quiet"]
    assert main(["train", "ce-apg", "cartpole", *small, "--alive-bonus", "10", "--epochs", "1",
                 "--out", str(first)]) == 0
    again = ["train", "ce-apg", "cartpole", *small, "--init", str(first / "final"), "--alive-bonus", "0",
             "--linear-velocity-weight", "0.5", "--epochs", "3", "--out", str(second)]
    with pytest.raises(SystemExit) as refused:
        main(again)
    assert refused.value.code == 2 and "reward." in str(refused.value) and "--force" in str(refused.value)
    assert not (second / "final").exists()
    assert main(again + ["--force"]) == 0
    record = json.loads((second / "eval.json").read_text())
    assert record["epochs"] == 3 and record["env_steps"] == 3 * 3 * 4 * 5
    tuned = Loaded.load(second / "final", force=True)
    assert tuned.config.linear_velocity_weight == 0.5 and tuned.config.alive_bonus == 0.0
    assert tuned.system.reward_linear_velocity_weight == 0.5
    rows = (second / "progress.csv").read_text().splitlines()
    header = rows[0].split(",")
    best = max(float(r.split(",")[header.index("best_return")]) for r in rows[1:])
    assert [int(r.split(",")[0]) for r in rows[1:]] == [2, 3]
    assert record["best_training_return"] == pytest.approx(best) and best < 0   # no alive bonus: every return < 0


@pytest.mark.slow
def test_compiled_step_gives_the_eager_gradients():
    """torch.compile of the per-step work (about 30 s to compile here): the same gradients."""
    from hybridctl.learn.apg import compiled_policy_step

    system, pop, x0 = gru_case(members=3, seed=5)
    eager = member_gradients(pop, -population_returns(system, pop, x0, 6, 5)[0].mean(1))
    fused = member_gradients(pop, -population_returns(system, pop, x0, 6, 5, step=compiled_policy_step())[0].mean(1))
    assert torch.allclose(eager, fused, rtol=1e-9, atol=1e-9 * float(eager.abs().max()))


@pytest.mark.parametrize("takeover", [False, True])
def test_several_policy_steps_per_call_give_the_step_by_step_rollout(takeover):
    """The fused path's bookkeeping (chunks of policy steps, cut where truncation detaches): the same
    returns, gradients, final states and observation sums as one step per call, with and without the
    LQR takeover (eager ``policy_steps``, so this runs without compiling)."""
    from hybridctl.learn.apg import LQRTakeover, policy_steps

    system, pop, x0 = gru_case(members=3, seed=5)
    hand = LQRTakeover(system) if takeover else None
    for truncation in (None, 3):
        one = population_returns(system, pop, x0, 10, 5, truncation=truncation, takeover=hand)
        calls = []

        def counted(*args):
            calls.append(args[-1])
            return policy_steps(*args)

        many = population_returns(system, pop, x0, 10, 5, truncation=truncation, takeover=hand, steps=counted,
                                  steps_per_call=4)
        assert calls == ([4, 4, 2] if truncation is None else [3, 3, 3, 1])
        assert torch.equal(one[0], many[0]) and torch.equal(one[1], many[1])
        for a, b in zip(one[3], many[3]):
            assert torch.equal(torch.as_tensor(a), torch.as_tensor(b))
        g_one = member_gradients(pop, -one[0].mean(1))
        g_many = member_gradients(pop, -many[0].mean(1))
        assert torch.equal(g_one, g_many)


@pytest.mark.slow
def test_compiled_policy_steps_give_the_eager_gradients():
    """Several policy steps per compiled call (``APGConfig.compile_steps``): the eager gradients."""
    from hybridctl.learn.apg import compiled_policy_steps

    system, pop, x0 = gru_case(members=3, seed=5)
    eager = member_gradients(pop, -population_returns(system, pop, x0, 6, 5)[0].mean(1))
    fused = member_gradients(pop, -population_returns(system, pop, x0, 6, 5, steps=compiled_policy_steps(),
                                                      steps_per_call=3)[0].mean(1))
    assert torch.allclose(eager, fused, rtol=1e-9, atol=1e-9 * float(eager.abs().max()))


def test_records_before_compile_steps_resume_one_compiled_call_per_step():
    assert APGConfig.upgrade_recorded({"compile": True})["compile_steps"] == 1
    assert APGConfig.upgrade_recorded({"compile_steps": 10})["compile_steps"] == 10
    assert APGConfig().compile_steps is None                                  # about 40 integrator steps a call
    from hybridctl.learn.apg.compiled import policy_steps_per_call
    assert [policy_steps_per_call(s) for s in (1, 4, 5, 20, 80)] == [40, 10, 8, 2, 1]
    with pytest.raises(ValueError, match="compile_steps"):
        APGConfig(compile_steps=0).validate()


def test_compile_auto_compiles_long_runs_only_and_reads_the_former_true_false():
    """``APGConfig.compile``: "auto" (the default) compiles a run of at least APG_AUTO_COMPILE_MIN_STEPS policy
    steps and falls back to eager if compiling fails; "on" raises instead; "off" and short runs stay eager.
    Building a problem compiles nothing (that happens at the first call), so this is cheap."""
    from hybridctl.learn.apg.compiled import APG_AUTO_COMPILE_MIN_STEPS
    from hybridctl.learn.apg.core import APGProblem, policy_step
    from hybridctl.systems.compiled import LazyCompiled

    system = systems.load("pendulum")
    short = APGConfig.preset("reduced", method="papg", epochs=1, population=2, elites=1, horizon=20)
    assert short.compile == "auto" and short.total_policy_steps(2) < APG_AUTO_COMPILE_MIN_STEPS
    problem = APGProblem.build(system, short, 2)
    assert problem.step is policy_step and problem.steps is None
    epochs = -(-APG_AUTO_COMPILE_MIN_STEPS // short.total_policy_steps(2))      # just long enough
    for mode, strict in (("auto", False), ("on", True)):
        config = APGConfig.preset("reduced", method="papg", epochs=epochs, population=2, elites=1, horizon=20,
                                  compile=mode)
        problem = APGProblem.build(system, config, 2)
        assert isinstance(problem.steps, LazyCompiled) and problem.steps.strict is strict
    on_short = APGProblem.build(system, APGConfig.preset("reduced", method="papg", epochs=1, population=2, elites=1,
                                                         horizon=20, compile="on"), 2)
    assert isinstance(on_short.steps, LazyCompiled)                              # "on" compiles any run
    off = APGConfig.preset("reduced", method="papg", epochs=epochs, population=2, elites=1, horizon=20, compile="off")
    assert APGProblem.build(system, off, 2).step is policy_step
    assert APGConfig(compile=True).compile == "on" and APGConfig(compile=False).compile == "off"
    assert APGConfig(**APGConfig.upgrade_recorded({"compile": False})).compile == "off"
    with pytest.raises(ValueError, match="compile must be one of"):
        APGConfig(compile="sometimes").validate()


def test_fig_7_1_diagnostics_gradient_norm_grows_with_horizon_and_landscape_probe():
    from hybridctl.learn.apg import gradient_norms_by_horizon, returns_along_direction

    system = systems.load("acrobot", reward__kind="angle_squared")
    pop = PolicyPopulation.gru(6, 1, system.action_limit, members=2, dtype=torch.float64, init_std=0.3,
                               generator=torch.Generator().manual_seed(6))
    x0 = torch.as_tensor(system.initial_state.nominal[None] + np.array([[0.01, 0.0, 0.0, 0.0]]))
    rows = gradient_norms_by_horizon(system, pop, x0, [5, 150], substeps=4)
    assert [r["horizon"] for r in rows] == [5, 150]
    assert all(b > 10 * a for a, b in zip(rows[0]["grad_norm"], rows[1]["grad_norm"]))
    d = torch.randn(pop.n_params, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    before = pop.to_flat()
    landscape = returns_along_direction(system, pop, x0, 20, 4, d, [-0.1, 0.0, 0.1])
    assert torch.equal(pop.to_flat(), before) and len(landscape) == 3
    centre = float(population_returns(system, pop, x0, 20, 4)[0][0].detach().mean())
    assert math.isclose(landscape[1], centre, rel_tol=1e-12)
    assert landscape[0] != landscape[2]


# ----------------------------------------------------------------------------- LQR takeover (switched training)

def test_lqr_takeover_applies_the_gate_hysteresis_and_the_saturated_lqr():
    from hybridctl.learn.apg import LQRTakeover
    from hybridctl.systems import control

    system = systems.load("cartpole")
    takeover = LQRTakeover(system)
    K, S = system.lqr()
    goal = torch.as_tensor(system.goal)
    near = goal + torch.tensor([0.01, 0.005, 0.0, 0.0], dtype=torch.float64)       # V well below the on level
    far = goal + torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64)           # V far above the off level
    scale = system.gate.cost_scale
    v_mid = scale * 0.5 * (math.log(1 / system.gate.on) + math.log(1 / system.gate.off))
    between = goal + torch.tensor([0.0, math.sqrt(v_mid / S[1, 1]), 0.0, 0.0], dtype=torch.float64)
    x = torch.stack([near, far, between, between])
    mode = torch.tensor([False, True, False, True])
    u_policy = torch.full((4, 1), 3.0, dtype=torch.float64)
    command, new_mode = takeover(x, mode, u_policy)
    assert new_mode.tolist() == [True, False, False, True]          # on, off, and the hysteresis band keeps the mode
    lqr = control.saturate(control.lqr_command(system.state_error(x), torch.as_tensor(K)), system.action_limit)
    assert torch.allclose(command[0], lqr[0]) and torch.allclose(command[3], lqr[3])
    assert command[1].item() == 3.0 and command[2].item() == 3.0


def test_takeover_rollout_balances_from_the_gate_region_and_counts_in_the_return():
    """From inside the gate's region the LQR holds the pole whatever the policy commands; without the
    takeover the same (random) policy lets it fall."""
    config = small("papg", takeover="lqr", init_std=0.5, horizon=40, start_noise=None)
    agent = APG("cartpole", config)
    system = agent.system
    x0 = torch.as_tensor(system.goal + np.array([0.02, 0.01, 0.0, 0.0]))[None].repeat(2, 1)
    with torch.no_grad():
        switched, *_ = population_returns(system, agent.pop, x0, 40, agent.substeps, takeover=agent.takeover)
        free, *_ = population_returns(system, agent.pop, x0, 40, agent.substeps)
    assert switched.max() > -1.0                        # held near upright: the reward is ~0 every step
    assert free.min() < 10 * switched.min()            # the random policy alone drops the pole


# ----------------------------------------------------------------------------- one class per method

def test_one_class_per_method_chosen_once_by_the_registry(tmp_path):
    import copy

    from hybridctl.learn.apg import CEAPG, CEM, METHOD_CLASSES, METHODS, PAPG, ShortHorizonAPG

    assert tuple(METHOD_CLASSES) == METHODS
    assert {m: c.__name__ for m, c in METHOD_CLASSES.items()} == {
        "apg": "APG", "shapg": "ShortHorizonAPG", "papg": "PAPG", "cem": "CEM", "ce-apg": "CEAPG"}
    for method, cls in METHOD_CLASSES.items():
        agent = APG("cartpole", small(method, short_horizon=5))
        assert type(agent) is cls and isinstance(agent, APG) and agent.algorithm_name == "APG"
        assert agent.K == (1 if method == "apg" else 3)
        assert agent.policy()  # the method's default member
        assert agent.evaluate(episodes=1)["which"] == ("mean" if method in ("cem", "ce-apg") else "best")
        assert type(copy.deepcopy(agent)) is cls                # copies rebuild the method's class
    assert type(APG("cartpole")) is CEAPG                     # APGConfig's default method, as before
    assert type(PAPG("cartpole")) is PAPG and PAPG("cartpole").config.method == "papg"
    assert type(APG("cartpole", small("apg"), method="cem")) is CEM
    assert type(ShortHorizonAPG("cartpole", small("shapg", short_horizon=5))) is ShortHorizonAPG
    with pytest.raises(ValueError, match="PAPG runs method 'papg', not 'ce-apg'"):
        PAPG("cartpole", small("ce-apg"))
    trained = APG("cartpole", small("papg", epochs=1)).learn(out=tmp_path, progress=False)
    loaded = APG.load(tmp_path / "final")
    assert type(loaded) is PAPG and torch.equal(loaded.best, trained.best)
    assert type(PAPG.load(tmp_path / "final")) is PAPG


def test_no_branch_on_a_method_name_in_the_algorithm():
    """What differs between the methods lives in their classes (methods.py) and the registry."""
    import re
    from pathlib import Path

    import hybridctl.learn.apg as package

    for path in Path(package.__file__).parent.glob("*.py"):
        source = path.read_text()
        assert not re.search(r"method\s*(==|!=|in\s*\()", source.replace("METHOD_CLASSES[m].method == m", "")), path


def test_a_chunk_of_members_is_a_function_of_arrays():
    """split_apg_phase over chunks gives the whole population's phase; neither touches its inputs."""
    from hybridctl.learn.apg import apg_phase, split_apg_phase
    from hybridctl.parallel import SerialBackend

    agent = APG("cartpole", small("papg", population=3, apg_iterations=2))
    theta, adam = agent.members.clone(), agent.adam
    whole = apg_phase(agent.problem, theta, adam, 1e-2, 0, 0, agent.config.horizon)

    class TwoChunks(SerialBackend):
        workers = 2
    split = split_apg_phase(TwoChunks(), agent.problem, "cartpole", theta, adam, 1e-2, 0, 0, agent.config.horizon)
    # Equal up to the last bits, not bit for bit: the matrix kernel a CPU's BLAS picks depends on the
    # number of rows (bit-equal on an Intel AVX-512 machine; 1.4e-17 apart on an AMD EPYC). A chunk of
    # the wrong members, a lost Adam state or a wrong start would differ by far more than 1e-12.
    close = dict(rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(split.theta, whole.theta, **close)
    torch.testing.assert_close(split.returns, whole.returns, **close)
    torch.testing.assert_close(split.adam.m, whole.adam.m, **close)
    assert torch.equal(split.adam.t, whole.adam.t)
    assert (split.iterations, split.env_steps, split.nan_grads) == (whole.iterations, whole.env_steps, 0)
    assert torch.allclose(split.obs_sums[0], whole.obs_sums[0], rtol=1e-12) and split.obs_sums[2] == whole.obs_sums[2]
    assert int(adam.t.sum()) == 0 and torch.equal(theta, agent.members)     # the inputs are untouched
    assert agent.iterations == agent.env_steps == 0                          # and so is the learner
