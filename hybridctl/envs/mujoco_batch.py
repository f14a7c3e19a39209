"""Batched closed-loop stepping of gymnasium's MuJoCo locomotion envs, bit-identical to ``env.step``.

:class:`MujocoBatchEnv` holds ``num_envs`` simulations of one of ``Hopper-v5``,
``Walker2d-v5`` or ``HalfCheetah-v5`` (any kwargs of those envs) and steps any subset of
them by one env step (``frame_skip`` physics steps) in MuJoCo's C thread pool
(:class:`mujoco.batch.Batch`, MuJoCo >= 3.17), with the gymnasium env's semantics computed
for the whole batch in numpy: the observation (``exclude_current_positions_from_observation``,
the hopper's and walker's velocity clip), the reward terms (forward, healthy, control cost),
healthy termination and reset noise (drawn by the gymnasium env itself from the reset seed,
or given as explicit ``qpos``/``qvel``). Pushes go through ``xfrc_applied`` for the env step.
The policy is evaluated between calls, for the whole batch at once or row by row.

>>> batch = MujocoBatchEnv("Hopper-v5", num_envs=64, nthread=2)
>>> obs = batch.reset(seeds=range(64))                      # = gymnasium env.reset(seed=s) for each s
>>> obs, reward, terminated, info = batch.step(obs @ K.T)  # = env.step(action) row by row

Why not ``mujoco.rollout``: it takes a batch of initial states and open-loop controls, but its
state output (``mjSTATE_FULLPHYSICS``) lacks ``qacc_warmstart``, which the constraint solver
starts from. Called once per env step, every step would restart the solver from a zero warm
start while gymnasium's ``MjData`` keeps it, and trajectories drift apart (measured here:
3e-10 on Walker2d after 300 random-action steps, and HalfCheetah chaotically, by 15). A
:class:`~mujoco.batch.Batch` row is the whole integration state (warm start included), so
results are bit-identical to gymnasium's at any thread count (tested in
``tests/test_mujoco_batch.py``).
"""

from __future__ import annotations

from typing import Iterable, Sequence

import gymnasium as gym
import numpy as np

#: gymnasium env classes this stepper reproduces, by class name: whether it has a healthy check
#: and whether its observation clips velocities to [-10, 10]
SUPPORTED = {"HopperEnv": (True, True), "Walker2dEnv": (True, True), "HalfCheetahEnv": (False, False)}
VELOCITY_CLIP = 10.0   # gymnasium Hopper-v5 / Walker2d-v5 _get_obs
ROOT_BODY = 1          # the torso: the first body after the world (where pushes act)


def _mujoco():
    """The mujoco module with :mod:`mujoco.batch` (ImportError naming the version otherwise)."""
    try:
        import mujoco
        import mujoco.batch  # noqa: F401  (MuJoCo >= 3.17)
    except ImportError as exc:
        raise ImportError(f"MujocoBatchEnv needs mujoco >= 3.17 with mujoco.batch (pip install -c constraints.txt "
                          f"-e '.[mujoco]'): {exc}") from exc
    return mujoco


def supports(env_id, env_kwargs: dict | None = None) -> bool:
    """Whether ``env_id`` is a gymnasium id this stepper reproduces (Hopper/Walker2d/HalfCheetah v5)."""
    if not isinstance(env_id, str) or env_id.split("-")[-1] != "v5" or \
            env_id.split("-")[0] not in ("Hopper", "Walker2d", "HalfCheetah"):
        return False
    try:
        _mujoco()
    except ImportError:
        return False
    return True


class MujocoBatchEnv:
    """``num_envs`` simulations of a gymnasium MuJoCo locomotion env, stepped together on ``nthread`` threads.

    ``env_id``: ``"Hopper-v5"``, ``"Walker2d-v5"`` or ``"HalfCheetah-v5"``; ``env_kwargs``: the
    env's own keyword arguments (reward weights, healthy ranges, ...), read back from the
    gymnasium env so that both agree. ``ids`` arguments pick a subset of the simulations
    (default: all), sorted and unique; arrays passed and returned have one row per picked
    simulation, in that order.
    """

    def __init__(self, env_id: str = "Hopper-v5", num_envs: int = 1, nthread: int = 1,
                 env_kwargs: dict | None = None):
        mujoco = _mujoco()
        if not (isinstance(num_envs, (int, np.integer)) and num_envs >= 1):
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if not (isinstance(nthread, (int, np.integer)) and nthread >= 1):
            raise ValueError(f"nthread must be an integer >= 1, got {nthread!r}")
        self.env_id, self.env_kwargs = env_id, dict(env_kwargs or {})
        self.env = gym.make(env_id, **self.env_kwargs)   # the reference: spaces, time limit, reset noise
        raw = self.env.unwrapped
        kind = type(raw).__name__
        if kind not in SUPPORTED or not hasattr(raw, "_exclude_current_positions_from_observation"):
            raise ValueError(f"env_id must be a gymnasium v5 env of {sorted(SUPPORTED)} (Hopper-v5, Walker2d-v5, "
                             f"HalfCheetah-v5), got {env_id!r} ({kind})")
        self._raw = raw
        has_health, self.clip_velocity = SUPPORTED[kind]
        self.model = raw.model
        self.frame_skip = int(raw.frame_skip)
        self.dt = raw.dt
        self.nq, self.nv, self.nu = self.model.nq, self.model.nv, self.model.nu
        self.forward_reward_weight = raw._forward_reward_weight
        self.ctrl_cost_weight = raw._ctrl_cost_weight
        self.exclude_positions = bool(raw._exclude_current_positions_from_observation)
        self.has_health = has_health
        if has_health:
            self.healthy_reward_value = raw._healthy_reward
            self.terminate_when_unhealthy = bool(raw._terminate_when_unhealthy)
            self.healthy_z_range = raw._healthy_z_range
            self.healthy_angle_range = raw._healthy_angle_range
            self.healthy_state_range = getattr(raw, "_healthy_state_range", None)   # the hopper's only
        self.observation_space, self.action_space = self.env.observation_space, self.env.action_space
        self.max_episode_steps = self.env.spec.max_episode_steps if self.env.spec is not None else None
        self.num_envs, self.nthread = int(num_envs), int(nthread)
        self.batch = mujoco.batch.Batch(self.model, nsim=self.num_envs, nthread=self.nthread)
        self.qpos, self.qvel = self.batch.bind("qpos"), self.batch.bind("qvel")
        self.ctrl, self.xfrc_applied = self.batch.bind("ctrl"), self.batch.bind("xfrc_applied")
        self._stage_none = mujoco.mjtStage.mjSTAGE_NONE

    # -- state -------------------------------------------------------------------------------
    def _ids(self, ids) -> np.ndarray | None:
        if ids is None:
            return None
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_envs):
            raise ValueError(f"ids must lie in [0, num_envs={self.num_envs}), got {ids.min()}..{ids.max()}")
        if ids.size > 1 and np.any(np.diff(ids) <= 0):
            raise ValueError("ids must be sorted and unique (mujoco.batch steps simulations in order)")
        return ids

    def _rows(self, ids):
        return slice(None) if ids is None else ids

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray, ids=None) -> np.ndarray:
        """Put simulations in ``qpos`` (n, nq), ``qvel`` (n, nv) as gymnasium's reset does
        (``mj_resetData``, write, ``mj_forward``: time, warm start, controls and pushes zero);
        returns their observations."""
        ids = self._ids(ids)
        n = self.num_envs if ids is None else ids.size
        qpos = np.asarray(qpos, dtype=np.float64)
        qvel = np.asarray(qvel, dtype=np.float64)
        if qpos.shape != (n, self.nq) or qvel.shape != (n, self.nv):
            raise ValueError(f"qpos and qvel must have shapes ({n}, {self.nq}) and ({n}, {self.nv}), got "
                             f"{qpos.shape} and {qvel.shape}")
        if n == 0:
            return np.zeros((0,) + self.observation_space.shape)
        self.batch.reset(ids, stage=self._stage_none)
        rows = self._rows(ids)
        self.qpos[rows] = qpos
        self.qvel[rows] = qvel
        self.batch.forward(ids)
        return self.observe(ids)

    def reset_states(self, seeds: Iterable[int]) -> tuple[np.ndarray, np.ndarray]:
        """The initial ``qpos``, ``qvel`` gymnasium's ``env.reset(seed=s)`` draws for each seed
        (the env's own reset noise, drawn by the env)."""
        qpos, qvel = [], []
        for s in seeds:
            self.env.reset(seed=int(s))
            qpos.append(self._raw.data.qpos.copy())
            qvel.append(self._raw.data.qvel.copy())
        return np.array(qpos).reshape(-1, self.nq), np.array(qvel).reshape(-1, self.nv)

    def reset(self, seeds: Iterable[int], ids=None) -> np.ndarray:
        """Reset simulations as ``env.reset(seed=s)`` would (one seed per simulation); their observations."""
        qpos, qvel = self.reset_states(seeds)
        return self.set_state(qpos, qvel, ids)

    # -- the env's semantics, batched ----------------------------------------------------------
    def observation(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """gymnasium's ``_get_obs`` for rows of ``qpos``, ``qvel``."""
        position = qpos[:, 1:] if self.exclude_positions else qpos
        velocity = np.clip(qvel, -VELOCITY_CLIP, VELOCITY_CLIP) if self.clip_velocity else qvel
        return np.concatenate((position, velocity), axis=1)

    def observe(self, ids=None) -> np.ndarray:
        """Observations of the simulations ``ids`` (n, obs_dim)."""
        rows = self._rows(self._ids(ids))
        return self.observation(self.qpos[rows], self.qvel[rows])

    def is_healthy(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """gymnasium's ``is_healthy`` for rows of ``qpos``, ``qvel`` (all True for HalfCheetah)."""
        if not self.has_health:
            return np.ones(qpos.shape[0], dtype=bool)
        z, angle = qpos[:, 1], qpos[:, 2]
        healthy = (self.healthy_z_range[0] < z) & (z < self.healthy_z_range[1])
        healthy &= (self.healthy_angle_range[0] < angle) & (angle < self.healthy_angle_range[1])
        if self.healthy_state_range is not None:
            state = np.concatenate((qpos, qvel), axis=1)[:, 2:]
            lo, hi = self.healthy_state_range
            healthy &= np.all((lo < state) & (state < hi), axis=1)
        return healthy

    def step(self, actions: np.ndarray, ids=None, push: np.ndarray | None = None):
        """One env step of the simulations ``ids`` with ``actions`` (n, nu): ``obs, reward,
        terminated, info`` (arrays, one row per simulation; ``info``: ``x_position``,
        ``x_velocity``, ``reward_forward``, ``reward_ctrl``, and ``reward_survive`` where the env
        has one), each equal to ``env.step(action)`` row by row. Time limits are the caller's.

        ``push``: (n, 3) forces in N (world x, y, z) on the torso during this step (0 after it),
        or (n, 6) with torques, as ``data.xfrc_applied[1]``.
        """
        ids = self._ids(ids)
        rows = self._rows(ids)
        n = self.num_envs if ids is None else ids.size
        actions = np.asarray(actions)
        if actions.shape != (n, self.nu):
            raise ValueError(f"actions must have shape ({n}, {self.nu}), got {actions.shape}")
        if n == 0:
            empty = np.zeros(0)
            return (np.zeros((0,) + self.observation_space.shape), empty, np.zeros(0, dtype=bool),
                    {"x_position": empty, "x_velocity": empty})
        x_before = self.qpos[rows, 0].copy()
        self.ctrl[rows] = actions
        if push is not None:
            push = np.asarray(push, dtype=np.float64)
            if push.ndim != 2 or push.shape[0] != n or push.shape[1] not in (3, 6):
                raise ValueError(f"push must have shape ({n}, 3) or ({n}, 6), got {push.shape}")
            forces = np.zeros((n, 6))
            forces[:, :push.shape[1]] = push
            frc = self.xfrc_applied[rows]
            frc[:, ROOT_BODY] = forces
            self.xfrc_applied[rows] = frc
        self.batch.step(ids, nstep=self.frame_skip)
        if push is not None:
            frc = self.xfrc_applied[rows]
            frc[:, ROOT_BODY] = 0.0
            self.xfrc_applied[rows] = frc
        qpos, qvel = self.qpos[rows], self.qvel[rows]
        x_after = qpos[:, 0]
        x_velocity = (x_after - x_before) / self.dt
        obs = self.observation(qpos, qvel)
        forward = self.forward_reward_weight * x_velocity
        ctrl_cost = self.ctrl_cost_weight * np.sum(np.square(actions), axis=1)
        info = {"x_position": x_after.copy(), "x_velocity": x_velocity, "reward_forward": forward,
                "reward_ctrl": -ctrl_cost}
        if self.has_health:
            healthy = self.is_healthy(qpos, qvel)
            survive = healthy * self.healthy_reward_value
            reward = (forward + survive) - ctrl_cost
            terminated = ~healthy & self.terminate_when_unhealthy
            info["reward_survive"] = survive
        else:
            reward = forward - ctrl_cost
            terminated = np.zeros(n, dtype=bool)
        return obs, reward, terminated, info

    def close(self) -> None:
        """Close the reference gymnasium env (the batch's threads go with the object)."""
        self.env.close()


def pushes_on_root(forces: Sequence | np.ndarray) -> np.ndarray:
    """(n, 3) world forces from a list of pushes ``(fx, fz)`` or ``(fx, fy, fz)`` (a scalar is ``fx``)."""
    out = []
    for f in forces:
        f = np.atleast_1d(np.asarray(f, dtype=np.float64))
        out.append([f[0], 0.0, f[1] if f.size > 1 else 0.0] if f.size <= 2 else f[:3])
    return np.array(out, dtype=np.float64).reshape(-1, 3)


__all__ = ["MujocoBatchEnv", "supports", "pushes_on_root", "SUPPORTED"]
