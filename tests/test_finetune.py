"""Fine-tuning by direct policy search (thesis Ch. 6, Alg. 8): the update, seeds, backends, resume,
the dimension reward, our own checkpoints as sources, the CLI and bad input."""

import copy
import json

import numpy as np
import pytest
import torch

from hybridctl.analysis.postprocess import PostProcessor
from hybridctl.cli import main
from hybridctl.envs.toy import PointReach, point_reach
from hybridctl.learn.checkpoint import CheckpointError
from hybridctl.learn.finetune import FineTune, FineTuneConfig, wilson_interval
from hybridctl.learn.finetune_sources import TunablePolicy, parse_source
from hybridctl.systems import load as load_system

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SSAC = "ssac:models/policies/ssac-acrobot"


def pd_module(seed=0):
    """A small tanh MLP for the 4-D point (actions in [-1, 1])."""
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2), torch.nn.Tanh())


def tuner(**overrides):
    cfg = dict(updates=3, n_directions=4, backend="serial", eval_episodes=4, chunk_size=3)
    cfg.update(overrides)
    return FineTune(point_reach, pd_module(), FineTuneConfig(**cfg))


def episode_return(module, seed):
    """An independent rollout: one PointReach episode, deterministic actions, summed rewards."""
    env = PointReach()
    obs, _ = env.reset(seed=seed)
    total, done, steps = 0.0, False, 0
    while not done:
        steps += 1
        with torch.no_grad():
            a = module(torch.as_tensor(obs, dtype=torch.float32)).numpy()
        obs, r, term, trunc, _ = env.step(a)
        total += r
        done = term or trunc
    return total, steps


def test_one_update_is_algorithm_8_with_the_authors_step():
    t = tuner(updates=1)
    theta0 = t.theta.copy()
    directions, seeds = t.draws(0)
    alpha, sigma = t.config.schedule(0)
    returns, lengths = [], 0
    for d, s in zip(directions, seeds):
        pair = []
        for sign in (1.0, -1.0):
            m = copy.deepcopy(t.tunable.module)
            torch.nn.utils.vector_to_parameters(torch.as_tensor(theta0 + sign * sigma * d, dtype=torch.float32),
                                                m.parameters())
            total, steps = episode_return(m, s)
            pair.append(total)
            lengths += steps
        returns.append(pair)
    r = np.array(returns)
    expected = theta0 + alpha / (4 * r.std() + 1e-6) * ((r[:, 0] - r[:, 1]) @ directions)
    t.learn(progress=False)
    np.testing.assert_allclose(t.theta, expected, rtol=1e-5, atol=1e-6)
    assert t.env_steps == lengths and t.update == 1


def test_schedules_are_linear_from_the_thesis_values():
    cfg = FineTuneConfig()
    assert cfg.schedule(0) == pytest.approx((0.02, 0.025))
    assert cfg.schedule(199) == pytest.approx((0.002, 0.0025))
    assert cfg.schedule(99) == pytest.approx((0.02 - 0.018 * 99 / 199, 0.025 - 0.0225 * 99 / 199))
    assert (cfg.updates, cfg.n_directions, cfg.select, cfg.eval_episodes) == (200, 64, "action", 100)


def test_same_seed_same_result_on_serial_and_processes_and_another_seed_differs():
    a = tuner().learn(progress=False)
    b = tuner(backend="processes", workers=2).learn(progress=False)
    c = tuner(seed=1).learn(progress=False)
    np.testing.assert_array_equal(a.theta, b.theta)
    assert not np.array_equal(a.theta, c.theta)


def test_resume_continues_exactly(tmp_path):
    whole = tuner(updates=4).learn(progress=False)
    part = tuner(updates=4, checkpoint_every=1)
    part.learn(total=2, out=tmp_path, progress=False)
    resumed = tuner(updates=4).learn(out=tmp_path, resume=True, progress=False)
    np.testing.assert_array_equal(resumed.theta, whole.theta)
    loaded = FineTune.load(tmp_path / "final", system=point_reach, policy=pd_module())
    np.testing.assert_array_equal(loaded.theta, whole.theta)
    np.testing.assert_allclose(loaded.predict(np.ones(4)), whole.predict(np.ones(4)))


def test_fine_tuning_improves_a_poor_policy_and_evaluate_reports_failures():
    t = tuner(updates=15, n_directions=8)
    before = t.evaluate(20, theta=t.theta0)
    t.learn(progress=False)
    after = t.evaluate(20)
    assert after["mean_return"] > before["mean_return"]
    assert 0.0 <= after["failure_rate"] <= 1.0
    lo, hi = after["failure_interval"]
    assert lo <= after["failure_rate"] <= hi


def test_selection_last_perturbs_only_the_last_layer():
    t = tuner(select="last", updates=2)
    assert t.names == ["2.weight", "2.bias"] and t.n_params == 18
    first = t.tunable.module[0].weight.detach().clone()
    t.learn(progress=False)
    t._write_theta()
    assert torch.equal(t.tunable.module[0].weight, first)


def test_dimension_reward_settings_and_too_short_episodes():
    author = FineTuneConfig(reward="mesh-mean").postprocessor(4, normalised=True)
    assert (author.scale_factor, author.initial_box, author.transient_steps, author.clip_low) == (1.2, 1.0, 0, 0.0)
    assert author.mean == (0.0,) * 4 and author.std == (1.0,) * 4
    ch4 = FineTuneConfig(reward="mesh-mean", dimension_settings="ch4").postprocessor(4, normalised=True)
    assert (ch4.scale_factor, ch4.initial_box, ch4.transient_steps, ch4.clip_low) == (1.5, 0.01, 200, 1.0)
    short = np.random.default_rng(0).normal(size=(5, 4))
    value, info = author(short, 10.0)
    assert value == pytest.approx(10.0 / 2.0) and "too short" in info["reason"]
    value, info = author(short, -10.0)
    assert value == pytest.approx(-20.0) and np.isfinite(value)
    constant = np.zeros((50, 4))   # dimension 0: never a division by zero
    value, info = PostProcessor("mesh-mean", transient_steps=0, clip_low=0.0)(constant, 5.0)
    assert np.isfinite(value) and value == pytest.approx(2.5)


def test_dimension_reward_changes_training_returns():
    t = tuner(reward="mesh-mean", updates=1)
    t.learn(progress=False)
    row = t.history[-1]
    assert row["mean_return"] != row["mean_raw_return"] and 0 <= row["mean_dimension"] <= 2


def test_ssac_source_fine_tunes_the_swing_up_inside_the_switched_controller():
    t = FineTune("acrobot", SSAC, updates=1, n_directions=2, backend="serial")
    before = t.evaluate(8, theta=t.theta0)
    assert before["success_rate"] == 1.0 and before["mean_return"] > 85
    plain = FineTune("acrobot", SSAC.replace("ssac:", "sac:"), updates=1, n_directions=2, backend="serial")
    assert plain.evaluate(8)["success_rate"] < 1.0   # the swing-up alone does not balance
    t.learn(progress=False)
    assert t.update == 1 and t.env_steps == 4 * 50


def test_a_system_checkpoint_is_tuned_on_the_reward_and_starts_it_was_trained_on():
    """ssac-cartpole was trained with reward.kind=upright_centered and starts on the whole circle
    (config.json's system overrides): fine-tuning rolls out that task, not the plain spec's
    tip-height reward, which pays for a pole held up over a cart that drives away."""
    from hybridctl.systems import load

    t = FineTune("cartpole", "ssac:models/policies/ssac-cartpole", updates=1, n_directions=2, backend="serial")
    assert t.tunable.system_overrides["reward.kind"] == "upright_centered"
    trained = load("cartpole", **t.tunable.system_overrides)
    plain = load("cartpole")
    assert trained.spec.get("reward.kind") == "upright_centered" != plain.spec.get("reward.kind")
    tuned = t.evaluate(8, theta=t.theta0)
    plain_t = FineTune("cartpole", "ssac:models/policies/ssac-cartpole", updates=1, n_directions=2, backend="serial")
    plain_t.tunable.system_overrides = {}
    assert tuned["mean_return"] != pytest.approx(plain_t.evaluate(8, theta=plain_t.theta0)["mean_return"])


def test_wilson_interval():
    lo, hi = wilson_interval(0, 300)
    assert lo == 0.0 and hi == pytest.approx(0.01264, abs=1e-4)
    lo, hi = wilson_interval(30, 100)
    assert lo == pytest.approx(0.2189, abs=1e-3) and hi == pytest.approx(0.3958, abs=1e-3)


@pytest.mark.parametrize("source, message", [
    ("foo", "KIND:PATH"), ("pkl:x", "KIND:PATH"), ("sb3:", "KIND:PATH")])
def test_bad_sources_are_named(source, message):
    with pytest.raises(ValueError, match=message):
        parse_source(source)


def test_bad_config_values_name_the_field():
    with pytest.raises(ValueError, match="select"):
        FineTuneConfig(select="value").validate()
    with pytest.raises(ValueError, match="n_directions"):
        FineTuneConfig(n_directions=0).validate()
    with pytest.raises(ValueError, match="env must be one of"):
        FineTune("Pendulum-v1", SSAC)


def test_cli_finetune_reports_before_and_after_and_resumes(tmp_path, capsys):
    out = tmp_path / "ft"
    args = ["finetune", "acrobot", "--policy", SSAC, "--updates", "2", "--directions", "2", "--eval-episodes", "4",
            "--backend", "serial", "--out", str(out), "--quiet"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "before return" in text and "after  return" in text and "success 100.0 %" in text
    report = json.loads((out / "report.json").read_text())
    assert report["updates"] == 2 and report["env_steps"] == 2 * 2 * 2 * 50
    assert (out / "finetune.png").stat().st_size > 0 and (out / "final" / "model.pt").exists()
    assert main([*args[:5], "3", *args[6:], "--resume"]) == 0
    assert json.loads((out / "report.json").read_text())["updates"] == 3


@pytest.mark.parametrize("argv, message", [
    (["finetune", "acrobot", "--policy", "nope"], "KIND:PATH"),
    (["finetune", "Pendulum-v1", "--policy", SSAC], "env must be one of"),
    (["finetune", "acrobot", "--policy", "ssac:/no/such/dir"], "/no/such/dir"),
])
def test_cli_bad_input_exits_2_without_traceback(argv, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(tmp_path / "x"), "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.slow   # kills a worker mid-run (~30-45 s); tests/test_ars.py keeps a dead-worker check in `make test`
def test_a_killed_worker_neither_hangs_nor_changes_the_result():
    """Tasks carry the module as plain bytes: after a worker is killed the rebuilt pool gets them
    (torch's shared-memory hand-over hung here), and the run equals the serial one."""
    import os
    import signal
    import time

    from hybridctl.parallel import make_backend

    reference = tuner(updates=3, n_directions=8, chunk_size=2).learn(progress=False)
    t = tuner(updates=3, n_directions=8, chunk_size=2)
    with make_backend("processes", 2) as backend:
        t.learn(total=1, progress=False, backend=backend)
        pid = next(iter(backend._pool._processes.values())).pid
        os.kill(pid, signal.SIGKILL)   # the next map finds the pool broken, rebuilds it and reruns
        time.sleep(0.5)
        t.learn(total=3, progress=False, backend=backend)
    np.testing.assert_array_equal(t.theta, reference.theta)


@pytest.mark.xdist_group("ray")
def test_ray_gives_the_serial_result(local_ray):
    a = tuner().learn(progress=False)
    b = tuner(backend="ray", workers=2).learn(progress=False)
    np.testing.assert_array_equal(a.theta, b.theta)


@pytest.mark.parametrize("policy", ["linear", "mlp:8"])
def test_ars_source_acts_like_the_ars_agent_with_its_frozen_statistics(policy, tmp_path):
    from hybridctl.learn import ARS, ARSConfig

    ars = ARS("Pendulum-v1", ARSConfig(n_directions=4, top_directions=2, backend="serial", policy=policy,
                                       episode_steps=50))
    ars.learn(total=2, out=tmp_path, progress=False)
    t = FineTune("Pendulum-v1", f"ars:{tmp_path / 'final'}", updates=1, n_directions=2, backend="serial")
    obs = np.random.default_rng(0).uniform(-1, 1, size=(10, 3))
    expected = np.stack([ars.predict(o) for o in obs])
    np.testing.assert_allclose(t.predict(obs), expected, atol=1e-9)
    t.learn(progress=False)
    assert not np.allclose(t.predict(obs), expected)


def test_report_figures_draw_rates_at_zero_and_one(tmp_path):
    """The Ch. 6 figures accept intervals at the ends (a rate of 0 % whose stored lower end is 1e-19)."""
    from hybridctl.viz.finetune import plot_dimension_table, plot_failure_table, plot_finetune_report, plot_return_table

    def ev(rate, lo, hi):
        return {"episodes": 300, "mean_return": 100.0, "std_return": 5.0, "returns": [95.0, 105.0],
                "failure_rate": rate, "failure_interval": [lo, hi], "mean_dimension": 2.0, "std_dimension": 0.1}

    rows = [{"label": "a", "before": ev(0.0, 8.7e-19, 0.0126), "after": ev(1.0, 0.987, 1.0),
             "continued": ev(0.5, 0.44, 0.56)}]
    history = [{"update": 1, "mean_return": 1.0, "mean_raw_return": 2.0}]
    for name, draw in (("r.png", lambda p: plot_return_table(rows, p)), ("f.png", lambda p: plot_failure_table(rows, p)),
                       ("d.png", lambda p: plot_dimension_table(rows, p)),
                       ("x.png", lambda p: plot_finetune_report(rows[0]["before"], rows[0]["after"], history, p))):
        draw(tmp_path / name)
        assert (tmp_path / name).stat().st_size > 5000


# ----------------------------------------------------------------------------- APG-family sources

@pytest.fixture(scope="module")
def tiny_papg(tmp_path_factory):
    """A tiny float64 PAPG-GRU trained through the LQR takeover on the cart-pole (1 epoch; 0.1 s decisions,
    not the spec's 0.05), saved."""
    from hybridctl.learn.apg import APG, APGConfig
    config = APGConfig(method="papg", horizon=12, batch=2, apg_iterations=2, population=2, elites=1, rank_window=1,
                       epochs=1, dtype="float64", takeover="lqr", control_period=0.1, start_noise=0.2,
                       init_std=0.3)
    out = tmp_path_factory.mktemp("papg")
    with torch.random.fork_rng():
        torch.set_num_threads(1)
        APG("cartpole", config).learn(out=out, progress=False)
    return out / "final"


def test_apg_source_rolls_out_what_apg_trains_recurrent_through_its_takeover(tiny_papg):
    """The fine-tuning's episodes of an APG-family checkpoint are the APG rollout (GRU state carried,
    the cost-to-go gate + LQR at every integrator step, the checkpoint's decision period, reward and
    starts): the same returns to 1e-9, on serial and on worker processes (the policy travels pickled)."""
    from hybridctl.learn.apg import APG
    from hybridctl.learn.apg.core import population_returns
    from hybridctl.parallel import make_backend
    from hybridctl.systems import load

    t = FineTune("cartpole", f"papg:{tiny_papg}", updates=1, n_directions=2, backend="serial")
    agent = APG.load(tiny_papg, device="cpu")
    assert t.tunable.decision_period == agent.period == 0.1 != load("cartpole").swingup_period
    assert t.tunable.system_overrides["initial_state__high"] == [0.2] * 4
    hanging = dict(t.tunable.system_overrides)
    # hanging down (the checkpoint's starts: the GRU and its state act) and just off upright (the gate fires
    # and the LQR holds what the tiny policy alone drops)
    upright = {**hanging, "initial_state__nominal": load("cartpole").goal.tolist(),
               "initial_state__low": [-0.01] * 4, "initial_state__high": [0.01] * 4}
    seeds, horizon = [3, 4, 5], 60
    rows = np.repeat(t.theta0[None], len(seeds), axis=0)
    for overrides, gate_acts in ((hanging, False), (upright, True)):
        t.tunable.system_overrides = overrides
        system = load("cartpole", **overrides)
        x0 = torch.as_tensor(np.concatenate([system.sample_initial_states(1, np.random.default_rng(s)) for s in seeds]))
        with torch.no_grad():
            expected, *_ = population_returns(agent.system, agent.policy().population, x0[None], horizon,
                                              agent.substeps, agent.config.observation, takeover=agent.takeover)
            free, *_ = population_returns(agent.system, agent.policy().population, x0[None], horizon,
                                          agent.substeps, agent.config.observation)
        # worker processes once (the policy travels pickled, its system rebuilt there), where the GRU acts
        backends = ("serial",) if gate_acts else ("serial", "processes")
        for backend in (make_backend(name, workers=2) for name in backends):
            try:
                got = t._rollouts(rows, seeds, backend, t._postprocessor(), max_steps=horizon)
            finally:
                backend.close()
            assert [r["raw_return"] for r in got] == pytest.approx(expected[0].tolist(), abs=1e-9)
        assert np.allclose(expected[0].numpy(), free[0].numpy()) != gate_acts


def test_apg_source_fine_tunes_saves_and_drives_drake(tiny_papg, tmp_path):
    """learn / predict (recurrent: action and state) / load, and the fine-tuned checkpoint as a Drake
    controller: the recurrent swing-up under the spec's cost-to-go gate at the checkpoint's period."""
    from hybridctl.experiments.controllers import controller_parts

    t = FineTune("cartpole", f"papg:{tiny_papg}", updates=2, n_directions=2, backend="serial", eval_episodes=2)
    t.learn(out=tmp_path, progress=False)
    assert t.update == 2 and t.env_steps == 2 * 2 * 2 * 100   # 10 s episodes of 0.1 s decisions
    assert not np.array_equal(t.theta, t.theta0)
    action, state = t.predict(np.zeros(4))
    assert action.shape == (1,) and state.shape == (t.tunable.module.policy.hidden_dim,)
    again, _ = t.predict(np.zeros(4), state=state)
    assert not np.array_equal(action, again)   # the state carries over
    parts = controller_parts(load_system("cartpole"), f"finetune:{tmp_path / 'final'}")
    from hybridctl.systems.switched import CostToGoGate
    assert type(parts.gate) is CostToGoGate and parts.decision_period == 0.1 and hasattr(parts.swingup, "initial_state")
    loaded = FineTune.load(tmp_path / "final")
    assert np.array_equal(loaded.theta, t.theta)


def test_apg_source_needs_the_takeover_and_its_own_system(tmp_path):
    from hybridctl.learn.apg import APG, APGConfig
    config = APGConfig(method="papg", horizon=4, batch=1, apg_iterations=1, population=2, elites=1, rank_window=1,
                       epochs=1, dtype="float64", takeover="none")
    APG("cartpole", config).learn(out=tmp_path, progress=False)
    with pytest.raises(ValueError, match="--takeover lqr"):
        FineTune("cartpole", f"papg:{tmp_path / 'final'}")
    from hybridctl.learn import CheckpointError
    with pytest.raises(CheckpointError, match="trained on system 'cartpole', but this system is 'acrobot'"):
        FineTune("acrobot", f"papg:{tmp_path / 'final'}")   # the plant check of every deployed checkpoint


def test_a_fine_tuned_checkpoint_loads_from_any_working_folder(tmp_path, monkeypatch):
    """Its source is recorded as given (e.g. models/policies/NAME, from the repository root): loading from
    another folder finds it above the checkpoint (a committed record) or among the package's own models."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    t = FineTune("acrobot", SSAC, updates=1, n_directions=2, backend="serial", eval_episodes=2)
    t.learn(out=tmp_path / "ft", progress=False)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    outside = FineTune.load(tmp_path / "ft" / "final")          # the package's shipped model
    assert outside.tunable.source == SSAC and np.array_equal(outside.theta, t.theta)
    committed = FineTune.load(root / "results" / "matrix" / "finetune" / "ceapg-gru-acrobot" / "final")
    assert committed.tunable.source == "ce-apg:models/policies/ceapg-gru-acrobot" and committed.update == 100
    with pytest.raises(CheckpointError, match="no checkpoint directory at models/policies/nope"):
        FineTune.load(_with_source(tmp_path / "ft" / "final", tmp_path / "broken", "ssac:models/policies/nope"))


def _with_source(final, copy_to, source):
    """A copy of the checkpoint ``final`` whose config.json names another source."""
    import shutil

    shutil.copytree(final, copy_to)
    meta = json.loads((copy_to / "config.json").read_text())
    meta["source"] = source
    (copy_to / "config.json").write_text(json.dumps(meta))
    return copy_to
