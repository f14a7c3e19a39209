"""Failure rates under disturbances (thesis Sec. 4.3, Table 4.4), for any policy.

A failure is an early termination (the env's ``terminated``, e.g. a hopper falling)
before ``episode_steps`` steps. Conditions (thesis Sec. 4.3): zero-mean Gaussian noise
on the actions or on the observations, and random pushes (at every step, with
probability ``rate``, a force of fixed ``magnitude`` at a random angle in the x-z plane
on the root body; MuJoCo envs only).

>>> failure_rates(agent, conditions={"none": {}, "action noise 0.1": {"action_noise": 0.1},
...                                  "push 0.01 x 50 N": {"push": (0.01, 50.0)}}, episodes=50)
"""

from __future__ import annotations

import math

import numpy as np

from ..analysis.postprocess import PostProcessor
from ..parallel import make_backend
from .episode_tasks import RolloutTask
from .flat_policy import FrozenPolicy, PolicySpec
from .rollout_envs import make_env
from .rollout_results import evaluation_seeds
from .rollouts import rollouts


def wilson_interval(failures: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a failure fraction (sensible at 0 and n, unlike the normal
    approximation; the ends are exact there, not 1e-19 from rounding)."""
    if n == 0:
        return (0.0, 1.0)
    p = failures / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    lo = 0.0 if failures == 0 else max(0.0, centre - half)
    hi = 1.0 if failures == n else min(1.0, centre + half)
    return (lo, hi)


def failure_rates(policy, env=None, conditions: dict | None = None,
                  episodes: int = 50, episode_steps: int = 10_000, seed: int = 0, backend: str = "processes",
                  workers: int | None = None, engine: str | None = None, address: str | None = None) -> dict:
    """Fraction of episodes that terminate early under each disturbance condition.

    ``policy``: an :class:`~hybridctl.learn.ars.ARS` agent (anything with ``frozen_policy()``,
    ``env``, ``env_kwargs`` and ``config.engine``: its env, normalisation and parameters are
    used), or a picklable callable ``obs -> action`` together with ``env`` (an id or a factory).
    The episodes are :class:`~hybridctl.learn.rollouts.RolloutTask` s of
    :mod:`hybridctl.learn.rollouts`, as ARS's own.
    ``conditions``: name -> dict with any of ``action_noise``, ``obs_noise`` (std) and
    ``push`` ((rate, magnitude)). The same ``episodes`` env seeds are used for every
    condition. Returns, per condition, failures, fraction, 95 % Wilson interval, mean return.

    ``engine``: ``"auto"`` (the default, or the agent's ``config.engine``) runs a condition's
    episodes together on the batched MuJoCo stepper where it applies (Hopper/Walker2d/HalfCheetah
    v5, linear or plain-callable policies; the same numbers bit for bit) on ``workers`` threads;
    ``"backend"``: one episode per task on ``backend``.

    ``backend``, ``workers``, ``address``: where the episodes run, as for every parallel workload
    (:func:`~hybridctl.parallel.make_backend`: ``address`` is a Ray cluster's, for ``backend="ray"``;
    None there: ``RAY_ADDRESS``, else a new local instance).
    """
    conditions = conditions or {"none": {}}
    if episodes < 1 or episode_steps < 1:
        raise ValueError(f"episodes and episode_steps must be >= 1, got {episodes} and {episode_steps}")
    for name, cond in conditions.items():
        unknown = set(cond) - {"action_noise", "obs_noise", "push"}
        if unknown:
            raise ValueError(f"condition {name!r}: unknown keys {sorted(unknown)}; use action_noise, obs_noise, push")
    agent = hasattr(policy, "frozen_policy")
    if agent:
        frozen, env, env_kwargs = policy.frozen_policy(), policy.env, policy.env_kwargs
    else:
        if env is None:
            raise ValueError("failure_rates needs env= when the policy is a plain callable")
        probe = make_env(env)
        obs_dim, act_dim = int(np.prod(probe.observation_space.shape)), int(np.prod(probe.action_space.shape))
        spec = PolicySpec(obs_dim, act_dim, probe.action_space.low, probe.action_space.high, function=policy)
        probe.close()
        frozen, env_kwargs = FrozenPolicy(spec, np.zeros(0), np.zeros(obs_dim), np.ones(obs_dim)), None
    if engine is None:
        engine = policy.config.engine if agent else "auto"
    if engine not in ("auto", "backend"):
        raise ValueError(f"engine must be 'auto' or 'backend', got {engine!r}")
    seeds = evaluation_seeds(seed, episodes)
    identity = PostProcessor("identity")
    report = {}
    with make_backend(backend, workers, address) as pool:
        for name, cond in conditions.items():
            tasks = [RolloutTask(env, env_kwargs, frozen.spec, frozen.theta, frozen.obs_mean, frozen.obs_std, s,
                                 episode_steps, 0.0, identity,
                                 action_noise=cond.get("action_noise", 0.0), obs_noise=cond.get("obs_noise", 0.0),
                                 push=cond.get("push")) for s in seeds]
            results = rollouts(tasks, pool, engine, workers)
            failed = sum(1 for r in results if not r["finite"] or r["terminated"])
            returns = [r["raw_return"] for r in results if r["finite"]]
            report[name] = {"condition": cond, "episodes": episodes, "failures": failed,
                            "failure_rate": failed / episodes, "interval95": wilson_interval(failed, episodes),
                            "mean_return": float(np.mean(returns)) if returns else None,
                            "mean_steps": float(np.mean([r["steps"] for r in results]))}
    return report
