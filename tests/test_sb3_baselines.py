"""hybridctl.reproduce.sb3_baselines and its workflow hybridctl.experiments.sb3_runs: every algorithm for a
tiny budget in two chunks, the resume that trains only the difference, the VecNormalize .npz round trip, the
report's JSON and figure, and bad input."""

import contextlib
import copy
import io
import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("sb3_contrib")


# one xdist worker runs the module, so its module-scoped training fixture runs once, not once per worker
pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.xdist_group("sb3_baselines")]

# algo -> (first budget, chunk, second budget): two chunks, then a resume for the difference. On-policy
# budgets are whole rollouts (n_envs * n_steps: PPO 16 * 256, TRPO 2 * 1024, A2C 16 * 5) so that every
# chunk ends where asked; SAC/TD3 chunks are whole 50-step episodes.
BUDGETS = {"ppo": (1024, 512, 1536), "trpo": (512, 256, 768), "a2c": (160, 80, 240),
           "sac": (200, 100, 300), "td3": (200, 100, 300)}


SHIPPED_ZOO: dict = {}
"""The zoo entries as shipped, before ``runs`` shortens them for the tests' budgets."""


@pytest.fixture(scope="module")
def runs():
    """The workflow module (ZOO, run folders, curves), with TD3's warm-up and PPO's and TRPO's rollouts shortened
    for tiny budgets (restored afterwards: the module is shared with the rest of the session)."""
    from hybridctl.experiments import sb3_runs

    # TD3's zoo warm-up (learning_starts 10000) would leave a few hundred steps untrained; start at 100
    # so that the resumed run updates its networks from the reloaded replay buffer
    # PPO's and TRPO's zoo rollouts (16 x 256 and 2 x 1024 steps) are cut to 16 x 32 and 2 x 128 steps, so that a
    # chunk of a few rollouts takes a second, not ten: the test is of the run folders, not of the zoo's numbers
    patched = {"td3": {"learning_starts": 100}, "ppo": {"n_steps": 32}, "trpo": {"n_steps": 128}}
    SHIPPED_ZOO.update(copy.deepcopy(sb3_runs.ZOO))
    before = {algo: {k: sb3_runs.ZOO[algo]["kwargs"][k] for k in values} for algo, values in patched.items()}
    for algo, values in patched.items():
        sb3_runs.ZOO[algo]["kwargs"].update(values)
    yield sb3_runs
    for algo, values in before.items():
        sb3_runs.ZOO[algo]["kwargs"].update(values)


@pytest.fixture(scope="module")
def sb(runs):
    """The driver module (its ZOO is the workflow's, patched by ``runs``)."""
    from hybridctl.reproduce import sb3_baselines

    return sb3_baselines


def _run(sb, capsys, *argv):
    code = sb.main([str(a) for a in argv])
    captured = capsys.readouterr()
    assert code == 0, captured.err[-3000:]
    return json.loads(captured.out)


@pytest.fixture(scope="module")
def trained(sb, tmp_path_factory):
    """Each algorithm trained to its first budget in two chunks, then resumed to its second budget.

    Module-scoped, so stdout is redirected here rather than read from capsys.
    """
    out = tmp_path_factory.mktemp("sb3") / "runs"
    first, second = {}, {}
    for algo, (b1, chunk, b2) in BUDGETS.items():
        for budget, record in ((b1, first), (b2, second)):
            stdout, stderr = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
                code = sb.main(["--algos", algo, "--seeds", "0", "--steps", str(budget), "--chunk-steps", str(chunk),
                                "--eval-episodes", "2", "--out", str(out)])
            assert code == 0, stderr.getvalue()[-3000:]
            (summary,) = json.loads(stdout.getvalue())["runs"]
            progress = json.loads((out / f"{algo}-s0" / "progress.json").read_text())
            record[algo] = {"summary": summary, "progress": progress}
    return out, first, second


@pytest.mark.parametrize("algo", list(BUDGETS))
def test_two_chunks_then_resume_trains_only_the_difference(runs, trained, algo):
    out, first, second = trained
    b1, chunk, b2 = BUDGETS[algo]
    run = out / f"{algo}-s0"
    p1, p2 = first[algo]["progress"], second[algo]["progress"]
    assert [(c["from"], c["to"]) for c in p1["chunks"]] == [(0, chunk), (chunk, b1)]
    assert p1["steps_done"] == b1 and first[algo]["summary"]["status"] == "done"
    # the resumed invocation starts where the checkpoint ended and trains b2 - b1 steps only
    assert p2["chunks"][:2] == p1["chunks"] and len(p2["chunks"]) == 3
    assert (p2["chunks"][2]["from"], p2["chunks"][2]["to"]) == (b1, b2)
    assert second[algo]["summary"]["steps_before"] == b1 and p2["steps_done"] == b2
    assert len(p2["commands"]) == 2 and p2["hyperparameters"] == runs.hyperparameters(algo)
    model = runs.algorithm_class(algo).load(run / "model.zip", device="cpu")
    assert model.num_timesteps == b2
    if algo in runs.ON_POLICY:
        assert (run / "vecnormalize.npz").is_file() and not (run / "replay_buffer.pkl").exists()
        with np.load(run / "vecnormalize.npz") as stats:
            assert int(stats["steps"]) == b2 and float(stats["count"]) > b2 / 2
        from hybridctl.learn.sb3_normalizer import Normalizer       # the package's reader takes the file as it is
        assert Normalizer.from_npz(run / "vecnormalize.npz").shape == model.observation_space.shape
    else:
        model.load_replay_buffer(run / "replay_buffer.pkl")
        assert model.replay_buffer.pos == b2 and not (run / "vecnormalize.npz").exists()
        assert model._n_updates > 0                      # it learnt (TD3 after the shortened warm-up)
    evaluation = json.loads((run / "eval.json").read_text())
    assert evaluation["env_steps"] == b2 and evaluation["episodes"] == 2
    assert np.isfinite(evaluation["mean_return"]) and 0 <= evaluation["success_rate"] <= 1
    assert (run / "curve.csv.xz").is_file() and not (run / "curve.csv").exists()   # packed at the budget
    rows = runs.read_curve(run / "curve.csv")
    assert np.all(np.diff(rows[:, 0]) >= 0) and (len(rows) == 0 or rows[-1, 0] <= b2)
    if algo in ("sac", "td3"):                            # one env: an episode every 50 steps, none lost
        assert rows[:, 0].tolist() == list(range(50, b2 + 1, 50)) and set(rows[:, 2]) == {50}
    assert not list(run.glob("*.tmp"))


def test_a_run_at_its_budget_is_skipped(sb, trained, capsys):
    out, _, second = trained
    b2 = BUDGETS["a2c"][2]
    before = (out / "a2c-s0" / "model.zip").stat().st_mtime_ns
    (summary,) = _run(sb, capsys, "--algos", "a2c", "--seeds", "0", "--steps", b2, "--eval-episodes", 2,
                      "--out", out)["runs"]
    assert summary["status"] == "skipped (at budget)" and "evaluated" not in summary
    assert (out / "a2c-s0" / "model.zip").stat().st_mtime_ns == before
    assert json.loads((out / "a2c-s0" / "progress.json").read_text()) == second["a2c"]["progress"]


def test_vecnormalize_npz_round_trip(runs, tmp_path):
    venv = runs.new_vecnormalize(runs.make_venv("trpo", seed=3), "trpo")
    venv.reset()
    for _ in range(30):
        venv.step(np.stack([venv.action_space.sample() for _ in range(venv.num_envs)]))
    runs.save_vecnormalize(venv, tmp_path / "vn.npz", steps=60)
    for training in (True, False):
        loaded, steps = runs.load_vecnormalize(tmp_path / "vn.npz", runs.make_venv("trpo", seed=4), training=training)
        assert steps == 60 and loaded.training is training and loaded.norm_reward is training
        for a, b in ((loaded.obs_rms, venv.obs_rms), (loaded.ret_rms, venv.ret_rms)):
            np.testing.assert_array_equal(a.mean, b.mean)
            np.testing.assert_array_equal(a.var, b.var)
            assert a.count == b.count
        assert (loaded.clip_obs, loaded.clip_reward, loaded.gamma, loaded.epsilon) == \
               (venv.clip_obs, venv.clip_reward, venv.gamma, venv.epsilon)
        obs = np.random.default_rng(0).normal(size=(5, 4)) * 3
        np.testing.assert_array_equal(loaded.normalize_obs(obs), venv.normalize_obs(obs))
        loaded.close()
    venv.close()
    assert venv.gamma == 0.99 and venv.norm_obs and venv.norm_reward       # the zoo's normalize: true


def test_curve_rows_past_the_checkpoint_are_dropped(runs, tmp_path):
    path = tmp_path / "curve.csv"
    runs.append_curve(path, [(50, -3.0, 50, 0), (100, -2.5, 50, 1)])
    runs.append_curve(path, [(150, -1.0, 50, 0)])
    runs.truncate_curve(path, 100)
    np.testing.assert_array_equal(runs.read_curve(path), [[50, -3.0, 50, 0], [100, -2.5, 50, 1]])
    runs.pack_curve(path)
    assert not path.exists() and (tmp_path / "curve.csv.xz").is_file()
    np.testing.assert_array_equal(runs.read_curve(path), [[50, -3.0, 50, 0], [100, -2.5, 50, 1]])
    runs.unpack_curve(path)                                   # trained further: rows are appended again
    runs.append_curve(path, [(150, -1.0, 50, 0)])
    assert runs.read_curve(path).shape == (3, 4) and not (tmp_path / "curve.csv.xz").exists()
    runs.truncate_curve(path, 100)
    curve = runs.binned_curve(runs.read_curve(path), 80)
    assert curve["env_steps"] == [80, 100] and curve["mean_return"] == [-3.0, -2.5] and curve["episodes"] == [1, 1]


def test_zoo_entries_become_sb3_arguments(runs, monkeypatch):
    from stable_baselines3.common.noise import NormalActionNoise

    monkeypatch.setattr(runs, "ZOO", SHIPPED_ZOO)     # the entries as shipped, not as shortened for the budgets

    kwargs = runs.model_kwargs("td3", n_actions=1)
    assert isinstance(kwargs["action_noise"], NormalActionNoise)
    np.testing.assert_array_equal(kwargs["action_noise"]._sigma, [0.1])   # in SB3's [-1, 1] action scale
    assert kwargs["train_freq"] == (1, "episode") and kwargs["policy_kwargs"] == {"net_arch": [400, 300]}
    assert runs.model_kwargs("ppo", 1) == {"n_steps": 256, "gae_lambda": 0.94, "gamma": 0.99, "n_epochs": 4,
                                         "ent_coef": 0.0}
    assert [runs.ZOO[a]["n_envs"] for a in runs.ALGOS] == [16, 16, 2, 1, 1]
    for algo in runs.ALGOS:
        assert runs.ZOO[algo]["source"].startswith(f"rl-baselines3-zoo hyperparams/{algo}.yml: ")


def test_report_writes_json_and_png(sb, trained, tmp_path, capsys):
    out, _, second = trained
    target = tmp_path / "data" / "results.json"
    printed = _run(sb, capsys, "--report", "--out", out, "--report-out", target, "--runs", tmp_path / "none")
    assert json.loads(target.read_text()) == printed
    png = target.with_suffix(".png")
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = printed["stable_baselines3"]
    assert set(table) == {"PPO", "A2C", "TRPO", "SAC", "TD3"}
    assert table["SAC"]["thesis"] == [73.01, 11.41] and table["TRPO"]["thesis"] == [17.63, 3.39]
    for algo, row in table.items():
        assert row["seeds"] == 1 and row["seed_list"] == [0] and row["steps"] == [BUDGETS[algo.lower()][2]]
        assert np.isfinite(row["mean_return"]) and row["std_over_seeds"] == 0.0 and row["train_wall_s_total"] > 0
    runs = {r["algo"]: r for r in printed["runs"]}
    assert runs["sac"]["curve"]["episodes"] == [6] and runs["sac"]["curve"]["env_steps"] == [300]
    assert runs["td3"]["eval"]["mean_return"] == json.loads((out / "td3-s0" / "eval.json").read_text())["mean_return"]


@pytest.mark.parametrize("argv, message", [
    (["--steps", "0"], "argument --steps: expected an integer >= 1"),
    (["--steps", "2e6x"], "argument --steps: expected an integer >= 1"),
    (["--seeds", "-1"], "argument --seeds: expected an integer >= 0"),
    (["--algos", "sac"], "argument --steps: required for sac"),
    (["--chunk-steps", "0"], "argument --chunk-steps"),
    (["--time-budget-s", "0"], "argument --time-budget-s: expected seconds > 0"),
    (["--report", "--report-out", "x.txt"], "argument --report-out"),
])
def test_bad_input_is_named_without_traceback(sb, capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        sb.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_missing_checkpoints_and_empty_roots_are_reported(sb, tmp_path, capsys):
    assert sb.main(["--report", "--out", str(tmp_path)]) == 2
    assert "no run folders" in capsys.readouterr().err
    assert sb.main(["--algos", "a2c", "--seeds", "0", "--steps", "80", "--resume", "--out", str(tmp_path)]) == 2
    assert "--resume" in capsys.readouterr().err and not (tmp_path / "a2c-s0").exists()
