"""hybridctl.reproduce.ch6_agents: one tiny Pendulum agent end to end, the files and record, the resume skip."""

import json
import os

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("sb3_contrib")


@pytest.fixture(scope="module")
def fa():
    from hybridctl.reproduce import ch6_agents

    return ch6_agents


def test_zoo_conventions(fa):
    """lin_ schedules, policy_kwargs strings, noise, train_freq lists and normalize become SB3 arguments."""
    from stable_baselines3.common.noise import NormalActionNoise
    from torch import nn

    kwargs, env_cfg = fa.resolve(fa.ZOO[("Pendulum-v1", "a2c")][1], n_actions=1)
    assert kwargs["learning_rate"](1.0) == pytest.approx(7e-4) and kwargs["learning_rate"](0.5) == pytest.approx(3.5e-4)
    assert kwargs["policy_kwargs"] == {"log_std_init": -2, "ortho_init": False}
    assert env_cfg == {"n_envs": 8, "normalize": True, "normalize_kwargs": {"gamma": 0.9}}
    assert "n_timesteps" not in kwargs and "normalize" not in kwargs

    kwargs, env_cfg = fa.resolve(fa.ZOO[("Hopper-v5", "ppo")][1], n_actions=3)
    assert kwargs["policy_kwargs"]["activation_fn"] is nn.ReLU
    assert kwargs["policy_kwargs"]["net_arch"] == {"pi": [256, 256], "vf": [256, 256]}

    kwargs, env_cfg = fa.resolve(fa.ZOO[("Pendulum-v1", "td3")][1], n_actions=1)
    assert isinstance(kwargs["action_noise"], NormalActionNoise) and kwargs["train_freq"] == (1, "episode")
    assert env_cfg["normalize"] is False and "noise_std" not in kwargs

    assert fa.our_budget(("Pendulum-v1", "a2c"), 1.0) == 300_000          # capped below the Zoo's 1e6
    assert fa.our_budget(("Pendulum-v1", "sac"), 1.0) == fa.zoo_budget(("Pendulum-v1", "sac")) == 20_000
    assert fa.our_budget(("Hopper-v5", "ppo"), 0.5) == 100_000
    assert set(fa.DEFAULT_ORDER) <= set(fa.ZOO) and set(fa.ZOO) == set(fa.BUDGET_CAPS)
    with pytest.raises(SystemExit):
        fa.parse_only(["Pendulum-v1:dqn"])


def test_one_agent_files_record_and_resume(fa, tmp_path, one_torch_thread):
    out, summary = tmp_path / "agents", tmp_path / "summary.json"
    argv = ["--only", "Pendulum-v1:a2c", "--budget-scale", "0.001", "--out", str(out), "--summary", str(summary)]
    report = fa.main(argv)
    assert report["trained"] == ["Pendulum-v1:a2c"] and not report["failed"]

    directory = out / "Pendulum-v1-a2c"
    assert sorted(p.name for p in directory.iterdir()) == ["model.zip", "record.json", "vecnormalize.npz"]
    with np.load(directory / "vecnormalize.npz") as z:
        assert set(z.files) == {"mean", "var", "count", "clip_obs", "epsilon", "norm_obs"}
        assert z["mean"].shape == z["var"].shape == (3,) and bool(z["norm_obs"]) and float(z["count"]) > 0

    record = json.loads((directory / "record.json").read_text())
    for key in ("command", "env", "algo", "seed", "zoo_n_timesteps", "budget", "env_steps", "wall_time_s",
                "steps_per_s", "machine", "hyperparameters", "eval", "zoo_source"):
        assert key in record, key
    assert (record["env"], record["algo"], record["seed"]) == ("Pendulum-v1", "a2c", 0)
    assert record["zoo_n_timesteps"] == 1_000_000 and record["budget"] == 300
    assert record["env_steps"] >= record["budget"] and record["steps_per_s"] > 0
    assert record["machine"]["torch_threads"] == 1 and record["machine"]["stable_baselines3"]
    ev = record["eval"]
    assert ev["episodes"] == 20 and len(ev["returns"]) == 20 and ev["seeds"] == [1000, 1019]
    assert ev["deterministic"] and ev["obs_normalized"] and np.isfinite(ev["mean_return"])
    assert ev["mean_return"] == pytest.approx(np.mean(ev["returns"]))

    merged = json.loads(summary.read_text())["agents"]
    assert list(merged) == ["Pendulum-v1:a2c"] and "hyperparameters" not in merged["Pendulum-v1:a2c"]
    assert merged["Pendulum-v1:a2c"]["eval"]["mean_return"] == ev["mean_return"]

    from stable_baselines3 import A2C

    model = A2C.load(directory / "model.zip", device="cpu")           # loads without this module
    assert model.num_timesteps == record["env_steps"]

    stamp = os.stat(directory / "model.zip").st_mtime_ns
    again = fa.main(argv)                                               # resumable: a record means done
    assert again["trained"] == [] and "Pendulum-v1:a2c" in again["skipped"]
    assert os.stat(directory / "model.zip").st_mtime_ns == stamp
