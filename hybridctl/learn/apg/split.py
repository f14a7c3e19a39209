"""The APG phase split over a parallel backend (:mod:`hybridctl.parallel`), as functions over arrays.

Members share nothing during an epoch's APG phase (own Adam moments; the same start states,
seeded by (seed, epoch, iteration)), so the phase runs as contiguous chunks of members, one task
each: :func:`split_apg_phase` cuts the parameters and Adam moments into chunks, the backend runs
:func:`apg_chunk` on each (plain arrays in and out; each worker builds its own
:class:`~.core.APGProblem` once and keeps it in its cache), and the chunks are joined in member
order into one :class:`~.core.Phase`, which the learner then uses as the serial phase's. The
rollouts of a chunk are bitwise those of the whole population; the observation sums are added
chunk by chunk, so a split run equals the serial one up to float rounding.

Devices: tasks and results carry CPU numpy arrays only (a worker may sit on another machine);
a worker builds its problem on the config's ``device`` and moves the arrays there, and the
joined results are moved back to the learner's device.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import torch

from ... import systems as systems_mod
from ...parallel import cached_env
from ..run import set_torch_threads
from .config import APGConfig
from .core import APGProblem, BatchedAdam, Phase, apg_phase

__all__ = ["apg_chunk", "split_apg_phase", "chunk_bounds"]


def _array(t: torch.Tensor) -> np.ndarray:
    """A tensor as a numpy copy (what tasks and results carry)."""
    return t.detach().cpu().numpy().copy()


def chunk_bounds(members: int, workers: int) -> list[tuple[int, int]]:
    """Contiguous [lo, hi) member ranges, one per worker (at most one per member), sizes within one."""
    return [(int(c[0]), int(c[-1]) + 1) for c in np.array_split(np.arange(members), min(workers, members))]


def apg_chunk(task: dict) -> dict:
    """The APG phase of one chunk of members, in a worker: arrays in, arrays out.

    ``task``: the system (name or spec path) and its spec overrides (the Ch. 7 reward among
    them), the config as a dict, ``epoch``, ``iterations`` (the count before the phase),
    ``lr``, ``unroll`` (the steps of one APG update), the chunk's parameters ``theta`` [k, P],
    its Adam state (``m``, ``v`` [k, P], ``t`` [k], ``betas``, ``eps``) and the frozen
    normalisation (mean, std). The worker's :class:`~.core.APGProblem` of k members is built
    once (:func:`~hybridctl.parallel.cached_env`). Returns the chunk's parameters, Adam
    moments, returns and gradient norms [iterations, k], observation sums and counters.
    """
    set_torch_threads(task["config"]["torch_threads"])
    members = np.shape(task["theta"])[0]
    problem = cached_env(("apg", task["system"], repr(task["overrides"]), repr(task["config"]), members),
                         lambda: APGProblem.build(systems_mod.load(task["system"], **task["overrides"]),
                                                  APGConfig(**task["config"]), members))
    theta = torch.tensor(task["theta"], device=problem.device)
    problem.pop.set_normalization(*task["normalization"])
    state = task["adam"]
    adam = BatchedAdam(members, theta.shape[1], state["betas"], state["eps"], device=problem.device)
    adam.m, adam.v, adam.t = (torch.tensor(state[k], device=problem.device) for k in ("m", "v", "t"))
    phase = apg_phase(problem, theta, adam, task["lr"], task["epoch"], task["iterations"], task["unroll"])
    o_sum, o_sq, count = phase.obs_sums
    return {"theta": _array(phase.theta), "returns": _array(phase.returns), "norms": _array(phase.norms),
            "adam": [_array(a) for a in (phase.adam.m, phase.adam.v, phase.adam.t)],
            "obs_sums": (_array(o_sum), _array(o_sq), count), "iterations": phase.iterations,
            "env_steps": phase.env_steps, "nan_grads": phase.nan_grads, "large_grads": phase.large_grads}


def split_apg_phase(backend, problem: APGProblem, system: str, theta: torch.Tensor, adam: BatchedAdam, lr: float,
                    epoch: int, iterations: int, unroll: int) -> Phase:
    """:func:`~.core.apg_phase` of the members ``theta`` [K, P] as contiguous chunks on ``backend``
    (one per worker), joined in member order: the same :class:`~.core.Phase` as in one process
    up to float rounding, on ``problem.device`` (the chunks travel as CPU arrays). ``system``:
    the name (or spec path) a worker loads ``problem.system`` by, with its spec overrides;
    ``adam`` is not changed."""
    cfg = problem.config
    record = dataclasses.asdict(cfg)
    normalization = (_array(problem.pop.obs_mean), _array(problem.pop.obs_std))
    tasks = [{"system": system, "overrides": dict(problem.system.spec.overrides), "config": record, "epoch": epoch,
              "iterations": iterations, "lr": lr, "unroll": unroll, "theta": _array(theta[lo:hi]),
              "adam": {"m": _array(adam.m[lo:hi]), "v": _array(adam.v[lo:hi]), "t": _array(adam.t[lo:hi]),
                       "betas": adam.betas, "eps": adam.eps},
              "normalization": normalization}
             for lo, hi in chunk_bounds(theta.shape[0], backend.workers)]
    results = backend.map(apg_chunk, tasks)
    device = problem.device

    def back(array) -> torch.Tensor:   # a copy of a worker's array (Ray's are read-only) on the learner's device
        return torch.tensor(np.asarray(array), device=device)

    joined = {key: torch.cat([back(r[key]) for r in results], dim=0 if key == "theta" else 1)
              for key in ("theta", "returns", "norms")}
    new_adam = copy.copy(adam)
    new_adam.m, new_adam.v, new_adam.t = (torch.cat([back(r["adam"][i]) for r in results]) for i in range(3))
    obs_sums = [back(sum(r["obs_sums"][i] for r in results)) for i in (0, 1)] + \
               [sum(r["obs_sums"][2] for r in results)]
    return Phase(joined["theta"], joined["returns"], joined["norms"], new_adam, obs_sums,
                 results[0]["iterations"],   # every chunk ran the same iterations
                 *(sum(r[counter] for r in results) for counter in ("env_steps", "nan_grads", "large_grads")))
