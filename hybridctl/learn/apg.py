"""Analytic policy gradients through the differentiable dynamics (thesis Ch. 7): APG, short-horizon
APG, PAPG, CEM and CE-APG, all as ONE batched torch computation over a population of policies.

The torch dynamics (:meth:`hybridctl.systems.System.step_unchecked`) are differentiable, so the
return R(theta) = sum_t r(s_t) of a deterministic policy has an exact gradient (eq. 7.10):

    theta <- theta + alpha grad_theta (1/N) sum_i sum_t r(s_t^i)          (APG, Adam)

Methods (``APGConfig.method``):

* ``"apg"`` -- one policy, full backpropagation through time over the T-step episode
  (optional truncation: the graph is cut every ``truncation`` steps);
* ``"shapg"`` -- the short-horizon peer (today's Brax APG, SHAC's actor without critic):
  ``short_horizon``-step unrolls from the carried state, one update each, clip 1.0, Adam
  betas (0.7, 0.95);
* ``"papg"`` -- K APG runs side by side; the BEST member (by its last training returns) is
  the result (the author's script returns the initial parameters by mistake);
* ``"cem"`` -- the cross-entropy method on the parameters (diagonal Gaussian, eqs. 7.11, 7.13);
* ``"ce-apg"`` -- Alg. 9: each epoch draws K_a candidates from N(mean, std^2), improves each
  by ``apg_iterations`` APG steps, and the K_e best (mean of the last ``rank_window``
  training returns, as the author's code) give the new mean (eq. 7.11) and the new
  per-parameter std sqrt(mean_e (old mean - theta_e)^2) (eq. 7.13), measured about the OLD
  mean as the author's code does (about the new mean would be the textbook CEM variance;
  about the old mean it also grows when the elites move together, which keeps exploring).

The population is one computation: parameters stacked [K, ...] (:mod:`.policies`), the
K x N states one (K N, n) batch through ``System.step_unchecked``, the loss the sum of the
members' losses, one backward; member k's gradient is the slice k (members share nothing).
Every member has its own Adam moments and step count (:class:`BatchedAdam`), so a member
whose gradient is skipped is not moved.

Faults: a member's gradient that is NaN/inf or whose norm exceeds ``grad_bound`` is counted
(``nan_grads``, ``large_grads``), skipped and logged, never applied; a member whose rollout
diverges (non-finite return) gets the worst score (-inf) and no update; NaN parameters stop
training with FloatingPointError before they are applied, so the last good checkpoint
stays intact (the training skeleton writes none after an error).

The parallel backends (``APGConfig.backend`` "processes" or "ray", :mod:`hybridctl.parallel`):
members share nothing during an epoch's APG phase (own Adam moments; the same start states,
seeded by (seed, epoch, iteration)), so for ce-apg, papg and shapg the phase runs as
``workers`` contiguous chunks of members, one task each (:func:`apg_chunk`: plain arrays in
and out; each worker builds its own learner once). The parent joins the chunks in member
order and goes on as in one process (CEM update, best member, normalisation, counters), so
a split run equals the serial one up to float rounding. apg (one member) and cem (no APG
phase) always run here. The backend opens on the first split epoch and closes when
``learn`` returns or fails (:meth:`APG.close_backend` after calling ``train_epoch`` directly).

Interactions are counted honestly: K x N x T policy steps per APG iteration (x the
integrator sub-steps per policy step for the physics steps, logged separately).

Speed: ``APGConfig.compile`` runs the per-step work (observe, act, sub-steps, reward) through
``torch.compile``; measured here (benchmarks/apg.py, 24 x 4 x 500 acrobot, float32, 1 thread)
1.22 s per eager iteration, 0.23 s compiled, 30 s for the loop over members.

Status (what a later session should know): with ``takeover="lqr"`` PAPG trains a cart-pole swing-up
that balances in Drake (models/policies/papg-cartpole: 93.4 % of the 11 x 11 map; seeds 0-3 71-93 %,
~200 s each). Without the takeover no method stabilises within 5 s at ~1/500 of the thesis' budget
(results/ch7/table71.json); the acrobot and double cart-pole have no balancing swing-up yet.

>>> agent = APG("cartpole", APGConfig.preset("reduced", method="ce-apg"))
>>> agent.learn(out="runs/ce-apg-cartpole")                   # progress, CSV, checkpoints
>>> agent.evaluate(episodes=16)                                   # held-out starts, stabilisation rate
>>> APG.load("runs/ce-apg-cartpole/final").policy()               # a policies.Policy
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .. import systems as systems_mod
from ..limits import MAX_SIMULATION_STEPS, check_at_most
from ..parallel import BACKENDS, cached_env, make_backend
from ..systems import System, known_systems
from ..systems import control
from ..systems.success import stabilisation
from . import checkpoint as ckpt
from .config_check import check_types
from .policies import KINDS as POLICY_KINDS
from .policies import Policy, PolicyPopulation
from .base import Learner
from .checkpoint import PROGRESS_FILE, Saved
from .config_check import check_fields
from .run import EVAL_SEED, EvalResult, check_finite, seeded, set_torch_threads

__all__ = ["APG", "APGConfig", "BatchedAdam", "apg_chunk", "ClosedLoopPolicy", "policy_step", "compiled_policy_step", "METHODS", "PRESETS", "observe", "population_returns",
           "member_gradients", "lr_schedule", "cem_update",
           "gradient_norms_by_horizon", "returns_along_direction"]

METHODS = ("apg", "shapg", "papg", "cem", "ce-apg")
PRESETS = ("thesis", "reduced")
OBSERVATIONS = ("trig", "state")
TAKEOVERS = ("none", "lqr")


# ============================================================================ the settings


@dataclass
class APGConfig:
    """Every setting of the Ch. 7 learners, with the thesis' value and its source.

    Sources: thesis Sec. 7.3.7 (table "CE-APG Hyperparameter") and the implementation
    notes, Ch. 7 (the author's sgillen/apg code). Our systems keep their own parameters
    (the thesis' Brax models differ), so no return here is comparable number for number.
    """

    method: str = "ce-apg"             # one of METHODS
    # --- task
    reward_kind: str = "angle_squared"  # a Ch. 7 reward kind of the spec (systems.spec.CH7_REWARD_KINDS); thesis
    #                                    Sec. 7.2.3-7.2.4 (acrobot, cart-pole); "tip_distance" eqs. 7.5-7.8
    alive_bonus: float = 0.0           # reward.alive_bonus; author's acrobot / double cart-pole: 10
    velocity_penalty: float = 0.0      # reward.velocity_penalty; author's acrobot / double cart-pole: 0.01
    position_weight: float = 0.0       # reward.position_weight (cart x^2); author's double cart-pole: 1
    horizon: int = 500                 # T policy steps per episode, thesis Sec. 7.3.4 ("at least 500 steps")
    control_period: float | None = None  # s per policy step; None: the spec's control.swingup_period
    start_noise: float | None = 0.01   # starts hanging down +- U(-0.01, 0.01) per state, author's envs
    #                                    (implementation notes Ch. 7); None: the spec's initial_state spread
    observation: str = "trig"          # "trig": [cart x, sin, cos of each angle error, velocities]; "state":
    #                                    the wrapped state error (jumps at +-pi). hybridctl choice.
    takeover: str = "none"             # "none": the policy acts all episode (thesis Ch. 7); "lqr": hybridctl, the
    #                                    switched controller as in Drake (Ch. 3): the spec's cost-to-go gate with
    #                                    hysteresis hands over to the saturated LQR every integrator step, and the
    #                                    gradient flows through the LQR phase (see LQRTakeover)
    # --- policy
    policy: str = "gru"                # "gru" (thesis Sec. 7.3.4), "linear" or "mlp:W1,W2,..." (ReLU widths)
    init_std: float = 0.05             # sigma_0 and the initial perturbation of zero weights, thesis Sec. 7.3.7
    normalize: bool = True             # running obs statistics, updated once per epoch, frozen during APG
    #                                    (implementation notes Ch. 7)
    dtype: str = "float32"             # "float32" (as JAX's default in the thesis' Brax) or "float64"
    compile: bool = False              # hybridctl: torch.compile the per-step work (policy, sub-steps, reward);
    #                                    measured 3.9x faster at 24 x 4 here, after ~30 s of compiling per shape
    # --- APG
    batch: int = 4                     # N starts per APG iteration, thesis Sec. 7.3.7
    apg_iterations: int = 100          # APG iterations per CE epoch, thesis Sec. 7.3.7 ("APG Epochs")
    lr_start: float = 1e-3             # thesis Sec. 7.3.7: 1e-3 -> 1e-6,
    lr_end: float = 1e-6               # log-linear over the CE epochs (implementation notes Ch. 7)
    beta1: float = 0.9                 # Adam betas: optax/torch defaults (the author's optax.adam);
    beta2: float = 0.999               # shapg: (0.7, 0.95) as Brax APG 0.14 and SHAC
    truncation: int | None = None      # cut the graph every this many steps; None: full BPTT (thesis)
    clip: float | None = None          # gradient clipping; None: off (the author's, effectively)
    clip_mode: str = "norm"            # "norm" (per member's global norm) or "value" (elementwise)
    grad_bound: float = 1e8            # a member gradient with a larger norm is skipped (hybridctl guard)
    short_horizon: int = 32            # shapg unroll length (Brax APG 0.14, SHAC)
    # --- population
    population: int = 24               # K_a, thesis Sec. 7.3.7 (one per XLA CPU device in the author's code)
    elites: int = 8                    # K_e, thesis Sec. 7.3.7
    rank_window: int = 5               # elites ranked by the mean of the last 5 APG training returns (author)
    epochs: int = 200                  # CE epochs, thesis Sec. 7.3.7 ("Total Epochs"); cem: thesis 2000
    # --- bookkeeping
    seed: int = 0
    checkpoint_every: int = 1          # epochs between checkpoints
    eval_episodes: int = 16            # held-out starts in evaluate()
    torch_threads: int = 1             # see run.set_torch_threads (also in each worker)
    # --- parallel (hybridctl; the thesis' author ran one member per XLA CPU device)
    backend: str = "serial"            # hybridctl: "serial" (one process), "processes" (spawned local processes)
    #                                    or "ray" (a population that does not fit one process): each epoch's
    #                                    APG phase runs as contiguous chunks of members, one per worker
    workers: int | None = None         # hybridctl: number of chunks; None: the backend's workers (every core,
    #                                    or the Ray cluster's CPUs)
    ray_address: str | None = None     # hybridctl: the Ray cluster ("ray://host:10001", "auto"); None starts a
    #                                    local Ray instance (backend "ray" only)

    def describe_budget(self) -> str:
        """The run's budget in a run's account: epochs of members x batch x horizon steps."""
        return (f"{self.epochs} epochs of {self.population if self.method != 'apg' else 1} x {self.batch} x "
                f"{self.horizon} steps, seed {self.seed}")

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        check_types(self)
        check_fields(self, integers_from_1=("horizon", "batch", "apg_iterations", "short_horizon", "population",
                                            "elites", "rank_window", "epochs", "checkpoint_every", "eval_episodes",
                                            "torch_threads"),
                     integers_from_0=("seed",), positive=("lr_start", "lr_end", "grad_bound"))
        parse_policy(self.policy)
        for name, options in (("method", METHODS), ("observation", OBSERVATIONS), ("takeover", TAKEOVERS),
                              ("backend", BACKENDS),
                              ("clip_mode", ("norm", "value")), ("dtype", ("float32", "float64"))):
            if getattr(self, name) not in options:
                raise ValueError(f"APGConfig.{name} must be one of {options}, got {getattr(self, name)!r}")
        if self.reward_kind not in systems_mod.spec.CH7_REWARD_KINDS:
            raise ValueError(f"APGConfig.reward_kind must be one of {systems_mod.spec.CH7_REWARD_KINDS}, "
                             f"got {self.reward_kind!r}")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"APGConfig.workers must be None (the backend's workers) or an integer >= 1, "
                             f"got {self.workers!r}")
        if self.ray_address is not None and (self.backend != "ray" or not self.ray_address.strip()):
            raise ValueError(f"APGConfig.ray_address must be None or a non-empty address with backend 'ray', "
                             f"got {self.ray_address!r} with backend {self.backend!r}")
        if self.elites > self.population:
            raise ValueError(f"APGConfig.elites ({self.elites}) must be <= population ({self.population})")
        for name in ("beta1", "beta2"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"APGConfig.{name} must be in [0, 1), got {getattr(self, name)!r}")
        check_fields(self, non_negative=("init_std", "alive_bonus", "velocity_penalty", "position_weight"))
        for name in ("truncation", "clip", "control_period", "start_noise"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"APGConfig.{name} must be None or a finite number > 0, got {value!r}")
        # an unroll or a graph cut longer than the episode would silently be the whole episode
        if self.method == "shapg" and self.short_horizon > self.horizon:
            raise ValueError(f"APGConfig.short_horizon ({self.short_horizon}) must be <= horizon ({self.horizon}): "
                             f"an unroll is part of an episode")
        if self.truncation is not None and self.truncation > self.horizon:
            raise ValueError(f"APGConfig.truncation ({self.truncation}) must be None or <= horizon "
                             f"({self.horizon}): the graph is cut within an episode")

    @classmethod
    def preset(cls, name: str = "thesis", method: str = "ce-apg", **overrides) -> "APGConfig":
        """Settings for ``method`` from a preset, then ``overrides``.

        ``"thesis"``: the values above (Sec. 7.3.7). Per method: ``apg`` one member;
        ``shapg`` clip 1.0 by norm and Adam betas (0.7, 0.95) (Brax APG 0.14 / SHAC);
        ``cem`` 2000 epochs (thesis Sec. 7.5).

        ``"reduced"`` (trains in minutes on a shared 2-core CPU): population 8 (thesis 24),
        elites 3 (8), apg_iterations 20 (100), horizon 100 policy steps (500; with the
        cart-pole's 0.05 s period 5 s of swing-up), epochs 10 (200), lr 1e-2 -> 1e-4
        (1e-3 -> 1e-6: fewer, larger steps), eval on 8 starts; the architecture, N = 4,
        sigma_0 and the update rules are the thesis'.
        """
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
        values: dict = {"method": method}
        if method == "apg":
            values["population"], values["elites"] = 1, 1
        if method == "shapg":
            values.update(clip=1.0, clip_mode="norm", beta1=0.7, beta2=0.95)
        if method == "cem":
            values["epochs"] = 2000
        if name == "reduced":
            values.update(apg_iterations=20, horizon=100, epochs=10, lr_start=1e-2, lr_end=1e-4, eval_episodes=8)
            if method != "apg":
                values.update(population=8, elites=3)
            if method == "cem":
                values["epochs"] = 200
        values.update(overrides)
        config = cls(**values)
        config.validate()
        return config


# ============================================================================ the pieces


def parse_policy(text: str) -> tuple[str, tuple[int, ...]]:
    """"gru" -> ("gru", ()); "linear" -> ("linear", ()); "mlp:32,32" -> ("mlp", (32, 32))."""
    if text in ("gru", "linear"):
        return text, ()
    if isinstance(text, str) and text.startswith("mlp:"):
        try:
            widths = tuple(int(w) for w in text[4:].split(",") if w)
        except ValueError:
            widths = ()
        if widths and all(w > 0 for w in widths):
            return "mlp", widths
    raise ValueError(f"APGConfig.policy must be one of {POLICY_KINDS[0]!r}, 'linear' or 'mlp:W1,W2,...' "
                     f"(positive widths), got {text!r}")


def lr_schedule(config: APGConfig, epoch: int) -> float:
    """Learning rate of ``epoch``: 10^(log10 lr_start -> log10 lr_end) linearly over the epochs (author)."""
    if config.epochs <= 1:
        return config.lr_start
    f = min(epoch, config.epochs - 1) / (config.epochs - 1)
    return float(10 ** ((1 - f) * math.log10(config.lr_start) + f * math.log10(config.lr_end)))


def observe(system: System, x: torch.Tensor, kind: str = "trig") -> torch.Tensor:
    """The policy's observation of states x (..., n): see ``APGConfig.observation`` (torch or numpy)."""
    err = system.state_error(x)
    if kind == "state":
        return err
    n_q = system.n_states // 2
    angles = system.angle_indices
    linear = [i for i in range(n_q) if i not in angles]
    phi = err[..., angles]
    if isinstance(err, torch.Tensor):
        return torch.cat([err[..., linear], torch.sin(phi), torch.cos(phi), err[..., n_q:]], dim=-1)
    return np.concatenate([err[..., linear], np.sin(phi), np.cos(phi), err[..., n_q:]], axis=-1)


def observation_size(system: System, kind: str = "trig") -> int:
    """Length of :func:`observe`'s output."""
    return system.n_states + (len(system.angle_indices) if kind == "trig" else 0)


def policy_step(system: System, pop: PolicyPopulation, x: torch.Tensor, h: torch.Tensor, substeps: int,
                observation: str = "trig", takeover: "LQRTakeover | None" = None, mode: torch.Tensor | None = None):
    """One policy step of K x N states x [K, N, n]: observe, act, hold the action over ``substeps``
    integrator steps of ``System.step_unchecked``; returns (next x, next h, reward [K, N], obs, mode).

    ``takeover``: the switched controller's LQR half (:class:`LQRTakeover`): at every integrator
    step the gate's ``mode`` [K, N] (bool, True = LQR) is updated with hysteresis and the LQR's
    command replaces the held policy action where the mode is on (as the Drake diagram does).
    """
    K, N, n = x.shape
    obs = observe(system, x, observation)
    action, h = pop(obs, h)
    u = action.reshape(K * N, system.n_actions)
    xs = x.reshape(K * N, n)
    ms = None if mode is None else mode.reshape(K * N)
    for _ in range(substeps):
        if takeover is not None:
            command, ms = takeover(xs, ms, u)
            xs = system.step_unchecked(xs, command)
        else:
            xs = system.step_unchecked(xs, u)
    x = xs.reshape(K, N, n)
    return x, h, system.reward(x), obs, (None if ms is None else ms.reshape(K, N))


class LQRTakeover:
    """The balance half of the switched controller inside a torch rollout (thesis Ch. 3 around Ch. 7).

    ``takeover(x [B, n], mode [B] bool, u_policy [B, m]) -> (command [B, m], next mode)``: the
    spec's cost-to-go gate p = exp(-V(x) / gate.cost_scale) (:class:`~hybridctl.systems.control.
    CostToGoGate`) with the spec's hysteresis (gate.on / gate.off) chooses, per state, the
    saturated LQR command -K (x - goal) (Drake's LQR, :meth:`System.lqr`) or the policy's.
    Every law comes from :mod:`hybridctl.systems.control`, as the Drake blocks'.

    Training a swing-up with it (``APGConfig.takeover = "lqr"``) optimises the switched
    controller that runs in Drake: the swing-up need only deliver the state into the gate's
    region, and the LQR phase, being stable, passes bounded gradients back to the state where
    the gate switched on. The switch itself is a hard choice: no gradient flows through the
    switching time.
    """

    def __init__(self, system: System, dtype: torch.dtype = torch.float64):
        K, S = system.lqr()
        gate = control.CostToGoGate(system)
        self.system = system
        self.K = torch.as_tensor(K, dtype=dtype)
        self.S = torch.as_tensor(S, dtype=dtype)
        self.scale, self.on, self.off = float(gate.scale), float(system.gate.on), float(system.gate.off)
        self.limit = float(system.action_limit)

    def __call__(self, x: torch.Tensor, mode: torch.Tensor | None, u_policy: torch.Tensor):
        err = self.system.state_error(x)
        probability = torch.exp(-control.cost_to_go(err, self.S) / self.scale)
        mode = torch.zeros_like(probability, dtype=torch.bool) if mode is None else mode
        mode = control.hysteresis(probability, mode, self.on, self.off)
        balance = control.saturate(control.lqr_command(err, self.K), self.limit)
        return torch.where(mode[:, None], balance, u_policy), mode


_COMPILED_STEP = None


def compiled_policy_step():
    """:func:`policy_step` through ``torch.compile`` (compiled on first use per shape; one shared cache)."""
    global _COMPILED_STEP
    if _COMPILED_STEP is None:
        _COMPILED_STEP = torch.compile(policy_step, dynamic=False)
    return _COMPILED_STEP


def population_returns(system: System, pop: PolicyPopulation, x0: torch.Tensor, horizon: int, substeps: int,
                       observation: str = "trig", truncation: int | None = None, state=None,
                       keep_states: bool = False, step=None, takeover: LQRTakeover | None = None):
    """Roll K members x N starts out as one batch; the differentiable returns [K, N].

    ``x0``: [N, n] (the same starts for every member) or [K, N, n]. ``state``: the policies'
    recurrent state [K, N, h] (None: zero). Each policy step holds the action over
    ``substeps`` integrator steps of ``System.step_unchecked`` and then collects
    ``System.reward`` of the new state. ``truncation``: detach the states every that many
    steps (truncated BPTT). Returns (returns [K, N], final x [K, N, n], final state, obs
    sums (sum, sum of squares, count) for the normalisation, and the states [K, N, T+1, n]
    when ``keep_states``, else None). ``step``: the per-step function (default
    :func:`policy_step`; :func:`compiled_policy_step` for the fused one). ``takeover``: the
    switched controller's LQR half (:class:`LQRTakeover`); then ``state`` and the returned state
    are the pair (recurrent state, gate mode [K, N]), the mode starting off (the swing-up acts).
    """
    step = step or policy_step
    K = pop.members
    if x0.dim() == 2:
        x0 = x0.unsqueeze(0).expand(K, -1, -1)
    N = x0.shape[1]
    x = x0.to(pop.dtype)
    if takeover is None:
        h, mode = (pop.initial_state(N) if state is None else state), None
    else:
        h, mode = (pop.initial_state(N), torch.zeros((K, N), dtype=torch.bool)) if state is None else state
    total = torch.zeros((K, N), dtype=pop.dtype)
    o_sum = torch.zeros(pop.obs_dim, dtype=torch.float64)
    o_sq = torch.zeros(pop.obs_dim, dtype=torch.float64)
    kept = [x.detach()] if keep_states else None
    for t in range(horizon):
        if truncation is not None and t > 0 and t % truncation == 0:
            x, h = x.detach(), h.detach()
        x, h, reward, obs, mode = step(system, pop, x, h, substeps, observation, takeover, mode)
        with torch.no_grad():
            od = obs.detach().reshape(-1, pop.obs_dim).double()
            finite = torch.isfinite(od).all(-1)
            od = od[finite]
            o_sum += od.sum(0)
            o_sq += (od * od).sum(0)
        total = total + reward
        if keep_states:
            kept.append(x.detach())
    count = K * N * horizon
    states = torch.stack(kept, dim=2) if keep_states else None
    return total, x, (h if takeover is None else (h, mode)), (o_sum, o_sq, count), states


def member_gradients(pop: PolicyPopulation, loss_per_member: torch.Tensor) -> torch.Tensor:
    """One backward of sum_k loss_k; the gradients as a [K, P] matrix (member k's in row k).

    A member whose loss is not finite contributes nothing to the backward (its row comes
    back NaN, for the caller to skip) and cannot spoil the others.
    """
    finite = torch.isfinite(loss_per_member.detach())
    params = pop.stacked()
    total = torch.where(finite, loss_per_member, torch.zeros_like(loss_per_member)).sum()
    grads = torch.autograd.grad(total, params, allow_unused=True)
    flat = torch.cat([(torch.zeros_like(p) if g is None else g).reshape(pop.members, -1)
                      for p, g in zip(params, grads)], dim=1)
    flat[~finite] = float("nan")
    return flat


class BatchedAdam:
    """Adam on K stacked parameter vectors [K, P], each member with its own moments and step
    count; a masked-out member is not touched (moments, counts and parameters unchanged)."""

    def __init__(self, members: int, n_params: int, betas=(0.9, 0.999), eps: float = 1e-8,
                 dtype: torch.dtype = torch.float64):
        self.betas, self.eps = (float(betas[0]), float(betas[1])), float(eps)
        self.m = torch.zeros((members, n_params), dtype=dtype)
        self.v = torch.zeros((members, n_params), dtype=dtype)
        self.t = torch.zeros(members, dtype=torch.int64)

    def step(self, theta: torch.Tensor, grad: torch.Tensor, mask: torch.Tensor, lr: float) -> torch.Tensor:
        """The new parameters [K, P] after a gradient DESCENT step on ``grad`` for members in ``mask``."""
        b1, b2 = self.betas
        g = torch.where(mask[:, None], grad, torch.zeros_like(grad))
        m = torch.where(mask[:, None], b1 * self.m + (1 - b1) * g, self.m)
        v = torch.where(mask[:, None], b2 * self.v + (1 - b2) * g * g, self.v)
        t = self.t + mask.long()
        tt = t.clamp_min(1).to(theta.dtype)[:, None]
        update = lr * (m / (1 - b1 ** tt)) / ((v / (1 - b2 ** tt)).sqrt() + self.eps)
        self.m, self.v, self.t = m, v, t
        return torch.where(mask[:, None], theta - update, theta)


def clip_gradients(grad: torch.Tensor, clip: float | None, mode: str) -> torch.Tensor:
    """Per member: scale to global norm <= ``clip`` ("norm") or clamp each entry to [-clip, clip]."""
    if clip is None:
        return grad
    if mode == "value":
        return grad.clamp(-clip, clip)
    norm = grad.norm(dim=1, keepdim=True)
    return grad * torch.clamp(clip / (norm + 1e-12), max=1.0)


def cem_update(mean: torch.Tensor, candidates: torch.Tensor, scores: torch.Tensor, elites: int):
    """Eqs. 7.11 and 7.13: the mean of the ``elites`` best candidates [K, P] (by ``scores`` [K],
    highest first) and the per-parameter std sqrt(mean_e (old mean - theta_e)^2) about the old mean.

    Returns (new mean [P], new std [P], elite indices)."""
    order = torch.argsort(torch.nan_to_num(scores, nan=-math.inf), descending=True, stable=True)[:elites]
    chosen = candidates[order]
    new_mean = chosen.mean(0)
    new_std = ((mean[None] - chosen) ** 2).mean(0).sqrt()
    return new_mean, new_std, order


class ClosedLoopPolicy(torch.nn.Module):
    """A trained policy on raw states: ``forward(x [B, n], h [B, hidden]) -> (action [B, m], h)``,
    the observation (:func:`observe`) included; ``initial_state(batch)`` the zero state. What the
    Drake block ``hybridctl.drake.RecurrentTorchPolicy`` runs."""

    def __init__(self, system: System, policy: Policy, observation: str = "trig"):
        super().__init__()
        self.system, self.policy, self.observation = system, policy, observation

    def initial_state(self, batch: int = 1) -> torch.Tensor:
        """Zero recurrent state [batch, hidden]."""
        return self.policy.initial_state(batch)

    def forward(self, x: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Action and next recurrent state for raw states x."""
        return self.policy(observe(self.system, x.to(self.policy.population.dtype), self.observation), state)

    def numpy_forward(self, x: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`forward` in numpy (:meth:`Policy.numpy_forward`), for the Drake block on one state."""
        dtype = np.float64 if self.policy.population.dtype == torch.float64 else np.float32
        obs = observe(self.system, np.asarray(x, dtype=dtype), self.observation)
        return self.policy.numpy_forward(obs, state)


# ============================================================================ diagnostics (thesis Fig. 7.1)


def gradient_norms_by_horizon(system: System, pop: PolicyPopulation, x0: torch.Tensor, horizons, substeps: int,
                              observation: str = "trig") -> list[dict]:
    """The APG gradient's norm (per member, [K]) and the mean return for each horizon in ``horizons``:
    why full BPTT through chaotic dynamics explodes (Metz et al. 2021; thesis Sec. 7.1.4)."""
    out = []
    for horizon in horizons:
        returns, *_ = population_returns(system, pop, x0, int(horizon), substeps, observation)
        grad = member_gradients(pop, -returns.mean(1))
        out.append({"horizon": int(horizon), "grad_norm": grad.norm(dim=1).tolist(),
                    "mean_return": returns.detach().mean(1).tolist()})
    return out


def returns_along_direction(system: System, pop: PolicyPopulation, x0: torch.Tensor, horizon: int, substeps: int,
                            direction: torch.Tensor, scales, observation: str = "trig") -> list[float]:
    """R(theta + s d) of member 0 for each s in ``scales`` (thesis Fig. 7.1: the return landscape along
    a random direction d), evaluated as one batch (one member per scale); theta is left unchanged."""
    scales = [float(v) for v in scales]
    theta = pop.to_flat()[0]
    probe = pop.resized(len(scales), torch.stack([theta + v * direction.to(theta.dtype) for v in scales]))
    with torch.no_grad():
        returns, *_ = population_returns(system, probe, x0, horizon, substeps, observation)
    return returns.mean(1).double().tolist()


# ============================================================================ the split APG phase (workers)


def _array(t: torch.Tensor) -> np.ndarray:
    """A tensor as a numpy copy (what tasks and results carry)."""
    return t.detach().cpu().numpy().copy()


def apg_chunk(task: dict) -> dict:
    """The APG phase of one chunk of members, in a worker (see :meth:`APG._split_apg_phase`).

    ``task``: plain data (system name and spec overrides, the chunk's config as a dict, epoch,
    iteration count, lr, parameters [k, P], Adam moments and steps, the frozen normalisation).
    The worker's learner of the chunk's size is built once (:func:`~hybridctl.parallel.cached_env`)
    and runs :meth:`APG._apg_phase`; returns the chunk's parameters, Adam state, returns and
    gradient norms [iters, k], counters and observation sums.
    """
    set_torch_threads(task["config"]["torch_threads"])
    agent = cached_env(("apg", task["system"], repr(task["overrides"]), repr(task["config"])),
                       lambda: APG(systems_mod.load(task["system"], **task["overrides"]), APGConfig(**task["config"])))
    agent.epoch, agent.iterations, agent._obs_sums = task["epoch"], task["iterations"], None
    agent.env_steps = agent.nan_grads = agent.large_grads = 0
    agent.pop.set_normalization(*task["normalization"])
    adam = agent.adam
    adam.m, adam.v, adam.t = (torch.tensor(a) for a in task["adam"])
    theta, returns, norms = agent._apg_phase(torch.tensor(task["theta"]), task["lr"], adam)
    o_sum, o_sq, count = agent._obs_sums
    return {"theta": _array(theta), "returns": _array(returns), "norms": _array(norms),
            "adam": [_array(a) for a in (adam.m, adam.v, adam.t)], "obs_sums": (_array(o_sum), _array(o_sq), count),
            "env_steps": agent.env_steps, "nan_grads": agent.nan_grads, "large_grads": agent.large_grads}


# ============================================================================ the learner


class APG(Learner):
    """APG, short-horizon APG, PAPG, CEM and CE-APG on a :class:`~hybridctl.systems.System`:
    ``learn`` / ``evaluate`` / ``policy`` / ``save`` / ``load`` (see the module docstring)."""

    algorithm_name = "APG"
    config_class = APGConfig
    budget_field, unit, uses_backend = "epochs", "epoch", True
    log_key = "epoch"

    @classmethod
    def run_label(cls, config) -> str:
        """The method's name ("papg", "ce-apg") in a run's account."""
        return config.method

    def training_record(self) -> dict:
        """eval.json's training counters: method, epochs, APG iterations, env steps, gradient guards, wall time."""
        return {"method": self.config.method, "epochs": self.epoch, "iterations": self.iterations,
                "env_steps": self.env_steps, "nan_grads": self.nan_grads, "large_grads": self.large_grads,
                "train_wall_time_s": self.wall_time}
    log_columns = ("epoch", "iterations", "env_steps", "physics_steps", "lr", "mean_return", "best_return",
                   "elite_score", "grad_norm", "nan_grads", "large_grads", "diverged", "sigma", "wall_time",
                   "steps_per_s")
    log_int_columns = ("epoch", "iterations", "env_steps", "physics_steps", "nan_grads", "large_grads", "diverged")
    saved = (Saved("mean", "mean", "tensor"), Saved("std", "std", "tensor"), Saved("members", "members", "tensor"),
             Saved("best", "best", "tensor"), Saved("adam_m", "adam.m", "tensor"), Saved("adam_v", "adam.v", "tensor"),
             Saved("adam_t", "adam.t", "tensor"), Saved("stats", "stats", "tensor"),
             Saved("obs_mean", "pop.obs_mean", "param"), Saved("obs_std", "pop.obs_std", "param"),
             Saved("best_score", "best_score", load=float),
             Saved("epoch", "epoch", file=PROGRESS_FILE, load=int),
             Saved("iterations", "iterations", file=PROGRESS_FILE, load=int),
             Saved("env_steps", "env_steps", file=PROGRESS_FILE, load=int),
             Saved("nan_grads", "nan_grads", file=PROGRESS_FILE, load=int),
             Saved("large_grads", "large_grads", file=PROGRESS_FILE, load=int),
             Saved("wall_time", "wall_time", file=PROGRESS_FILE, load=float),
             Saved("history", "history", file=PROGRESS_FILE, optional=True, load=list))

    def __init__(self, system: str | System, config: APGConfig | None = None, **overrides):
        self.config = dataclasses.replace(config or APGConfig(), **overrides)
        self.config.validate()
        cfg = self.config
        self.system = self._system(system, cfg)
        self.dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
        period = cfg.control_period if cfg.control_period is not None else self.system.swingup_period
        ratio = period / self.system.dt
        check_at_most("APGConfig.horizon x control_period / integrator.dt", cfg.horizon * ratio,
                      MAX_SIMULATION_STEPS, why="integrator steps of one episode", force_flag=None)
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ValueError(f"APGConfig.control_period ({period}) must be a whole multiple of {self.system.name}'s "
                             f"integrator.dt ({self.system.dt})")
        self.period, self.substeps = float(period), int(round(ratio))
        self.K = 1 if cfg.method == "apg" else cfg.population
        obs_dim = observation_size(self.system, cfg.observation)
        kind, widths = parse_policy(cfg.policy)
        with seeded(cfg.seed):
            self.pop = PolicyPopulation.build(kind, obs_dim, self.system.n_actions, self.system.action_limit,
                                              members=self.K, hidden=widths, init_std=cfg.init_std,
                                              dtype=self.dtype)
        P = self.pop.n_params
        # CEM / CE-APG: theta = 0 with std sigma_0 (the author's zero-initialised weights); PAPG/APG: members
        # start as the population's own perturbed-zero initialisation
        self.mean = torch.zeros(P, dtype=torch.float64)
        self.std = torch.full((P,), float(cfg.init_std), dtype=torch.float64)
        self.members = self.pop.to_flat().double()
        self.best = self.members[0].clone()
        self.best_score = -math.inf
        self.adam = BatchedAdam(self.K, P, (cfg.beta1, cfg.beta2))
        self.stats = torch.zeros(2 * obs_dim + 1, dtype=torch.float64)   # sum, sum of squares, count
        self.epoch = self.iterations = self.env_steps = self.nan_grads = self.large_grads = 0
        self.wall_time = 0.0
        self.history: list[dict] = []
        self.log_rows: list[dict] = []
        self._step = compiled_policy_step() if cfg.compile else policy_step
        self.takeover = LQRTakeover(self.system, self.dtype) if cfg.takeover == "lqr" else None
        self.last_scores = torch.full((self.K,), -math.inf, dtype=torch.float64)
        self._obs_sums = None   # observation sums of the current epoch (for the normalisation)
        self._backend = None    # the worker pool of a split APG phase (opened on first use)

    @staticmethod
    def _system(system: str | System, cfg: APGConfig) -> System:
        """The system with the config's Ch. 7 reward (as spec overrides, recorded in the spec)."""
        reward = {"reward__kind": cfg.reward_kind, "reward__alive_bonus": float(cfg.alive_bonus),
                  "reward__velocity_penalty": float(cfg.velocity_penalty),
                  "reward__position_weight": float(cfg.position_weight)}
        if isinstance(system, System):
            base = system.name if system.name in known_systems() else str(system.spec.path)
            return systems_mod.load(base, **{**system.spec.overrides, **reward})
        if not isinstance(system, str):
            raise ValueError(f"system must be a name ({', '.join(known_systems())}) or a System, got {system!r}")
        return systems_mod.load(system, **reward)

    @property
    def progress_count(self) -> int:
        """CE / PAPG epochs so far (the progress.csv key)."""
        return self.epoch

    # ------------------------------------------------------------------ randomness
    def _generator(self, epoch: int) -> torch.Generator:
        """The torch generator of ``epoch`` (from the seed alone: a resumed run continues exactly)."""
        return torch.Generator().manual_seed(int(np.random.SeedSequence([self.config.seed, epoch]).generate_state(1)[0]))

    def starts(self, n: int, seed_words) -> torch.Tensor:
        """n start states [n, n_states]: hanging down +- U(-start_noise, start_noise), or the spec's spread."""
        rng = np.random.default_rng(np.random.SeedSequence(list(seed_words)))
        cfg = self.config
        if cfg.start_noise is None:
            x0 = self.system.sample_initial_states(n, rng)
        else:
            x0 = self.system.initial_state.nominal + rng.uniform(-cfg.start_noise, cfg.start_noise,
                                                                 size=(n, self.system.n_states))
        return torch.as_tensor(x0, dtype=self.dtype)

    # ------------------------------------------------------------------ one APG iteration
    def apg_step(self, theta: torch.Tensor, x0: torch.Tensor, lr: float, adam: BatchedAdam | None = None,
                 state=None, horizon: int | None = None):
        """One batched APG update of the members ``theta`` [K, P] from starts x0 [N, n].

        Returns (new theta, per-member mean returns [K] (-inf where diverged), gradient
        norms [K], applied mask [K], final x, final recurrent state).
        """
        cfg = self.config
        pop = self.pop
        pop.from_flat(theta.to(self.dtype))
        returns, x, h, sums, _ = population_returns(self.system, pop, x0, horizon or cfg.horizon, self.substeps,
                                                    cfg.observation, cfg.truncation, state, step=self._step,
                                                    takeover=self.takeover)
        self._obs_sums = [a + b for a, b in zip(self._obs_sums, sums)] if self._obs_sums else list(sums)
        member_return = returns.mean(1)
        grad = member_gradients(pop, -member_return).double()
        norms = grad.norm(dim=1)
        finite = torch.isfinite(norms) & torch.isfinite(member_return.detach())
        large = finite & (norms > cfg.grad_bound)
        ok = finite & ~large
        self.nan_grads += int((~finite).sum())
        self.large_grads += int(large.sum())
        grad = torch.where(ok[:, None], clip_gradients(torch.nan_to_num(grad), cfg.clip, cfg.clip_mode),
                           torch.zeros_like(grad))
        new = (adam or self.adam).step(theta, grad, ok, lr)
        check_finite("APG parameters", new, f"at epoch {self.epoch}, iteration {self.iterations}")
        scores = torch.where(torch.isfinite(member_return.detach()), member_return.detach().double(),
                             torch.full_like(member_return.detach().double(), -math.inf))
        h = (h[0].detach(), h[1]) if isinstance(h, tuple) else h.detach()
        return new, scores, norms, ok, x.detach(), h

    def _apg_phase(self, theta: torch.Tensor, lr: float, adam: BatchedAdam):
        """``apg_iterations`` APG (or short-horizon APG) iterations; (theta, returns [iters, K], grad norms)."""
        cfg = self.config
        all_returns, all_norms = [], []
        for it in range(cfg.apg_iterations):
            x0 = self.starts(cfg.batch, [cfg.seed, self.epoch, it, 1])
            if cfg.method == "shapg":
                theta, ret, norms = self._short_horizon_episode(theta, x0, lr, adam)
            else:
                theta, ret, norms, _, _, _ = self.apg_step(theta, x0, lr, adam)
            all_returns.append(ret)
            all_norms.append(norms)
            self.iterations += 1
            self.env_steps += self.K * cfg.batch * cfg.horizon
        return theta, torch.stack(all_returns), torch.stack(all_norms)

    def _split_apg_phase(self, theta: torch.Tensor, lr: float, adam: BatchedAdam):
        """:meth:`_apg_phase` as contiguous chunks of members on the config's backend (see the module
        docstring); the same results, counters and ``adam`` state as in one process. With the
        "serial" backend or one member, :meth:`_apg_phase` itself."""
        cfg = self.config
        if cfg.backend == "serial" or self.K == 1:
            return self._apg_phase(theta, lr, adam)
        if self._backend is None:
            self._backend = make_backend(cfg.backend, workers=cfg.workers, address=cfg.ray_address)
        system = self.system.name if self.system.name in known_systems() else str(self.system.spec.path)
        tasks = []
        for chunk in np.array_split(np.arange(self.K), min(self._backend.workers, self.K)):
            lo, hi = int(chunk[0]), int(chunk[-1]) + 1
            sub = dataclasses.replace(cfg, population=hi - lo, elites=min(cfg.elites, hi - lo), backend="serial",
                                      workers=None, ray_address=None)
            tasks.append({"system": system, "overrides": dict(self.system.spec.overrides),
                          "config": dataclasses.asdict(sub), "epoch": self.epoch, "iterations": self.iterations,
                          "lr": lr, "theta": _array(theta[lo:hi]),
                          "adam": [_array(a[lo:hi]) for a in (adam.m, adam.v, adam.t)],
                          "normalization": (_array(self.pop.obs_mean), _array(self.pop.obs_std))})
        results = self._backend.map(apg_chunk, tasks)
        joined = {key: torch.cat([torch.tensor(r[key]) for r in results], dim=0 if key == "theta" else 1)
                  for key in ("theta", "returns", "norms")}
        adam.m, adam.v, adam.t = (torch.cat([torch.tensor(r["adam"][i]) for r in results]) for i in range(3))
        self._obs_sums = [torch.tensor(sum(r["obs_sums"][i] for r in results)) for i in (0, 1)] + \
                         [sum(r["obs_sums"][2] for r in results)]
        self.iterations += cfg.apg_iterations        # every chunk ran the same iterations
        for counter in ("env_steps", "nan_grads", "large_grads"):
            setattr(self, counter, getattr(self, counter) + sum(r[counter] for r in results))
        return joined["theta"], joined["returns"], joined["norms"]

    def close_backend(self) -> None:
        """Close the worker pool of the split APG phase, if one is open (``learn`` does it when it ends)."""
        backend, self._backend = self._backend, None
        if backend is not None:
            backend.close()

    def _short_horizon_episode(self, theta, x0, lr, adam):
        """One episode of ``horizon`` steps as short-horizon unrolls with the state carried over."""
        cfg = self.config
        done, state, x, total, norms = 0, None, x0, torch.zeros(self.K, dtype=torch.float64), []
        while done < cfg.horizon:
            steps = min(cfg.short_horizon, cfg.horizon - done)
            theta, ret, nrm, _, x, state = self.apg_step(theta, x, lr, adam, state=state, horizon=steps)
            total = total + ret
            norms.append(nrm)
            done += steps
        return theta, total, torch.stack(norms).nanmean(0)

    # ------------------------------------------------------------------ one epoch
    def train_epoch(self) -> dict:
        """One CE-APG / CEM epoch, or ``apg_iterations`` iterations of APG / PAPG / short-horizon APG."""
        cfg = self.config
        lr = lr_schedule(cfg, self.epoch)
        self._obs_sums = None
        nan_before, large_before = self.nan_grads, self.large_grads
        gen = self._generator(self.epoch)
        grad_norm = float("nan")
        if cfg.method in ("ce-apg", "cem"):
            noise = torch.randn((self.K, self.pop.n_params), dtype=torch.float64, generator=gen)
            candidates = self.mean[None] + self.std[None] * noise
            if cfg.method == "cem":
                self.pop.from_flat(candidates.to(self.dtype))
                x0 = self.starts(cfg.batch, [cfg.seed, self.epoch, 0, 1])
                with torch.no_grad():
                    returns, _, _, sums, _ = population_returns(self.system, self.pop, x0, cfg.horizon,
                                                                self.substeps, cfg.observation, step=self._step,
                                                                takeover=self.takeover)
                self._obs_sums = list(sums)
                r = returns.mean(1).double()
                scores = torch.where(torch.isfinite(r), r, torch.full_like(r, -math.inf))
                finals, history = candidates, scores[None]
                self.iterations += 1
                self.env_steps += self.K * cfg.batch * cfg.horizon
            else:
                finals, history, norms = self._split_apg_phase(candidates, lr, BatchedAdam(self.K, self.pop.n_params,
                                                                                       (cfg.beta1, cfg.beta2)))
                scores = history[-cfg.rank_window:].mean(0)
                grad_norm = float(norms[torch.isfinite(norms)].median()) if torch.isfinite(norms).any() else grad_norm
            new_mean, new_std, elite = cem_update(self.mean, finals, scores, cfg.elites)
            self.mean, self.std = new_mean, new_std
            self.members = finals
        else:
            finals, history, norms = self._split_apg_phase(self.members, lr, self.adam)
            scores = history[-cfg.rank_window:].mean(0)
            elite = torch.argsort(scores, descending=True, stable=True)[:cfg.elites]
            self.members = finals
            grad_norm = float(norms[torch.isfinite(norms)].median()) if torch.isfinite(norms).any() else grad_norm
        self.last_scores = scores          # this epoch's ranking scores [K] (-inf: diverged)
        top = int(torch.argmax(torch.nan_to_num(scores, nan=-math.inf)))
        if cfg.method in ("apg", "shapg", "papg"):   # the best member NOW is the result (not the initial one)
            self.best, self.best_score = finals[top].clone(), float(scores[top])
        elif float(scores[top]) > self.best_score:   # CE-APG / CEM: the best member seen (the author's metric)
            self.best, self.best_score = finals[top].clone(), float(scores[top])
        if cfg.normalize and self._obs_sums is not None:
            o_sum, o_sq, count = self._obs_sums
            self.stats += torch.cat([o_sum, o_sq, torch.tensor([float(count)], dtype=torch.float64)])
            self._apply_stats()
        self.epoch += 1
        finite = history[torch.isfinite(history)]
        return {"epoch": self.epoch, "iterations": self.iterations, "env_steps": self.env_steps,
                "physics_steps": self.env_steps * self.substeps, "lr": lr,
                "mean_return": float(finite.mean()) if finite.numel() else float("nan"),
                "best_return": float(scores[top]), "elite_score": float(scores[elite].mean()),
                "grad_norm": grad_norm, "nan_grads": self.nan_grads - nan_before,
                "large_grads": self.large_grads - large_before,
                "diverged": int((~torch.isfinite(scores)).sum()), "sigma": float(self.std.mean())}

    def _apply_stats(self) -> None:
        """Freeze the running observation mean/std into the policies (std 1 where below 1e-4)."""
        d = self.pop.obs_dim
        count = float(self.stats[-1])
        if count < 2:
            return
        mean = self.stats[:d] / count
        var = (self.stats[d:2 * d] / count - mean ** 2).clamp_min(0.0)
        std = torch.where(var < 1e-8, torch.ones_like(var), var.sqrt())
        self.pop.set_normalization(mean, std)

    def run_description(self) -> str:
        """The progress bar's label."""
        return f"{self.config.method} {self.system.name}"

    def train(self, run, target: int, backend) -> None:
        """The APG family's loop inside ``learn``'s run: one epoch at a time (the population split
        over ``backend``, default the config's, opened when first needed), a checkpoint every
        ``checkpoint_every`` epochs and at least every ``checkpoint_minutes``."""
        if backend is not None:
            self._backend = backend
        try:
            run.updates(target, self._timed_epoch, 1, self.config.checkpoint_every,
                        lambda row: {"ret": f"{row['best_return']:.1f}", "gnorm": f"{row['grad_norm']:.2g}",
                                     "nan": self.nan_grads, "sps": f"{row['steps_per_s']:.0f}"})
        finally:
            if backend is None:
                self.close_backend()
            else:
                self._backend = None

    def _timed_epoch(self) -> dict:
        """One epoch's row, with ``episode_steps`` the epoch's env steps (so that :meth:`Run.updates`'s
        steps per second count every member's and batch's steps)."""
        before = self.env_steps
        row = self.train_epoch()
        row["episode_steps"] = self.env_steps - before
        return row

    # ------------------------------------------------------------------ use
    def policy(self, which: str | None = None) -> Policy:
        """The trained policy: ``"best"`` (the best member; default for apg/shapg/papg) or ``"mean"``
        (the CEM mean; default for cem/ce-apg), with the frozen normalisation."""
        which = which or ("mean" if self.config.method in ("cem", "ce-apg") else "best")
        if which not in ("best", "mean"):
            raise ValueError(f"which must be 'best' or 'mean', got {which!r}")
        theta = self.mean if which == "mean" else self.best
        return Policy(self.pop.resized(1, theta.to(self.dtype)[None]))

    def closed_loop_policy(self, which: str | None = None) -> ClosedLoopPolicy:
        """:meth:`policy` with the observation, on raw states (for Drake's RecurrentTorchPolicy)."""
        return ClosedLoopPolicy(self.system, self.policy(which), self.config.observation)

    def run_evaluation(self, episodes: int, seed: int, which: str | None = None,
                       horizon: int | None = None, keep_states: bool = False) -> EvalResult:
        """``evaluate(episodes, seed=, ...)``: returns of the trained policy on held-out starts, and the stabilisation rate: the share of
        episodes whose last second (of policy-step states) stays within the spec's success eps of
        the goal (thesis eq. 3.2 with lookback = one second; the L2 norm over every coordinate, a
        cart's position and the velocities included). ``upright_rate``: the share whose angle
        errors alone all stay below eps over the last second (the pole held up, the cart anywhere).
        ``best_training_return``: the best member's training score (the author's metric)."""
        n = episodes
        policy = self.policy(which)
        x0 = self.starts(n, [seed, 2])
        with torch.no_grad():
            returns, _, _, _, states = population_returns(self.system, policy.population, x0,
                                                          horizon or self.config.horizon, self.substeps,
                                                          self.config.observation, keep_states=True,
                                                          takeover=self.takeover)
        r = returns[0].double().numpy()
        s = states[0].double().numpy()
        balanced, upright = stabilisation(s, self.system, lookback=max(1, int(round(1.0 / self.period))))
        out = EvalResult.from_returns(r[np.isfinite(r)], success_rate=float(balanced.mean()),
                                      upright_rate=float(upright.mean()),
                                      first={"episodes": n, "seed": seed},
                                      which=which or ("mean" if self.config.method in ("cem", "ce-apg") else "best"),
                                      diverged=int((~np.isfinite(r)).sum()), best_training_return=self.best_score)
        if keep_states:
            out["states"] = s
        return out

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_extra(self) -> dict:
        """config.json beside algorithm, system (its record, the config's reward settings among its
        overrides) and config: the method, the policy's architecture, substeps and control period."""
        return {"method": self.config.method, "policy": self.pop.describe(), "substeps": self.substeps,
                "period": self.period}

    def normalization(self) -> dict:
        """normalization.json: the frozen observation mean and std."""
        return {"type": "frozen_mean_std", "mean": self.pop.obs_mean.tolist(), "std": self.pop.obs_std.tolist()}

    @classmethod
    def from_checkpoint(cls, found: Path, meta: dict, config: APGConfig, system, force: bool) -> "APG":
        """:meth:`~hybridctl.learn.base.Learner.load`'s learner: on ``system`` (None: the recorded one,
        rebuilt from its name and spec overrides; the config's reward settings are applied again).
        When today's spec of that system differs from the recorded plant, loading is refused naming
        the values (``force``: a warning), as for another algorithm's checkpoint."""
        record = meta["system"]
        if system is None:
            overrides = {k: v for k, v in (record.get("overrides") or {}).items() if not k.startswith("reward__")}
            system = ckpt.recorded_system(found, record["name"], overrides)
        agent = cls(system, config)  # applies the config's reward settings to the system
        if "spec_hash" in record:
            ckpt.check_plant(found, record, agent.system, force)
        return agent
