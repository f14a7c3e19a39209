"""learn/sb3.py: SB3 zips read without unpickling give SB3's own deterministic actions; save_zip round trip."""

from __future__ import annotations

import io
import json
import pickle
import subprocess
import sys
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hybridctl.learn.checkpoint import CheckpointError
from hybridctl.learn.sb3 import load_sb3
from hybridctl.learn.sb3_normalizer import Normalizer
from hybridctl.learn.sb3_policy import SELECTIONS
from hybridctl.learn.sb3_zip import OPTIMIZER_ENTRIES, SB3_ALGORITHMS

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ROOT = Path(__file__).resolve().parents[1]
# name -> (algorithm, constructor kwargs); tiny nets, a few learn steps (real trained-format zips)
MODELS = {
    "ppo": ("ppo", dict(n_steps=32, batch_size=32, n_epochs=1)),
    "a2c": ("a2c", dict(n_steps=8)),
    "sac": ("sac", dict(learning_starts=10, batch_size=16)),
    "td3": ("td3", dict(learning_starts=10, batch_size=16)),
    "ddpg": ("ddpg", dict(learning_starts=10, batch_size=16)),
    "tqc": ("tqc", dict(learning_starts=10, batch_size=16)),
    "ppo_sde": ("ppo", dict(n_steps=32, batch_size=32, n_epochs=1, use_sde=True)),
    "ppo_squash_relu": ("ppo", dict(n_steps=32, batch_size=32, n_epochs=1, use_sde=True,
                                    policy_kwargs=dict(net_arch=dict(pi=[16, 8], vf=[4]), squash_output=True,
                                                       activation_fn=torch.nn.ReLU))),
    "sac_sde": ("sac", dict(learning_starts=10, batch_size=16, use_sde=True)),
}


def _cls(algo: str):
    if algo == "tqc":
        return pytest.importorskip("sb3_contrib").TQC
    sb3 = pytest.importorskip("stable_baselines3")
    return getattr(sb3, algo.upper())


@pytest.fixture(scope="module")
def zoo(tmp_path_factory):
    """name -> (zip path, the SB3 model): each model trained once, on first use."""
    cache = {}
    folder = tmp_path_factory.mktemp("sb3")

    def get(name):
        if name not in cache:
            algo, kwargs = MODELS[name]
            cls = _cls(algo)
            kwargs = dict(kwargs)
            policy_kwargs = kwargs.pop("policy_kwargs", dict(net_arch=[16, 16]))
            model = cls("MlpPolicy", "Pendulum-v1", policy_kwargs=policy_kwargs, seed=0, device="cpu", **kwargs)
            model.learn(32)
            (folder / name).mkdir()
            path = folder / name / "model.zip"
            model.save(path)
            cache[name] = (path, model)
        return cache[name]
    return get


def _obs(n=50, seed=0):
    # beyond the Pendulum bounds too, so that PPO's clipping is exercised
    return (np.random.default_rng(seed).normal(size=(n, 3)) * np.array([1.0, 1.0, 8.0]) * 1.5).astype(np.float32)


@pytest.mark.parametrize("name", list(MODELS))
def test_deterministic_action_matches_sb3_predict(zoo, name):
    path, model = zoo(name)
    agent = load_sb3(path)
    assert agent.algo == MODELS[name][0]
    obs = _obs()
    ours, state = agent.predict(obs)
    theirs, _ = model.predict(obs, deterministic=True)
    assert state is None and ours.shape == theirs.shape == (50, 1)
    np.testing.assert_allclose(ours, theirs, atol=1e-6, rtol=0)
    single, _ = agent.predict(obs[0])
    np.testing.assert_allclose(single, model.predict(obs[0], deterministic=True)[0], atol=1e-6, rtol=0)
    assert all(p.dtype == torch.float32 for p in agent.policy.parameters())
    assert agent.observation_space.shape == (3,) and agent.action_space.shape == (1,)
    np.testing.assert_array_equal(agent.action_space.high, [2.0])
    with pytest.raises(ValueError, match="maximum-likelihood"):
        agent.predict(obs, deterministic=False)


def test_never_unpickles_the_zip(zoo, monkeypatch):
    cloudpickle = pytest.importorskip("cloudpickle")
    paths = [zoo(name)[0] for name in MODELS if MODELS[name][0] != "tqc" or _has("sb3_contrib")]

    def refuse(*args, **kwargs):
        raise AssertionError("unpickling was called")
    for module in (pickle, cloudpickle):
        monkeypatch.setattr(module, "loads", refuse)
        monkeypatch.setattr(module, "load", refuse)
    for path in paths:
        assert load_sb3(path).algo in SB3_ALGORITHMS


def _has(module: str) -> bool:
    try:
        __import__(module)
        return True
    except ImportError:
        return False


def test_module_imports_and_reads_zips_without_sb3(zoo):
    path = zoo("sac")[0]
    code = ("import sys\n"
            "for m in ('stable_baselines3', 'sb3_contrib', 'cloudpickle'): sys.modules[m] = None\n"
            "from hybridctl.learn import load_sb3\n"
            f"a = load_sb3({str(path)!r})\n"
            "print(a.algo, a.predict([[1.0, 0.0, 0.0]])[0].shape)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60,
                         env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["sac", "(1,", "1)"]


@pytest.fixture(scope="module")
def normalized(tmp_path_factory):
    """A PPO trained under VecNormalize, its statistics saved as vecnormalize.npz beside the zip."""
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    venv = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1, seed=0), clip_obs=2.0)
    model = sb3.PPO("MlpPolicy", venv, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu",
                    policy_kwargs=dict(net_arch=[16, 16]))
    model.learn(64)
    venv.training = False
    folder = tmp_path_factory.mktemp("vecnorm")
    model.save(folder / "model.zip")
    Normalizer.from_vecnormalize(venv).save_npz(folder / "vecnormalize.npz")
    return folder, model, venv


def test_vecnormalize_npz_agent_matches_sb3_on_normalised_obs(normalized):
    folder, model, venv = normalized
    agent = load_sb3(folder / "model.zip")  # finds vecnormalize.npz beside it
    assert agent.normalizer is not None and agent.normalizer.count > 1
    obs = _obs()
    np.testing.assert_array_equal(agent.normalizer(obs), venv.normalize_obs(obs))
    ours, _ = agent.predict(obs)
    theirs, _ = model.predict(venv.normalize_obs(obs), deterministic=True)
    np.testing.assert_allclose(ours, theirs, atol=1e-6, rtol=0)
    again = Normalizer.from_npz(folder / "vecnormalize.npz")
    assert again.to_dict() == agent.normalizer.to_dict()
    assert json.loads(json.dumps(again.to_dict()))["clip_obs"] == 2.0


def test_pkl_normalisation_is_refused_without_trust(normalized, tmp_path):
    folder, model, venv = normalized
    (tmp_path / "model.zip").write_bytes((folder / "model.zip").read_bytes())
    venv.save(str(tmp_path / "vecnormalize.pkl"))
    with pytest.raises(CheckpointError, match=r"vecnormalize\.pkl.*trust=True.*--trust"):
        load_sb3(tmp_path / "model.zip")
    with pytest.raises(CheckpointError, match="trust=True"):
        load_sb3(tmp_path / "model.zip", normalizer=tmp_path / "vecnormalize.pkl")
    trusted = load_sb3(tmp_path / "model.zip", trust=True)
    obs = _obs()
    np.testing.assert_array_equal(trusted.normalizer(obs), venv.normalize_obs(obs))
    trusted.normalizer.save_npz(tmp_path / "vecnormalize.npz")  # converted: now read without trust
    np.testing.assert_array_equal(load_sb3(tmp_path / "model.zip").normalizer(obs), venv.normalize_obs(obs))


@pytest.mark.parametrize("name", ["ppo", "a2c", "sac", "td3", "ddpg", "tqc", "ppo_sde"])
def test_perturbed_save_zip_loads_in_sb3_and_predicts_our_actions(zoo, name, tmp_path):
    path, _ = zoo(name)
    agent = load_sb3(path)
    params = dict(agent.policy.named_parameters())
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for key in agent.policy.parameter_names("all"):
            params[key].add_(0.1 * torch.randn(params[key].shape, generator=generator))
    out = agent.save_zip(tmp_path / "tuned.zip")
    loaded = _cls(MODELS[name][0]).load(out, device="cpu")
    obs = _obs(seed=2)
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], agent.predict(obs)[0], atol=1e-6, rtol=0)
    original, tuned = zipfile.ZipFile(path), zipfile.ZipFile(out)
    # a fixed entry list, built from what was parsed (system_info.txt and unknown entries are not written)
    order = ("data", "pytorch_variables.pth", "policy.pth", *OPTIMIZER_ENTRIES, "_stable_baselines3_version")
    assert tuned.namelist() == [entry for entry in order if entry in original.namelist()]
    reference = _cls(MODELS[name][0]).load(path, device="cpu")
    assert loaded.policy_kwargs == reference.policy_kwargs and loaded.policy_class is reference.policy_class
    for key in ("gamma", "learning_rate", "batch_size", "use_sde", "num_timesteps", "observation_space", "action_space"):
        assert getattr(loaded, key, None) == getattr(reference, key, None), key
    for entry in OPTIMIZER_ENTRIES:  # the optimizer states survive (re-saved from their weights_only load)
        if entry in original.namelist():
            mine, theirs = (torch.load(io.BytesIO(z.read(entry)), weights_only=True) for z in (tuned, original))
            assert mine["param_groups"] == theirs["param_groups"]
            for index, values in theirs["state"].items():
                for key, value in values.items():
                    torch.testing.assert_close(mine["state"][index][key], value)
    before = torch.load(io.BytesIO(original.read("policy.pth")), weights_only=True)
    after = torch.load(io.BytesIO(tuned.read("policy.pth")), weights_only=True)
    assert list(before) == list(after)
    changed = {key for key in before if not torch.equal(before[key], after[key])}
    assert changed == set(agent.policy.parameter_names("all"))
    assert load_sb3(out).algo == agent.algo


def test_parameter_names_selections(zoo):
    ppo = load_sb3(zoo("ppo")[0]).policy
    action, everything = ppo.parameter_names("action"), ppo.parameter_names("all")
    assert action and all(n.startswith(("mlp_extractor.policy_net.", "action_net.")) for n in action)
    assert "log_std" not in action and not any("value_net" in n for n in action)
    assert "log_std" in everything and "value_net.weight" in everything and "mlp_extractor.value_net.0.weight" in everything
    assert ppo.parameter_names("last") == ["action_net.weight", "action_net.bias"]
    sac = load_sb3(zoo("sac")[0]).policy
    assert not any("log_std" in n for n in sac.parameter_names("action"))
    assert "actor.log_std.weight" in sac.parameter_names("all")
    assert all(n.startswith("actor.") for n in sac.parameter_names("all"))
    td3 = load_sb3(zoo("td3")[0]).policy
    assert td3.parameter_names("action") == td3.parameter_names("all")
    assert td3.parameter_names("last") == ["actor.mu.4.weight", "actor.mu.4.bias"]
    with pytest.raises(ValueError, match="last"):
        ppo.parameter_names("critic")
    assert set(SELECTIONS) == {"action", "all", "last"}


def test_functional_call_and_vmap_over_perturbed_parameters(zoo):
    agent = load_sb3(zoo("sac")[0])
    policy = agent.policy
    params = dict(policy.named_parameters())
    names = policy.parameter_names("action")
    obs = torch.as_tensor(_obs(8))
    same = torch.func.functional_call(policy, {n: params[n] for n in names}, (obs,))
    torch.testing.assert_close(same, policy(obs))
    population = {n: params[n].detach() + 0.05 * torch.randn(4, *params[n].shape) for n in names}
    actions = torch.func.vmap(lambda p: torch.func.functional_call(policy, p, (obs,)))(population)
    assert actions.shape == (4, 8, 1) and actions.dtype == torch.float32
    first = torch.func.functional_call(policy, {n: v[0] for n, v in population.items()}, (obs,))
    torch.testing.assert_close(actions[0], first)


def test_check_env_names_both_spaces(zoo):
    gym = pytest.importorskip("gymnasium")
    agent = load_sb3(zoo("ppo")[0])
    agent.check_env(gym.make("Pendulum-v1"))
    with pytest.raises(ValueError, match=r"observation space.*\(2,\).*\(3,\)"):
        agent.check_env(gym.make("MountainCarContinuous-v0"))
    box = gym.spaces.Box
    wider = SimpleNamespace(observation_space=agent.observation_space, action_space=box(-3.0, 3.0, (1,), np.float32))
    with pytest.raises(ValueError, match=r"action space.*3\..*checkpoint's.*2\."):
        agent.check_env(wider)


def _rewrite(src: Path, dst: Path, drop=(), replace=None) -> Path:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for entry in zin.namelist():
            if entry not in drop:
                zout.writestr(entry, (replace or {}).get(entry, zin.read(entry)))
    return dst


def test_damaged_checkpoints_name_the_file_and_the_entry(zoo, tmp_path):
    path = zoo("ppo")[0]
    with pytest.raises(CheckpointError, match="no such file"):
        load_sb3(tmp_path / "absent.zip")
    (tmp_path / "text.zip").write_text("not a zip")
    with pytest.raises(CheckpointError, match=r"text\.zip is not a zip"):
        load_sb3(tmp_path / "text.zip")
    no_policy = _rewrite(path, tmp_path / "no_policy.zip", drop=("policy.pth",))
    with pytest.raises(CheckpointError, match=r"no_policy\.zip has no 'policy\.pth' entry"):
        load_sb3(no_policy)
    no_data = _rewrite(path, tmp_path / "no_data.zip", drop=("data",))
    with pytest.raises(CheckpointError, match=r"no_data\.zip has no 'data' entry"):
        load_sb3(no_data)
    bad_json = _rewrite(path, tmp_path / "bad_json.zip", replace={"data": b"{not json"})
    with pytest.raises(CheckpointError, match=r"bad_json\.zip: entry 'data' is not valid JSON"):
        load_sb3(bad_json)
    buffer = io.BytesIO()
    torch.save({**torch.load(io.BytesIO(zipfile.ZipFile(path).read("policy.pth")), weights_only=True),
                "action_net.weight": torch.zeros(1, 5)}, buffer)
    misfit = _rewrite(path, tmp_path / "misfit.zip", replace={"policy.pth": buffer.getvalue()})
    with pytest.raises(CheckpointError, match=r"misfit\.zip: entry 'policy\.pth'.*action_net\.weight"):
        load_sb3(misfit)
    garbage = _rewrite(path, tmp_path / "garbage.zip", replace={"policy.pth": b"garbage"})
    with pytest.raises(CheckpointError, match=r"garbage\.zip: entry 'policy\.pth'"):
        load_sb3(garbage)
    with pytest.raises(ValueError, match="ppo"):
        load_sb3(path, algo="dqn")
    with pytest.raises(CheckpointError, match="policy.pth"):
        load_sb3(path, algo="sac")  # a PPO state dict does not fit a SAC actor


def test_damaged_normalizer_npz_names_the_file_and_the_key(tmp_path):
    np.savez(tmp_path / "partial.npz", mean=np.zeros(3), count=1.0, clip_obs=10.0, epsilon=1e-8)
    with pytest.raises(CheckpointError, match=r"partial\.npz has no key 'var'"):
        Normalizer.from_npz(tmp_path / "partial.npz")
    (tmp_path / "broken.npz").write_bytes(b"nonsense")
    with pytest.raises(CheckpointError, match=r"broken\.npz is not a readable \.npz"):
        Normalizer.from_npz(tmp_path / "broken.npz")
    np.savez(tmp_path / "shapes.npz", mean=np.zeros(3), var=np.ones(2), count=1.0, clip_obs=10.0, epsilon=1e-8)
    with pytest.raises(CheckpointError, match=r"shapes\.npz.*'var' has shape"):
        Normalizer.from_npz(tmp_path / "shapes.npz")
    with pytest.raises(CheckpointError, match="no such"):
        Normalizer.from_npz(tmp_path / "absent.npz")
    norm = Normalizer(mean=[0.0, 1.0], var=[4.0, 1.0], count=3, clip_obs=1.0, epsilon=0.0)
    norm.save_npz(tmp_path / "ok.npz")
    assert not list(tmp_path.glob(".ok.npz.*")), "the temporary file is renamed into place"
    np.testing.assert_allclose(Normalizer.from_npz(tmp_path / "ok.npz")([[2.0, 9.0]]), [[1.0, 1.0]])
    off = Normalizer(mean=[0.0], var=[1.0], count=1, clip_obs=1.0, epsilon=1e-8, norm_obs=False)
    np.testing.assert_array_equal(off(np.array([5.0])), [5.0])
