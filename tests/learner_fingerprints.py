"""Fingerprints of a short seeded run of every learner, to show a refactor changes no user's numbers.

Not a test (pytest does not collect it): floating-point results of a training run depend on the
CPU's kernels, so a fingerprint recorded on one machine need not match another. Run it on one
machine before and after a change and compare:

    python tests/learner_fingerprints.py > before.json
    ...change...
    python tests/learner_fingerprints.py > after.json && diff before.json after.json

Each entry: the evaluation's return statistics and a SHA-256 of the final checkpoint's model.pt
tensors (names, dtypes, shapes and bytes; not its format number), so a change in any weight shows.
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

import torch

from hybridctl.experiments.finetune import finetune_and_report
from hybridctl.experiments.training import train_and_evaluate
from hybridctl.learn.finetune import FineTuneConfig

TINY = {
    "sac": ("pendulum", {"total_steps": 1200, "num_envs": 4, "exploration_steps": 400, "hidden_size": 16,
                         "replay_batch_size": 32, "seed": 3}),
    "ssac": ("acrobot", {"total_steps": 1200, "num_envs": 4, "exploration_steps": 400, "hidden_size": 16,
                         "replay_batch_size": 32, "seed": 3}),
    "ars": ("Pendulum-v1", {"epochs": 3, "n_directions": 4, "top_directions": 2, "episode_steps": 50, "seed": 3,
                         "backend": "serial", "eval_episodes": 3}),
    **{method: ("cartpole", {"epochs": 2, "population": 3, "elites": 2, "batch": 2, "horizon": 40, "short_horizon": 20, "apg_iterations": 2,
                             "seed": 3, "eval_episodes": 3, "backend": "serial", "compile": False})
       for method in ("apg", "shapg", "papg", "cem", "ce-apg")},
}


def model_hash(folder: Path) -> str:
    """SHA-256 over the tensors of ``folder/model.pt`` (sorted names, dtype, shape, bytes)."""
    state = torch.load(folder / "model.pt", weights_only=True)
    digest = hashlib.sha256()

    def walk(prefix, value):
        if isinstance(value, dict):
            for key in sorted(value):
                walk(f"{prefix}.{key}", value[key])
        elif isinstance(value, torch.Tensor):
            digest.update(f"{prefix}:{value.dtype}:{tuple(value.shape)}".encode())
            digest.update(value.detach().contiguous().cpu().numpy().tobytes())
        # other entries (the file's format number) are not the learner's numbers
    walk("", state)
    return digest.hexdigest()[:16]


def numbers(record: dict) -> dict:
    """The evaluation's scalar numbers (times left out: they change run to run)."""
    return {k: v for k, v in sorted(record.items())
            if isinstance(v, (int, float)) and "time" not in k and "per_s" not in k}


def main() -> None:
    """Print one JSON object: algorithm -> evaluation numbers and model hash."""
    torch.set_num_threads(1)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for algorithm, (system, settings) in TINY.items():
            if algorithm == "apg":
                settings = {k: v for k, v in settings.items() if k not in ("population", "elites")}
            out = Path(tmp) / algorithm
            run = train_and_evaluate(algorithm, system, out=out, settings=dict(settings), progress=False,
                                     report=None)
            results[algorithm] = {**numbers(run.evaluation), "model": model_hash(out / "final")}
            print(algorithm, "done", file=sys.stderr)
        ars_final = Path(tmp) / "ars" / "final"
        config = FineTuneConfig(updates=2, n_directions=3, episode_steps=40, seed=3, backend="serial",
                                eval_episodes=3, chunk_size=2)
        report = finetune_and_report("Pendulum-v1", f"ars:{ars_final}", Path(tmp) / "ft", config,
                                     progress=False, figures=False)
        results["finetune"] = {"before": numbers(report["before"]), "after": numbers(report["after"]),
                               "env_steps": report["env_steps"], "model": model_hash(Path(tmp) / "ft" / "final")}
    print(json.dumps(results, indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
