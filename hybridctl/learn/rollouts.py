"""One rollout module: the episodes of antithetic random search (ARS, fine-tuning) and of the
robustness measures, with one result format.

What to roll out is a list of tasks (plain, picklable objects) for a :mod:`hybridctl.parallel`
backend; :func:`rollouts` runs them and returns one result dict per episode, in task order.
Two execution strategies, kept apart because each reproduces its learner's numbers bit for bit:

* one-episode tasks (:mod:`~hybridctl.learn.episode_tasks`: :class:`~hybridctl.learn.episode_tasks.RolloutTask`)
  -- ONE episode of a flat-parameter policy (:class:`~hybridctl.learn.flat_policy.PolicySpec`: ARS's linear
  map, a torch module loaded by ``vector_to_parameters``, or a fixed function) behind a frozen affine
  normalisation, with optional action / observation noise and pushes (thesis Sec. 4.3). One task per
  backend job (``run_episode``, a gymnasium env), or a whole batch stepped together on the MuJoCo batch
  stepper (:class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv`, ``run_episodes_batched``,
  ``engine="auto"``). ARS and :func:`~hybridctl.learn.robustness.failure_rates` use them.
* chunk tasks (:mod:`~hybridctl.learn.chunk_tasks`: :class:`~hybridctl.learn.chunk_tasks.ChunkTask`) -- a
  chunk of B episodes of a torch module whose named parameters come from the rows of ``thetas``: one
  ``torch.func.vmap`` forward of ``functional_call`` per env step, over gymnasium envs, the MuJoCo batch
  stepper (one thread), or a hybridctl system's batched torch dynamics: the switched controller's one
  rollout, :func:`~hybridctl.systems.switched.closed_loop_rollout`, with the chunk's gate object (SSAC's
  learned gate, the spec's cost-to-go gate of an APG-family swing-up whose hidden state is carried per
  episode, or none), on any torch device with no copy to the host until the chunk ends. What every chunk
  of a batch reads and none changes (the policy, its gate and normaliser, the post-processor:
  ``ChunkInputs``) is shipped once per batch (``backend.put``; the tasks carry the reference);
  ``chunk_slices`` splits a batch into chunks, by default from the backend's worker count. Fine-tuning
  uses them.

Every result: ``finite`` (False: only ``steps`` follows), ``return`` (post-processed by the
task's :class:`~hybridctl.analysis.PostProcessor`, e.g. the dimension reward), ``raw_return``,
``steps``, ``terminated``, ``success`` (the thesis success test on a hybridctl system, else
None), ``dimension``, ``reason``, ``sum`` / ``sumsq`` / ``count`` (of the episode's states but
the last: ARS's running normalisation), and on request ``states`` (what the post-processor saw:
observations, normalised by the frozen normaliser in a chunk) and ``dimensions``
(:func:`~hybridctl.learn.rollout_results.measure_dimensions`).

By concern: envs from ids (:mod:`~hybridctl.learn.rollout_envs`), policies as flat parameters
(:mod:`~hybridctl.learn.flat_policy`), the result format (:mod:`~hybridctl.learn.rollout_results`), the
one-episode tasks and the chunk tasks; this module runs either kind.
"""

from __future__ import annotations

import os

from .chunk_tasks import ChunkTask, run_chunk
from .episode_tasks import RolloutTask, batchable, run_episode, run_episodes_batched


def rollouts(tasks: list[RolloutTask] | list[ChunkTask], backend, engine: str = "auto",
             nthread: int | None = None) -> list[dict]:
    """Every episode of ``tasks`` on ``backend``: one result dict per episode, in task order.

    Chunk tasks: one backend job per chunk (:func:`run_chunk`). Episode tasks: batched on this
    machine's MuJoCo threads (``engine="auto"``, :func:`batchable` tasks and a local backend;
    ``nthread`` threads, default every core), else one :func:`run_episode` per job (always on a
    Ray backend, which may reach a cluster's CPUs).
    """
    if tasks and isinstance(tasks[0], ChunkTask):
        return [r for chunk in backend.map(run_chunk, tasks) for r in chunk]
    if engine == "auto" and getattr(backend, "name", "serial") != "ray" and batchable(tasks):
        threads = nthread or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
        return run_episodes_batched(tasks, max(1, int(threads or 1)))
    return backend.map(run_episode, tasks)
