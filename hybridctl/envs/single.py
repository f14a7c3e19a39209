"""One swing-up episode of one benchmark system as a ``gymnasium.Env``.

An action is held for one decision period (the spec's ``control.swingup_period``
unless given), integrated every ``dt`` with ``System.step_single`` (one state on plain
floats; the batched envs use ``System.step_unchecked`` in :func:`advance`); the reward is
``System.reward`` of the state after the decision (thesis eq. 3.1, tip height).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.envs.registration import EnvSpec

from .. import systems
from ..systems import System, control
from ..systems.success import is_balanced

STATE_BOUND = control.DIVERGENCE_BOUND
"""States with a coordinate beyond +-STATE_BOUND (or non-finite) count as diverged
(``hybridctl.systems.control.DIVERGENCE_BOUND``)."""


def resolve_system(system: str | System, **spec_overrides: Any) -> System:
    """A System from a name (loaded with ``spec_overrides``) or a System (no overrides allowed)."""
    if isinstance(system, System):
        if spec_overrides:
            raise ValueError(f"spec_overrides ({sorted(spec_overrides)}) need a system name, not a loaded System")
        return system
    if isinstance(system, str):
        return systems.load(system, **spec_overrides)
    raise ValueError(f"system must be a name in {systems.known_systems()} or a System, got {type(system).__name__}")


def decision_schedule(system: System, decision_period: float | None) -> tuple[float, int, int]:
    """(decision_period, integration steps per decision, decisions per episode).

    ``decision_period`` must be a positive multiple of ``system.dt`` that divides
    ``system.episode_duration``; None means ``system.swingup_period``.
    """
    period = system.swingup_period if decision_period is None else float(decision_period)
    substeps = round(period / system.dt) if math.isfinite(period) else 0
    decisions = round(system.episode_duration / period) if period > 0 and math.isfinite(period) else 0
    if (substeps < 1 or decisions < 1 or not math.isclose(substeps * system.dt, period, rel_tol=1e-9)
            or not math.isclose(decisions * period, system.episode_duration, rel_tol=1e-9)):
        raise ValueError(f"decision_period must be a positive multiple of dt={system.dt} s that divides "
                         f"episode_duration={system.episode_duration} s, got {decision_period}")
    return period, substeps, decisions


def advance(system: System, x: torch.Tensor, u: torch.Tensor, substeps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Hold u over ``substeps`` integration steps from x (B, n); returns (x_next, diverged (B,)).

    A row that leaves [-STATE_BOUND, STATE_BOUND] or turns non-finite is diverged;
    it is put back to its start state (the last finite decision-rate state) so that
    no NaN reaches the batched solve. Other rows equal repeated ``System.step`` exactly.
    """
    x0, diverged = x, torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    for _ in range(substeps):
        x = system.step_unchecked(x, u)
        diverged = diverged | control.is_diverged(x)
        x = torch.where(diverged[:, None], x0, x)
    return x, diverged


def check_state(name: str, value, system: System, batch: int | None = None) -> np.ndarray:
    """Validate a state (n,) (or (batch, n) when ``batch``): finite and within +-STATE_BOUND."""
    x = np.array(value.detach().cpu() if isinstance(value, torch.Tensor) else value, dtype=float)
    n = system.n_states
    if not (x.shape == (n,) or (batch is not None and x.shape == (batch, n))):
        shapes = f"({n},)" + (f" or ({batch}, {n})" if batch is not None else "")
        raise ValueError(f"{name} must have shape {shapes}, got {x.shape}")
    if not np.all(np.abs(x) <= STATE_BOUND):
        raise ValueError(f"{name} must be finite with every entry in [-{STATE_BOUND:g}, {STATE_BOUND:g}]")
    return x


RENDER_MODES = ("rgb_array",)
"""The render modes of :class:`SwingupEnv` (live viewing lives in ``hybridctl.viz``: meshcat, HTML replays)."""
RENDER_SIZE = 256
"""Height and width in pixels of a ``render_mode="rgb_array"`` frame."""
_BACKGROUND, _RAIL, _LINK, _JOINT, _CART = ((255, 255, 255), (150, 150, 150), (40, 90, 200), (20, 20, 20),
                                            (110, 110, 110))


def chain_points(system: System, state) -> np.ndarray:
    """(n_links + 1, 2) points (horizontal, height) of the chain of ``state``: the pivot (on the cart, if
    any), then each link's far end; the height is measured from the pivot, as ``tip_position``."""
    x = np.asarray(state, dtype=float)
    if system.chain is None:   # a multibody model: its body origins (and tip) seen from -y, x right, z up
        points = system.dynamics.points(x)[0][:, [0, 2]]
        return np.vstack([np.zeros((1, 2)), points])
    phi, base = system.dynamics.absolute_angles(x[: system.n_states // 2])
    lengths = np.asarray(system.chain.link_length, dtype=float)
    pivot = np.array([float(base[0]) if base is not None else 0.0, 0.0])
    steps = np.stack([lengths * np.sin(phi), -lengths * np.cos(phi)], axis=-1)
    return np.vstack([pivot, pivot + np.cumsum(steps, axis=0)])


def _paint_segment(frame: np.ndarray, a, b, radius: float, color) -> None:
    """Colour the pixels within ``radius`` of the segment a-b (pixel coordinates: column, row)."""
    rows, cols = np.mgrid[0:frame.shape[0], 0:frame.shape[1]]
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip(((cols - a[0]) * ab[0] + (rows - a[1]) * ab[1]) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    frame[(cols - a[0] - t * ab[0]) ** 2 + (rows - a[1] - t * ab[1]) ** 2 <= radius ** 2] = color


def _render_multibody(system: System, points: np.ndarray, size: int) -> np.ndarray:
    """A frame of a multibody model: segments from each body's parent origin (the world origin for the
    first) to its own, and to the tip; the view is centred on the world origin, scaled to the model's
    reach at its goal state."""
    goal = chain_points(system, system.goal)
    reach = max(float(np.abs(goal).max()), float(np.abs(points).max()), 1e-3)
    scale = 0.45 * size / reach
    pixels = np.column_stack([points[:, 0] * scale + size / 2, size / 2 - points[:, 1] * scale])
    frame = np.empty((size, size, 3), dtype=np.uint8)
    frame[:] = _BACKGROUND
    for parent, child in system.dynamics.segments():
        _paint_segment(frame, pixels[parent + 1], pixels[child + 1], max(2.0, size / 80), _LINK)
    for point in pixels:
        _paint_segment(frame, point, point, max(3.0, size / 60), _JOINT)
    return frame


def render_frame(system: System, state, size: int = RENDER_SIZE) -> np.ndarray:
    """An RGB uint8 frame (size, size, 3) of the chain in ``state``, drawn with numpy only.

    The view is centred on the pivot (a cart's pivot moves with it: the rail's ticks, 0.5 total link
    lengths apart, are fixed in the world, so cart motion shows), the chain fills 90 % of it.
    """
    points = chain_points(system, state)
    if system.chain is None:
        return _render_multibody(system, points, size)
    reach = float(np.sum(system.chain.link_length))
    scale = 0.45 * size / reach
    centre = points[0]
    pixels = np.column_stack([(points[:, 0] - centre[0]) * scale + size / 2,
                              size / 2 - (points[:, 1] - centre[1]) * scale])
    frame = np.empty((size, size, 3), dtype=np.uint8)
    frame[:] = _BACKGROUND
    if system.chain.has_cart:
        rail = size / 2
        _paint_segment(frame, (0, rail), (size - 1, rail), 1.0, _RAIL)
        spacing = 0.5 * reach
        for k in np.arange(np.ceil((centre[0] - reach) / spacing), np.floor((centre[0] + reach) / spacing) + 1):
            tick = (k * spacing - centre[0]) * scale + size / 2
            _paint_segment(frame, (tick, rail - 4), (tick, rail + 4), 1.0, _RAIL)
        half = 0.06 * size
        frame[int(rail - half / 2):int(rail + half / 2), int(size / 2 - half):int(size / 2 + half)] = _CART
    for a, b in zip(pixels[:-1], pixels[1:]):
        _paint_segment(frame, a, b, max(2.0, size / 80), _LINK)
    for point in pixels:
        _paint_segment(frame, point, point, max(3.0, size / 60), _JOINT)
    return frame


def env_id(system_name: str) -> str:
    """The gymnasium id registered for a system, e.g. 'hybridctl/DoubleCartpoleSwingup-v0'."""
    return f"hybridctl/{''.join(part.capitalize() for part in system_name.split('_'))}Swingup-v0"


class SwingupEnv(gym.Env):
    """Swing-up of one benchmark system (thesis Ch. 3 episodes) as a gymnasium environment.

    Args:
        system: a name from ``hybridctl.systems.known_systems()`` or a loaded System.
        decision_period: seconds each action is held (a multiple of ``dt`` dividing the
            episode duration); default ``system.swingup_period`` (acrobot: 0.2 s).
        render_mode: None or ``"rgb_array"`` (:meth:`render` returns an RGB uint8 frame of the chain,
            :data:`RENDER_SIZE` square; what Stable-Baselines3 asks for when it builds an env by id).
            There is no "human" mode: live viewing lives in ``hybridctl.viz`` (meshcat, HTML replays).
        **spec_overrides: passed to ``hybridctl.systems.load`` (with a system name only).

    Observation: the state in the spec's convention (angles not wrapped), float64,
    in a Box of +-``STATE_BOUND``. Action: torque/force in a float32 Box
    [-action_limit, action_limit]; out-of-range actions are clipped to the limit, and
    NaN/Inf or a wrong shape raise ValueError. Reward: ``system.reward`` of the state
    after the decision (acrobot: tip height, at most 2, so an episode returns <= 100).

    Episodes have a fixed length: truncated after ``max_decisions`` =
    episode_duration / decision_period decisions (acrobot: 50). They are terminated
    only on divergence (a state non-finite or beyond +-STATE_BOUND); that step returns
    the last finite decision-rate state and reward 0. At the end of an episode
    ``info["success"]`` is the thesis success test (:func:`is_balanced`) over the
    decision-rate states s_0 .. s_T (False when diverged). ``reset(options={"state": x0})``
    starts from x0 instead of the spec's initial distribution.
    """

    metadata = {"render_modes": list(RENDER_MODES)}

    def __init__(self, system: str | System, decision_period: float | None = None,
                 render_mode: str | None = None, **spec_overrides: Any):
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)} (live viewing is in "
                             f"hybridctl.viz), got {render_mode!r}")
        self.system = resolve_system(system, **spec_overrides)
        self.decision_period, self.substeps, self.max_decisions = decision_schedule(self.system, decision_period)
        self.metadata = {**type(self).metadata, "render_fps": 1.0 / self.decision_period}
        n, m, limit = self.system.n_states, self.system.n_actions, self.system.action_limit
        self.observation_space = spaces.Box(-STATE_BOUND, STATE_BOUND, (n,), np.float64)
        self.action_space = spaces.Box(-limit, limit, (m,), np.float32)
        self.render_mode = render_mode
        # How to build this env again (gymnasium.make replaces it with the registry's spec).
        shown = {"render_mode": render_mode} if render_mode is not None else {}
        self.spec = EnvSpec(env_id(self.system.name), entry_point="hybridctl.envs.single:SwingupEnv",
                            kwargs={"system": system, "decision_period": decision_period, **shown, **spec_overrides})
        self._state: list[float] | None = None   # the state, plain floats (System.step_single)
        self._history: deque = deque(maxlen=self.system.success_lookback)
        self._t = 0
        self._done = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode from ``options["state"]`` or from ``system.sample_initial_states``."""
        super().reset(seed=seed)
        if options and "state" in options:
            x0 = check_state('options["state"]', options["state"], self.system)
        else:
            x0 = self.system.sample_initial_states(1, self.np_random)[0]
        self._state = x0.tolist()
        self._t, self._done = 0, False
        self._history.clear()
        self._history.append(self._state)
        return x0.copy(), {}

    def step(self, action):
        """Hold ``action`` (clipped) for one decision period; returns (obs, reward, terminated, truncated, info).

        One state steps on plain floats (``System.step_single``, the batched formula written
        out for one state), which agrees with :func:`advance` on torch to rounding.
        """
        if self._state is None or self._done:
            raise RuntimeError("call reset() before step() (and after an episode has ended)")
        system = self.system
        u = np.array(action.detach().cpu() if isinstance(action, torch.Tensor) else action, dtype=np.float64)
        if u.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {u.shape}")
        limit = system.action_limit
        us = u.tolist()
        if not all(map(math.isfinite, us)):
            raise ValueError(f"action must be finite (clipped to [-{limit}, {limit}]), got {u}")
        us = [min(max(v, -limit), limit) for v in us]            # np.clip, on floats
        x = system.step_single(self._state, us, self.substeps, STATE_BOUND)
        self._t += 1
        terminated = x is None
        truncated = self._t >= self.max_decisions and not terminated
        if terminated:
            x, reward = self._state, 0.0          # the last finite decision-rate state
        else:
            reward = system.reward_single(x)
        self._state = x
        self._history.append(x)
        info = {}
        if terminated or truncated:
            self._done = True
            info["success"] = truncated and bool(is_balanced(np.array(self._history), system))
        return np.array(x), reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """The current state drawn as an RGB uint8 array (:data:`RENDER_SIZE` square) with
        ``render_mode="rgb_array"``; None (with gymnasium's warning) without a render mode."""
        if self.render_mode is None:
            gym.logger.warn("SwingupEnv.render() was called without a render_mode; pass render_mode='rgb_array'")
            return None
        return render_frame(self.system, self.state)

    @property
    def state(self) -> np.ndarray:
        """A copy of the current state (n,)."""
        if self._state is None:
            raise RuntimeError("call reset() first")
        return np.array(self._state)
