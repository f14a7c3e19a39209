"""Learning: SAC and Switched SAC on batched torch envs (thesis Ch. 3), gate learning, checkpoints;
ARS with dimension post-processing and parallel rollouts, failure rates under disturbances (Ch. 4).

>>> from hybridctl.learn import SAC, SSAC
>>> agent = SAC("acrobot", seed=0).learn(total_steps=200_000, log_dir="runs/sac")
>>> agent = SSAC("acrobot", seed=0).learn(log_dir="runs/ssac")
"""

from .ars import ARS, ARSConfig
from .checkpoint import CheckpointError, resolve_checkpoint_dir, write_checkpoint_dir
from .export import load_controller
from .gate import GateConfig, GateNet, fit_gate, gate_metrics, warm_start_gate
from .sac import (Actor, DeterministicPolicy, EpisodeStaging, ObsTransform, QNetwork, ReplayBuffer, SAC,
                  SACConfig, plot_training_curves, sample_mixed)
from .robustness import failure_rates
from ..parallel import ProcessBackend, RayBackend, SerialBackend, make_backend
from .ssac import SSAC, GateDataset, SSACConfig

__all__ = ["SAC", "SACConfig", "SSAC", "SSACConfig", "GateDataset", "Actor", "QNetwork", "ObsTransform",
           "DeterministicPolicy", "ReplayBuffer", "EpisodeStaging", "sample_mixed", "plot_training_curves",
           "CheckpointError", "resolve_checkpoint_dir", "write_checkpoint_dir", "GateConfig", "GateNet",
           "fit_gate", "gate_metrics", "warm_start_gate", "load_controller", "ARS", "ARSConfig", "failure_rates",
           "make_backend", "SerialBackend", "ProcessBackend", "RayBackend"]
