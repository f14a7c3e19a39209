"""Thesis Table 3.1: Stable-Baselines3 SAC, TD3, PPO and A2C on the same acrobot env and budget.

    .venv/bin/pip install -c constraints.txt -e ".[baselines]"
    .venv/bin/python benchmarks/ssac_baselines.py --steps 2000000 --seeds 0 1 2 3      # hours per algorithm
    .venv/bin/python benchmarks/ssac_baselines.py --steps 20000 --seeds 0 --algos sac   # a smoke run

Each algorithm trains on ``gymnasium.make("hybridctl/AcrobotSwingup-v0")`` (thesis
dynamics, reward, 0.2 s decisions, 50 per episode) for ``--steps`` environment
interactions per seed, with Stable-Baselines3's default hyperparameters (the
thesis used rl-zoo's tuned values, which are not available offline here). Each
trained policy is evaluated deterministically on ``--eval-episodes`` episodes
from the spec's initial-state distribution. The printed JSON puts those next to
the thesis' numbers and to hybridctl's SSAC/SAC runs found in ``--runs``
(``runs/train/*/eval.json`` written by ``hybridctl train``).
Not run in CI (SB3 is an optional extra and 2e6 steps take hours on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

THESIS_TABLE_3_1 = {  # mean reward +- std over 4 seeds after 2e6 interactions (thesis Table 3.1)
    "SSAC": (92.12, 2.35), "SAC": (73.01, 11.41), "PPO": (0.43, 8.89), "TD3": (78.67, 61.85),
    "TRPO": (17.63, 3.39), "A2C": (2.57, 3.63),
}
ALGOS = ("sac", "td3", "ppo", "a2c")


def evaluate(model, env_id: str, episodes: int, seed: int) -> dict:
    """Deterministic return and thesis success rate over ``episodes`` fresh episodes."""
    import gymnasium as gym

    env = gym.make(env_id)
    returns, successes = [], []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        total, done, info = 0.0, False, {}
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        successes.append(bool(info.get("success", False)))
    return {"mean_return": float(np.mean(returns)), "std_return": float(np.std(returns)),
            "success_rate": float(np.mean(successes))}


def train_one(algo: str, env_id: str, steps: int, seed: int, eval_episodes: int) -> dict:
    """Train one SB3 algorithm for ``steps`` interactions; return timing and evaluation."""
    import gymnasium as gym
    import stable_baselines3 as sb3
    import torch

    torch.set_num_threads(1)
    cls = {"sac": sb3.SAC, "td3": sb3.TD3, "ppo": sb3.PPO, "a2c": sb3.A2C}[algo]
    model = cls("MlpPolicy", gym.make(env_id), seed=seed, verbose=0, device="cpu")
    start = time.perf_counter()
    model.learn(total_timesteps=steps, progress_bar=False)
    wall = time.perf_counter() - start
    return {"algo": algo.upper(), "seed": seed, "steps": steps, "train_wall_s": wall,
            "steps_per_s": steps / wall, **evaluate(model, env_id, eval_episodes, 10_000 + seed)}


def hybridctl_runs(runs: Path) -> dict:
    """Per-algorithm summaries of ``hybridctl train`` eval.json files under ``runs``."""
    found: dict[str, list[dict]] = {}
    for path in sorted(runs.glob("*/eval.json")):
        data = json.loads(path.read_text())
        algo = "SSAC" if path.parent.name.startswith("ssac") else "SAC"
        found.setdefault(algo, []).append({"run": str(path.parent), "mean_return": data["mean_return"],
                                           "env_steps": data.get("env_steps")})
    return {a: {"seeds": len(v), "mean_return": float(np.mean([r["mean_return"] for r in v])),
                "std_over_seeds": float(np.std([r["mean_return"] for r in v])), "runs": v}
            for a, v in found.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2_000_000, help="interactions per seed (thesis 2e6)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS))
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--runs", default="runs/train", help="hybridctl train runs to include")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.eval_episodes < 1:
        parser.error("--steps and --eval-episodes must be >= 1")
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        print('stable-baselines3 is not installed: pip install -c constraints.txt -e ".[baselines]"',
              file=sys.stderr)
        return 2
    import hybridctl.envs  # noqa: F401 - registers the gymnasium ids
    env_id = "hybridctl/AcrobotSwingup-v0"
    results = [train_one(a, env_id, args.steps, s, args.eval_episodes) for a in args.algos for s in args.seeds]
    table = {}
    for algo in sorted({r["algo"] for r in results}):
        rows = [r for r in results if r["algo"] == algo]
        table[algo] = {"seeds": len(rows), "mean_return": float(np.mean([r["mean_return"] for r in rows])),
                       "std_over_seeds": float(np.std([r["mean_return"] for r in rows])),
                       "success_rate": float(np.mean([r["success_rate"] for r in rows])),
                       "thesis": THESIS_TABLE_3_1.get(algo)}
    report = {"benchmark": "ssac_baselines", "env": env_id, "steps_per_seed": args.steps,
              "machine": {"python": platform.python_version(), "platform": platform.platform(),
                          "processor": platform.processor()},
              "command": " ".join(["python", "benchmarks/ssac_baselines.py", *(argv or sys.argv[1:])]),
              "stable_baselines3": table, "hybridctl": hybridctl_runs(Path(args.runs)),
              "thesis_table_3_1": {k: {"mean": m, "std": s} for k, (m, s) in THESIS_TABLE_3_1.items()},
              "runs": results}
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
