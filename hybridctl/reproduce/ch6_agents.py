"""Thesis Ch. 6: train the Stable-Baselines3 agents that the fine-tuning starts from.

    python -m hybridctl.reproduce.ch6_agents                          # the default set, ~30-40 min
    python -m hybridctl.reproduce.ch6_agents --only Pendulum-v1:ppo --budget-scale 0.05   # smoke run
    python -m hybridctl.reproduce.ch6_agents --out runs/agents-s1 --seed 1 --only Hopper-v5:ppo

The thesis fine-tunes RL-Zoo agents; the Zoo's trained files cannot be downloaded here, so we
train our own with the Zoo's hyperparameters, transcribed below from
``DLR-RM/rl-baselines3-zoo`` ``hyperparams/<algo>.yml`` (the commit of each file is named in
``ZOO_SOURCES``). The Zoo's v4/v2/v0 env names are mapped to what gymnasium 1.4 has
(``ENV_ALIASES``). Zoo conventions handled here: ``n_envs`` (DummyVecEnv), ``normalize`` (True
or a dict string -> VecNormalize, with the Zoo's ``gamma`` passed on as the Zoo does),
``policy_kwargs`` strings (evaluated with only ``dict`` and ``nn`` in scope), ``lin_<x>``
schedules (SB3's picklable ``LinearSchedule(x, 0, 1)`` = ``x * progress_remaining``),
``noise_type``/``noise_std`` (Normal / Ornstein-Uhlenbeck action noise), ``train_freq`` lists
(-> tuples), ``n_timesteps`` (the Zoo's budget; ours is ``min(Zoo, BUDGET_CAPS)`` times
``--budget-scale``; on-policy runs round up to whole rollouts).

For each agent, ``OUT/<env>-<algo>/`` gets ``model.zip`` (``model.save``), ``vecnormalize.npz``
when normalised (``mean``, ``var``, ``count``, ``clip_obs``, ``epsilon``, ``norm_obs``: the
frozen observation statistics, never the VecNormalize pickle) and ``record.json`` (written last:
an agent with a record is done and is skipped on the next run, so a killed run resumes). The
record holds the command, budgets, steps, wall time, the machine and the hyperparameters, and a
deterministic evaluation: 20 episodes, ``deterministic=True``, reset seeds 1000..1019, the
observations normalised with the frozen statistics when the agent was trained normalised.
A merged summary of every record under ``OUT`` goes to ``--summary``
(default ``results/ch6/agents.json``); the final JSON summary is printed. Relative paths are from the
working directory (the repository root, for these commands), and are recorded relative.

One torch thread (two ran SB3 11x slower on the shared 2-core machine).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path

import numpy as np  # noqa: E402

from hybridctl.io import atomic_write, write_json  # noqa: E402
from hybridctl.learn.sb3 import silent_logger  # noqa: E402
from hybridctl.learn.sb3_normalizer import Normalizer  # noqa: E402
from hybridctl.reproduce import common  # noqa: E402
from hybridctl.reproduce.common import RESULTS, recorded_path  # noqa: E402

DEFAULT_OUT = Path("runs") / "finetune-agents"
DEFAULT_SUMMARY = RESULTS / "ch6" / "agents.json"

EVAL_EPISODES = 20
EVAL_SEED0 = 1000

# Where each algorithm's values were read (DLR-RM/rl-baselines3-zoo, the stored version of the file).
ZOO_SOURCES = {
    "ppo": "DLR-RM/rl-baselines3-zoo hyperparams/ppo.yml @ 208b6fdf3a9aa24de44b2e068c6e5f6a07d97fcc",
    "a2c": "DLR-RM/rl-baselines3-zoo hyperparams/a2c.yml @ c6c209e7d487635f0b835fb916ec4468142b28ff",
    "sac": "DLR-RM/rl-baselines3-zoo hyperparams/sac.yml @ c94924e5b31bce36920f29d3eb18b975231bdec4",
    "td3": "DLR-RM/rl-baselines3-zoo hyperparams/td3.yml @ a02f4fbfaefa1c24e9dadc11ff596dc51f740a90",
    "ddpg": "DLR-RM/rl-baselines3-zoo hyperparams/ddpg.yml @ 1159e2840a3df711dcc590331110853a68027306",
    "tqc": "DLR-RM/rl-baselines3-zoo hyperparams/tqc.yml @ 994cc30e6b3ac2bb3b27ca2429eb2bf103349b7d",
}

# Zoo env name -> the gymnasium 1.4 env we train on.
ENV_ALIASES = {
    "Pendulum-v0": "Pendulum-v1",
    "LunarLanderContinuous-v2": "LunarLanderContinuous-v3",
    "Hopper-v3": "Hopper-v5", "Hopper-v4": "Hopper-v5",
    "Walker2d-v3": "Walker2d-v5", "Walker2d-v4": "Walker2d-v5",
}

# (our env, algo) -> (the entry's name in the Zoo file, its values transcribed as written there).
ZOO = {
    # hyperparams/ppo.yml, "Pendulum-v1" (# Tuned)
    ("Pendulum-v1", "ppo"): ("Pendulum-v1", dict(
        n_envs=4, n_timesteps=1e5, policy="MlpPolicy", n_steps=1024, gae_lambda=0.95, gamma=0.9,
        n_epochs=10, ent_coef=0.0, learning_rate=1e-3, clip_range=0.2, use_sde=True, sde_sample_freq=4)),
    # hyperparams/sac.yml, "Pendulum-v1"
    ("Pendulum-v1", "sac"): ("Pendulum-v1", dict(
        n_timesteps=20000, policy="MlpPolicy", learning_rate=1e-3)),
    # hyperparams/td3.yml, "Pendulum-v0" (the stored td3.yml has no v1 entry)
    ("Pendulum-v1", "td3"): ("Pendulum-v0", dict(
        n_timesteps=20000, policy="MlpPolicy", gamma=0.98, buffer_size=200000, learning_starts=10000,
        noise_type="normal", noise_std=0.1, gradient_steps=-1, train_freq=[1, "episode"],
        learning_rate=1e-3, policy_kwargs="dict(net_arch=[400, 300])")),
    # hyperparams/a2c.yml, "Pendulum-v1" (# Tuned)
    ("Pendulum-v1", "a2c"): ("Pendulum-v1", dict(
        normalize=True, n_envs=8, n_timesteps=1e6, policy="MlpPolicy", ent_coef=0.0, max_grad_norm=0.5,
        n_steps=8, gae_lambda=0.9, vf_coef=0.4, gamma=0.9, use_rms_prop=True, normalize_advantage=False,
        learning_rate="lin_7e-4", use_sde=True, policy_kwargs="dict(log_std_init=-2, ortho_init=False)")),
    # hyperparams/ddpg.yml, "Pendulum-v0" (the stored ddpg.yml has no v1 entry)
    ("Pendulum-v1", "ddpg"): ("Pendulum-v0", dict(
        n_timesteps=20000, policy="MlpPolicy", gamma=0.98, buffer_size=200000, learning_starts=10000,
        noise_type="normal", noise_std=0.1, gradient_steps=-1, train_freq=[1, "episode"],
        learning_rate=1e-3, policy_kwargs="dict(net_arch=[400, 300])")),
    # hyperparams/tqc.yml, "Pendulum-v0" (the stored tqc.yml has no v1 entry)
    ("Pendulum-v1", "tqc"): ("Pendulum-v0", dict(
        n_timesteps=20000, policy="MlpPolicy", learning_rate=1e-3, use_sde=True, gradient_steps=64,
        train_freq=64, policy_kwargs="dict(log_std_init=-2, net_arch=[64, 64])")),
    # hyperparams/ppo.yml, "MountainCarContinuous-v0" (# Tuned)
    ("MountainCarContinuous-v0", "ppo"): ("MountainCarContinuous-v0", dict(
        normalize=True, n_envs=1, n_timesteps=20000, policy="MlpPolicy", batch_size=256, n_steps=8,
        gamma=0.9999, learning_rate=7.77e-05, ent_coef=0.00429, clip_range=0.1, n_epochs=10,
        gae_lambda=0.9, max_grad_norm=5, vf_coef=0.19, use_sde=True,
        policy_kwargs="dict(log_std_init=-3.29, ortho_init=False)")),
    # hyperparams/sac.yml, "MountainCarContinuous-v0" (# Tuned)
    ("MountainCarContinuous-v0", "sac"): ("MountainCarContinuous-v0", dict(
        n_timesteps=50000, policy="MlpPolicy", learning_rate=3e-4, buffer_size=50000, batch_size=512,
        ent_coef=0.1, train_freq=32, gradient_steps=32, gamma=0.9999, tau=0.01, learning_starts=0,
        use_sde=True, policy_kwargs="dict(log_std_init=-3.67, net_arch=[64, 64])")),
    # hyperparams/ppo.yml, "LunarLanderContinuous-v3"
    ("LunarLanderContinuous-v3", "ppo"): ("LunarLanderContinuous-v3", dict(
        n_envs=16, n_timesteps=1e6, policy="MlpPolicy", n_steps=1024, batch_size=64, gae_lambda=0.98,
        gamma=0.999, n_epochs=4, ent_coef=0.01)),
    # hyperparams/ppo.yml, "Hopper-v4"
    ("Hopper-v5", "ppo"): ("Hopper-v4", dict(
        normalize=True, n_envs=1, policy="MlpPolicy", n_timesteps=1e6, batch_size=32, n_steps=512,
        gamma=0.999, learning_rate=9.80828e-05, ent_coef=0.00229519, clip_range=0.2, n_epochs=5,
        gae_lambda=0.99, max_grad_norm=0.7, vf_coef=0.835671,
        policy_kwargs="dict(log_std_init=-2, ortho_init=False, activation_fn=nn.ReLU, "
                      "net_arch=dict(pi=[256, 256], vf=[256, 256]))")),
    # hyperparams/ppo.yml, "Walker2d-v4"
    ("Walker2d-v5", "ppo"): ("Walker2d-v4", dict(
        normalize=True, n_envs=1, policy="MlpPolicy", n_timesteps=1e6, batch_size=32, n_steps=512,
        gamma=0.99, learning_rate=5.05041e-05, ent_coef=0.000585045, clip_range=0.1, n_epochs=20,
        gae_lambda=0.95, max_grad_norm=1, vf_coef=0.871923)),
}

# What this machine affords (2 shared cores, one torch thread); None = the Zoo's budget.
BUDGET_CAPS = {
    ("Pendulum-v1", "ppo"): None, ("Pendulum-v1", "sac"): None, ("Pendulum-v1", "td3"): None,
    ("Pendulum-v1", "a2c"): 300_000, ("Pendulum-v1", "ddpg"): None, ("Pendulum-v1", "tqc"): None,
    ("MountainCarContinuous-v0", "ppo"): None, ("MountainCarContinuous-v0", "sac"): None,
    ("LunarLanderContinuous-v3", "ppo"): 300_000,
    ("Hopper-v5", "ppo"): 200_000,
    ("Walker2d-v5", "ppo"): 200_000,
}

DEFAULT_ORDER = [
    ("Pendulum-v1", "ppo"), ("Pendulum-v1", "sac"), ("Pendulum-v1", "td3"), ("Pendulum-v1", "a2c"),
    ("Pendulum-v1", "ddpg"), ("Pendulum-v1", "tqc"),
    ("MountainCarContinuous-v0", "ppo"), ("MountainCarContinuous-v0", "sac"),
    ("LunarLanderContinuous-v3", "ppo"), ("Hopper-v5", "ppo"), ("Walker2d-v5", "ppo"),
]

# MountainCarContinuous SAC runs by default only if Pendulum SAC was fast enough (steps/s).
CONDITIONS = {("MountainCarContinuous-v0", "sac"): (("Pendulum-v1", "sac"), 150.0)}


def agent_dir(out: Path, env_id: str, algo: str) -> Path:
    return out / f"{env_id}-{algo}"


def zoo_budget(key) -> int:
    return int(ZOO[key][1]["n_timesteps"])


def our_budget(key, scale: float) -> int:
    cap = BUDGET_CAPS.get(key)
    base = zoo_budget(key) if cap is None else min(zoo_budget(key), cap)
    return max(1, int(round(base * scale)))


# ---------------------------------------------------------------- Zoo conventions -> SB3 arguments

def _schedule(value):
    """'lin_7e-4' -> SB3's LinearSchedule (value x progress_remaining, as the Zoo's linear_schedule)."""
    if isinstance(value, str) and value.startswith("lin_"):
        from stable_baselines3.common.utils import LinearSchedule

        return LinearSchedule(float(value[4:]), 0.0, 1.0)
    return float(value) if isinstance(value, str) else value


def _eval_kwargs(text: str) -> dict:
    """A Zoo policy_kwargs / normalize string, e.g. "dict(activation_fn=nn.ReLU)", as a dict."""
    from torch import nn

    value = eval(text, {"__builtins__": {}, "dict": dict, "nn": nn, "True": True, "False": False})  # noqa: S307
    if not isinstance(value, dict):
        raise ValueError(f"not a dict: {text!r}")
    return value


def resolve(hp: dict, n_actions: int) -> tuple[dict, dict]:
    """Split the Zoo entry into (SB3 constructor kwargs, env settings)."""
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

    hp = dict(hp)
    env_cfg = {"n_envs": int(hp.pop("n_envs", 1)), "normalize": hp.pop("normalize", False)}
    hp.pop("n_timesteps")
    for unsupported in ("frame_stack", "env_wrapper", "callback", "vec_env_wrapper"):
        if unsupported in hp:
            raise ValueError(f"Zoo key {unsupported!r} is not handled by this script")
    noise_type, noise_std = hp.pop("noise_type", None), hp.pop("noise_std", None)
    kwargs = {}
    for k, v in hp.items():
        if k in ("learning_rate", "clip_range", "clip_range_vf"):
            v = _schedule(v)
        elif k == "policy_kwargs" and isinstance(v, str):
            v = _eval_kwargs(v)
        elif k == "train_freq" and isinstance(v, list):
            v = tuple(v)
        kwargs[k] = v
    if noise_type is not None:
        mean, sigma = np.zeros(n_actions), float(noise_std) * np.ones(n_actions)
        if noise_type == "normal":
            kwargs["action_noise"] = NormalActionNoise(mean=mean, sigma=sigma)
        elif noise_type == "ornstein-uhlenbeck":
            kwargs["action_noise"] = OrnsteinUhlenbeckActionNoise(mean=mean, sigma=sigma)
        else:
            raise ValueError(f"unknown noise_type {noise_type!r}")
    norm = env_cfg["normalize"]
    if isinstance(norm, str):
        env_cfg["normalize_kwargs"] = _eval_kwargs(norm)
        env_cfg["normalize"] = True
    elif norm:
        env_cfg["normalize_kwargs"] = {}
    if env_cfg["normalize"] and "gamma" in kwargs:     # the Zoo's exp_manager does the same
        env_cfg["normalize_kwargs"]["gamma"] = kwargs["gamma"]
    return kwargs, env_cfg


def _algo_class(algo: str):
    import stable_baselines3 as sb3

    if algo == "tqc":
        from sb3_contrib import TQC

        return TQC
    return {"ppo": sb3.PPO, "a2c": sb3.A2C, "sac": sb3.SAC, "td3": sb3.TD3, "ddpg": sb3.DDPG}[algo]


# ---------------------------------------------------------------- files

def machine_info() -> dict:
    """The machine record of every driver (:func:`hybridctl.reproduce.common.machine_info`) with the
    Stable-Baselines3 versions the agents were trained with."""
    return {**common.machine_info(), "stable_baselines3": common.package_version("stable-baselines3"),
            "sb3_contrib": common.package_version("sb3-contrib")}


# ---------------------------------------------------------------- training and evaluation

def evaluate(model, env_id: str, stats: Normalizer | None, episodes: int = EVAL_EPISODES,
             seed0: int = EVAL_SEED0) -> dict:
    """Deterministic return over ``episodes`` episodes reset with seeds seed0, seed0+1, ..."""
    import gymnasium as gym

    env = gym.make(env_id)
    returns, lengths = [], []
    try:
        for k in range(episodes):
            obs, _ = env.reset(seed=seed0 + k)
            total, n, done = 0.0, 0, False
            while not done:
                action, _ = model.predict(stats(obs) if stats is not None else obs, deterministic=True)
                obs, reward, terminated, truncated, _ = env.step(action)
                total += float(reward)
                n += 1
                done = terminated or truncated
            returns.append(total)
            lengths.append(n)
    finally:
        env.close()
    return {"episodes": episodes, "seeds": [seed0, seed0 + episodes - 1], "deterministic": True,
            "obs_normalized": stats is not None and stats.norm_obs,
            "mean_return": float(np.mean(returns)), "std_return": float(np.std(returns)),
            "returns": returns, "mean_length": float(np.mean(lengths))}


def _progress_callback(total: int, label: str):
    from stable_baselines3.common.callbacks import BaseCallback

    class Progress(BaseCallback):
        """One line every ~10 % of the budget (SB3's progress_bar needs rich)."""

        def _on_training_start(self) -> None:
            self.t0, self.next = time.perf_counter(), max(1, total // 10)

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                dt = time.perf_counter() - self.t0
                print(f"  {label}: {self.num_timesteps}/{total} steps ({100 * self.num_timesteps / total:.0f} %),"
                      f" {dt:.0f} s, {self.num_timesteps / max(dt, 1e-9):.0f} steps/s", flush=True)
                while self.next <= self.num_timesteps:
                    self.next += max(1, total // 10)
                if self.num_timesteps >= total:     # on-policy runs overshoot to a whole rollout
                    self.next = float("inf")
            return True

    return Progress()


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    if isinstance(value, type):
        return f"{value.__module__}.{value.__qualname__}"
    return repr(value)


def train_agent(key, out: Path, seed: int, scale: float, command: list[str]) -> dict:
    """Train, save and evaluate one agent; return its record (also written to record.json)."""
    import gymnasium as gym
    import torch
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    env_id, algo = key
    zoo_env, hp = ZOO[key]
    directory = agent_dir(out, env_id, algo)
    directory.mkdir(parents=True, exist_ok=True)
    n_actions = int(np.prod(gym.make(env_id).action_space.shape))
    kwargs, env_cfg = resolve(hp, n_actions)
    budget = our_budget(key, scale)

    venv = make_vec_env(env_id, n_envs=env_cfg["n_envs"], seed=seed, vec_env_cls=DummyVecEnv)
    if env_cfg["normalize"]:
        venv = VecNormalize(venv, **env_cfg["normalize_kwargs"])
    policy = kwargs.pop("policy")
    model = _algo_class(algo)(policy, venv, seed=seed, device="cpu", verbose=0, **kwargs)
    model.set_logger(silent_logger())
    t0 = time.perf_counter()
    model.learn(total_timesteps=budget, callback=_progress_callback(budget, f"{env_id}:{algo}"))
    wall = time.perf_counter() - t0
    steps = int(model.num_timesteps)

    atomic_write(directory / "model.zip", model.save)
    stats = None
    if env_cfg["normalize"]:    # the observation statistics, frozen, as load_sb3 and fine-tuning read them
        Normalizer.from_vecnormalize(venv).save_npz(directory / "vecnormalize.npz")
        stats = Normalizer.from_npz(directory / "vecnormalize.npz")
    t1 = time.perf_counter()
    evaluation = evaluate(model, env_id, stats)
    evaluation["wall_time_s"] = time.perf_counter() - t1
    venv.close()

    record = {
        "command": command, "env": env_id, "algo": algo, "seed": seed,
        "zoo_env": zoo_env, "zoo_source": ZOO_SOURCES[algo],
        "zoo_n_timesteps": zoo_budget(key), "budget_cap": BUDGET_CAPS.get(key), "budget_scale": scale,
        "budget": budget, "env_steps": steps, "wall_time_s": wall, "steps_per_s": steps / wall,
        "normalized": bool(env_cfg["normalize"]),
        "files": ["model.zip"] + (["vecnormalize.npz"] if env_cfg["normalize"] else []) + ["record.json"],
        "machine": machine_info(),
        "hyperparameters": {"zoo": _jsonable(hp), "sb3_kwargs": _jsonable(dict(kwargs, policy=policy)),
                            "env": _jsonable(env_cfg)},
        "eval": evaluation,
    }
    write_json(directory / "record.json", record)
    return record


# ---------------------------------------------------------------- driver

def parse_only(items: list[str]) -> list[tuple[str, str]]:
    keys = []
    for item in items:
        env_id, sep, algo = item.rpartition(":")
        key = (env_id, algo.lower())
        if not sep or key not in ZOO:
            known = ", ".join(f"{e}:{a}" for e, a in DEFAULT_ORDER)
            raise SystemExit(f"--only {item!r}: not one of {known}")
        keys.append(key)
    return keys


def summary_entry(record: dict) -> dict:
    entry = {k: v for k, v in record.items() if k != "hyperparameters"}
    entry["eval"] = {k: v for k, v in record["eval"].items() if k != "returns"}
    return entry


def collect(out: Path) -> dict:
    """Every record.json under ``out``, keyed 'env:algo' (without the bulky hyperparameters)."""
    agents = {}
    for path in sorted(out.glob("*/record.json")):
        record = json.loads(path.read_text())
        agents[f"{record['env']}:{record['algo']}"] = summary_entry(record) | {"dir": path.parent.name}
    return agents


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", action="append", default=[], metavar="ENV:ALGO",
                        help="train only these (repeatable), e.g. Pendulum-v1:ppo")
    parser.add_argument("--budget-scale", type=float, default=1.0, help="multiplies every budget")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="relative paths are from the working directory")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--summary", default=str(DEFAULT_SUMMARY),
                        help="merged summary JSON ('' to skip)")
    args = parser.parse_args(argv)
    if args.budget_scale <= 0:
        parser.error("--budget-scale must be > 0")
    out = args.out
    command = ["python", "-m", "hybridctl.reproduce.ch6_agents",
               *(recorded_path(a) if os.path.isabs(a) else a for a in (sys.argv[1:] if argv is None else argv))]

    import torch

    torch.set_num_threads(1)
    keys = parse_only(args.only) if args.only else list(DEFAULT_ORDER)
    done, skipped, failed = [], {}, {}
    for key in keys:
        label = f"{key[0]}:{key[1]}"
        record_path = agent_dir(out, *key) / "record.json"
        if record_path.exists():
            skipped[label] = "record.json exists"
            print(f"[skip] {label}: {record_path} exists", flush=True)
            continue
        if key in CONDITIONS and not args.only:
            other, threshold = CONDITIONS[key]
            other_path = agent_dir(out, *other) / "record.json"
            rate = json.loads(other_path.read_text())["steps_per_s"] if other_path.exists() else None
            if rate is None or rate < threshold:
                skipped[label] = (f"{other[0]}:{other[1]} ran {rate if rate is None else round(rate)} steps/s"
                                  f" (< {threshold:g}): too slow here")
                print(f"[skip] {label}: {skipped[label]}", flush=True)
                continue
        print(f"[train] {label}: budget {our_budget(key, args.budget_scale)} (Zoo {zoo_budget(key)})", flush=True)
        try:
            record = train_agent(key, out, args.seed, args.budget_scale, command)
        except Exception as exc:  # one agent's failure must not stop the others
            failed[label] = f"{type(exc).__name__}: {exc}"
            traceback.print_exc()
            print(f"[fail] {label}: {failed[label]}", flush=True)
            continue
        done.append(label)
        ev = record["eval"]
        print(f"[done] {label}: {record['env_steps']} steps in {record['wall_time_s']:.0f} s"
              f" ({record['steps_per_s']:.0f}/s), eval {ev['mean_return']:.1f} +- {ev['std_return']:.1f}", flush=True)

    agents = collect(out) if out.exists() else {}
    if args.summary:
        summary_path = Path(args.summary)
        merged = json.loads(summary_path.read_text()).get("agents", {}) if summary_path.exists() else {}
        merged.update(agents)
        summary_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(summary_path, {"source": "hybridctl/reproduce/ch6_agents.py", "out": recorded_path(out),
                                  "agents": dict(sorted(merged.items()))})
    report = {"out": recorded_path(out), "trained": done, "skipped": skipped, "failed": failed,
              "agents": {k: {"budget": a["budget"], "zoo_n_timesteps": a["zoo_n_timesteps"],
                             "env_steps": a["env_steps"], "wall_time_s": round(a["wall_time_s"], 1),
                             "steps_per_s": round(a["steps_per_s"], 1),
                             "eval_mean_return": round(a["eval"]["mean_return"], 2),
                             "eval_std_return": round(a["eval"]["std_return"], 2)} for k, a in agents.items()}}
    print(json.dumps(report, indent=2), flush=True)
    return report


if __name__ == "__main__":
    sys.exit(1 if main()["failed"] else 0)
