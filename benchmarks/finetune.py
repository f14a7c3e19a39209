"""Fine-tuning (thesis Ch. 6): wall time of one update (2 x 64 rollouts of an SB3 PPO agent) for
Pendulum-v1 and Hopper-v5, on three paths measured in the same run:

* ``sb3_predict_loop`` (the peer): what a user writes with SB3 alone, 128 episodes one after
  another, ``model.predict(obs, deterministic=True)`` every step (the perturbed weights loaded
  with ``set_parameters``);
* ``batched_serial``: :class:`hybridctl.learn.FineTune`, one vmapped forward of a chunk's
  policies per step, in this process;
* ``batched_processes``: the same chunks on the local process backend (``--workers``).

Prints one JSON document with seconds per update and ratios against the peer (no thresholds).
Its speed aims: batched >= 10x the predict loop on Pendulum; 200 updates <= 5 min.

    .venv/bin/python benchmarks/finetune.py [--quick] [--workers 2] [--repeats 2] [--out FILE]

The agents are untrained PPO MlpPolicy networks of the RL Zoo's sizes (64-64 for both: the
Zoo's defaults); the time of an update does not depend on what the weights have learnt, only
on the episode lengths, which are recorded (Hopper's episodes end when it falls).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from common import emit, machine_info  # noqa: E402


def make_agent(env_id: str, folder: Path) -> Path:
    """An untrained SB3 PPO agent for ``env_id`` saved as a zip (64-64 tanh MLP, SB3 defaults)."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    model = PPO("MlpPolicy", gym.make(env_id), seed=0, device="cpu", n_steps=64, batch_size=64)
    path = folder / f"{env_id}-ppo.zip"
    model.save(path)
    return path


def predict_loop_update(model, env, thetas: np.ndarray, seeds: list[int], names: list[str]) -> int:
    """The peer: 2n episodes one after another with SB3's predict; returns the env steps."""
    params = dict(model.policy.named_parameters())
    steps = 0
    for theta, seed in zip(thetas, seeds):
        start = 0
        with torch.no_grad():
            for name in names:
                n = params[name].numel()
                params[name].copy_(torch.as_tensor(theta[start:start + n]).view_as(params[name]))
                start += n
        obs, _ = env.reset(seed=int(seed))
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, term, trunc, _ = env.step(action)
            steps += 1
            done = term or trunc
    return steps


def time_paths(env_id: str, zip_path: Path, workers: int, repeats: int, directions: int, peer_updates: int) -> dict:
    """Seconds per update on the three paths for one env."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    from hybridctl.learn.finetune import FineTune
    from hybridctl.parallel import make_backend

    out = {"env": env_id, "directions": directions, "rollouts_per_update": 2 * directions}
    tuner = FineTune(env_id, f"sb3:{zip_path}", updates=200, n_directions=directions, backend="serial")
    out["n_params"] = tuner.n_params
    directions_, seeds = tuner.draws(0)
    alpha, sigma = tuner.config.schedule(0)
    thetas = np.stack([tuner.theta + s * sigma * d for d in directions_ for s in (1.0, -1.0)])
    pair_seeds = [s for s in seeds for _ in (0, 1)]

    model = PPO.load(zip_path, device="cpu")   # our own file, just written: trusted
    env = gym.make(env_id)
    times, steps = [], 0
    for _ in range(peer_updates):
        start = time.perf_counter()
        steps = predict_loop_update(model, env, thetas, pair_seeds, tuner.names)
        times.append(time.perf_counter() - start)
    peer = statistics.median(times)
    out["sb3_predict_loop"] = {"s_per_update": peer, "env_steps": steps, "steps_per_s": steps / peer,
                               "updates_timed": peer_updates}

    for name, backend in (("batched_serial", make_backend("serial")),
                          ("batched_processes", make_backend("processes", workers))):
        with backend:
            tuner.learn(total=tuner.update + 1, progress=False, backend=backend)   # warm-up (worker start)
            times = []
            for _ in range(repeats):
                before = tuner.env_steps
                start = time.perf_counter()
                tuner.learn(total=tuner.update + 1, progress=False, backend=backend)
                times.append(time.perf_counter() - start)
                update_steps = tuner.env_steps - before
        t = statistics.median(times)
        out[name] = {"s_per_update": t, "env_steps": update_steps, "steps_per_s": update_steps / t,
                     "ratio_vs_sb3_predict_loop": (peer / steps) / (t / update_steps),
                     "projected_200_updates_s": 200 * t}
        if name == "batched_processes":
            out[name]["workers"] = workers
    out["note"] = ("ratio_vs_sb3_predict_loop compares time per env step (episode lengths can differ between "
                   "paths once the weights have moved)")
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its JSON report."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="Pendulum only, 8 directions, one repeat")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:   # the peer is SB3 itself: nothing to compare against (make bench goes on)
        emit({"benchmark": "finetune", "skipped": "needs stable-baselines3 (pip install -c constraints.txt -e '.[sb3]')"},
             args.out)
        return 0
    envs = ["Pendulum-v1"]
    if not args.quick:
        try:
            import mujoco  # noqa: F401
            envs.append("Hopper-v5")
        except ImportError:
            pass
    report = {"benchmark": "finetune", "quick": args.quick, "command": sys.argv if argv is None else argv,
              "timestamp": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
              "machine": machine_info(), "results": []}
    with tempfile.TemporaryDirectory() as tmp:
        for env_id in envs:
            path = make_agent(env_id, Path(tmp))
            report["results"].append(time_paths(env_id, path, args.workers, 1 if args.quick else args.repeats,
                                                8 if args.quick else 64, 1))
    emit(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
