"""Thousands of swing-up episodes at once: a torch ``gymnasium.vector.VectorEnv``.

The whole batch advances with one ``System.step_unchecked`` call per integration
step (no Python loop over environments); observations, rewards, flags and infos
are torch tensors on the env's device.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..limits import check_fits_memory
from ..systems import System
from ..systems.compiled import LazyCompiled, check_compile_mode
from ..systems.success import is_balanced
from .single import STATE_BOUND, advance, check_state, decision_schedule, resolve_system

STEP_TEMPORARIES = 8
"""State-sized tensors per env a step holds at once besides the history (state, observation, final
observation, sub-step intermediates): what the memory check of ``num_envs`` counts."""


def _autoreset_mode(mode) -> AutoresetMode:
    """AutoresetMode from an enum, its value ('SameStep') or its name ('same_step')."""
    if isinstance(mode, AutoresetMode):
        found = mode
    else:
        by_key = {m.value.lower(): m for m in AutoresetMode} | {m.name.lower(): m for m in AutoresetMode}
        found = by_key.get(str(mode).lower())
    if found not in (AutoresetMode.SAME_STEP, AutoresetMode.NEXT_STEP):
        raise ValueError(f"autoreset_mode must be AutoresetMode.SAME_STEP or NEXT_STEP, got {mode!r}")
    return found


class TorchVectorEnv(VectorEnv):
    """``num_envs`` independent swing-up episodes of one system, batched in torch.

    Args:
        system: a name from ``hybridctl.systems.known_systems()`` or a loaded System
            (load one with overrides, e.g. ``systems.load("acrobot", duration=1.0)``).
        num_envs: number of sub-environments (>= 1).
        decision_period: as in :class:`SwingupEnv` (default ``system.swingup_period``).
        device, dtype: where and in which precision (float32 or float64) to simulate.
        seed: seeds the env's numpy generator (``reset(seed=...)`` re-seeds it).
        autoreset_mode: ``"same_step"`` (default) or ``"next_step"`` (or the
            ``gymnasium.vector.AutoresetMode`` members).
        compile: ``"off"`` (default: eager torch), ``"on"`` (each decision's integration steps
            as one ``torch.compile``-d function; a failure to compile raises) or ``"auto"``
            (compiled, falling back to eager with a warning): :mod:`hybridctl.systems.compiled`.

    Each sub-environment behaves as :class:`SwingupEnv`: actions (num_envs, m) are
    clipped to the limit (NaN/Inf or a wrong shape raise ValueError); truncated
    after ``max_decisions`` decisions, terminated only on divergence (then that
    row's observation is its last finite state and its reward 0; never both flags).

    Autoreset. SAME_STEP: ended sub-envs restart in the same call; the returned
    observation is the new initial state and ``infos["final_obs"]`` holds the state
    reached by this step's dynamics for every row (``infos["_final_obs"]`` marks the
    ended rows, for which it differs from the observation). NEXT_STEP (gymnasium's
    default): the call after an end resets that sub-env, ignoring its action, and
    returns reward 0 and both flags False for it.

    ``infos`` always holds ``"success"`` and ``"_success"`` (N,) bool tensors:
    ``_success`` marks the rows that ended this step and ``success`` the thesis test
    (:func:`is_balanced` over the last ``success_lookback`` decision-rate states, False
    when diverged or when the episode had fewer states). Initial states come from
    ``system.sample_initial_states`` with the env's generator, so the same seed gives
    the same run; ``reset(options={"state": x})`` sets every sub-env's state to x (n,)
    or to the rows of x (num_envs, n).
    """

    metadata = {"render_modes": []}

    def __init__(self, system: str | System, num_envs: int, decision_period: float | None = None,
                 device: str | torch.device = "cpu", dtype: torch.dtype = torch.float64,
                 seed: int | None = None, autoreset_mode: str | AutoresetMode = "same_step",
                 compile: str = "off"):
        if not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.system = resolve_system(system)
        self.decision_period, self.substeps, self.max_decisions = decision_schedule(self.system, decision_period)
        self.num_envs, self.device, self.dtype = int(num_envs), torch.device(device), dtype
        self.autoreset_mode = _autoreset_mode(autoreset_mode)
        self.set_compile(compile)
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}
        n, m, limit = self.system.n_states, self.system.n_actions, self.system.action_limit
        # before the batched spaces and states are made: the state history (success_lookback states
        # per env) and a few state-sized temporaries of a step
        check_fits_memory("num_envs (--num-envs)", self.num_envs * (self.system.success_lookback + STEP_TEMPORARIES)
                          * n * (8 if dtype == torch.float64 else 4), f"{self.num_envs:,} environments")
        np_dtype = np.float64 if dtype == torch.float64 else np.float32
        self.single_observation_space = spaces.Box(-STATE_BOUND, STATE_BOUND, (n,), np_dtype)
        self.single_action_space = spaces.Box(-limit, limit, (m,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.render_mode = None
        if seed is not None:
            self._np_random, self._np_random_seed = seeding.np_random(seed)
        N, b = self.num_envs, self.system.success_lookback
        self._state = torch.zeros(N, n, dtype=dtype, device=self.device)
        self._history = torch.full((N, b, n), torch.nan, dtype=dtype, device=self.device)
        self._t = torch.zeros(N, dtype=torch.long, device=self.device)
        self._needs_reset = torch.zeros(N, dtype=torch.bool, device=self.device)
        self._started = False

    # ------------------------------------------------------------------ helpers
    def _restart(self, rows: torch.Tensor, x0=None) -> None:
        """Begin new episodes in the masked rows, from x0 or from fresh initial states."""
        k = int(rows.sum())
        if k == 0:
            return
        if x0 is None:
            x0 = self.system.sample_initial_states(k, self.np_random)
        x0 = torch.as_tensor(x0, dtype=self.dtype, device=self.device).expand(k, -1)
        self._state[rows] = x0
        self._t[rows] = 0
        self._history[rows] = torch.nan
        self._history[rows, -1] = x0
        self._needs_reset[rows] = False

    def _check_actions(self, actions) -> torch.Tensor:
        """Actions as a (N, m) tensor on the env's device, clipped to the limit."""
        u = torch.as_tensor(actions, device=self.device).to(self.dtype)
        if tuple(u.shape) != self.action_space.shape:
            raise ValueError(f"actions must have shape {self.action_space.shape}, got {tuple(u.shape)}")
        if not bool(torch.isfinite(u).all()):
            limit = self.system.action_limit
            raise ValueError(f"actions must be finite (clipped to [-{limit}, {limit}]); got NaN or Inf")
        return u.clamp(-self.system.action_limit, self.system.action_limit)

    def set_compile(self, mode: str) -> None:
        """Run the decisions eagerly (``"off"``) or ``torch.compile``-d from the next step on (``"on"``:
        a failure to compile raises; ``"auto"``: it falls back to eager with a warning)."""
        check_compile_mode(mode)
        if getattr(self, "compile", None) == mode:
            return
        self.compile = mode
        self._decision_fn = self._make_decision_fn(mode != "off", mode == "on")

    def _make_decision_fn(self, enabled: bool, strict: bool) -> LazyCompiled:
        """The function :meth:`_advance` calls (subclasses wrap their own decision)."""
        return LazyCompiled(advance, enabled, strict=strict, name="the env's decision")

    def _advance(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Dynamics of one decision from the current states: (x_next, diverged). Subclasses
        (e.g. the switched env) override this to put controllers inside the decision."""
        return self._decision_fn(self.system, self._state, u, self.substeps)

    def _step_infos(self) -> dict[str, torch.Tensor]:
        """Extra per-step infos of subclasses (computed before autoreset)."""
        return {}

    # --------------------------------------------------------------------- API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Restart every sub-env; returns (observations (N, n), {})."""
        super().reset(seed=seed)
        x0 = None
        if options and "state" in options:
            x0 = check_state('options["state"]', options["state"], self.system, batch=self.num_envs)
        self._restart(torch.ones(self.num_envs, dtype=torch.bool, device=self.device), x0)
        self._started = True
        return self._state.clone(), {}

    def step(self, actions):
        """Advance every sub-env by one decision; returns (obs, rewards, terminations, truncations, infos)."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        u = self._check_actions(actions)
        x, terminated = self._advance(u)
        self._t += 1
        truncated = (self._t >= self.max_decisions) & ~terminated
        rewards = torch.where(terminated, 0.0, self.system.reward(x))
        self._state = x
        self._history = torch.cat([self._history[:, 1:], x[:, None]], dim=1)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            skipped = self._needs_reset.clone()
            self._restart(skipped)
            rewards = torch.where(skipped, 0.0, rewards)
            terminated, truncated = terminated & ~skipped, truncated & ~skipped
        ended = terminated | truncated
        success = torch.zeros_like(ended)
        if bool(ended.any()):
            balanced = torch.as_tensor(is_balanced(self._history[ended], self.system), device=self.device)
            success[ended] = balanced & truncated[ended]
        infos = {"success": success, "_success": ended.clone(), **self._step_infos()}
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            infos["final_obs"], infos["_final_obs"] = x.clone(), ended.clone()
            self._restart(ended)
        else:
            self._needs_reset = ended.clone()
        return self._state.clone(), rewards, terminated, truncated, infos

    @property
    def episode_steps(self) -> torch.Tensor:
        """Decisions taken in each sub-env's current episode (N,) (a copy)."""
        return self._t.clone()

    @property
    def state(self) -> torch.Tensor:
        """A copy of the current states (N, n)."""
        return self._state.clone()
