"""The core of the APG family (thesis Ch. 7), shared by every method: the differentiable rollout of a
population of policies, the member gradients, the batched Adam, gradient clipping, the LQR
takeover of the switched controller, the CEM update, the observation, and one APG iteration /
episode / phase as functions over tensors (:class:`APGProblem` holds what they need).

The population is one computation: parameters stacked [K, ...] (:mod:`..policies`), the
K x N states one (K N, n) batch through ``System.step_unchecked``, the loss the sum of the
members' losses, one backward; member k's gradient is the slice k (members share nothing).
Every member has its own Adam moments and step count (:class:`BatchedAdam`), so a member
whose gradient is skipped is not moved.

Device: everything here follows its inputs' device (the population's, ``APGConfig.device``):
states, returns, masks, observation sums and Adam moments are made there, and nothing in a
rollout copies to the host (a NaN guard and the guard counters read back once per APG update).
The start states are drawn by numpy from their seed words (the same starts on every device)
and copied to the device once per APG phase.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np
import torch

from ...limits import MAX_SIMULATION_STEPS, check_at_most
from ...systems import System
from ...systems.compiled import wants_compile
from ...systems.switched import CostToGoGate, SwitchedController, gate_command, switched_decision
from ..policies import Policy, PolicyPopulation
from ..run import check_finite, seeded
from .compiled import APG_AUTO_COMPILE_MIN_STEPS, LazyCompiled, compiled, policy_steps_per_call
from .config import APGConfig, parse_policy

__all__ = ["APGProblem", "Phase", "BatchedAdam", "LQRTakeover", "takeover_controller",
           "ClosedLoopPolicy", "observe", "observation_size",
           "policy_step", "compiled_policy_step", "policy_steps", "compiled_policy_steps", "population_returns",
           "member_gradients", "clip_gradients",
           "cem_update", "start_states", "start_array", "apg_iteration", "apg_episode", "apg_phase",
           "evaluate_members", "add_observation_sums", "median_norm", "gradient_norms_by_horizon",
           "returns_along_direction"]


# ============================================================================ the rollout and its gradients


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

    ``takeover``: the switched controller's LQR half (:class:`LQRTakeover`): the held action is one
    decision of its :class:`~hybridctl.systems.SwitchedController` (:func:`~hybridctl.systems.switched.
    switched_decision`): every gate period (every integrator step for the APG's) the gate's ``mode``
    [K, N] (bool, True = LQR) is updated with hysteresis and the saturated LQR command replaces the held
    policy action where the mode is on (as the Drake diagram does).
    """
    K, N, n = x.shape
    obs = observe(system, x, observation)
    action, h = pop(obs, h)
    u = action.reshape(K * N, system.n_actions)
    xs = x.reshape(K * N, n)
    ms = None if mode is None else mode.reshape(K * N)
    if takeover is not None:
        xs, ms = takeover.decide(xs, u, ms, substeps)
    else:
        for _ in range(substeps):
            xs = system.step_unchecked(xs, u)
    x = xs.reshape(K, N, n)
    return x, h, system.reward(x), obs, (None if ms is None else ms.reshape(K, N))


def takeover_controller(system: System, decision_period: float | None = None) -> SwitchedController:
    """The switched controller the APG family trains through (``APGConfig.takeover = "lqr"``):
    :meth:`SwitchedController.for_system` with the spec's :class:`~hybridctl.systems.switched.CostToGoGate`,
    hysteresis and LQR; its swing-up the population's actions (None); ``decision_period`` the policy
    step (None: the spec's ``swingup_period``); and the gate and LQR acting every integrator step
    (``gate_period = integrator.dt``: what ``takeover = "lqr"`` in a checkpoint's config has always
    meant; the spec's ``control.period`` equals ``dt`` for every shipped system)."""
    return SwitchedController.for_system(system, gate=CostToGoGate(system), decision_period=decision_period,
                                         gate_period=system.dt).replace(swingup=None)


class LQRTakeover:
    """The balance half of the switched controller inside the population rollout (thesis Ch. 3 around
    Ch. 7): a view of a :class:`~hybridctl.systems.SwitchedController` (default :func:`takeover_controller`)
    on the rollout's dtype and device, run by the one switched decision of :mod:`hybridctl.systems.switched`.

    ``takeover.decide(x [B, n], u [B, m], mode [B] | None, substeps) -> (x, mode)``: the policy action
    ``u`` held over ``substeps`` integrator steps while, every ``controller.gate_period`` (``stride``
    steps), the controller's gate (the spec's cost-to-go gate p = exp(-V(x) / gate.cost_scale)) with its
    hysteresis (gate.on / gate.off) chooses, per state, the saturated LQR command -K (x - goal) (Drake's
    LQR, :meth:`System.lqr`) or the policy's (:func:`~hybridctl.systems.switched.switched_decision`; a
    diverging row runs on to Inf / NaN: the member's return is then non-finite and its gradient skipped).
    ``takeover(x, mode, u) -> (command, mode)``: one gate evaluation
    (:func:`~hybridctl.systems.switched.gate_command`).

    Training a swing-up with it (``APGConfig.takeover = "lqr"``) optimises the switched
    controller that runs in Drake: the swing-up need only deliver the state into the gate's
    region, and the LQR phase, being stable, passes bounded gradients back to the state where
    the gate switched on. The switch itself is a hard choice: no gradient flows through the
    switching time (autograd as :func:`~hybridctl.systems.closed_loop_rollout` with ``differentiable=True``).

    Why the population rollout is not :func:`~hybridctl.systems.closed_loop_rollout` itself: its states are
    [K, N, n] under K stacked policies that act on observations, it sums the reward and the
    observation statistics every policy step, cuts the graph every ``truncation`` steps and fuses
    ``compile_steps`` policy steps into one compiled call (:func:`policy_steps`); the decision inside
    each policy step is the shared one.
    """

    def __init__(self, system: System, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu",
                 controller: SwitchedController | None = None, decision_period: float | None = None):
        device = torch.device(device)
        controller = takeover_controller(system, decision_period) if controller is None else controller
        if not isinstance(controller, SwitchedController):
            raise TypeError(f"controller must be a SwitchedController, got {type(controller).__name__}")
        self.system, self.controller = system, controller
        self.gate = controller.gate.to(device)   # on the rollout's device: no copy per step
        self.gate_dtype = self.gate.compute_dtype or dtype
        self.K = torch.as_tensor(controller.K, dtype=dtype, device=device)
        self.goal = (None if np.array_equal(controller.goal, system.goal)
                     else torch.as_tensor(controller.goal, dtype=dtype, device=device))
        self.on, self.off = controller.gate_on, controller.gate_off
        self.stride = controller.gate_stride(system)
        self.limit = float(system.action_limit)

    def __call__(self, x: torch.Tensor, mode: torch.Tensor | None, u_policy: torch.Tensor):
        """One gate evaluation at states x [B, n]: (command [B, m], next mode [B]); ``mode`` None: swing-up."""
        mode = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device) if mode is None else mode
        return gate_command(self.system, self.gate, x, u_policy, mode, self.K, self.gate_dtype, self.on, self.off,
                            self.goal)

    def decide(self, x: torch.Tensor, u: torch.Tensor, mode: torch.Tensor | None, substeps: int):
        """``u`` held over ``substeps`` integrator steps under the takeover: (next x [B, n], next mode [B])."""
        mode = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device) if mode is None else mode
        x, _, mode, _ = switched_decision(self.system, self.gate, x, u, mode, self.K, substeps, self.stride,
                                          self.gate_dtype, self.on, self.off, goal=self.goal, restore_diverged=False)
        return x, mode


def compiled_policy_step(strict: bool = True) -> LazyCompiled:
    """:func:`policy_step` through ``torch.compile`` (compiled on first use per shape; one shared cache)."""
    return compiled(policy_step, strict)


def policy_steps(system: System, pop: PolicyPopulation, x: torch.Tensor, h: torch.Tensor, substeps: int,
                 observation: str, takeover: "LQRTakeover | None", mode: torch.Tensor | None, total: torch.Tensor,
                 o_sum: torch.Tensor, o_sq: torch.Tensor, count: int):
    """``count`` :func:`policy_step` calls with the bookkeeping of :func:`population_returns` (the return
    ``total`` [K, N] and the observation sums, non-finite rows zeroed): the unit that
    :func:`compiled_policy_steps` fuses into one compiled call. Returns (x, h, mode, total, o_sum, o_sq)."""
    for _ in range(count):
        x, h, reward, obs, mode = policy_step(system, pop, x, h, substeps, observation, takeover, mode)
        o_sum, o_sq = _add_observations(obs.detach(), pop.obs_dim, o_sum, o_sq)
        total = total + reward
    return x, h, mode, total, o_sum, o_sq


def _add_observations(obs: torch.Tensor, obs_dim: int, o_sum: torch.Tensor, o_sq: torch.Tensor):
    """The running observation sums plus one step's observations (float64). A non-finite row is zeroed
    rather than dropped: the same sums, without the host sync a boolean index costs on a GPU (it must
    learn how many rows remain)."""
    od = obs.reshape(-1, obs_dim).double()
    od = torch.where(torch.isfinite(od).all(-1, keepdim=True), od, torch.zeros_like(od))
    return o_sum + od.sum(0), o_sq + (od * od).sum(0)


def compiled_policy_steps(strict: bool = True) -> LazyCompiled:
    """:func:`policy_steps` through ``torch.compile``: ``count`` policy steps (each with its integrator
    sub-steps, reward and observation sums) as one compiled call, forward and backward. One graph per
    distinct ``count`` (a run needs one or two: the chunk and a remainder), compiled on first use.

    Why: at the thesis' 24 x 4 population the per-step work is a few microseconds of arithmetic;
    the cost is the calls around it (measured on the acrobot task, T = 500, 5 sub-steps: 0.35 s per
    APG iteration compiled per step, 0.17 s with 10 steps per call; 25 steps per call compiled for
    6 minutes and ran no faster)."""
    return compiled(policy_steps, strict)


def population_returns(system: System, pop: PolicyPopulation, x0: torch.Tensor, horizon: int, substeps: int,
                       observation: str = "trig", truncation: int | None = None, state=None,
                       keep_states: bool = False, step=None, takeover: LQRTakeover | None = None,
                       steps=None, steps_per_call: int = 1):
    """Roll K members x N starts out as one batch; the differentiable returns [K, N].

    ``x0``: [N, n] (the same starts for every member) or [K, N, n], moved to the population's
    dtype and device. ``state``: the policies' recurrent state [K, N, h] (None: zero). Each
    policy step holds the action over ``substeps`` integrator steps of
    ``System.step_unchecked`` and then collects ``System.reward`` of the new state.
    ``truncation``: detach the states every that many steps (truncated BPTT). Returns
    (returns [K, N], final x [K, N, n], final state, obs sums (sum, sum of squares, count) for
    the normalisation, and the states [K, N, T+1, n] when ``keep_states``, else None).
    ``step``: the per-step function (default :func:`policy_step`; :func:`compiled_policy_step`
    for the fused one). ``takeover``: the switched controller's LQR half
    (:class:`LQRTakeover`); then ``state`` and the returned state are the pair (recurrent
    state, gate mode [K, N]), the mode starting off (the swing-up acts). ``steps``: a
    :func:`policy_steps`-like function doing ``steps_per_call`` (> 1) policy steps per call
    (:func:`compiled_policy_steps`, the fused path; a call ends where ``truncation`` cuts the
    graph); ignored with ``keep_states``.
    """
    step = step or policy_step
    K = pop.members
    if x0.dim() == 2:
        x0 = x0.unsqueeze(0).expand(K, -1, -1)
    N = x0.shape[1]
    x = x0.to(dtype=pop.dtype, device=pop.device)
    if takeover is None:
        h, mode = (pop.initial_state(N) if state is None else state), None
    else:
        h, mode = ((pop.initial_state(N), torch.zeros((K, N), dtype=torch.bool, device=x.device)) if state is None
                   else state)
    total = torch.zeros((K, N), dtype=pop.dtype, device=x.device)
    o_sum = torch.zeros(pop.obs_dim, dtype=torch.float64, device=x.device)
    o_sq = torch.zeros(pop.obs_dim, dtype=torch.float64, device=x.device)
    kept = [x.detach()] if keep_states else None
    fused = steps is not None and steps_per_call > 1 and not keep_states
    t = 0
    while t < horizon:
        if truncation is not None and t > 0 and t % truncation == 0:
            x, h = x.detach(), h.detach()
        if fused:   # a chunk ends where the graph is cut
            done = min(steps_per_call, horizon - t, truncation - t % truncation if truncation else horizon)
            x, h, mode, total, o_sum, o_sq = steps(system, pop, x, h, substeps, observation, takeover, mode,
                                                   total, o_sum, o_sq, done)
        else:
            done = 1
            x, h, reward, obs, mode = step(system, pop, x, h, substeps, observation, takeover, mode)
            o_sum, o_sq = _add_observations(obs.detach(), pop.obs_dim, o_sum, o_sq)
            total = total + reward
            if keep_states:
                kept.append(x.detach())
        t += done
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
    return flat.masked_fill(~finite[:, None], float("nan"))   # no boolean index: no host sync on a GPU


class BatchedAdam:
    """Adam on K stacked parameter vectors [K, P], each member with its own moments and step
    count; a masked-out member is not touched (moments, counts and parameters unchanged).
    The moments live on ``device`` (None: torch's default), the parameters' device."""

    def __init__(self, members: int, n_params: int, betas=(0.9, 0.999), eps: float = 1e-8,
                 dtype: torch.dtype = torch.float64, device: str | torch.device | None = None):
        self.betas, self.eps = (float(betas[0]), float(betas[1])), float(eps)
        self.m = torch.zeros((members, n_params), dtype=dtype, device=device)
        self.v = torch.zeros((members, n_params), dtype=dtype, device=device)
        self.t = torch.zeros(members, dtype=torch.int64, device=device)

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
        """Action and next recurrent state for raw states x (moved to the policy's dtype and device)."""
        population = self.policy.population
        return self.policy(observe(self.system, x.to(dtype=population.dtype, device=population.device),
                                   self.observation), state)

    def numpy_forward(self, x: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`forward` in numpy (:meth:`Policy.numpy_forward`), for the Drake block on one state."""
        dtype = np.float64 if self.policy.population.dtype == torch.float64 else np.float32
        obs = observe(self.system, np.asarray(x, dtype=dtype), self.observation)
        return self.policy.numpy_forward(obs, state)


# ============================================================================ one APG iteration, episode, phase


@dataclass
class APGProblem:
    """What an APG iteration needs, built once per (system, config, member count): the system (with
    the config's Ch. 7 reward), the population whose parameters are the iteration's scratch
    buffer (``from_flat``) and whose frozen normalisation the rollouts use, the integrator
    sub-steps per policy step, the per-step function (eager or compiled), the LQR takeover and
    the device (``config.device``) everything lives on. A learner holds one; a worker of the
    split APG phase builds its own."""

    system: System
    config: APGConfig
    pop: PolicyPopulation
    dtype: torch.dtype
    period: float
    substeps: int
    step: Callable
    takeover: "LQRTakeover | None"
    device: torch.device
    steps: Callable | None = None    # steps_per_call policy steps per compiled call (compile, steps_per_call > 1)
    steps_per_call: int = 1          # config.compile_steps, or (None) :func:`policy_steps_per_call`

    @classmethod
    def build(cls, system: System, config: APGConfig, members: int) -> "APGProblem":
        """The problem of ``members`` policies (initialised from ``config.seed`` on the CPU, then moved to
        ``config.device``: the same initial members on every device) on ``system``."""
        dtype = torch.float64 if config.dtype == "float64" else torch.float32
        device = torch.device(config.device)
        period = config.control_period if config.control_period is not None else system.swingup_period
        ratio = period / system.dt
        check_at_most("APGConfig.horizon x control_period / integrator.dt", config.horizon * ratio,
                      MAX_SIMULATION_STEPS, why="integrator steps of one episode", force_flag=None)
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ValueError(f"APGConfig.control_period ({period}) must be a whole multiple of {system.name}'s "
                             f"integrator.dt ({system.dt})")
        kind, widths = parse_policy(config.policy)
        with seeded(config.seed):
            pop = PolicyPopulation.build(kind, observation_size(system, config.observation), system.n_actions,
                                         system.action_limit, members=members, hidden=widths,
                                         init_std=config.init_std, dtype=dtype)
        use_compile = wants_compile(config.compile, config.total_policy_steps(members), APG_AUTO_COMPILE_MIN_STEPS)
        strict = config.compile == "on"
        per_call = policy_steps_per_call(int(round(ratio))) if config.compile_steps is None else config.compile_steps
        return cls(system, config, pop.to(device), dtype, float(period), int(round(ratio)),
                   compiled_policy_step(strict) if use_compile else policy_step,
                   LQRTakeover(system, dtype, device, decision_period=period) if config.takeover == "lqr" else None,
                   device,
                   compiled_policy_steps(strict) if use_compile and per_call > 1 else None, per_call)

    def starts(self, n: int, seed_words) -> torch.Tensor:
        """:func:`start_states` of this problem, on its device."""
        return start_states(self.system, self.config, n, seed_words, self.dtype, self.device)

    def phase_starts(self, epoch: int) -> torch.Tensor:
        """The starts of every APG iteration of ``epoch``'s phase [apg_iterations, batch, n]: iteration i's
        are :meth:`starts` seeded (seed, epoch, i, 1), drawn together and copied to the device once."""
        cfg = self.config
        draws = [start_array(self.system, cfg, cfg.batch, [cfg.seed, epoch, it, 1]) for it in range(cfg.apg_iterations)]
        return torch.as_tensor(np.stack(draws), dtype=self.dtype, device=self.device)


def start_array(system: System, config: APGConfig, n: int, seed_words) -> np.ndarray:
    """n start states [n, n_states] (float64 numpy) from the numpy seed ``seed_words``: hanging down
    +- U(-start_noise, start_noise), or the spec's spread when ``config.start_noise`` is None."""
    rng = np.random.default_rng(np.random.SeedSequence(list(seed_words)))
    if config.start_noise is None:
        return np.asarray(system.sample_initial_states(n, rng))
    return system.initial_state.nominal + rng.uniform(-config.start_noise, config.start_noise,
                                                      size=(n, system.n_states))


def start_states(system: System, config: APGConfig, n: int, seed_words, dtype: torch.dtype,
                 device: str | torch.device = "cpu") -> torch.Tensor:
    """:func:`start_array` as a tensor of ``dtype`` on ``device``: drawn by numpy from the seed words,
    so every device starts from the same states."""
    return torch.as_tensor(start_array(system, config, n, seed_words), dtype=dtype, device=device)


def add_observation_sums(total, sums):
    """The running observation sums (sum, sum of squares, count) with one rollout's ``sums`` added
    (``total`` None: the first); added in call order, so a run's normalisation is reproducible."""
    return [a + b for a, b in zip(total, sums)] if total else list(sums)


def median_norm(norms: torch.Tensor) -> float:
    """The median of the finite gradient norms (NaN when none is finite)."""
    finite = torch.isfinite(norms)
    return float(norms[finite].median()) if finite.any() else float("nan")


class Iteration(NamedTuple):
    """One APG iteration's result (:func:`apg_iteration`)."""

    theta: torch.Tensor        # the new parameters [K, P]
    scores: torch.Tensor       # per-member mean returns [K] (float64; -inf where diverged)
    norms: torch.Tensor        # gradient norms [K]
    ok: torch.Tensor           # the applied mask [K]
    x: torch.Tensor            # final states [K, N, n]
    state: object              # final recurrent state (with the gate mode under the takeover)
    obs_sums: list             # the rollout's observation sums
    nan_grads: int             # members whose gradient or return was not finite
    large_grads: int           # members whose gradient norm exceeded grad_bound


def apg_iteration(problem: APGProblem, theta: torch.Tensor, x0: torch.Tensor, lr: float, adam: "BatchedAdam",
                  state=None, horizon: int | None = None, where: str = "") -> Iteration:
    """One batched APG update of the members ``theta`` [K, P] from starts x0 ([N, n] or [K, N, n]),
    ``horizon`` policy steps (None: the config's) from the recurrent ``state`` (None: zero).

    A member's gradient that is NaN/inf or whose norm exceeds ``grad_bound`` is counted, skipped
    and never applied (its Adam moments and count stay); NaN parameters raise FloatingPointError
    (``where`` says when) before anything is returned. ``adam`` is stepped in place.
    """
    cfg = problem.config
    pop = problem.pop
    pop.from_flat(theta.to(problem.dtype))
    returns, x, h, sums, _ = population_returns(problem.system, pop, x0, horizon or cfg.horizon, problem.substeps,
                                                cfg.observation, cfg.truncation, state, step=problem.step,
                                                steps=problem.steps, steps_per_call=problem.steps_per_call,
                                                takeover=problem.takeover)
    member_return = returns.mean(1)
    grad = member_gradients(pop, -member_return).double()
    norms = grad.norm(dim=1)
    finite = torch.isfinite(norms) & torch.isfinite(member_return.detach())
    large = finite & (norms > cfg.grad_bound)
    ok = finite & ~large
    grad = torch.where(ok[:, None], clip_gradients(torch.nan_to_num(grad), cfg.clip, cfg.clip_mode),
                       torch.zeros_like(grad))
    new = adam.step(theta, grad, ok, lr)
    check_finite("APG parameters", new, where)
    scores = torch.where(torch.isfinite(member_return.detach()), member_return.detach().double(),
                         torch.full_like(member_return.detach().double(), -math.inf))
    h = (h[0].detach(), h[1]) if isinstance(h, tuple) else h.detach()
    nan_grads, large_grads = torch.stack([(~finite).sum(), large.sum()]).tolist()   # one read-back for both
    return Iteration(new, scores, norms, ok, x.detach(), h, list(sums), nan_grads, large_grads)


def apg_episode(problem: APGProblem, theta: torch.Tensor, x0: torch.Tensor, lr: float, adam: "BatchedAdam",
                unroll: int, obs_sums=None, where: str = ""):
    """One episode of ``horizon`` policy steps as APG updates of ``unroll`` steps each, the state
    carried over (``unroll`` = the horizon: one update through the whole episode, APG; shorter:
    short-horizon APG). Returns (theta, episode returns [K], mean gradient norms [K], the
    observation sums with this episode's added to ``obs_sums``, NaN gradients, large gradients)."""
    horizon = problem.config.horizon
    done, state, x, nan, large = 0, None, x0, 0, 0
    total, norms = torch.zeros(theta.shape[0], dtype=torch.float64, device=theta.device), []
    while done < horizon:
        steps = min(unroll, horizon - done)
        it = apg_iteration(problem, theta, x, lr, adam, state=state, horizon=steps, where=where)
        theta, x, state = it.theta, it.x, it.state
        total = total + it.scores
        norms.append(it.norms)
        obs_sums = add_observation_sums(obs_sums, it.obs_sums)
        nan, large = nan + it.nan_grads, large + it.large_grads
        done += steps
    return theta, total, torch.stack(norms).nanmean(0), obs_sums, nan, large


class Phase(NamedTuple):
    """An APG phase's result (:func:`apg_phase`, or joined from chunks of members)."""

    theta: torch.Tensor        # the members' parameters after the phase [K, P]
    returns: torch.Tensor      # training returns [iterations, K]
    norms: torch.Tensor        # gradient norms [iterations, K]
    adam: "BatchedAdam"        # the members' Adam state after the phase
    obs_sums: list             # the phase's observation sums
    iterations: int            # APG iterations done
    env_steps: int             # policy steps taken (K x N x T per iteration)
    nan_grads: int
    large_grads: int


def apg_phase(problem: APGProblem, theta: torch.Tensor, adam: "BatchedAdam", lr: float, epoch: int,
              iterations: int, unroll: int) -> Phase:
    """``apg_iterations`` APG episodes (:func:`apg_episode`) of the members ``theta`` [K, P] at epoch
    ``epoch``; iteration i starts from ``config.batch`` states seeded (seed, epoch, i, 1), so a
    chunk of members run apart gives the rows of the whole population. ``adam`` is not changed
    (the phase steps a copy, returned in the :class:`Phase`); ``iterations``: the count before
    the phase (for the message of a NaN)."""
    cfg = problem.config
    adam = copy.copy(adam)
    returns, norms, obs_sums, nan, large = [], [], None, 0, 0
    starts = problem.phase_starts(epoch)     # one host-to-device copy for the phase
    for it in range(cfg.apg_iterations):
        x0 = starts[it]
        theta, ret, nrm, obs_sums, n, l = apg_episode(problem, theta, x0, lr, adam, unroll, obs_sums,
                                                      f"at epoch {epoch}, iteration {iterations + it}")
        returns.append(ret)
        norms.append(nrm)
        nan, large = nan + n, large + l
    steps = cfg.apg_iterations * theta.shape[0] * cfg.batch * cfg.horizon
    return Phase(theta, torch.stack(returns), torch.stack(norms), adam, obs_sums, cfg.apg_iterations, steps, nan,
                 large)


def evaluate_members(problem: APGProblem, theta: torch.Tensor, x0: torch.Tensor):
    """The members ``theta`` [K, P] rolled out once (no gradient) from x0: (scores [K] float64, the
    mean return over the starts, -inf where diverged; the observation sums)."""
    cfg = problem.config
    problem.pop.from_flat(theta.to(problem.dtype))
    with torch.no_grad():
        returns, _, _, sums, _ = population_returns(problem.system, problem.pop, x0, cfg.horizon, problem.substeps,
                                                    cfg.observation, step=problem.step, takeover=problem.takeover,
                                                    steps=problem.steps, steps_per_call=problem.steps_per_call)
    r = returns.mean(1).double()
    return torch.where(torch.isfinite(r), r, torch.full_like(r, -math.inf)), list(sums)


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
    direction = direction.to(dtype=theta.dtype, device=theta.device)
    probe = pop.resized(len(scales), torch.stack([theta + v * direction for v in scales]))
    with torch.no_grad():
        returns, *_ = population_returns(system, probe, x0, horizon, substeps, observation)
    return returns.mean(1).double().tolist()
