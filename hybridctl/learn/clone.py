"""Behaviour cloning of a tracked swing-up into a learner's actor: where ``hybridctl fit`` starts its policy.

The collocation swing-up tracked by TVLQR (:mod:`hybridctl.drake.trajopt`) reads the time; a learned swing-up
reads only the state. :func:`tracker_demonstrations` runs the tracker (:class:`TrackingSwingup`, the Drake
``TrajectoryTracker``'s law at the learner's decisions) inside the switched controller (gate with hysteresis, LQR)
from the spec's starts, with noise on the executed action and the noise-free command as the label (DART, Laskey
et al. 2017, "DART: Noise Injection for Robust Imitation Learning": the clone sees the corrections back to the
trajectory that it will need once its own errors move it off). :func:`clone_into_actor` fits a squashed-Gaussian
actor's mean to those labels by least squares, and its log-std to a small target, so that SAC explores around
the clone. :func:`balanced_fraction` measures a controller the same way for the tracker and for the clone.

>>> tracker = TrackingSwingup(tracking_gains(system, trajectory, period), system)
>>> data = tracker_demonstrations(system, tracker, controller, starts, steps, CloneConfig())
>>> clone_into_actor(agent.actor, data["states"], data["actions"], CloneConfig())
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from ..systems import System
from ..systems.control import saturate, tracking_command, wrap_angles
from ..systems.success import is_balanced
from ..systems.switched import SwitchedController, closed_loop_rollout

__all__ = ["CloneConfig", "TrackingSwingup", "tracker_demonstrations", "clone_into_actor", "balanced_fraction",
           "clone_swingup"]


@dataclass(frozen=True)
class CloneConfig:
    """Every number of the cloning, with its source."""

    rollouts: int = 256                       # tracked runs from the spec's start range (and per DAgger round)
    dagger_rounds: int = 3                    # rounds of the clone acting, the tracker labelling (DAgger); the
    #                                           round whose clone balances most held-out starts is kept
    noise: tuple = (0.0, 0.05, 0.1, 0.2)      # std of the executed action's noise, a share of the action limit; the
    #                                           runs split evenly among them (DART's noise levels are of this order)
    steps: int = 3000                         # Adam steps of the fit
    batch: int = 512                          # samples per step
    lr: float = 1e-3                          # Adam (SAC's actor rate is 3e-4; a supervised fit takes a larger one)
    std: float = 0.1                          # the clone's pre-tanh std: SAC starts exploring this close to it
    std_weight: float = 0.1                   # weight of the log-std term beside the action's squared error
    held_out: float = 0.1                     # share of the samples kept out of the fit to measure it
    seed: int = 0

    def __post_init__(self):
        if not (isinstance(self.dagger_rounds, int) and self.dagger_rounds >= 0):
            raise ValueError(f"CloneConfig.dagger_rounds must be an integer >= 0, got {self.dagger_rounds!r}")
        for name in ("rollouts", "steps", "batch"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"CloneConfig.{name} must be an integer >= 1, got {value!r}")
        if not self.noise or not all(0.0 <= float(v) <= 1.0 for v in self.noise):
            raise ValueError(f"CloneConfig.noise must be shares of the action limit in [0, 1], got {self.noise!r}")
        for name in ("lr", "std", "std_weight"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"CloneConfig.{name} must be a finite number > 0, got {value!r}")
        if not 0.0 < self.held_out < 0.5:
            raise ValueError(f"CloneConfig.held_out must be in (0, 0.5), got {self.held_out!r}")


class TrackingSwingup(torch.nn.Module):
    """The TVLQR tracking of a swing-up as a recurrent torch swing-up (states (B, n) and h -> actions, h + 1).

    ``gains``: a :class:`hybridctl.drake.trajopt.TrackingGains` table sampled at the decision period the
    controller holds its actions for. Its state h (B,) is the decision index k: decision k tracks row k (the last
    row, the goal, once the trajectory has ended) with :func:`hybridctl.systems.control.tracking_command`, the
    angles of the error wrapped, the command clipped to the action limit: the Drake ``TrajectoryTracker``'s law.
    """

    def __init__(self, gains, system: System):
        super().__init__()
        for name in ("x0", "u0", "K", "k0"):
            self.register_buffer(name, torch.as_tensor(np.asarray(getattr(gains, name)), dtype=torch.float64))
        self.period = float(gains.period)
        self.angles = list(system.angle_indices)
        self.limit = float(system.action_limit)

    def initial_state(self, n: int) -> torch.Tensor:
        """Every run starts at the trajectory's first row."""
        return torch.zeros(n, dtype=torch.long, device=self.x0.device)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        k = h.clamp(max=len(self.x0) - 1)
        err = wrap_angles(x.to(self.x0.dtype) - self.x0[k], self.angles)
        u = saturate(tracking_command(err, self.u0[k], self.K[k], self.k0[k]), self.limit)
        return u.to(x.dtype), h + 1


def balanced_fraction(system: System, controller: SwitchedController, starts, duration: float) -> dict:
    """Run ``controller`` from every row of ``starts`` for ``duration`` s (batched torch) and apply the success test
    (thesis eq. 3.2) over the spec's success window in seconds (``success.lookback`` x ``swingup_period``) to the
    states at every decision: ``{"balanced": (N,) bool, "fraction", "seconds"}``."""
    start = time.perf_counter()
    period = controller.decision_period
    steps = int(round(duration / period))
    run = closed_loop_rollout(system, controller, torch.as_tensor(np.asarray(starts, dtype=float)), steps)
    window = system.success.lookback * system.swingup_period
    lookback = max(1, int(math.ceil(window / period - 1e-9)))
    balanced = is_balanced(run.states.numpy(), system, lookback=lookback) & (run.diverged_at.numpy() > steps)
    return {"balanced": balanced, "fraction": float(balanced.mean()), "seconds": time.perf_counter() - start}


def tracker_demonstrations(system: System, tracker: TrackingSwingup, controller: SwitchedController, starts,
                           steps: int, config: CloneConfig, policy=None) -> dict:
    """States and noise-free tracker commands at every decision the swing-up acts (the gate off), from each row
    of ``starts``, the executed action perturbed by ``config.noise`` (one level per share of the runs).

    ``controller``: the switched controller the clone will act in (its gate, hysteresis and LQR; its swing-up is
    replaced by the noisy actions). ``policy``: None, the tracker acts (DART); a states -> actions callable, it
    acts and the tracker labels the states it visits, at the same decision index (DAgger, Ross et al. 2011).
    Returns ``states`` (M, n) and ``actions`` (M, m) float64 tensors, ``samples``, ``runs`` and the ``noise`` per
    run; a run's states stop at its divergence."""
    generator = torch.Generator().manual_seed(int(config.seed))
    x = torch.as_tensor(np.asarray(starts, dtype=float))
    runs = len(x)
    levels = torch.as_tensor(np.asarray(config.noise, dtype=float))
    noise = levels[torch.arange(runs) * len(levels) // runs] * system.action_limit
    h = tracker.initial_state(runs)
    mode = torch.zeros(runs, dtype=torch.bool)
    alive = torch.ones(runs, dtype=torch.bool)
    states, actions = [], []
    with torch.no_grad():
        for _ in range(int(steps)):
            u, h = tracker(x, h)
            acting = alive & ~mode
            states.append(x[acting])
            actions.append(u[acting])
            if policy is not None:
                u = policy(x).to(u.dtype)
            executed = saturate(u + noise[:, None] * torch.randn(u.shape, generator=generator, dtype=u.dtype),
                                system.action_limit)
            run = closed_loop_rollout(system, controller, x, 1, actions=executed[:, None], mode=mode, record=False)
            alive = alive & (run.diverged_at > 1)
            x, mode = run.final, run.mode
    states, actions = torch.cat(states), torch.cat(actions)
    return {"states": states, "actions": actions, "samples": int(len(states)), "runs": runs,
            "noise": [float(v) for v in noise]}


def clone_into_actor(actor: torch.nn.Module, states: torch.Tensor, actions: torch.Tensor, config: CloneConfig) -> dict:
    """Fit ``actor`` (a :class:`hybridctl.learn.networks.Actor`: mean and log-std of a tanh-squashed Gaussian scaled
    by ``actor.action_scale``) in place: the squashed mean to ``actions`` (least squares, in shares of the action
    scale) and the log-std to ``log(config.std)``. Returns the held-out root-mean-square error (a share of the
    action scale) before and after, the samples and the seconds."""
    if len(states) != len(actions) or len(states) < 2:
        raise ValueError(f"clone_into_actor needs as many states as actions, at least 2; got {len(states)} states "
                         f"and {len(actions)} actions")
    start = time.perf_counter()
    dtype = next(actor.parameters()).dtype
    device = next(actor.parameters()).device
    generator = torch.Generator().manual_seed(int(config.seed))
    order = torch.randperm(len(states), generator=generator)
    n_held = max(1, int(len(states) * config.held_out))
    held, fit = order[:n_held], order[n_held:]
    x = states.to(device=device, dtype=dtype)
    scale = actor.action_scale.to(device=device, dtype=dtype)
    y = actions.to(device=device, dtype=dtype) / scale
    target_log_std = math.log(config.std)

    def held_out_rmse() -> float:
        with torch.no_grad():
            mu, _ = actor(x[held])
            return float((torch.tanh(mu) - y[held]).pow(2).mean().sqrt())

    before = held_out_rmse()
    optimizer = torch.optim.Adam(actor.parameters(), lr=config.lr)
    for _ in range(int(config.steps)):
        batch = fit[torch.randint(len(fit), (config.batch,), generator=generator)]
        mu, log_std = actor(x[batch])
        loss = ((torch.tanh(mu) - y[batch]).pow(2).mean()
                + config.std_weight * (log_std - target_log_std).pow(2).mean())
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return {"held_out_rmse_before": before, "held_out_rmse": held_out_rmse(), "samples": int(len(states)),
            "held_out": n_held, "seconds": time.perf_counter() - start, "config": asdict(config)}


def clone_swingup(system: System, tracker: TrackingSwingup, controller: SwitchedController, actor: torch.nn.Module,
                  starts, test_starts, duration: float, config: CloneConfig, progress=None) -> dict:
    """Clone the tracked swing-up into ``actor`` (in place): DART demonstrations from ``starts``, then
    ``config.dagger_rounds`` rounds in which the clone acts from the same starts and the tracker labels what it
    visits, each round refitting on all data so far. After every fit the clone runs in ``controller`` (its swing-up
    replaced) from ``test_starts`` (not trained on) for ``duration`` s; the weights of the round that balances
    most of them are kept (ties: the earlier round). ``progress``: a tqdm bar advanced once a round.

    Returns ``tracker`` and per-round ``rounds`` (samples, held-out error, fraction balanced, seconds),
    ``kept_round``, ``fraction`` (the kept clone's) and ``tracker_fraction`` (the tracker's own, same starts)."""
    import copy

    steps = int(round(duration / controller.decision_period))
    tracked = balanced_fraction(system, controller.replace(swingup=tracker), test_starts, duration)
    data = tracker_demonstrations(system, tracker, controller, starts, steps, config)
    states, actions = data["states"], data["actions"]
    rounds, best, best_state = [], -1.0, None
    for round_index in range(config.dagger_rounds + 1):
        t0 = time.perf_counter()
        if round_index > 0:
            visited = tracker_demonstrations(system, tracker, controller, starts, steps,
                                             replace(config, seed=config.seed + round_index), policy=_acting(actor))
            states, actions = torch.cat([states, visited["states"]]), torch.cat([actions, visited["actions"]])
        fitted = clone_into_actor(actor, states, actions, replace(config, seed=config.seed + round_index))
        measured = balanced_fraction(system, controller.replace(swingup=_acting(actor)), test_starts, duration)
        rounds.append({"round": round_index, "samples": fitted["samples"], "held_out_rmse": fitted["held_out_rmse"],
                       "fraction": measured["fraction"], "seconds": time.perf_counter() - t0})
        if measured["fraction"] > best:
            best, best_state = measured["fraction"], copy.deepcopy(actor.state_dict())
        if progress is not None:
            progress.update()
    actor.load_state_dict(best_state)
    kept = max(range(len(rounds)), key=lambda i: (rounds[i]["fraction"], -i))
    return {"rounds": rounds, "kept_round": kept, "fraction": best, "tracker_fraction": tracked["fraction"],
            "test_starts": int(len(test_starts)), "duration_s": float(duration)}


def _acting(actor: torch.nn.Module):
    """The actor's deterministic action (states -> ``action_scale * tanh(mu)``) in float64 on the states' device,
    without autograd (the actor may live on another device)."""
    parameter = next(actor.parameters())

    def act(x: torch.Tensor) -> torch.Tensor:     # the rollout's states stay where they are (the CPU)
        with torch.no_grad():
            return actor.deterministic(x.to(parameter.device, parameter.dtype)).to(x.device, torch.float64)
    return act
