"""What fine-tuning (:mod:`hybridctl.learn.finetune`) tunes: a trained policy as a :class:`TunablePolicy`.

The sources (:func:`load_policy`, thesis Ch. 6): Stable-Baselines3 zips read without unpickling, our
ARS checkpoints (their running statistics frozen as an :class:`AffineNormalizer`, the policy in env
units as a :class:`ScaledModule`), SAC / SSAC swing-ups of a system (SSAC with its gate) and the APG
family's recurrent swing-ups under the spec's cost-to-go gate and LQR; the parameter selections.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from ..systems import known_systems
from ..systems import load as load_system
from ..systems.switched import CostToGoGate, Gate, LearnedGate, NeverGate
from .registry import checkpoint_kinds, gate_of_kind, load_deployed
from .rollout_envs import make_env

__all__ = ["SELECTIONS", "source_kinds", "AffineNormalizer", "ScaledModule", "TunablePolicy", "parse_source",
           "load_policy"]

SELECTIONS = ("action", "all", "last")
"""The parameter selections (``FineTuneConfig.select``): the action path, every parameter, the last layer."""


class AffineNormalizer:
    """A frozen ``(obs - mean) / std`` observation normaliser (ARS checkpoints); picklable."""

    def __init__(self, mean, std):
        self.mean, self.std = np.asarray(mean, dtype=np.float64), np.asarray(std, dtype=np.float64)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The normalised observation(s)."""
        return (np.asarray(obs, dtype=np.float64) - self.mean) / self.std

    def to_dict(self) -> dict:
        """JSON-ready statistics."""
        return {"type": "affine", "mean": self.mean.tolist(), "std": self.std.tolist()}


class ScaledModule(torch.nn.Module):
    """``mid + half * net(z)`` clipped to [low, high]: an ARS torch policy in env units."""

    def __init__(self, net: torch.nn.Module | None, obs_dim: int, act_dim: int, low, high):
        super().__init__()
        self.net = net
        # built on the CPU, as the learner's copy of every policy (rollout workers move their own copy)
        if net is None:  # ARS's linear policy: action = M z, M (act_dim, obs_dim)
            self.weight = torch.nn.Parameter(torch.zeros(act_dim, obs_dim, dtype=torch.float64, device="cpu"))
        low = torch.as_tensor(low, dtype=torch.float64, device="cpu")
        high = torch.as_tensor(high, dtype=torch.float64, device="cpu")
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """The action for normalised observations ``z``."""
        if self.net is None:
            y = z @ self.weight.T
        else:
            y = (self.high + self.low) / 2 + (self.high - self.low) / 2 * self.net(z)
        return torch.clamp(y, self.low, self.high)


@dataclass
class TunablePolicy:
    """What fine-tuning needs from a trained agent: a deterministic torch policy of normalised
    observations (actions in env units), its frozen observation normaliser, and where it came from.

    ``module`` may define ``parameter_names(select)`` (SB3 policies do: the action path, all, or
    the last layer); otherwise "action" and "all" are every parameter and "last" the last
    ``nn.Linear``'s. ``system``: a hybridctl system name when the policy drives that system's
    swing-up (sac/ssac/APG-family sources: rollouts on its batched torch env); ``gate``: the
    :class:`~hybridctl.systems.switched.Gate` the rollouts run the swing-up under (SSAC's
    :class:`~hybridctl.systems.switched.LearnedGate`, or the spec's LQR
    :class:`~hybridctl.systems.switched.CostToGoGate`, the APG family's takeover), None (or a
    ``NeverGate``) for none; a torch classifier becomes a ``LearnedGate`` and the registry's gate name
    ``"cost-to-go"`` the ``CostToGoGate`` of ``system`` with ``system_overrides``, once, here;
    ``decision_period``: the swing-up's decision period in seconds (None: the spec's). A recurrent
    ``module`` (``forward(x, state) -> (action, state)``, ``initial_state``) starts each episode at its
    zero state.
    """

    module: torch.nn.Module
    normalizer: Callable[[np.ndarray], np.ndarray] | None = None
    source: str = "module"
    sb3: Any = None                 # the SB3Agent for sb3 sources (written back by save_sb3)
    system: str | None = None
    gate: Gate | None = None
    meta: dict = field(default_factory=dict)
    system_overrides: dict = field(default_factory=dict)   # the checkpoint's spec overrides (reward, starts)
    decision_period: float | None = None

    def __post_init__(self):
        gate = self.gate
        if gate is None or isinstance(gate, NeverGate):
            self.gate = None
        elif isinstance(gate, str):
            if gate != "cost-to-go" or self.system is None:
                raise ValueError(f"a TunablePolicy's gate by name must be 'cost-to-go' (the spec's cost-to-go gate) "
                                 f"with a system, got {gate!r} with system {self.system!r}")
            self.gate = CostToGoGate(load_system(self.system, **self.system_overrides))
        elif not isinstance(gate, Gate):
            self.gate = LearnedGate(gate)   # a torch classifier, e.g. SSAC's GateNet

    def parameter_names(self, select: str) -> list[str]:
        """Names of the parameters perturbed under ``select`` (see :data:`SELECTIONS`)."""
        if select not in SELECTIONS:
            raise ValueError(f"select must be one of {SELECTIONS}, got {select!r}")
        own = getattr(self.module, "parameter_names", None)
        if callable(own):
            return list(own(select))
        names = [n for n, p in self.module.named_parameters()]
        if select == "last":
            linears = [n for n, m in self.module.named_modules() if isinstance(m, torch.nn.Linear)]
            if linears:
                prefix = linears[-1] + "."
                names = [n for n in names if n.startswith(prefix)]
            else:
                names = names[-1:]
        return names


def source_kinds() -> tuple[str, ...]:
    """The ``KIND`` of a ``KIND:PATH`` policy source: ``sb3`` and ``ars`` (gymnasium policies), and every kind
    of a checkpoint that drives a system (:func:`hybridctl.learn.registry.checkpoint_kinds`: ``sac``,
    ``ssac``, the APG family's methods, ``finetune``, any registered learner's name)."""
    return tuple(dict.fromkeys(("sb3", "ars", *checkpoint_kinds())))


def parse_source(text: str) -> tuple[str, str]:
    """"sb3:PATH" -> ("sb3", "PATH"); the kinds are :func:`source_kinds`."""
    kind, sep, path = str(text).partition(":")
    if not sep or kind not in source_kinds() or not path:
        raise ValueError(f"--policy must be KIND:PATH with KIND one of {source_kinds()} (e.g. sb3:runs/agent/model.zip), "
                         f"got {text!r}")
    return kind, path


def load_policy(source: str, env: str, trust: bool = False, normalizer: str | None = None) -> TunablePolicy:
    """The :class:`TunablePolicy` of ``source`` ("sb3:PATH", "ars:PATH", or a checkpoint's controller:
    "sac:PATH", "ssac:PATH", an APG family's "ce-apg:PATH", "papg:PATH", ...) for ``env``.

    sb3: a Stable-Baselines3 zip read without unpickling (:func:`hybridctl.learn.sb3.load_sb3`;
    its normaliser from ``normalizer`` or a ``vecnormalize.npz`` beside it; a pickle only with
    ``trust``). ars: an ARS checkpoint, its running statistics frozen. Every other kind: the
    controller of a checkpoint that drives a system (``env`` must be that system's name), read
    through the learner contract (:func:`hybridctl.learn.registry.load_deployed`: the learner registered
    for its config.json's algorithm, ``learner.controller(system)``), with the gate its kind selects
    (``sac``: none; ``ssac``: the learned gate; ``ssac-costgate``: the spec's cost-to-go gate; other
    kinds the checkpoint's own: SSAC's learned gate, the APG family's cost-to-go gate and LQR at its
    own decision period), on the task it was trained on (``learner.fine_tuning_task()``).
    Raises CheckpointError / ValueError naming the file or what does not fit the env.
    """
    kind, path = parse_source(source)
    if kind == "sb3":
        from .sb3 import load_sb3  # reading a zip needs only torch; SB3 itself is optional
        agent = load_sb3(path, normalizer=normalizer, trust=trust)
        probe = make_env(env)
        try:
            agent.check_env(probe)
        finally:
            probe.close()
        return TunablePolicy(agent.policy, agent.normalizer, source, sb3=agent,
                             meta={"algo": agent.algo, "path": str(path)})
    if kind == "ars":
        from .ars import ARS
        agent = ARS.load(path)
        spec = agent.policy
        module = ScaledModule(spec.module, spec.obs_dim, spec.act_dim, spec.low, spec.high)
        if spec.module is None:
            with torch.no_grad():
                module.weight.copy_(torch.as_tensor(agent.theta.reshape(spec.act_dim, spec.obs_dim), device="cpu"))
        else:
            spec.actor(agent.theta)  # loads theta into the module's weights
        tunable = TunablePolicy(module, AffineNormalizer(agent.stats.mean, agent.stats.std), source,
                                meta={"algo": "ars", "trained_env": agent.env_name})
        _check_gym_spaces(tunable, env, spec.obs_dim, spec.act_dim, path)
        return tunable
    # a checkpoint whose controller drives a system
    if env not in known_systems():
        raise ValueError(f"a {kind}: policy drives a hybridctl system; env must be one of {known_systems()}, "
                         f"got {env!r}")
    learner, controller = load_deployed(path, load_system(env), gate=gate_of_kind(kind))
    if not isinstance(controller.swingup, torch.nn.Module):
        raise ValueError(f"{path}: its swing-up is not a torch module; fine-tuning perturbs a module's weights")
    gate = controller.gate   # the rollouts' gate: a learned module, the spec's cost-to-go gate or none
    if not isinstance(gate, (LearnedGate, CostToGoGate, NeverGate)):
        raise ValueError(f"{path}: fine-tuning runs a swing-up with a learned gate, the spec's cost-to-go gate or "
                         f"none, not {type(gate).__name__}")
    # the task it was trained on: the spec overrides of its reward and starts (the plain spec would tune
    # it for another reward than it learned)
    overrides = learner.fine_tuning_task()
    if isinstance(gate, CostToGoGate):   # the spec's gate of the system the rollouts run on
        gate = CostToGoGate(load_system(env, **overrides))
    period = float(controller.decision_period)
    return TunablePolicy(controller.swingup, None, source, system=env, gate=gate, system_overrides=overrides,
                         decision_period=period,
                         meta={"algo": kind, "trained_algorithm": learner.run_label(learner.config),
                               "system_overrides": overrides, "decision_period": period,
                               "gate": {"gate_on": controller.gate_on, "gate_off": controller.gate_off}})


def _check_gym_spaces(tunable: TunablePolicy, env: str, obs_dim: int, act_dim: int, path) -> None:
    probe = make_env(env)
    try:
        got = (int(np.prod(probe.observation_space.shape)), int(np.prod(probe.action_space.shape)))
    finally:
        probe.close()
    if got != (obs_dim, act_dim):
        raise ValueError(f"{path} has {obs_dim} observations and {act_dim} actions; env {env} has {got[0]} "
                         f"observations and {got[1]} actions")
