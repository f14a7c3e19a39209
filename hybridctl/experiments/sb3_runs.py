"""Stable-Baselines3 baselines on the acrobot swing-up (thesis Table 3.1 / Fig. 3.3): the RL Zoo's
hyperparameters, the resumable run folders and their evaluation, and the report's per-run records.

One run is ``OUT/<algo>-s<seed>/``, trained in chunks by :func:`train_run`; after every chunk it receives,
each written atomically (:func:`hybridctl.io.atomic_write`): ``model.zip`` (SB3's own save),
``replay_buffer.pkl`` (SAC/TD3), ``vecnormalize.npz`` (PPO/A2C/TRPO: the running obs/return statistics),
``curve.csv`` (one row per finished training episode, packed into ``curve.csv.xz`` when the run reaches its
budget) and ``progress.json`` last (it marks the checkpoint). A finished run's deterministic policy is
scored by :func:`evaluate_run` into ``eval.json``. :func:`collect_runs` and :func:`summarise` read the run
folders back for a report. The driver ``python -m hybridctl.reproduce.sb3_baselines`` is the command line
of this workflow and draws Fig. 3.3.
"""

from __future__ import annotations

import csv
import json
import lzma
import os
import platform
import re
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from hybridctl.io import atomic_write, write_json
from hybridctl.learn.sb3 import silent_logger
from hybridctl.learn.sb3_normalizer import load_vecnormalize, save_vecnormalize

ENV_ID = "hybridctl/AcrobotSwingup-v0"
THESIS_TABLE_3_1 = {  # mean reward +- std over 4 seeds after 2e6 interactions (thesis Table 3.1)
    "SSAC": (92.12, 2.35), "SAC": (73.01, 11.41), "PPO": (0.43, 8.89), "TD3": (78.67, 61.85),
    "TRPO": (17.63, 3.39), "A2C": (2.57, 3.63),
}
ALGOS = ("ppo", "a2c", "trpo", "sac", "td3")
ON_POLICY = ("ppo", "a2c", "trpo")
THESIS_STEPS = 2_000_000
EVAL_SEED_BASE = 10_000
CURVE_HEADER = ("env_steps", "return", "length", "success")

# The RL Baselines3 Zoo's tuned hyperparameters (github.com/DLR-RM/rl-baselines3-zoo, hyperparams/*.yml),
# copied literally (no YAML, no eval of the zoo's policy_kwargs strings). In every entry the zoo's
# n_timesteps is replaced by our --steps; "zoo_n_timesteps" only records the zoo's own budget. Keys the
# zoo leaves out take the installed SB3's defaults (SB3 2.x: e.g. TD3 batch_size 256 since SB3 2.0; 100
# in the SB3 1.x the thesis used). How the zoo turns the entries into objects (rl_zoo3/exp_manager.py):
#   normalize: true -> VecNormalize(venv) with the defaults (obs and reward, clip 10, epsilon 1e-8) and
#                      gamma = the entry's gamma when it has one (_preprocess_normalization);
#   n_envs         -> make_vec_env(env_id, n_envs, seed=seed) with DummyVecEnv and Monitor (default 1);
#   noise_type: normal, noise_std: s -> NormalActionNoise(zeros(n_actions), s * ones(n_actions))
#                      (_preprocess_action_noise); SB3 adds it to the action rescaled to [-1, 1]
#                      (OffPolicyAlgorithm._sample_action), so 0.1 means 10 % of the half range: 2.5 N m
#                      on our +-25 N m torque, not 0.1 N m. SAC's tanh-squashed policy is scaled the same
#                      way. The on-policy Gaussian policies (PPO, A2C, TRPO) are NOT rescaled: they act
#                      in N m, start with std exp(log_std_init=0) = 1 N m (4 % of the range) and are
#                      clipped to +-25; the zoo entries (tuned on Acrobot-v1's discrete actions) say
#                      nothing about that, so we leave SB3's behaviour as it is.
# Verified by reading the zoo files with the search tools: ppo.yml at commits 00128b5d and 208b6fdf,
# a2c.yml at 02846e4d and c6c209e7, trpo.yml at 13a3fe74 and eb5d9c77, sac.yml at 00128b5d and c94924e5,
# td3.yml at a02f4fbf (its Pendulum-v0 entry; the Pendulum-v1 entry of later commits has the same values,
# as printed in the model card of the zoo's trained sb3/td3-Pendulum-v1 agent), exp_manager.py at 068adc87.
ZOO: dict[str, dict[str, Any]] = {
    # hyperparams/ppo.yml, key Acrobot-v1:
    #   normalize: true, n_envs: 16, n_timesteps: 1e6, policy: MlpPolicy, n_steps: 256, gae_lambda: 0.94,
    #   gamma: 0.99, n_epochs: 4, ent_coef: 0.0
    "ppo": {"source": "rl-baselines3-zoo hyperparams/ppo.yml: Acrobot-v1", "zoo_n_timesteps": 1_000_000,
            "normalize": True, "n_envs": 16,
            "kwargs": {"policy": "MlpPolicy", "n_steps": 256, "gae_lambda": 0.94, "gamma": 0.99, "n_epochs": 4,
                       "ent_coef": 0.0}},
    # hyperparams/a2c.yml, key Acrobot-v1:
    #   normalize: true, n_envs: 16, n_timesteps: 5e5, policy: MlpPolicy, ent_coef: .0
    "a2c": {"source": "rl-baselines3-zoo hyperparams/a2c.yml: Acrobot-v1", "zoo_n_timesteps": 500_000,
            "normalize": True, "n_envs": 16,
            "kwargs": {"policy": "MlpPolicy", "ent_coef": 0.0}},
    # hyperparams/trpo.yml (the zoo's file for sb3-contrib's TRPO), key Acrobot-v1 ("# Tuned"):
    #   normalize: true, n_envs: 2, n_timesteps: 1e5, policy: MlpPolicy, n_steps: 1024
    "trpo": {"source": "rl-baselines3-zoo hyperparams/trpo.yml: Acrobot-v1", "zoo_n_timesteps": 100_000,
             "normalize": True, "n_envs": 2,
             "kwargs": {"policy": "MlpPolicy", "n_steps": 1024}},
    # hyperparams/sac.yml, key Pendulum-v1:
    #   n_timesteps: 20000, policy: MlpPolicy, learning_rate: !!float 1e-3   (everything else SB3's default:
    #   buffer_size 1e6, learning_starts 100, batch_size 256, tau 0.005, gamma 0.99, ent_coef auto)
    "sac": {"source": "rl-baselines3-zoo hyperparams/sac.yml: Pendulum-v1", "zoo_n_timesteps": 20_000,
            "normalize": False, "n_envs": 1,
            "kwargs": {"policy": "MlpPolicy", "learning_rate": 1e-3}},
    # hyperparams/td3.yml, key Pendulum-v1 (Pendulum-v0 before the gymnasium rename, same values):
    #   n_timesteps: 20000, policy: MlpPolicy, gamma: 0.98, buffer_size: 200000, learning_starts: 10000,
    #   noise_type: normal, noise_std: 0.1, gradient_steps: -1, train_freq: [1, "episode"],
    #   learning_rate: !!float 1e-3, policy_kwargs: "dict(net_arch=[400, 300])"
    "td3": {"source": "rl-baselines3-zoo hyperparams/td3.yml: Pendulum-v1", "zoo_n_timesteps": 20_000,
            "normalize": False, "n_envs": 1, "noise_type": "normal", "noise_std": 0.1,
            "kwargs": {"policy": "MlpPolicy", "gamma": 0.98, "buffer_size": 200_000, "learning_starts": 10_000,
                       "gradient_steps": -1, "train_freq": [1, "episode"], "learning_rate": 1e-3,
                       "policy_kwargs": {"net_arch": [400, 300]}}},
}


class UsageError(Exception):
    """A problem with the user's input or run folders: reported as one line, no traceback."""


# --------------------------------------------------------------------------------------- small helpers


def hyperparameters(algo: str) -> dict:
    """The JSON form of ``ZOO[algo]`` (what progress.json records and a resume compares against)."""
    return json.loads(json.dumps(ZOO[algo]))


def algorithm_class(algo: str):
    """The SB3 (or sb3-contrib, for TRPO) class of ``algo``."""
    if algo == "trpo":
        try:
            from sb3_contrib import TRPO
        except ImportError as exc:
            raise UsageError('TRPO needs sb3-contrib: pip install -c constraints.txt -e ".[sb3]"') from exc
        return TRPO
    import stable_baselines3 as sb3

    return {"ppo": sb3.PPO, "a2c": sb3.A2C, "sac": sb3.SAC, "td3": sb3.TD3}[algo]


def model_kwargs(algo: str, n_actions: int) -> dict:
    """Constructor keyword arguments of ``algo`` from :data:`ZOO` (policy excluded), as the zoo builds them."""
    entry = ZOO[algo]
    kwargs = {k: v for k, v in entry["kwargs"].items() if k != "policy"}
    if isinstance(kwargs.get("train_freq"), list):        # zoo: YAML list -> tuple (1, "episode")
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    if "policy_kwargs" in kwargs:
        kwargs["policy_kwargs"] = dict(kwargs["policy_kwargs"])
    if entry.get("noise_type") is not None:
        kwargs["action_noise"] = action_noise(entry["noise_type"], entry["noise_std"], n_actions)
    return kwargs


def action_noise(noise_type: str, noise_std: float, n_actions: int):
    """The zoo's action noise: ``noise_std * ones(n_actions)`` (SB3 adds it in the [-1, 1] action scale)."""
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

    cls = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}[noise_type]
    return cls(mean=np.zeros(n_actions), sigma=noise_std * np.ones(n_actions))


def resume_seed(seed: int, steps_done: int) -> int:
    """Seed for the envs and RNGs of a run resumed at ``steps_done`` (fresh initial states, reproducible)."""
    if steps_done == 0:
        return seed
    return int(np.random.SeedSequence([seed, steps_done]).generate_state(1)[0] % (2**31 - 1))


def make_venv(algo: str, seed: int):
    """``n_envs`` monitored copies of the env in a DummyVecEnv, as the zoo's ``make_vec_env`` call builds them."""
    import gymnasium as gym

    import hybridctl.envs  # noqa: F401 - registers the gymnasium ids
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv

    # a callable, as the zoo passes (an id string would make SB3 ask for render_mode="rgb_array")
    return make_vec_env(lambda: gym.make(ENV_ID), n_envs=ZOO[algo]["n_envs"], seed=seed, vec_env_cls=DummyVecEnv,
                        monitor_kwargs={"info_keywords": ("success",)})


def new_vecnormalize(venv, algo: str):
    """VecNormalize with the zoo's settings: SB3 defaults, and the entry's gamma when it sets one."""
    from stable_baselines3.common.vec_env import VecNormalize

    kwargs = {"gamma": ZOO[algo]["kwargs"]["gamma"]} if "gamma" in ZOO[algo]["kwargs"] else {}
    return VecNormalize(venv, **kwargs)


def read_curve(path: Path) -> np.ndarray:
    """Rows of ``curve.csv`` (or of its compressed ``curve.csv.xz``, a finished run's) as an (n, 4) float array:
    env_steps, return, length, success."""
    packed = path.with_name(path.name + ".xz")
    if not path.is_file() and packed.is_file():
        text = lzma.decompress(packed.read_bytes()).decode()
    elif path.is_file():
        text = path.read_text()
    else:
        return np.zeros((0, 4))
    rows = [r for r in csv.reader(text.splitlines()) if r and r[0] != CURVE_HEADER[0]]
    return np.array(rows, dtype=float).reshape(-1, 4)


def pack_curve(path: Path) -> None:
    """A finished run's ``curve.csv`` as ``curve.csv.xz`` (the same text, lzma; a ninth of the bytes in the
    records tree): written atomically, then the plain file removed."""
    if path.is_file():
        atomic_write(path.with_name(path.name + ".xz"), lambda f: f.write(lzma.compress(path.read_bytes(), preset=9)))
        path.unlink()


def unpack_curve(path: Path) -> None:
    """Back to a plain ``curve.csv`` (rows are appended to it) when a run is trained further from its
    ``curve.csv.xz``."""
    packed = path.with_name(path.name + ".xz")
    if not path.is_file() and packed.is_file():
        atomic_write(path, lambda f: f.write(lzma.decompress(packed.read_bytes())))
        packed.unlink()


def truncate_curve(path: Path, steps: int) -> None:
    """Drop curve rows past ``steps`` (episodes of a chunk that never reached its checkpoint)."""
    rows = read_curve(path)
    if len(rows) and rows[:, 0].max() > steps:
        keep = rows[rows[:, 0] <= steps]
        atomic_write(path, lambda f: f.write(_curve_text(keep, header=True).encode()))


def _curve_text(rows, header: bool) -> str:
    lines = [",".join(CURVE_HEADER)] if header else []
    lines += [f"{int(s)},{r:.6f},{int(n)},{int(ok)}" for s, r, n, ok in rows]
    return "".join(line + "\n" for line in lines)


def append_curve(path: Path, rows: list) -> None:
    """Append finished-episode rows to ``curve.csv`` (header on a new file) and fsync."""
    new = not path.is_file()
    with open(path, "a", newline="") as f:
        f.write(_curve_text(rows, header=new))
        f.flush()
        os.fsync(f.fileno())


def binned_curve(rows: np.ndarray, bin_steps: int) -> dict:
    """Training curve per ``bin_steps`` env steps: bin end, mean return, success rate, episode count.

    A bin's ``env_steps`` is its end, or the last recorded step for the run's last, partial bin.
    """
    if len(rows) == 0:
        return {"bin_steps": bin_steps, "env_steps": [], "mean_return": [], "success_rate": [], "episodes": []}
    index = np.ceil(rows[:, 0] / bin_steps).astype(int)
    out = {"bin_steps": bin_steps, "env_steps": [], "mean_return": [], "success_rate": [], "episodes": []}
    for b in np.unique(index):
        sel = rows[index == b]
        out["env_steps"].append(int(min(b * bin_steps, rows[:, 0].max())))
        out["mean_return"].append(round(float(sel[:, 1].mean()), 4))
        out["success_rate"].append(round(float(sel[:, 3].mean()), 4))
        out["episodes"].append(int(len(sel)))
    return out


def versions() -> dict:
    """Versions of the learning libraries (the machine record adds torch, numpy, gymnasium)."""
    import importlib.metadata

    found = {}
    for dist in ("stable-baselines3", "sb3-contrib"):
        try:
            found[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            found[dist] = None
    return found


# ------------------------------------------------------------------------------------------ training


class Clock:
    """Wall time since the start of this invocation against ``--time-budget-s`` (None: no budget)."""

    def __init__(self, budget_s: float | None):
        self.start, self.budget_s = time.perf_counter(), budget_s

    def elapsed(self) -> float:
        """Seconds since the start."""
        return time.perf_counter() - self.start

    def expired(self) -> bool:
        """Whether the time budget is used up."""
        return self.budget_s is not None and self.elapsed() >= self.budget_s


def _curve_recorder():
    from stable_baselines3.common.callbacks import BaseCallback

    class CurveRecorder(BaseCallback):
        """Collects (env_steps, return, length, success) of every finished training episode."""

        def __init__(self):
            super().__init__()
            self.rows: list[tuple] = []

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", ()):
                episode = info.get("episode")
                if episode is not None:   # Monitor's record: the raw return, before VecNormalize
                    self.rows.append((self.num_timesteps, float(episode["r"]), int(episode["l"]),
                                      int(bool(episode.get("success", False)))))
            return True

    return CurveRecorder()


def load_run(run_dir: Path, algo: str, progress: dict):
    """The model of a checkpoint, with its env (VecNormalize restored) and replay buffer, ready to learn on."""
    cls = algorithm_class(algo)
    steps = int(progress["steps_done"])
    seed = resume_seed(int(progress["seed"]), steps)
    venv = make_venv(algo, seed)
    if ZOO[algo]["normalize"]:
        venv, npz_steps = load_vecnormalize(run_dir / "vecnormalize.npz", venv, training=True)
        if npz_steps != steps:
            raise UsageError(f"{run_dir}: vecnormalize.npz is at {npz_steps} steps, progress.json at {steps} "
                             "(interrupted while saving?); move the folder away to restart this run")
    # model.zip and replay_buffer.pkl are our own files, written by train_run: loading them with SB3's
    # loaders (which unpickle) is acceptable here; never point --out at run folders from elsewhere.
    model = cls.load(run_dir / "model.zip", env=venv, device="cpu")
    if model.num_timesteps != steps:
        raise UsageError(f"{run_dir}: model.zip is at {model.num_timesteps} steps, progress.json at {steps} "
                         "(interrupted while saving?); move the folder away to restart this run")
    if algo not in ON_POLICY:
        model.load_replay_buffer(run_dir / "replay_buffer.pkl")
        buffer = model.replay_buffer
        if buffer.pos != steps % buffer.buffer_size:
            raise UsageError(f"{run_dir}: replay_buffer.pkl does not match the {steps} steps of progress.json "
                             "(interrupted while saving?); move the folder away to restart this run")
        if ZOO[algo].get("noise_type") is not None:   # a fresh noise object, as the zoo builds it
            model.action_noise = action_noise(ZOO[algo]["noise_type"], ZOO[algo]["noise_std"],
                                              venv.action_space.shape[0])
    model.set_random_seed(seed)
    return model


def save_checkpoint(run_dir: Path, algo: str, model, progress: dict, curve_rows: list) -> None:
    """Write model, replay buffer, VecNormalize statistics and curve rows, then progress.json last."""
    atomic_write(run_dir / "model.zip", model.save)
    if algo not in ON_POLICY:
        atomic_write(run_dir / "replay_buffer.pkl", model.save_replay_buffer)
    if ZOO[algo]["normalize"]:
        save_vecnormalize(model.get_vec_normalize_env(), run_dir / "vecnormalize.npz", steps=model.num_timesteps)
    append_curve(run_dir / "curve.csv", curve_rows)
    write_json(run_dir / "progress.json", progress, indent=1)


def read_progress(run_dir: Path) -> dict | None:
    """The run's progress.json, or None for a run not started."""
    path = run_dir / "progress.json"
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise UsageError(f"{path} is not valid JSON ({exc}); move the folder away to restart this run") from exc


def check_run(run_dir: Path, algo: str, require_checkpoint: bool) -> dict | None:
    """The run's progress.json after checking it may be resumed by this script (None: a fresh run)."""
    progress = read_progress(run_dir)
    if progress is None and require_checkpoint:
        raise UsageError(f"--resume: {run_dir} has no checkpoint (progress.json) to resume from")
    if progress is not None and progress.get("hyperparameters") != hyperparameters(algo):
        raise UsageError(f"{run_dir} was trained with other hyperparameters than this script's ZOO['{algo}']; "
                         "move it away or choose another --out")
    return progress


def train_run(algo: str, seed: int, budget: int, *, out: Path, chunk_steps: int, eval_episodes: int,
              resume: bool, clock: Clock, command: str, machine: Callable[[], dict]) -> dict:
    """Train ``algo`` with ``seed`` up to ``budget`` steps in chunks of ``chunk_steps``, checkpointing after
    each, in ``out/<algo>-s<seed>``; evaluate on ``eval_episodes`` episodes when done. ``resume``: a missing
    checkpoint is an error; ``command`` is recorded in progress.json, with ``machine()`` for a new run.

    Returns a summary: status (done, paused, skipped) and steps.
    """
    import torch

    run_dir = out / f"{algo}-s{seed}"
    progress = check_run(run_dir, algo, resume)
    steps_done = int(progress["steps_done"]) if progress else 0
    summary = {"algo": algo, "seed": seed, "budget": budget, "steps_before": steps_done}
    if steps_done < budget:
        if clock.expired():
            return {**summary, "status": "not started (time budget)", "steps": steps_done}
        run_dir.mkdir(parents=True, exist_ok=True)
        if progress is None:
            progress = {"algo": algo, "seed": seed, "env": ENV_ID, "budget": budget, "steps_done": 0,
                        "train_wall_s": 0.0, "chunks": [], "commands": [], "hyperparameters": hyperparameters(algo),
                        "versions": versions(), "machine": machine()}
            venv = make_venv(algo, seed)
            if ZOO[algo]["normalize"]:
                venv = new_vecnormalize(venv, algo)
            model = algorithm_class(algo)(ZOO[algo]["kwargs"]["policy"], venv, seed=seed, verbose=0, device="cpu",
                                          **model_kwargs(algo, venv.action_space.shape[0]))
        else:
            unpack_curve(run_dir / "curve.csv")
            truncate_curve(run_dir / "curve.csv", steps_done)
            model = load_run(run_dir, algo, progress)
        progress["budget"] = budget
        progress["commands"].append(command)
        model.set_logger(silent_logger())
        recorder = _curve_recorder()
        host = platform.node()
        while model.num_timesteps < budget:
            start_steps = model.num_timesteps
            started = time.perf_counter()
            # constant learning rates and clip ranges: chunking does not change SB3's schedules here
            model.learn(min(chunk_steps, budget - start_steps), reset_num_timesteps=False,
                        callback=recorder, progress_bar=False)
            wall = time.perf_counter() - started
            progress["steps_done"] = int(model.num_timesteps)
            progress["train_wall_s"] = float(progress["train_wall_s"] + wall)
            progress["chunks"].append({"from": int(start_steps), "to": int(model.num_timesteps),
                                       "wall_s": round(wall, 3),
                                       "steps_per_s": round((model.num_timesteps - start_steps) / wall, 1),
                                       "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                                       "host": host, "torch_threads": torch.get_num_threads()})
            (run_dir / "eval.json").unlink(missing_ok=True)      # the model changed: its eval is stale
            save_checkpoint(run_dir, algo, model, progress, recorder.rows)
            recorder.rows = []
            rate = (model.num_timesteps - start_steps) / wall
            print(f"[{algo}-s{seed}] {model.num_timesteps}/{budget} steps, chunk {wall:.1f} s ({rate:,.0f} steps/s), "
                  f"elapsed {clock.elapsed():.0f} s", file=sys.stderr, flush=True)
            if model.num_timesteps < budget and clock.expired():
                model.get_env().close()
                return {**summary, "status": "paused (time budget)", "steps": int(model.num_timesteps)}
        model.get_env().close()
        steps_done = int(model.num_timesteps)
    pack_curve(run_dir / "curve.csv")
    result = {**summary, "status": "done" if summary["steps_before"] < budget else "skipped (at budget)",
              "steps": steps_done}
    eval_path = run_dir / "eval.json"
    current = json.loads(eval_path.read_text()) if eval_path.is_file() else None
    if current is None or current.get("env_steps") != steps_done or current.get("episodes") != eval_episodes:
        current = evaluate_run(run_dir, algo, seed, eval_episodes)
        write_json(eval_path, current, indent=1)
        result["evaluated"] = True
    result["eval"] = {k: current[k] for k in ("mean_return", "std_return", "success_rate")}
    return result


# ---------------------------------------------------------------------------------------- evaluation


def evaluate_run(run_dir: Path, algo: str, seed: int, episodes: int) -> dict:
    """Deterministic return and thesis success rate of the run's model on ``episodes`` fresh episodes.

    Episode ``k`` starts from ``reset(seed=10000 + seed + k)``; observations are normalised with the
    run's frozen VecNormalize statistics (no reward normalisation).
    """
    import gymnasium as gym

    import hybridctl.envs  # noqa: F401 - registers the gymnasium ids
    from stable_baselines3.common.vec_env import DummyVecEnv

    model = algorithm_class(algo).load(run_dir / "model.zip", device="cpu")   # our own file (see load_run)
    normalizer = None
    if ZOO[algo]["normalize"]:
        normalizer, _ = load_vecnormalize(run_dir / "vecnormalize.npz", DummyVecEnv([lambda: gym.make(ENV_ID)]),
                                          training=False)
    env = gym.make(ENV_ID)
    returns, successes = [], []
    started = time.perf_counter()
    for k in range(episodes):
        obs, _ = env.reset(seed=EVAL_SEED_BASE + seed + k)
        total, done, info = 0.0, False, {}
        while not done:
            x = normalizer.normalize_obs(obs) if normalizer is not None else obs
            action, _ = model.predict(x, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        successes.append(bool(info.get("success", False)))
    env.close()
    return {"algo": algo, "seed": seed, "env": ENV_ID, "env_steps": int(model.num_timesteps), "episodes": episodes,
            "episode_seeds": [EVAL_SEED_BASE + seed, EVAL_SEED_BASE + seed + episodes - 1], "deterministic": True,
            "mean_return": float(np.mean(returns)), "std_return": float(np.std(returns)),
            "min_return": float(np.min(returns)), "max_return": float(np.max(returns)),
            "success_rate": float(np.mean(successes)), "returns": [round(r, 4) for r in returns],
            "eval_wall_s": round(time.perf_counter() - started, 3)}



# -------------------------------------------------------------------------------------------- report


RUN_DIR_RE = re.compile(r"^(?P<algo>[a-z0-9]+)-s(?P<seed>\d+)$")


def collect_runs(out: Path, curve_bin: int) -> list[dict]:
    """One record per run folder under ``out``: progress, evaluation and the binned training curve."""
    runs = []
    for run_dir in sorted(p for p in out.iterdir() if p.is_dir()) if out.is_dir() else []:
        match = RUN_DIR_RE.match(run_dir.name)
        if not match or match["algo"] not in ALGOS:
            continue
        progress = read_progress(run_dir)
        if progress is None:
            continue
        eval_path = run_dir / "eval.json"
        evaluation = json.loads(eval_path.read_text()) if eval_path.is_file() else None
        steps = int(progress["steps_done"])
        wall = float(progress["train_wall_s"])
        runs.append({"algo": match["algo"], "seed": int(match["seed"]), "run_dir": str(run_dir), "steps": steps,
                     "budget": progress.get("budget"), "complete": steps >= int(progress.get("budget") or 0),
                     "train_wall_s": round(wall, 3), "steps_per_s": round(steps / wall, 1) if wall > 0 else None,
                     "chunks": len(progress["chunks"]),
                     "hosts": sorted({c.get("host") for c in progress["chunks"] if c.get("host")}),
                     "eval": None if evaluation is None else
                     {k: evaluation[k] for k in ("env_steps", "episodes", "mean_return", "std_return", "min_return",
                                                 "max_return", "success_rate")},
                     "curve": binned_curve(read_curve(run_dir / "curve.csv"), curve_bin)})
    return runs


def summarise(runs: list[dict]) -> dict:
    """Per algorithm (upper-case key): seeds, steps, mean +- std over seeds of the deterministic return."""
    table = {}
    for algo in ALGOS:
        rows = [r for r in runs if r["algo"] == algo]
        if not rows:
            continue
        evaluated = [r for r in rows if r["eval"] is not None and r["eval"]["env_steps"] == r["steps"]]
        returns = [r["eval"]["mean_return"] for r in evaluated]
        thesis = THESIS_TABLE_3_1.get(algo.upper())
        table[algo.upper()] = {
            "seeds": len(evaluated), "seed_list": [r["seed"] for r in evaluated],
            "seeds_unevaluated": [r["seed"] for r in rows if r not in evaluated],
            "steps": [r["steps"] for r in rows],
            "mean_return": float(np.mean(returns)) if returns else None,
            "std_over_seeds": float(np.std(returns)) if returns else None,
            "success_rate": float(np.mean([r["eval"]["success_rate"] for r in evaluated])) if evaluated else None,
            "train_wall_s_mean": float(np.mean([r["train_wall_s"] for r in rows])),
            "train_wall_s_total": float(np.sum([r["train_wall_s"] for r in rows])),
            "hyperparameters_source": ZOO[algo]["source"],
            "thesis": list(thesis) if thesis else None}
    return table
