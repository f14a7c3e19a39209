"""Chunk tasks (:class:`ChunkTask`): a chunk of B episodes of a torch module whose named parameters come from
the rows of ``thetas``, one ``torch.func.vmap`` forward of ``functional_call`` per env step, over gymnasium envs,
the MuJoCo batch stepper (one thread), or a hybridctl system's batched torch dynamics: the chunk's policies as
the swing-up of a :class:`~hybridctl.systems.SwitchedController` with the chunk's gate object (SSAC's
``LearnedGate``; the spec's ``CostToGoGate`` of a recurrent APG-family swing-up, its hidden state carried per
episode; ``NeverGate`` for none) and the spec's LQR, run by
:func:`~hybridctl.systems.switched.closed_loop_rollout` on any torch device with no copy to the host until the
chunk ends. What every chunk of a batch reads and none changes (the policy, its gate and normaliser, the
post-processor: :class:`ChunkInputs`) is shipped once per batch (``backend.put``; the tasks carry the reference).
:func:`chunk_slices` splits a batch into chunks, by default from the backend's worker count. Fine-tuning uses
them, through :func:`hybridctl.learn.rollouts.rollouts`."""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.func import functional_call, vmap

from ..analysis.postprocess import PostProcessor
from ..envs.mujoco_batch import MujocoBatchEnv
from ..envs.mujoco_batch import supports as batch_supports
from ..parallel import cached_env
from ..systems import load as load_system
from .rollout_envs import make_env
from .rollout_results import episode_result


class Shipped:
    """A torch module sent to workers as plain pickled bytes, decoded once per worker.

    A module inside a task would otherwise travel by torch's shared-memory file descriptors,
    whose hand-over hangs after a process pool was rebuilt (a worker killed); bytes always
    arrive. The bytes are made by this process from its own module, never read from a file.
    """

    _decoded: dict[str, torch.nn.Module] = {}
    KEEP = 2

    def __init__(self, module: torch.nn.Module | None):
        import hashlib
        import pickle

        self.blob = pickle.dumps(module) if module is not None else None
        self.key = hashlib.sha1(self.blob).hexdigest() if self.blob is not None else ""

    def get(self) -> torch.nn.Module | None:
        """The module (built from the bytes once per process)."""
        import pickle

        if self.blob is None:
            return None
        if self.key not in Shipped._decoded:
            if len(Shipped._decoded) >= Shipped.KEEP:   # a batch's policy and gate at a time per worker
                del Shipped._decoded[next(iter(Shipped._decoded))]
            Shipped._decoded[self.key] = pickle.loads(self.blob)
        return Shipped._decoded[self.key]


@dataclass
class ChunkInputs:
    """What every chunk of one batch of rollouts reads and none changes (plain, picklable): shipped
    once per batch with ``backend.put`` (Ray: one copy in the object store), the tasks carry the
    reference (:attr:`ChunkTask.inputs`)."""

    shipped: Shipped              # the policy module (non-perturbed parameters at their values)
    names: list[str]              # the perturbed parameters, in the order of a theta row
    normalizer: Any               # frozen observation normaliser (None: observations as they are)
    postprocessor: PostProcessor
    gate: Shipped | None = None   # a system's gate (a Gate: SSAC's LearnedGate, the spec's CostToGoGate): the
    #                               switched controller, gate + LQR inside the rollout; None: no gate


def shared_value(value: Any) -> Any:
    """The value behind ``backend.put(value)``'s result, in a worker: ``ray.get`` of a Ray object
    reference (Ray resolves references only where they are a task's own argument, not inside
    one), the value itself from every other backend (their ``put`` is the identity)."""
    ray = sys.modules.get("ray")   # a Ray reference exists only where ray is imported already
    if ray is not None and isinstance(value, getattr(ray, "ObjectRef", ())):
        return ray.get(value)
    return value


@dataclass
class ChunkTask:
    """Episodes of ``len(seeds)`` policies (rows of ``thetas``), one per env seed (plain, picklable)."""

    env: Any
    env_kwargs: dict | None
    inputs: Any                   # a ChunkInputs, or the reference backend.put returned for it
    thetas: np.ndarray            # (B, P) float64
    seeds: list[int]
    max_steps: int | None
    system: str | None = None     # a hybridctl system's name: its batched torch dynamics (sac/ssac policies)
    keep_states: bool = False
    engine: str = "auto"          # "auto": the MuJoCo batch stepper where it applies; "backend": gymnasium envs
    device: str = "cpu"           # where a system's rollout runs (gymnasium and MuJoCo envs step on the host)
    system_overrides: dict | None = None   # the system's spec overrides (a checkpoint's reward, starts)
    decision_period: float | None = None   # a system's swing-up decision period (None: the spec's swingup_period)

    @property
    def shared(self) -> ChunkInputs:
        """The batch's shared inputs (fetched from the object store where :attr:`inputs` is a reference)."""
        return shared_value(self.inputs)

    @property
    def module(self) -> torch.nn.Module:
        """The policy module (non-perturbed parameters at their values; perturbed ones come from thetas)."""
        return self.shared.shipped.get()

    @property
    def names(self) -> list[str]:
        """The perturbed parameters' names, in the order of a theta row."""
        return self.shared.names

    @property
    def normalizer(self):
        """The frozen observation normaliser (None: none)."""
        return self.shared.normalizer

    @property
    def postprocessor(self) -> PostProcessor:
        """The return post-processor."""
        return self.shared.postprocessor


AUTO_CHUNK_MAX = 64
"""Largest chunk :func:`chunk_slices` makes by itself on the CPU (the fixed size of earlier versions):
more rows gain a CPU worker little, and smaller chunks leave other workers something to do."""
AUTO_CHUNK_MAX_ACCELERATOR = 4096
"""Largest automatic chunk of a system's rollouts on an accelerator, where one wide batch is the point."""
TASKS_PER_WORKER = 2
"""Automatic chunking gives every worker at least this many tasks (where there are rows enough), so a
worker that finishes early finds another."""


def chunk_slices(total: int, chunk_size: int | None, workers: int = 1, largest: int = AUTO_CHUNK_MAX) -> list[slice]:
    """The row ranges of the chunks of a batch of ``total`` rollouts.

    ``chunk_size`` an int: consecutive chunks of that many rows (the last one shorter). None
    ("auto"): near-equal chunks (sizes differ by at most one), enough that each of the backend's
    ``workers`` gets :data:`TASKS_PER_WORKER` of them, none larger than ``largest`` and none of a
    single row (where ``total`` >= 2). Chunks of 2 rows or more give the same numbers bit for bit
    whatever their size (measured on gymnasium, MuJoCo and system envs); a one-row chunk of a
    system's float64 CPU rollout takes :meth:`~hybridctl.systems.System.step`'s plain-float path,
    which can differ from the batched one in the last bit.
    """
    if total < 1:
        return []
    if chunk_size is not None:
        return [slice(i, min(i + chunk_size, total)) for i in range(0, total, chunk_size)]
    chunks = max(-(-total // largest), TASKS_PER_WORKER * max(1, int(workers)))
    chunks = max(1, min(chunks, total // 2))
    base, extra = divmod(total, chunks)
    bounds = np.cumsum([0] + [base + 1] * extra + [base] * (chunks - extra))
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def unflatten(module: torch.nn.Module, names: list[str], thetas: torch.Tensor) -> dict[str, torch.Tensor]:
    """{name: (B, *shape)} from flat rows (B, P), in each parameter's dtype."""
    params = dict(module.named_parameters())
    out, start = {}, 0
    for name in names:
        p = params[name]
        out[name] = thetas[:, start:start + p.numel()].reshape(thetas.shape[0], *p.shape).to(p.dtype)
        start += p.numel()
    return out


def batched_actions(module: torch.nn.Module, params: dict[str, torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
    """Actions (B, act) of B policies (module with ``params`` row b) for observations (B, obs): one vmapped forward."""
    with torch.no_grad():
        return vmap(lambda p, o: functional_call(module, p, (o,)))(params, obs)


def batched_recurrent_actions(module: torch.nn.Module, params: dict[str, torch.Tensor], obs: torch.Tensor,
                              state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(actions (B, act), next states (B, hidden)) of B recurrent policies, ``module(obs, state) -> (action,
    state)`` with ``params`` row b, for observations (B, obs) and their states (B, hidden): one vmapped forward."""
    with torch.no_grad():
        return vmap(lambda p, o, h: functional_call(module, p, (o, h)))(params, obs, state)


def is_recurrent(module: torch.nn.Module) -> bool:
    """True for a policy that carries a state: ``forward(x, state) -> (action, state)`` with
    ``initial_state(batch)`` (an APG-family :class:`~hybridctl.learn.apg.ClosedLoopPolicy`)."""
    return callable(getattr(module, "initial_state", None))



def run_chunk(task: ChunkTask) -> list[dict]:
    """Roll out one episode per row of ``task.thetas``; one result dict per row, in row order."""
    torch.set_num_threads(1)
    task = dataclasses.replace(task, inputs=task.shared)   # fetched once per task (Ray: from the object store)
    if task.system is not None:
        return _run_system_chunk(task)
    if task.engine == "auto" and batch_supports(task.env, task.env_kwargs):
        return _run_mujoco_chunk(task)
    n = len(task.seeds)
    envs = cached_env(("finetune", repr(task.env), repr(task.env_kwargs), task.max_steps, n),
                      lambda: [make_env(task.env, task.env_kwargs, task.max_steps) for _ in range(n)])
    module, params = _host_policy(task)
    space = envs[0].action_space
    obs = np.stack([np.asarray(e.reset(seed=int(s))[0], dtype=np.float64).reshape(-1)
                    for e, s in zip(envs, task.seeds)])
    z = normalise(task.normalizer, obs)
    history = [z.copy()]          # normalised observations of every member at each step (one copy per step)
    returns, rewards, steps = np.zeros(n), np.zeros(n), np.zeros(n, dtype=int)
    active, terminated, finite, success = np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool), [None] * n
    limit = task.max_steps or math.inf
    while active.any():
        actions = _host_actions(module, params, z)
        actions = actions.astype(space.dtype, copy=False).reshape((n, *space.shape))
        stepped = np.flatnonzero(active)
        for i in stepped:
            o, r, term, trunc, info = envs[i].step(actions[i])
            obs[i], rewards[i] = o, r
            if term or trunc:
                active[i], terminated[i] = False, bool(term)
                if "success" in info:
                    success[i] = bool(info["success"])
        returns[stepped] += rewards[stepped]
        z = _after_step(task, obs, returns, steps, stepped, finite, active, limit, history)
    return _chunk_results(task, history, returns, steps, terminated, finite, success)


def _host_policy(task: ChunkTask) -> tuple[torch.nn.Module, dict[str, torch.Tensor]]:
    """The policy module on the CPU and the chunk's parameter rows for it: gymnasium and MuJoCo envs
    step on the host, so their policies run there (their observations and actions are numpy)."""
    module = task.module.to("cpu")
    rows = torch.as_tensor(task.thetas, dtype=torch.float64, device="cpu")
    return module, unflatten(module, task.names, rows)


def _host_actions(module: torch.nn.Module, params: dict[str, torch.Tensor], z: np.ndarray) -> np.ndarray:
    """The chunk's actions (numpy) for normalised observations ``z`` (numpy) on the host."""
    dtype = next(module.parameters()).dtype
    return batched_actions(module, params, torch.as_tensor(z, dtype=dtype, device="cpu")).numpy()


def _after_step(task: ChunkTask, obs, returns, steps, stepped, finite, active, limit, history) -> np.ndarray:
    """Book-keeping after the ``stepped`` episodes took a step (their rewards already in ``returns``):
    count the step, stop non-finite and over-long episodes, record and return the normalised observations."""
    steps[stepped] += 1
    bad = stepped[~(np.isfinite(obs[stepped]).all(axis=1) & np.isfinite(returns[stepped]))]
    finite[bad], active[bad] = False, False
    active &= steps < limit
    z = normalise(task.normalizer, obs)
    history.append(z.copy())
    return z


def _chunk_results(task: ChunkTask, history, returns, steps, terminated, finite, success) -> list[dict]:
    """One result per episode of a chunk; member i's episode is states[: steps[i] + 1, i]."""
    states = np.stack(history)    # (T + 1, n, obs)
    return [episode_result(states[: steps[i] + 1, i], returns[i], returns[i], int(steps[i]), bool(terminated[i]),
                           task.postprocessor, finite=bool(finite[i]), success=None if success is None else success[i],
                           keep_states=task.keep_states) for i in range(len(steps))]


def _run_mujoco_chunk(task: ChunkTask) -> list[dict]:
    """:func:`run_chunk` on a Hopper/Walker2d/HalfCheetah v5 env: the chunk's episodes stepped together
    on :class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv` (one thread; the backend's workers run the
    chunks side by side). Bit-identical to the gymnasium loop of :func:`run_chunk` (tested)."""
    n = len(task.seeds)
    env = cached_env(("finetune-batch", task.env, repr(task.env_kwargs), n),
                     lambda: MujocoBatchEnv(task.env, num_envs=n, nthread=1, env_kwargs=task.env_kwargs))
    module, params = _host_policy(task)
    space = env.action_space
    obs = env.reset(task.seeds)
    z = normalise(task.normalizer, obs)
    history = [z.copy()]
    returns, steps = np.zeros(n), np.zeros(n, dtype=int)
    active, terminated, finite = np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool)
    limit = task.max_steps or env.max_episode_steps or math.inf
    while active.any():
        actions = _host_actions(module, params, z)
        actions = actions.astype(space.dtype, copy=False).reshape((n, *space.shape))
        stepped = np.flatnonzero(active)
        o, r, term, _ = env.step(actions[stepped], ids=stepped)
        obs[stepped] = o
        terminated[stepped] = term
        active[stepped[term]] = False
        returns[stepped] += r
        z = _after_step(task, obs, returns, steps, stepped, finite, active, limit, history)
    return _chunk_results(task, history, returns, steps, terminated, finite, None)


class RowPolicies(torch.nn.Module):
    """The chunk's B policies as one swing-up of a :class:`~hybridctl.systems.SwitchedController`: row b of
    the states acts through ``module`` with row b of ``params`` (the parameters not in ``params`` the
    module's own), one vmapped forward (:func:`batched_actions`) per decision."""

    def __init__(self, module: torch.nn.Module, params: dict[str, torch.Tensor]):
        super().__init__()
        self.module = module
        self.params = params      # (B, *shape) per perturbed parameter; plain tensors, not parameters

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return batched_actions(self.module, self.params, x)


class RecurrentRowPolicies(RowPolicies):
    """:class:`RowPolicies` of a recurrent module (``forward(x, state) -> (action, state)``), each row's
    state carried through its episode from the module's zero ``initial_state``."""

    def forward(self, x: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return batched_recurrent_actions(self.module, self.params, x, state)

    def initial_state(self, batch: int) -> torch.Tensor:
        return self.module.initial_state(batch).to(next(iter(self.params.values())).device)


def _run_system_chunk(task: ChunkTask) -> list[dict]:
    """A hybridctl system's swing-up: the chunk's episodes as one
    :func:`~hybridctl.systems.switched.closed_loop_rollout` of the switched controller (the chunk's policies
    as its swing-up, :class:`RowPolicies`; the chunk's gate: SSAC's learned one, the spec's cost-to-go gate
    of an APG-family source, or none (:class:`~hybridctl.systems.switched.NeverGate`); the LQR, the hysteresis
    and the gate period of the spec, as the Drake diagram's) on ``task.device``, with the semantics of the
    system's :class:`~hybridctl.envs.TorchVectorEnv` / :class:`~hybridctl.envs.SwitchedVectorEnv`: actions
    clipped, a recurrent policy's state carried per episode, an episode ends where it diverges (the rollout
    goes on deciding from its last finite state, ``on_divergence="continue"``; its reward counts 0 there and
    nothing after), truncation after the episode's decisions, the thesis success test on the last states
    of a truncated episode.

    No copy to the host until the chunk ends: returns, step counts, terminations and states stay on the
    device; every episode starts together, so the rollout runs a known number of decisions (the episode
    length or ``max_steps``) and asks the device nothing about which episodes still run.
    """
    from ..envs.single import decision_schedule
    from ..systems.success import is_balanced
    from ..systems.switched import CostToGoGate, NeverGate, SwitchedController, closed_loop_rollout
    device = torch.device(task.device)
    if device.type == "cuda":
        from .config_check import check_device_available
        check_device_available("the rollout device", device)
    system = load_system(task.system, **(task.system_overrides or {}))
    n = len(task.seeds)
    _, _, decisions = decision_schedule(system, task.decision_period)
    module = task.module.to(device)
    params = unflatten(module, task.names, torch.as_tensor(task.thetas, dtype=torch.float64, device=device))
    swingup = (RecurrentRowPolicies if is_recurrent(module) else RowPolicies)(module, params)
    gate = NeverGate() if task.shared.gate is None else task.shared.gate.get()
    if isinstance(gate, CostToGoGate):   # the same gate on this worker's system object (the LQR's error shared)
        gate = CostToGoGate.of(gate, system)
    controller = SwitchedController.for_system(system, swingup=swingup, gate=gate, decision_period=task.decision_period)
    x0 = np.concatenate([system.sample_initial_states(1, np.random.default_rng(int(s))) for s in task.seeds])
    horizon = int(min(task.max_steps or decisions, decisions))
    rollout = closed_loop_rollout(system, controller, x0, horizon, on_divergence="continue", device=device)
    states = rollout.states.transpose(0, 1).contiguous()              # (horizon + 1, n, states)
    returns = torch.zeros(n, dtype=torch.float64, device=device)
    steps = torch.zeros(n, dtype=torch.long, device=device)
    active = torch.ones(n, dtype=torch.bool, device=device)
    terminated = torch.zeros(n, dtype=torch.bool, device=device)
    for k in range(horizon):
        diverged = rollout.diverged[:, k]
        reward = torch.where(diverged, 0.0, system.reward(states[k + 1]))
        returns = torch.where(active, returns + reward, returns)
        steps += active.long()
        terminated |= active & diverged
        active &= ~diverged
    # one copy to the host per chunk
    states_np, returns_np = states.cpu().numpy(), returns.cpu().numpy()
    steps_np, terminated_np = steps.cpu().numpy(), terminated.cpu().numpy()
    if not rollout.actions_finite.cpu().numpy():
        limit = system.action_limit
        raise ValueError(f"actions must be finite (clipped to [-{limit}, {limit}]); got NaN or Inf")
    # the env's success test: an episode truncated after its decisions, balanced over its last states
    success = np.zeros(n, dtype=bool)
    if horizon == decisions:
        success = ~terminated_np & np.asarray(is_balanced(states_np.transpose(1, 0, 2), system), dtype=bool)
    return [episode_result(states_np[: steps_np[i] + 1, i], float(returns_np[i]), float(returns_np[i]),
                           int(steps_np[i]), bool(terminated_np[i]), task.postprocessor,
                           finite=bool(np.isfinite(returns_np[i])), success=bool(success[i]),
                           keep_states=task.keep_states) for i in range(n)]


def normalise(normalizer, obs: np.ndarray) -> np.ndarray:
    """``normalizer(obs)`` as float64 (a frozen observation normaliser; None: ``obs`` itself)."""
    return obs if normalizer is None else np.asarray(normalizer(obs), dtype=np.float64)
