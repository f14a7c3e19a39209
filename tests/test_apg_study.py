"""The Ch. 7 study (Tables 7.1 / 7.2 direction) and its figures: one scorer for every learner,
resumable records, and the Fig. 7.1 plots."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from hybridctl.experiments.apg_study import (StudySettings, apg_controller, held_out_starts, rollout_metrics, run_one,
                                             summarize, swingup_alone, task_system, zero_policy_baseline)
from hybridctl.systems.switched import AlwaysGate, CostToGoGate, NeverGate, SwitchedController, ZeroSwingup

TINY = StudySettings(apg_iterations=2, epochs=2, sac_steps=200, sb3_steps=200, eval_episodes=3, compile=False)


pytestmark = pytest.mark.usefixtures("one_torch_thread")   # tests/conftest.py


def test_rollout_metrics_score_a_held_pole_as_stabilised_and_a_hanging_one_as_not():
    system = task_system("cartpole")
    K, _ = system.lqr()
    lqr = lambda x: -(system.state_error(x) @ torch.as_tensor(K).T)   # noqa: E731
    near = np.tile(system.goal, (2, 1)) + np.array([[0.05, 0.02, 0, 0], [-0.05, -0.02, 0, 0]])
    held = rollout_metrics(system, swingup_alone(system, lqr, 0.05), near, 100)
    assert held["stabilised"] == 1.0 and held["upright"] == 1.0 and held["mean_return"] > -5
    # the same LQR as the switched controller's own (AlwaysGate): the LQR acts from the first gate evaluation on
    always = SwitchedController.for_system(system, swingup=ZeroSwingup(), gate=AlwaysGate(), decision_period=0.05)
    assert rollout_metrics(system, always, near, 100)["stabilised"] == 1.0
    hanging = zero_policy_baseline("cartpole", TINY)
    assert hanging["stabilised"] == 0.0 and hanging["mean_return"] < -390     # 100 steps of 2 (1 - cos pi) = 4


def test_rollout_metrics_keep_a_diverging_row_out_of_the_return():
    """A row that runs to Inf / NaN (``on_divergence="propagate"``, as the APG family's own rollouts) is
    counted as diverged and left out of the return; the others are scored."""
    system = task_system("cartpole")
    x0 = np.tile(system.initial_state.nominal, (3, 1))
    x0[1, 3] = np.inf
    metrics = rollout_metrics(system, swingup_alone(system, ZeroSwingup(), 0.05), x0, 20)
    assert metrics["diverged"] == 1 and np.isfinite(metrics["mean_return"]) and metrics["episodes"] == 3


def test_an_apg_run_is_scored_under_the_controller_it_trained_through():
    """``takeover="lqr"``: the run's recurrent swing-up under the takeover's own controller (the spec's
    cost-to-go gate, every integrator step); without it, the swing-up alone (NeverGate)."""
    from hybridctl.learn.apg import APG, APGConfig

    system = task_system("cartpole")
    small = dict(method="papg", horizon=10, batch=2, population=2, elites=1, apg_iterations=1, epochs=1)
    switched = apg_controller(APG(system, APGConfig(takeover="lqr", **small)))
    assert isinstance(switched.gate, CostToGoGate) and switched.gate_period == system.dt
    assert switched.decision_period == system.swingup_period
    alone = apg_controller(APG(system, APGConfig(**small)))
    assert isinstance(alone.gate, NeverGate)
    x0 = held_out_starts(system, 2, 1)
    assert rollout_metrics(system, switched, x0, 10)["episodes"] == 2


def test_held_out_starts_are_the_spec_distribution_and_reproduce():
    system = task_system("cartpole")
    a, b = held_out_starts(system, 5, 1), held_out_starts(system, 5, 1)
    assert np.array_equal(a, b) and not np.array_equal(a, held_out_starts(system, 5, 2))
    assert np.all(np.abs(a[:, 0]) <= 0.5) and np.all(np.abs(a[:, 1]) <= 0.3)


@pytest.mark.parametrize("method", ["papg", "sac"])
def test_run_one_writes_a_record_and_resumes_by_skipping(tmp_path, method):
    record = run_one(method, "cartpole", 0, tmp_path / method, TINY, command="test")
    assert (tmp_path / method / "record.json").is_file()
    assert record["eval"]["episodes"] == 3 and record["interactions"] > 0
    if method == "papg":
        assert record["interactions"] == 8 * 4 * 100 * 4 and record["best_training_return"] is not None
    again = run_one(method, "cartpole", 0, tmp_path / method, TINY)
    assert again["wall_time_s"] == record["wall_time_s"]                         # read back, not retrained
    rows = summarize([record, again])
    assert rows[0]["seeds"] == 2 and rows[0]["method"] == method
    assert rows[0]["train_wall_time_s"] == record["train_wall_time_s"]


@pytest.mark.parametrize("method", ["sb3-ppo", "sb3-sac"])
def test_sb3_learners_train_through_the_gym_wrapper_and_are_scored_by_the_same_code(tmp_path, method,
                                                                                     monkeypatch):
    pytest.importorskip("stable_baselines3")
    import tempfile

    from hybridctl.learn import load_sb3

    monkeypatch.delenv("SB3_LOGDIR", raising=False)     # SB3's default would make a folder in the temp dir
    litter = lambda: set(Path(tempfile.gettempdir()).glob("SB3-*"))   # noqa: E731
    before = litter()
    record = run_one(method, "acrobot", 0, tmp_path / method, TINY, command="test")
    assert litter() == before
    assert record["eval"]["episodes"] == 3 and record["config"]["hyperparameters"] == "SB3 defaults"
    assert record["interactions"] >= 200          # PPO collects whole rollouts of n_steps (2048)
    agent = load_sb3(tmp_path / method / "run" / "model.zip")      # our reader: no unpickling
    system = task_system("acrobot")
    x0 = held_out_starts(system, 3, TINY.eval_seed)
    action, _ = agent.predict(x0)
    assert action.shape == (3, 1) and np.all(np.abs(action) <= system.action_limit)


def test_every_study_method_has_one_trainer():
    from hybridctl.experiments.apg_study import STUDY_METHODS, TRAINERS

    assert tuple(TRAINERS) == STUDY_METHODS


def test_unknown_names_are_listed():
    with pytest.raises(ValueError, match="known: ce-apg, papg"):
        run_one("ppo", "cartpole", 0, "unused", TINY)
    with pytest.raises(ValueError, match="known: cartpole, acrobot"):
        task_system("hopper")


def test_fig_7_1_and_comparison_plots_write_pngs_and_reject_empty_input(tmp_path):
    from hybridctl.viz import plot_gradient_norms, plot_method_comparison, plot_return_landscape

    assert plot_return_landscape([-1, 0, 1], {"T = 10": [1, 2, 1]}, tmp_path / "a.png").stat().st_size > 0
    rows = [{"horizon": 5, "grad_norm": [1.0, 2.0]}, {"horizon": 50, "grad_norm": [100.0, 300.0]}]
    assert plot_gradient_norms(rows, tmp_path / "b.png").stat().st_size > 0
    summary = [{"system": "cartpole", "method": "papg", "return_mean": -250, "return_std": 3, "stabilised": 0.0,
                "seeds": 4}]
    assert plot_method_comparison(summary, tmp_path / "c.png").stat().st_size > 0
    with pytest.raises(ValueError, match="curve 'x' has 2 values for 3 scales"):
        plot_return_landscape([-1, 0, 1], {"x": [1, 2]}, tmp_path / "d.png")
    with pytest.raises(ValueError, match="at least one"):
        plot_gradient_norms([], tmp_path / "e.png")


def test_return_curves_plot_runs_side_by_side_and_reject_no_rows(tmp_path):
    from hybridctl.viz import plot_return_curves

    rows = [{"env_steps": 96 * k, "mean_return": -10.0 + k, "best_return": -8.0 + k, "grad_norm": 10.0 ** k}
            for k in range(1, 4)]
    assert plot_return_curves({"ce-apg": rows, "apg": rows[:1]}, tmp_path / "f.png").stat().st_size > 0
    with pytest.raises(ValueError, match="at least one run"):
        plot_return_curves({"apg": []}, tmp_path / "g.png")


def test_the_thesis_budget_gives_every_method_the_same_interactions():
    """StudySettings.thesis: K 24 x N 4 x T 500 x 100 x 200 = 9.6e8 interactions for CE-APG and PAPG, and
    APG (one policy) on 96 starts per iteration so it sees as many."""
    from hybridctl.experiments.apg_study import apg_config
    from hybridctl.learn.apg import METHOD_CLASSES

    settings = StudySettings.thesis()
    budgets = {}
    for method in ("ce-apg", "papg", "apg"):
        c = apg_config(method, "acrobot", 0, settings)
        c.validate()
        budgets[method] = (METHOD_CLASSES[method].member_count(c) * c.batch * c.horizon * c.apg_iterations * c.epochs)
        assert (c.horizon, c.apg_iterations, c.epochs, c.lr_end, c.checkpoint_every) == (500, 100, 200, 1e-6, 5)
    assert set(budgets.values()) == {24 * 4 * 500 * 100 * 200}
    assert apg_config("apg", "acrobot", 0, StudySettings()).batch == 4    # the reduced study: the thesis' APG


def test_thesis_collect_draws_every_runs_curves_finished_or_not(tmp_path):
    from hybridctl.reproduce.table71 import write_curves

    header = "epoch,env_steps,mean_return,best_return,grad_norm\n"
    for name, rows in (("ce-apg-s0", 3), ("apg-s1", 1)):
        run = tmp_path / "acrobot" / name / "run"
        run.mkdir(parents=True)
        (run / "progress.csv").write_text(header + "".join(f"{k},{96 * k},{-10 + k},{-9 + k},{10.0 ** k}\n"
                                                           for k in range(1, rows + 1)))
    assert write_curves(tmp_path, tmp_path / "curves.png").stat().st_size > 0
    with pytest.raises(ValueError, match="at least one run"):
        write_curves(tmp_path / "acrobot" / "none", tmp_path / "empty.png")
