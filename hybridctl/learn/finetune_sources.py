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
from . import checkpoint as ckpt
from .apg import METHODS as APG_METHODS
from .rollouts import COST_TO_GO_GATE, make_env

__all__ = ["SELECTIONS", "SOURCE_KINDS", "AffineNormalizer", "ScaledModule", "TunablePolicy", "parse_source",
           "load_policy"]

SELECTIONS = ("action", "all", "last")
"""The parameter selections (``FineTuneConfig.select``): the action path, every parameter, the last layer."""
SOURCE_KINDS = ("sb3", "ars", "sac", "ssac", *APG_METHODS)
"""The ``KIND`` of a ``KIND:PATH`` policy source."""


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
    swing-up (sac/ssac/APG-family sources: rollouts on its batched torch env); ``gate``: SSAC's gate,
    or :data:`~hybridctl.learn.rollouts.COST_TO_GO_GATE` (the spec's LQR cost-to-go gate, the APG
    family's takeover); ``decision_period``: the swing-up's decision period in seconds (None: the
    spec's). A recurrent ``module`` (``forward(x, state) -> (action, state)``, ``initial_state``)
    starts each episode at its zero state.
    """

    module: torch.nn.Module
    normalizer: Callable[[np.ndarray], np.ndarray] | None = None
    source: str = "module"
    sb3: Any = None                 # the SB3Agent for sb3 sources (written back by save_sb3)
    system: str | None = None
    gate: torch.nn.Module | str | None = None
    meta: dict = field(default_factory=dict)
    system_overrides: dict = field(default_factory=dict)   # the checkpoint's spec overrides (reward, starts)
    decision_period: float | None = None

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


def parse_source(text: str) -> tuple[str, str]:
    """"sb3:PATH" -> ("sb3", "PATH"); the kinds are :data:`SOURCE_KINDS`."""
    kind, sep, path = str(text).partition(":")
    if not sep or kind not in SOURCE_KINDS or not path:
        raise ValueError(f"--policy must be KIND:PATH with KIND one of {SOURCE_KINDS} (e.g. sb3:runs/agent/model.zip), "
                         f"got {text!r}")
    return kind, path


def load_policy(source: str, env: str, trust: bool = False, normalizer: str | None = None) -> TunablePolicy:
    """The :class:`TunablePolicy` of ``source`` ("sb3:PATH", "ars:PATH", "sac:PATH", "ssac:PATH", or an APG
    family's "ce-apg:PATH", "papg:PATH", ...) for ``env``.

    sb3: a Stable-Baselines3 zip read without unpickling (:func:`hybridctl.learn.sb3.load_sb3`;
    its normaliser from ``normalizer`` or a ``vecnormalize.npz`` beside it; a pickle only with
    ``trust``). ars: an ARS checkpoint, its running statistics frozen. sac / ssac: a hybridctl
    checkpoint of a system (``env`` must be that system's name); ssac keeps its gate and LQR.
    apg, shapg, papg, cem, ce-apg: an APG-family checkpoint of the system (its default policy: the
    best member or the CEM mean), recurrent, under the spec's cost-to-go gate and LQR as in its Drake
    controller, at its own decision period, on its training's reward and starts.
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
    # sac / ssac / the APG family: our swing-up checkpoints drive a system
    if env not in known_systems():
        raise ValueError(f"a {kind}: policy drives a hybridctl system; env must be one of {known_systems()}, "
                         f"got {env!r}")
    if kind in APG_METHODS:
        return _apg_policy(kind, path, env, source)
    from .export import load_controller
    policy, gate, meta = load_controller(path, load_system(env))
    if kind == "ssac" and gate is None:
        raise ckpt.CheckpointError(f"{path} is a {meta.get('algorithm')} checkpoint without a gate; use sac:{path}")
    # the task it was trained on: the spec overrides its config.json records (e.g. a reward kind or
    # wider starts); the plain spec would tune it for another reward than it learned
    overrides = dict((meta.get("system") or {}).get("overrides") or {})
    return TunablePolicy(policy, None, source, system=env, gate=gate if kind == "ssac" else None,
                         system_overrides=overrides,
                         meta={"algo": kind, "trained_algorithm": meta.get("algorithm"), "system_overrides": overrides,
                               "gate": {k: v for k, v in (meta.get("gate") or {}).items() if k in ("gate_on", "gate_off")}})


def _apg_policy(kind: str, path: str, env: str, source: str) -> TunablePolicy:
    """An APG-family checkpoint as a recurrent swing-up under the spec's cost-to-go gate and LQR."""
    from .apg import APG
    agent = APG.load(path, device="cpu")   # the learner's copy on the CPU (workers move theirs to the device)
    if agent.system.name != env:
        raise ValueError(f"{path} was trained on {agent.system.name}, not {env}")
    if agent.config.takeover != "lqr":
        raise ValueError(f"{path} was trained without the LQR takeover (takeover={agent.config.takeover!r}); "
                         f"fine-tuning inside the switched controller needs one trained through it "
                         f"(hybridctl train {kind} {env} --takeover lqr)")
    system = agent.system
    # the task it was trained on: its reward (the system's overrides) and its starts (hanging down +-
    # start_noise on every state, or the spec's spread when start_noise is None)
    overrides = dict(system.spec.overrides)
    if agent.config.start_noise is not None:
        noise = float(agent.config.start_noise)
        overrides.update(initial_state__low=[-noise] * system.n_states, initial_state__high=[noise] * system.n_states)
    on, off = float(system.gate.on), float(system.gate.off)
    return TunablePolicy(agent.closed_loop_policy(), None, source, system=env, gate=COST_TO_GO_GATE,
                         system_overrides=overrides, decision_period=float(agent.period),
                         meta={"algo": kind, "trained_algorithm": agent.config.method, "system_overrides": overrides,
                               "decision_period": float(agent.period), "gate": {"gate_on": on, "gate_off": off}})


def _check_gym_spaces(tunable: TunablePolicy, env: str, obs_dim: int, act_dim: int, path) -> None:
    probe = make_env(env)
    try:
        got = (int(np.prod(probe.observation_space.shape)), int(np.prod(probe.action_space.shape)))
    finally:
        probe.close()
    if got != (obs_dim, act_dim):
        raise ValueError(f"{path} has {obs_dim} observations and {act_dim} actions; env {env} has {got[0]} "
                         f"observations and {got[1]} actions")
