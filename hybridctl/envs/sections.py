"""Apex-to-apex Poincare map of a gymnasium MuJoCo hopper under a policy (thesis Ch. 5).

The section is the apex of the torso height: the first control step at which the
torso's vertical velocity turns from positive to non-positive. A state on the section
is the simulator state there without the forward position (``Hopper-v5``: ``qpos[1:]``
and ``qvel``, 11 numbers; the dynamics do not depend on the forward position). It is
the env's observation except that the observation clips velocities to [-10, 10]; the
section keeps them unclipped so that a state restores the simulator exactly. One
transition: put the simulator in that state (forward position 0), apply the push
``(fx, fz)`` in newtons to the torso for one env step, then run the policy until the
next apex. Failure: the env terminates (Hopper-v5: torso below 0.7 m, tilted more
than 0.2 rad, or any state beyond 100) or no apex comes within ``timeout_steps``.

>>> agent = ARS.load("models/policies/ars-hopper")
>>> section = HopperApexMap(agent.frozen_policy())
>>> seeds = section.apex_states(steps=1000)                  # apexes of one unpushed run
>>> mesh = build_mesh(section, seeds, x_pushes(15.0, 25), box_size=0.5, mean=..., std=..., backend="processes")

The env is built lazily in each process that steps the map, so the map pickles to workers.

``engine="batch"`` (default where MuJoCo >= 3.17 is installed): ``step_many`` runs all its
states together on :class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv` (``nthread``
threads), the policy evaluated row by row between env steps; results are bit-identical to
``engine="gym"``, the gymnasium env stepped one state at a time (tested). Every transition
starts from a freshly reset simulator (``mj_resetData``: time and the solver's warm start
zero), so a state's successor does not depend on which states the process stepped before.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import gymnasium as gym
import numpy as np

from ..analysis.poincare import FiniteDisturbances, SectionMap, check_section_states
from ..parallel import cached_env
from .mujoco_batch import MujocoBatchEnv, pushes_on_root, supports

TORSO_BODY = 1        # MuJoCo body id of the torso (body 0 is the world)
HEIGHT, VZ = 1, 1     # qpos[1]: torso height; qvel[1]: its vertical velocity


@dataclass
class HopperApexMap(SectionMap):
    """Apex-to-apex map of a planar MuJoCo hopper (``Hopper-v5`` by default) under ``policy``.

    ``policy``: a picklable callable observation -> action (e.g. ``ARS.frozen_policy()``).
    Disturbance: a push ``(fx, fz)`` in N on the torso for one env step (a scalar is
    ``fx``). ``timeout_steps``: env steps allowed to reach the next apex. ``engine``:
    ``"batch"`` (all states of a ``step_many`` call stepped together on ``nthread`` MuJoCo
    threads; the default where MuJoCo >= 3.17 is installed) or ``"gym"`` (one state at a time
    through the gymnasium env); both give the same bits.
    """

    policy: Callable[[np.ndarray], np.ndarray]
    env_id: str = "Hopper-v5"
    timeout_steps: int = 300
    env_kwargs: dict = field(default_factory=dict)
    engine: str = "auto"
    nthread: int = 1

    def __post_init__(self):
        if not callable(self.policy):
            raise ValueError(f"policy must be a callable observation -> action, got {type(self.policy).__name__}")
        if not (isinstance(self.timeout_steps, int) and self.timeout_steps >= 2):
            raise ValueError(f"timeout_steps must be an integer >= 2, got {self.timeout_steps!r}")
        if self.engine not in ("auto", "batch", "gym"):
            raise ValueError(f"engine must be 'auto', 'batch' or 'gym', got {self.engine!r}")
        if not (isinstance(self.nthread, int) and self.nthread >= 1):
            raise ValueError(f"nthread must be an integer >= 1, got {self.nthread!r}")
        if self.engine == "auto":
            self.engine = "batch" if supports(self.env_id) else "gym"
        elif self.engine == "batch" and not supports(self.env_id):
            raise ValueError(f"engine='batch' needs mujoco >= 3.17 and a Hopper/Walker2d v5 env, got {self.env_id!r}")

    @property
    def state_names(self) -> tuple[str, ...]:
        """Hopper-v5 observation names."""
        return ("z", "torso", "thigh", "leg", "foot", "vx", "vz", "w_torso", "w_thigh", "w_leg", "w_foot")

    def _env(self) -> gym.Env:
        def make():
            env = gym.make(self.env_id, **self.env_kwargs).unwrapped
            env.reset(seed=0)
            return env
        return cached_env(("apex-map", self.env_id, repr(sorted(self.env_kwargs.items()))), make)

    def _set_state(self, env, state: np.ndarray) -> None:
        import mujoco
        nq = env.model.nq
        qpos = np.concatenate([[0.0], state[:nq - 1]])
        mujoco.mj_resetData(env.model, env.data)   # as gymnasium's reset: time, warm start, pushes zero
        env.set_state(qpos, state[nq - 1:])

    def _batch_env(self, n: int) -> MujocoBatchEnv:
        """This process' batched stepper with room for ``n`` simulations (grown in powers of 2)."""
        holder = cached_env(("apex-map-batch", self.env_id, repr(sorted(self.env_kwargs.items())), self.nthread),
                            dict)
        if holder.get("env") is None or holder["env"].num_envs < n:
            size = 1 << max(0, int(n - 1).bit_length())
            holder["env"] = MujocoBatchEnv(self.env_id, num_envs=size, nthread=self.nthread,
                                           env_kwargs=self.env_kwargs)
        return holder["env"]

    def step_many(self, states, disturbances) -> np.ndarray:
        """Next apex states (NaN rows for failures) of ``states[i]`` pushed by ``disturbances[i]``."""
        if self.engine != "batch":
            return super().step_many(states, disturbances)
        states = check_section_states(states, disturbances)
        n = states.shape[0]
        env = self._batch_env(n)
        nq = env.nq
        if states.shape[1] != nq - 1 + env.nv:
            raise ValueError(f"states must have {nq - 1 + env.nv} columns (qpos[1:], qvel), got {states.shape[1]}")
        ids = np.arange(n)
        obs = env.set_state(np.concatenate([np.zeros((n, 1)), states[:, :nq - 1]], axis=1), states[:, nq - 1:], ids)
        push = pushes_on_root(disturbances)
        out = np.full(states.shape, np.nan)
        alive, rising = np.ones(n, dtype=bool), np.zeros(n, dtype=bool)
        for k in range(self.timeout_steps):
            idx = ids[alive]
            if idx.size == 0:
                break
            actions = self._actions(obs[idx], env.nu)
            new, _, terminated, _ = env.step(actions, ids=idx, push=push[idx] if k == 0 else None)
            obs[idx] = new
            failed = terminated | ~np.all(np.isfinite(new), axis=1)
            up = env.qvel[idx, VZ] > 0
            apex = ~failed & ~up & rising[idx]
            rising[idx] |= ~failed & up
            done = idx[apex]
            out[done] = np.concatenate([env.qpos[done, 1:], env.qvel[done]], axis=1)
            alive[idx[failed | apex]] = False
        return out

    def _actions(self, obs: np.ndarray, nu: int) -> np.ndarray:
        """The policy's actions for rows of ``obs``: its ``many`` where it has one (which must equal
        calling it row by row, as ``FrozenPolicy.many`` does), else one call per row."""
        many = getattr(self.policy, "many", None)
        if many is not None:
            return np.asarray(many(obs), dtype=np.float64).reshape(obs.shape[0], nu)
        return np.array([self.policy(o) for o in obs], dtype=np.float64).reshape(obs.shape[0], nu)

    def step(self, state, disturbance):
        """The next apex state after a push at this apex, or None for failure."""
        if self.engine == "batch":
            return super().step(state, disturbance)
        env = self._env()
        state = np.asarray(state, dtype=np.float64)
        self._set_state(env, state)
        push = np.atleast_1d(np.asarray(disturbance, dtype=np.float64))
        force = np.array([push[0], 0.0, push[1] if push.size > 1 else 0.0])
        state, _, _ = self._run_to_apex(env, env._get_obs(), self.timeout_steps, force)
        return state

    def _run_to_apex(self, env, obs: np.ndarray, limit: int, force: np.ndarray | None = None):
        """Run the policy from ``obs`` (the env's own, clipped observation) until the torso height
        peaks, with ``force`` on the torso during the first step: (apex state or None for failure /
        no apex within ``limit`` steps, last observation, steps taken)."""
        rising = False
        for k in range(limit):
            if force is not None and k == 0:
                env.data.xfrc_applied[TORSO_BODY, :3] = force
            obs, _, terminated, _, _ = env.step(self.policy(obs))
            if k == 0:
                env.data.xfrc_applied[TORSO_BODY, :3] = 0.0
            if terminated or not np.all(np.isfinite(obs)):
                return None, obs, k + 1
            if env.data.qvel[VZ] > 0:
                rising = True
            elif rising:
                return self._state(env), obs, k + 1
        return None, obs, limit

    @staticmethod
    def _state(env) -> np.ndarray:
        return np.concatenate([env.data.qpos[1:], env.data.qvel]).astype(np.float64)

    def apex_states(self, steps: int = 1000, skip: int = 3, seed: int = 0) -> np.ndarray:
        """Apex states of one unpushed run from the env's reset (``seed``), skipping the first
        ``skip`` apexes (the start transient): seeds for a mesh or starts for Monte Carlo."""
        env = self._env()
        obs, _ = env.reset(seed=seed)
        apexes, left = [], steps
        while left > 0:
            state, obs, used = self._run_to_apex(env, obs, left)
            left -= used
            if state is None:
                break
            apexes.append(state)
        if len(apexes) <= skip:
            raise ValueError(f"the policy reached {len(apexes)} apexes in {steps} steps from reset (seed {seed}); "
                             f"need more than skip={skip}: is it hopping?")
        return np.array(apexes[skip:])


def x_pushes(magnitude: float = 15.0, count: int = 25) -> FiniteDisturbances:
    """``count`` pushes along x evenly spaced in [-magnitude, magnitude] N (thesis Ch. 5: 15 N, 25)."""
    if not (magnitude > 0 and isinstance(count, int) and count >= 1):
        raise ValueError(f"magnitude must be > 0 and count an integer >= 1, got {magnitude!r}, {count!r}")
    return FiniteDisturbances([np.array([f, 0.0]) for f in np.linspace(-magnitude, magnitude, count)])


def random_pushes(count: int = 100, low: float = 5.0, high: float = 15.0, seed: int = 0) -> FiniteDisturbances:
    """``count`` pushes of magnitude U(low, high) N at an angle U(0, 2 pi) in the x-z plane (thesis Ch. 5)."""
    if not (0 <= low <= high and isinstance(count, int) and count >= 1):
        raise ValueError(f"need 0 <= low <= high and an integer count >= 1, got {low!r}, {high!r}, {count!r}")
    rng = np.random.default_rng(seed)
    size, angle = rng.uniform(low, high, count), rng.uniform(0, 2 * np.pi, count)
    return FiniteDisturbances([np.array([m * np.cos(a), m * np.sin(a)]) for m, a in zip(size, angle)])


__all__ = ["HopperApexMap", "x_pushes", "random_pushes"]
