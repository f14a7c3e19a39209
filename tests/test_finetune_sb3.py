"""Fine-tuning Stable-Baselines3 agents end to end: the CLI on a zip, the written-back zip read by
SB3's own load, and the bad-input cases of issue 14 (spaces, pickles, damaged files)."""

import json
import pickle
import zipfile

import numpy as np
import pytest
import torch

sb3 = pytest.importorskip("stable_baselines3")

from hybridctl.cli import main  # noqa: E402
from hybridctl.learn.checkpoint import CheckpointError  # noqa: E402
from hybridctl.learn.finetune import FineTune  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def ppo_zip(tmp_path_factory):
    import gymnasium as gym
    torch.set_num_threads(1)
    folder = tmp_path_factory.mktemp("agent")
    model = sb3.PPO("MlpPolicy", gym.make("Pendulum-v1"), n_steps=64, batch_size=64, n_epochs=1, seed=0,
                    policy_kwargs={"net_arch": [16, 16]}, device="cpu")
    model.learn(64)
    model.save(folder / "model.zip")
    return folder / "model.zip"


def test_cli_fine_tunes_a_zip_and_sb3_loads_the_result(ppo_zip, tmp_path, capsys):
    out = tmp_path / "ft"
    code = main(["finetune", "Pendulum-v1", "--policy", f"sb3:{ppo_zip}", "--updates", "2", "--directions", "4",
                 "--eval-episodes", "4", "--backend", "serial", "--out", str(out), "--quiet"])
    assert code == 0
    assert "before return" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["sb3_zip"] and report["env_steps"] == 2 * 8 * 200
    tuned = sb3.PPO.load(out / "model.zip", device="cpu")
    tuner = FineTune.load(out / "final")
    obs = np.random.default_rng(0).uniform(-1, 1, size=(20, 3))
    np.testing.assert_allclose(tuned.predict(obs, deterministic=True)[0], tuner.predict(obs), atol=1e-6)
    original = sb3.PPO.load(ppo_zip, device="cpu")
    assert not np.allclose(original.predict(obs, deterministic=True)[0], tuner.predict(obs))
    # the value net and log_std (not on the action path) are untouched by the default selection
    for name, p in original.policy.state_dict().items():
        if "value_net" in name or name == "log_std":
            torch.testing.assert_close(tuned.policy.state_dict()[name], p)


def test_an_env_with_other_spaces_is_named(ppo_zip):
    with pytest.raises(ValueError, match="differs from the checkpoint"):
        FineTune("MountainCarContinuous-v0", f"sb3:{ppo_zip}")


def test_a_vecnormalize_pickle_is_refused_without_trust(ppo_zip, tmp_path, capsys):
    folder = tmp_path / "agent"
    folder.mkdir()
    (folder / "model.zip").write_bytes(ppo_zip.read_bytes())
    (folder / "vecnormalize.pkl").write_bytes(pickle.dumps({"not": "read"}))
    with pytest.raises(SystemExit) as exc:
        main(["finetune", "Pendulum-v1", "--policy", f"sb3:{folder / 'model.zip'}", "--out", str(tmp_path / "o"),
              "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--trust" in err and "Traceback" not in err


def test_a_damaged_zip_is_named(ppo_zip, tmp_path):
    broken = tmp_path / "broken.zip"
    with zipfile.ZipFile(ppo_zip) as src, zipfile.ZipFile(broken, "w") as dst:
        for item in src.infolist():
            if item.filename != "policy.pth":
                dst.writestr(item, src.read(item.filename))
    with pytest.raises(CheckpointError, match="policy.pth"):
        FineTune("Pendulum-v1", f"sb3:{broken}")
    with pytest.raises(CheckpointError, match="no_such.zip"):
        FineTune("Pendulum-v1", f"sb3:{tmp_path / 'no_such.zip'}")


def test_selection_all_perturbs_the_value_net_too(ppo_zip):
    action = FineTune("Pendulum-v1", f"sb3:{ppo_zip}", backend="serial")
    everything = FineTune("Pendulum-v1", f"sb3:{ppo_zip}", backend="serial", select="all")
    assert any("value_net" in n for n in everything.names) and "log_std" in everything.names
    assert not any("value_net" in n or n == "log_std" for n in action.names)
    assert everything.n_params > action.n_params


def test_a_normalised_agent_round_trips_through_the_hybridctl_checkpoint(ppo_zip, tmp_path):
    """An agent with vecnormalize.npz: FineTune.load(final/) and the written-back zip + npz act alike."""
    from hybridctl.learn.sb3_normalizer import Normalizer

    folder = tmp_path / "agent"
    folder.mkdir()
    (folder / "model.zip").write_bytes(ppo_zip.read_bytes())
    Normalizer(mean=np.array([0.1, -0.2, 0.5]), var=np.array([0.5, 0.4, 4.0]), count=100.0, clip_obs=10.0,
               epsilon=1e-8).save_npz(folder / "vecnormalize.npz")
    out = tmp_path / "ft"
    assert main(["finetune", "Pendulum-v1", "--policy", f"sb3:{folder / 'model.zip'}", "--updates", "1",
                 "--directions", "2", "--eval-episodes", "2", "--backend", "serial", "--out", str(out),
                 "--quiet"]) == 0
    tuner = FineTune.load(out / "final")
    stats = np.load(out / "vecnormalize.npz")
    obs = np.random.default_rng(1).normal(size=(6, 3))
    z = np.clip((obs - stats["mean"]) / np.sqrt(stats["var"] + stats["epsilon"]), -10, 10)
    tuned = sb3.PPO.load(out / "model.zip", device="cpu")
    np.testing.assert_allclose(tuned.predict(z, deterministic=True)[0], tuner.predict(obs), atol=1e-5)
