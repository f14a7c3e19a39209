"""Thesis Ch. 6 in direction (Tables 6.1-6.3): fine-tune the agents of :mod:`hybridctl.reproduce.ch6_agents`,
train the same agents on with their own algorithm for comparison, collect the results.

    python -m hybridctl.reproduce.ch6_finetune finetune Pendulum-v1-ppo --updates 50    # -> runs/ch6/identity/...
    python -m hybridctl.reproduce.ch6_finetune finetune Hopper-v5-ppo --updates 20 --reward mesh-mean
    python -m hybridctl.reproduce.ch6_finetune continue Pendulum-v1-ppo                  # same env steps, own algorithm
    python -m hybridctl.reproduce.ch6_finetune ours ssac-acrobot --updates 50            # our SSAC checkpoint
    python -m hybridctl.reproduce.ch6_finetune collect                                   # -> results/ch6/results.json

``finetune`` and ``ours`` run each update's rollouts on ``--backend``/``--workers``/``--address``
(default 2 local processes, as recorded; the numbers do not depend on them).
A finished run (its record.json) is skipped; an interrupted fine-tune resumes from its newest
checkpoint. Agents are read from runs/finetune-agents/AGENT/model.zip (+ vecnormalize.npz), never
unpickled by the fine-tuning; ``continue`` trains on with SB3 itself, which loads the zip with
its own (pickle-based) loader: these are files this machine wrote (trusted). ``collect`` keeps
the records already in results.json and adds the ones found under runs/ch6.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from hybridctl import io
from hybridctl.experiments.finetune import finetune_and_report
from hybridctl.learn.finetune import FineTuneConfig, wilson_interval
from hybridctl.learn.sb3 import silent_logger
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_options, check_backend_flags, command_line,
                                       machine_info)

AGENTS = Path("runs/finetune-agents")
OUT = Path("runs/ch6")
RECORD = RESULTS / "ch6" / "results.json"
EVAL_SEED = 12345
FAILURE_ENVS = ("Hopper-v5", "Walker2d-v5")   # Table 6.2: 300 initial conditions
SOURCES = {"ssac-acrobot": ("acrobot", "ssac:models/policies/ssac-acrobot"),
           # plain SAC of Ch. 3 (return ~86 at 3e5 steps, success 0 %): hybridctl train sac acrobot --seed 0
           # --steps 300000 --set polyak=0.9 --set obs_transform=angle_sincos --out runs/train/sac-acrobot-300k
           "sac-acrobot-300k": ("acrobot", "sac:runs/train/sac-acrobot-300k")}


def agent_record(agent: str) -> dict:
    """The training record of a pretrained agent (budget, steps, wall time, eval)."""
    return io.read_json(AGENTS / agent / "record.json")


def eval_seeds(n: int) -> list[int]:
    """The initial-condition seeds FineTune.evaluate uses (so every comparison sees the same starts)."""
    return [int(s) for s in np.random.default_rng(EVAL_SEED).integers(0, 2 ** 31 - 1, size=n)]


def run_finetune(agent: str, updates: int, reward: str, command: str, parallel: dict | None = None) -> dict:
    """Fine-tune one agent (resumable) and write runs/ch6/REWARD/AGENT/record.json; ``parallel``: the
    rollouts' ``backend``/``workers``/``address`` (default 2 local processes)."""
    rec = agent_record(agent)
    env = rec["env"]
    out = OUT / reward / agent
    if (out / "record.json").exists():
        return io.read_json(out / "record.json")
    episodes = 300 if env in FAILURE_ENVS else 100
    config = FineTuneConfig(updates=updates, reward=reward, eval_episodes=episodes,
                            **(parallel or {"backend": "processes", "workers": 2}))
    resume = (out / "checkpoint").exists() or (out / "before.json").exists()
    report = finetune_and_report(env, f"sb3:{AGENTS / agent / 'model.zip'}", out, config, resume=resume,
                                 overwrite=not resume and out.exists(), progress=False, command=command)
    record = {"kind": "finetune", "agent": agent, "env": env, "algo": rec["algo"], "reward": reward,
              "pretrained": {k: rec.get(k) for k in ("budget", "zoo_n_timesteps", "env_steps", "wall_time_s")},
              **{k: report[k] for k in ("command", "seed", "updates", "n_params", "select", "env_steps",
                                        "train_wall_time_s", "total_wall_time_s", "machine", "before", "after")}}
    io.write_json(out / "record.json", record)
    return record


def run_continue(agent: str, steps: int | None, cap_scale: float, command: str) -> dict:
    """Train the agent on with its own algorithm for the fine-tune's env steps (capped at
    ``cap_scale`` x its own training budget), then evaluate it like FineTune.evaluate."""
    import gymnasium as gym
    import stable_baselines3 as sb3
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    rec = agent_record(agent)
    env_id, algo = rec["env"], rec["algo"]
    out = OUT / "continue" / agent
    if (out / "record.json").exists():
        return io.read_json(out / "record.json")
    tuned = OUT / "identity" / agent / "record.json"
    target = steps if steps is not None else (io.read_json(tuned)["env_steps"] if tuned.exists() else None)
    if target is None:
        raise SystemExit(f"no fine-tune record for {agent} ({tuned}); run finetune first or pass --steps")
    cap = int(cap_scale * rec["budget"])
    done_steps = min(int(target), cap)
    if algo == "tqc":
        import sb3_contrib
        cls = sb3_contrib.TQC
    else:
        cls = getattr(sb3, algo.upper())
    venv = DummyVecEnv([lambda: gym.make(env_id)])
    npz = AGENTS / agent / "vecnormalize.npz"
    if npz.exists():
        stats = np.load(npz)
        venv = VecNormalize(venv, norm_obs=bool(stats["norm_obs"]) if "norm_obs" in stats else True,
                            clip_obs=float(stats["clip_obs"]), epsilon=float(stats["epsilon"]))
        venv.obs_rms.mean, venv.obs_rms.var, venv.obs_rms.count = stats["mean"], stats["var"], float(stats["count"])
    # SB3's own loader (cloudpickle): this zip was written on this machine by finetune_agents.py
    model = cls.load(AGENTS / agent / "model.zip", env=venv, device="cpu")
    model.set_logger(silent_logger())
    start = time.perf_counter()
    model.learn(total_timesteps=done_steps, reset_num_timesteps=False)
    wall = time.perf_counter() - start
    episodes = 300 if env_id in FAILURE_ENVS else 100
    returns, fails = [], 0
    env = gym.make(env_id)
    for seed in eval_seeds(episodes):
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            seen = venv.normalize_obs(obs) if isinstance(venv, VecNormalize) else obs
            action, _ = model.predict(seen, deterministic=True)
            obs, r, term, trunc, _ = env.step(action)
            total += float(r)
            done = term or trunc
        returns.append(total)
        fails += bool(term)
    r = np.asarray(returns)
    record = {"kind": "continue", "agent": agent, "env": env_id, "algo": algo, "command": command,
              "env_steps_target": int(target), "env_steps": done_steps, "capped": done_steps < int(target),
              "cap": cap, "train_wall_time_s": wall, "machine": machine_info(),
              "notes": "replay buffers and reward-normalisation statistics were not saved with the agent: "
                       "off-policy learners start from an empty buffer, VecNormalize's return statistics afresh",
              "after": {"episodes": episodes, "seed": EVAL_SEED, "mean_return": float(r.mean()),
                        "std_return": float(r.std()), "min_return": float(r.min()), "failures": fails,
                        "failure_rate": fails / episodes, "failure_interval": wilson_interval(fails, episodes),
                        "returns": r.tolist()}}
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(out / "record.json", record)
    return record


def run_ours(name: str, updates: int, command: str, parallel: dict | None = None) -> dict:
    """Fine-tune one of our own checkpoints (SSAC acrobot) and record the success rate before and after;
    ``parallel`` as for :func:`run_finetune`."""
    env, source = SOURCES[name]
    out = OUT / "ours" / name
    if (out / "record.json").exists():
        return io.read_json(out / "record.json")
    resume = (out / "checkpoint").exists() or (out / "before.json").exists()
    config = FineTuneConfig(updates=updates, eval_episodes=100, **(parallel or {"backend": "processes", "workers": 2}))
    report = finetune_and_report(env, source, out, config, resume=resume, overwrite=not resume and out.exists(),
                                 progress=False, command=command)
    record = {"kind": "ours", "agent": name, "env": env, "source": source,
              **{k: report[k] for k in ("command", "seed", "updates", "n_params", "select", "env_steps",
                                        "train_wall_time_s", "machine", "before", "after")}}
    io.write_json(out / "record.json", record)
    return record


def collect(record: Path = RECORD) -> dict:
    """Merge the committed records (``record``) with the ones under runs/ch6 and write ``record``."""
    key = lambda r: (r["kind"], r.get("reward", ""), r["agent"])   # noqa: E731
    merged = {key(r): r for r in (io.read_json(record)["runs"] if record.exists() else [])}
    merged.update({key(r): r for r in (io.read_json(p) for p in sorted(OUT.glob("*/*/record.json")))})
    runs = sorted(merged.values(), key=key)
    agents = {}
    for path in sorted(AGENTS.glob("*/record.json")):
        rec = io.read_json(path)
        agents[path.parent.name] = {k: rec.get(k) for k in ("env", "algo", "seed", "zoo_n_timesteps", "budget",
                                                            "env_steps", "wall_time_s", "steps_per_s", "machine")}
        agents[path.parent.name]["eval"] = {k: rec["eval"][k] for k in ("episodes", "mean_return", "std_return")}
    old = io.read_json(record) if record.exists() else {}
    result = {"agents": {**old.get("agents", {}), **agents}, "runs": runs}
    io.write_json(record, result)
    print(f"wrote {record}: {len(runs)} runs, {len(result['agents'])} agents")
    return result


def main(argv: list[str] | None = None) -> int:
    """Parse and run one of the sub-commands."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="cmd", required=True)
    ft = sub.add_parser("finetune")
    ft.add_argument("agents", nargs="+")
    ft.add_argument("--updates", type=int, default=200)
    ft.add_argument("--reward", default="identity")
    add_backend_flags(ft, "processes", "the fine-tuning's rollouts", workers=2)
    co = sub.add_parser("continue")
    co.add_argument("agents", nargs="+")
    co.add_argument("--steps", type=int)
    co.add_argument("--cap-scale", type=float, default=1.0, help="cap: this many x the agent's training budget")
    ours = sub.add_parser("ours")
    ours.add_argument("names", nargs="+", choices=sorted(SOURCES))
    ours.add_argument("--updates", type=int, default=200)
    add_backend_flags(ours, "processes", "the fine-tuning's rollouts", workers=2)
    co = sub.add_parser("collect")
    co.add_argument("--record", type=Path, default=RECORD, help=f"the record to update (default {RECORD})")
    args = parser.parse_args(argv)
    if args.cmd in ("finetune", "ours"):
        check_backend_flags(args, ft if args.cmd == "finetune" else ours)
    command = command_line("hybridctl.reproduce.ch6_finetune", argv)
    torch.set_num_threads(1)
    if args.cmd == "finetune":
        for agent in args.agents:
            r = run_finetune(agent, args.updates, args.reward, command, backend_options(args))
            print(agent, f"{r['before']['mean_return']:.1f} -> {r['after']['mean_return']:.1f}", flush=True)
    elif args.cmd == "continue":
        for agent in args.agents:
            r = run_continue(agent, args.steps, args.cap_scale, command)
            print(agent, f"continued {r['env_steps']} steps -> {r['after']['mean_return']:.1f}", flush=True)
    elif args.cmd == "ours":
        for name in args.names:
            r = run_ours(name, args.updates, command, backend_options(args))
            print(name, f"success {r['before']['success_rate']} -> {r['after']['success_rate']}", flush=True)
    else:
        collect(args.record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
