"""Learning: SAC and Switched SAC on batched torch envs (thesis Ch. 3), gate learning, checkpoints;
ARS with dimension post-processing and parallel rollouts, failure rates under disturbances (Ch. 4);
analytic policy gradients through the torch dynamics: APG, PAPG, CEM, CE-APG with GRU policies (Ch. 7);
Stable-Baselines3 checkpoints read without unpickling, for fine-tuning their weights (Ch. 6, :mod:`.sb3`).
Every learner stands on the training skeleton of :mod:`.run` (run log, checkpoints, resume,
callbacks, NaN guard, evaluation results).

>>> from hybridctl.learn import SAC, SSAC
>>> agent = SAC("acrobot", seed=0).learn(total=200_000, out="runs/sac")
>>> agent = SSAC("acrobot", seed=0).learn(out="runs/ssac")
"""

from .apg import APG, APGConfig
from .ars import ARS, ARSConfig
from .finetune import FineTune, FineTuneConfig
from .finetune_sources import TunablePolicy
from .checkpoint import CheckpointError, resolve_checkpoint_dir, write_checkpoint_dir
from .registry import load_controller, register_learner, registered_learners, trainable_learners
from .gate import GateConfig, GateNet, fit_gate, gate_metrics, warm_start_gate
from .policies import Policy, PolicyPopulation
from .networks import Actor, DeterministicPolicy, ObsTransform, QNetwork
from .replay import EpisodeStaging, ReplayBuffer, sample_mixed
from .base import Learner
from .callbacks import Callback, CallbackList
from .checkpoint import Checkpointer, Saved
from .run import EvalResult, check_finite
from .runlog import RunLog
from .sac import SAC, SACConfig
from .robustness import failure_rates
from .sb3 import SB3Agent, load_sb3, silent_logger
from .sb3_normalizer import Normalizer
from .sb3_policy import SB3Policy
from ..parallel import ProcessBackend, RayBackend, SerialBackend, make_backend
from .ssac import SSAC, SSACConfig
from .gate_data import GateDataset

__all__ = ["APG", "APGConfig", "FineTune", "FineTuneConfig", "TunablePolicy", "Policy", "PolicyPopulation", "SAC", "SACConfig", "SSAC", "SSACConfig", "GateDataset", "Actor", "QNetwork", "ObsTransform",
           "DeterministicPolicy", "ReplayBuffer", "EpisodeStaging", "sample_mixed", "plot_training_curves",
           "CheckpointError", "silent_logger", "resolve_checkpoint_dir", "write_checkpoint_dir", "GateConfig", "GateNet",
           "fit_gate", "gate_metrics", "warm_start_gate", "load_controller", "register_learner", "registered_learners", "trainable_learners", "ARS", "ARSConfig", "failure_rates",
           "make_backend", "SerialBackend", "ProcessBackend", "RayBackend",
           "Learner", "Saved", "Checkpointer", "RunLog", "Callback", "CallbackList", "EvalResult", "check_finite",
           "load_sb3", "SB3Agent", "SB3Policy", "Normalizer"]


def __getattr__(name):
    # plot_training_curves lives in hybridctl.viz.training (matplotlib): re-exported on first use,
    # so that importing the learners does not load matplotlib
    if name == "plot_training_curves":
        from ..viz.training import plot_training_curves
        return plot_training_curves
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
