"""One benchmark system built from its spec: :class:`System` (dynamics, reward, Drake plant, LQR).

The package :mod:`hybridctl.systems` exports it with ``load`` and ``from_drake``; a System pickles as
its spec and is rebuilt where it lands (:func:`_rebuild_system`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from . import control
from .dynamics import ChainDynamics, ChainParams
from .equilibrium import EQUILIBRIUM_XDOT, settle_goal
from .multibody import GeneratedDynamics, ModelError, MultibodyModel
from .rewards import Reward, reward_for
from .spec import (OPTIONAL_DEFAULTS, GateSection, InitialStateSection, Spec, SuccessSection, SwingupSection,
                   typed_sections, validate_shapes)
from .spec import _require_in_range as require_in_range

__all__ = ["System", "check_array", "multibody_request", "PHYSICS_KEYS", "TUNED_VALUES", "MULTIBODY_REWARD_KINDS"]

PHYSICS_KEYS = ("params.", "model.file")
"""Prefixes of the spec keys that are the physics: overriding one (a ``params.`` key, or the model
file) keeps :data:`TUNED_VALUES` that were tuned for the spec's own physics, and says so."""
TUNED_VALUES = ("control.period", "gate.cost_scale")
"""Values tuned for a spec's physics (with every ``swingup.`` gain): the LQR's hold and the gate's scale."""

MULTIBODY_REWARD_KINDS = ("quadratic", "angle_squared", "angle_cosine", "tip_height", "tip_height_centered")
"""The reward kinds a multibody system has (the tip-height ones need the spec's model.tip_body):
``upright_centered`` and ``tip_distance`` are written for planar chains."""


def _plants():
    """The Drake plant builders, imported on first use: ``import hybridctl.systems`` stays free of pydrake."""
    from . import plants
    return plants


_functorch_wrapped = torch._C._functorch.is_functorch_wrapped_tensor


def check_array(name: str, value, width: int) -> None:
    """Raise ValueError naming ``name`` if ``value`` is not (width,) or (B, width) and finite."""
    shape = tuple(value.shape)
    if len(shape) not in (1, 2) or shape[-1] != width:
        raise ValueError(f"{name} must have shape ({width},) or (batch, {width}), got {shape}")
    if len(shape) == 2 and shape[0] == 0:
        raise ValueError(f"{name} is an empty batch (0, {width}); give at least one row")
    if isinstance(value, torch.Tensor):
        # NaN and Inf make the sum non-finite, so a finite sum proves every entry finite: one
        # reduction, no temporary. Only a non-finite sum (bad input, or finite values whose
        # sum overflows) needs the entry-wise test.
        finite = torch.isfinite(value.sum())
        if not bool(finite):
            finite = torch.isfinite(value).all()
    else:
        finite = np.isfinite(value).all()
    if not bool(finite):
        raise ValueError(f"{name} contains NaN or Inf")


class System:
    """One benchmark system, built from its spec.

    Attributes: ``name``, ``spec``, ``state_names``, ``action_names``, ``goal``,
    ``params`` (the physical parameters by name), ``n_states``, ``n_actions``,
    ``dt``, ``integrator``, ``control_period``, ``swingup_period``,
    ``episode_duration``, ``action_limit``, ``angle_indices``, ``Q``, ``R``,
    ``success_eps``, ``success_lookback``, ``chain`` (ChainParams), ``dynamics``.

    Typed spec sections: ``gate`` (:class:`GateSection`: on, off, cost_scale,
    label_horizon, warm_near, warm_far), ``success`` (eps, lookback),
    ``initial_state`` (nominal, low, high) and ``swingup`` (controller, gains).

    A System pickles as its spec (plain values, sources, path and overrides) and is rebuilt where it
    is unpickled (a worker process, a Ray task): its generated dynamics do not pickle. A multibody
    system is rebuilt from its model file, which must still hold the same bytes there.
    ``copy.copy`` and ``copy.deepcopy`` share a System rather than copying it: nothing changes one after it is built.
    """

    def __init__(self, spec: Spec):
        self.spec = spec
        self.name: str = spec.name
        self.family: str = spec.get("model.family")
        self.model: MultibodyModel | None = None     # the multibody family's generated equations
        self.model_request = None
        if self.family == "multibody":
            self._load_multibody()
        self.state_names: list[str] = list(spec.get("state.names"))
        self.action_names: list[str] = list(spec.get("action.names"))
        self.n_states = len(self.state_names)
        self.n_actions = len(self.action_names)
        self.goal: np.ndarray = np.asarray(spec.get("state.goal"), dtype=float)
        self.params: dict[str, Any] = {k.split(".", 1)[1]: v for k, v in spec.values.items()
                                       if k.startswith("params.")}
        self.dt = float(spec.get("integrator.dt"))
        self.integrator: str = spec.get("integrator.method")
        self.control_period = float(spec.get("control.period"))
        self.swingup_period = float(spec.get("control.swingup_period"))
        self.episode_duration = float(spec.get("episode.duration"))
        self.action_limit = float(spec.get("action.limit"))
        self.angle_indices: list[int] = list(spec.get("state.angles"))
        # A slice where the angles are contiguous (all our systems): indexing one state with it
        # is several times cheaper than with an index array (the Drake blocks wrap one state at
        # every control period), and it selects the same columns.
        idx = self.angle_indices
        contiguous = bool(idx) and idx == list(range(idx[0], idx[-1] + 1))
        self._angle_index = slice(idx[0], idx[-1] + 1) if contiguous else np.asarray(idx, dtype=np.int64)
        self.Q = np.atleast_2d(spec.get("lqr.Q"))
        self.R = np.atleast_2d(spec.get("lqr.R"))
        sections = typed_sections(spec)
        self.gate: GateSection = sections["gate"]
        self.success: SuccessSection = sections["success"]
        self.initial_state: InitialStateSection = sections["initial_state"]
        self.swingup: SwingupSection = sections["swingup"]
        self.success_eps = self.success.eps
        self.success_lookback = self.success.lookback
        self.description: str = spec.get("system.description", "")
        self.drake_model: str | None = spec.get("model.drake", None)  # name of a pydrake.examples plant, if any
        self.reward_kind: str = spec.get("reward.kind")
        # Ch. 7 reward settings (optional keys, default 0; used by the Ch. 7 kinds only)
        self.reward_alive_bonus = float(spec.get("reward.alive_bonus", OPTIONAL_DEFAULTS["reward.alive_bonus"]))
        self.reward_velocity_penalty = float(spec.get("reward.velocity_penalty",
                                                      OPTIONAL_DEFAULTS["reward.velocity_penalty"]))
        self.reward_position_weight = float(spec.get("reward.position_weight",
                                                     OPTIONAL_DEFAULTS["reward.position_weight"]))
        self.reward_linear_velocity_weight = float(spec.get("reward.linear_velocity_weight",
                                                            OPTIONAL_DEFAULTS["reward.linear_velocity_weight"]))
        self.reward_cost_to_go_weight = float(spec.get("reward.cost_to_go_weight",
                                                       OPTIONAL_DEFAULTS["reward.cost_to_go_weight"]))
        # upright_centered settings (optional keys): Gaussian widths of the cart's distance and speed
        self.reward_position_scale = float(spec.get("reward.position_scale",
                                                    OPTIONAL_DEFAULTS["reward.position_scale"]))
        self.reward_speed_scale = float(spec.get("reward.speed_scale", OPTIONAL_DEFAULTS["reward.speed_scale"]))
        self.reward_function: Reward = reward_for(self)   # reward.kind, chosen once
        if self.family == "multibody":
            self.chain = None
            self.dynamics = GeneratedDynamics(self.model)
        else:
            self.chain = self._chain_params()
            self.dynamics = ChainDynamics(self.chain)
        try:                                  # the plain-float path of one state (step_single)
            self.dynamics.scalar(self.dt, self.integrator)
            self._has_scalar = True
        except NotImplementedError:          # > 3 joint coordinates: batched LU only
            self._has_scalar = False
        if self.integrator in ("euler", "runge_kutta2"):  # generated now: not inside a torch.compile trace
            self.dynamics.generate_torch_step(self.dt, self.integrator)
            for dtype in (torch.float64, torch.float32):    # one step fills the constant caches too (a trace
                self._step_torch(torch.zeros(2, self.n_states, dtype=dtype),   # that filled them would
                                 torch.zeros(2, self.n_actions, dtype=dtype))  # compile twice)
        self._lqr_cache: dict = {}
        self._input_matrix: np.ndarray | None = None
        self.goal = settle_goal(self)      # a goal within GOAL_TOLERANCE of an equilibrium moves there, said
        self._warn_tuned_values_kept()

    def __repr__(self) -> str:
        return f"System({self.name!r}, n_states={self.n_states}, dt={self.dt}, integrator={self.integrator!r})"

    # ----------------------------------------------------------------- parameters
    def _warn_tuned_values_kept(self) -> None:
        """Warn when an override changed the physics (``params.*``, ``model.file``) but kept values tuned
        for the spec's own physics: the LQR's hold (``control.period``), the gate's cost scale and the
        swing-up gains. Drake's default acrobot, for one, cannot be balanced under the thesis' 0.01 s hold.
        Said once per process (worker processes that rebuild the system stay quiet)."""
        import multiprocessing
        import warnings

        spec = self.spec
        physics = [k for k in spec.overridden if k.startswith(PHYSICS_KEYS)]
        tuned = [k for k in spec.values if k in TUNED_VALUES or (k.startswith("swingup.") and k != "swingup.controller")]
        kept = [k for k in tuned if k not in spec.overridden]
        if not physics or not kept or multiprocessing.parent_process() is not None:
            return
        shown = ", ".join(f"{k}={spec.values[k]!r}" for k in kept)
        warnings.warn(f"{self.name}: {', '.join(spec.overridden[k] for k in physics)} changes the physics, but the "
                      f"values tuned for {spec.path.name} were kept and may no longer fit: {shown}; check the LQR "
                      f"under the hold (hybridctl simulate {self.name} --controller lqr --x0=... near the goal) and "
                      f"rescale the gate (hybridctl.systems.control.lqr_basin_level; docs: Bring your own robot)",
                      UserWarning, stacklevel=4)

    def __reduce__(self):
        return (_rebuild_system, (self.spec,))

    def __copy__(self) -> "System":
        # without it copy.copy would go through __reduce__ and rebuild the system on the same spec object
        return self

    def __deepcopy__(self, memo: dict) -> "System":
        return self

    def _load_multibody(self) -> None:
        """Read the model file through Drake (or the cache), fill the spec's defaults from it
        (state and action names, angles, the action limit from the actuators' effort limits) and
        check every shape against it."""
        from . import symbolic

        spec = self.spec
        self.model_request = multibody_request(spec)
        self.model = symbolic.load_model(self.model_request)
        model, where = self.model, f"model file {spec.get('model.file')}"
        defaults = {"state.names": [*model.positions, *model.velocities],
                    "state.angles": [i for i, r in enumerate(model.revolute) if r],
                    "action.names": list(model.actuators)}
        for key, value in defaults.items():
            if not spec.has(key):
                spec.values[key], spec.sources[key] = value, where
        if not spec.has("action.limit"):
            limits = np.asarray([np.inf if e is None else e for e in model.info.get("effort_limits", [])], dtype=float)
            if limits.size == 0 or not np.all(np.isfinite(limits)) or np.ptp(limits) != 0.0 or limits[0] <= 0:
                raise spec.error("action.limit", f"is needed: the model's actuators give no single finite effort "
                                                 f"limit ({limits.tolist()}); set action.limit in the spec")
            spec.values["action.limit"], spec.sources["action.limit"] = float(limits[0]), f"{where} (effort limit)"
            if all(model.revolute):          # every actuator then drives a revolute joint: a torque
                spec.units["action.limit"] = "N m"
            require_in_range(spec, "action.limit")   # as a spec's own value: a model's 1e300 is no limit either
        # the model file's bytes are part of the plant: a checkpoint records this with the spec values
        # (learn.checkpoint.system_record), so a changed model is refused on load unless forced
        spec.values["model.file_sha256"] = model.info["file_sha256"]
        spec.sources["model.file_sha256"] = f"sha256 of {self.model_request.source}"
        validate_shapes(spec, model.n_q, model.n_u)
        kind = spec.get("reward.kind")
        if kind not in MULTIBODY_REWARD_KINDS:
            raise spec.error("reward.kind", f"must be one of {MULTIBODY_REWARD_KINDS} for a multibody system, "
                                            f"got {kind!r}")
        if kind.startswith("tip_height") and not model.tip:
            raise spec.error("reward.kind", f"{kind!r} needs a tip point: set model.tip_body (and model.tip_point)")

    def _chain_params(self) -> ChainParams:
        s = self.spec
        has_cart = s.get("model.base") == "cart"
        n_q = self.n_states // 2
        actuation = np.zeros((n_q, self.n_actions))
        for col, joint in enumerate(s.get("model.actuated_joints")):
            actuation[joint, col] = 1.0
        return ChainParams(
            has_cart=has_cart,
            cart_mass=float(s.get("params.cart_mass", 0.0)),
            link_mass=np.atleast_1d(s.get("params.link_mass")).astype(float),
            link_length=np.atleast_1d(s.get("params.link_length")).astype(float),
            link_com=np.atleast_1d(s.get("params.link_com")).astype(float),
            link_inertia=np.atleast_1d(s.get("params.link_inertia")).astype(float),
            joint_damping=np.atleast_1d(s.get("params.joint_damping")).astype(float),
            gravity=float(s.get("params.gravity")),
            angle_offset=float(s.get("model.angle_offset", 0.0)),
            actuation=actuation,
        )

    # ------------------------------------------------------------------ dynamics
    def _check(self, x, u) -> None:
        if not isinstance(x, torch.Tensor) or not isinstance(u, torch.Tensor):
            raise ValueError("x and u must be torch tensors (use torch.as_tensor)")
        check_array("x", x, self.n_states)
        check_array("u", u, self.n_actions)
        # exact shapes: a (n,) state with (B, m) inputs would broadcast into B states silently
        if x.dim() != u.dim():
            raise ValueError(f"x and u must both be single ((n,), (m,)) or both batched ((B, n), (B, m)), "
                             f"got shapes {tuple(x.shape)} and {tuple(u.shape)}")
        if x.dim() == 2 and x.shape[0] != u.shape[0]:
            raise ValueError(f"x and u batch sizes differ: {x.shape[0]} vs {u.shape[0]}")

    def derivatives(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """dx/dt for states (B, n) and inputs (B, m); differentiable, float32 or float64."""
        self._check(x, u)
        return self.dynamics.derivatives(x, u)

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """One step of length ``dt`` with the spec's integrator (input held over the step).

        ``euler``: x + dt f(x, u). ``runge_kutta2``: Heun's method, as Drake's
        RungeKutta2Integrator. No saturation is applied here.

        One float64 CPU state ((n,) or (1, n)) that needs no gradient takes the plain-float
        path (:meth:`step_single`), which agrees with the batched torch path to rounding.
        """
        fast = self._step_one(x, u, check=True)
        if fast is not None:
            return fast
        self._check(x, u)
        return self._step_torch(x, u)

    def step_unchecked(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``step`` without input validation, for inner loops that validated once."""
        fast = self._step_one(x, u, check=False)
        if fast is not None:
            return fast
        return self._step_torch(x, u)

    def _step_torch(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The batched, differentiable torch step: ``euler`` x + dt f(x, u); ``runge_kutta2``
        x + (0.5 dt)(k1 + k2), k2 = f(x + dt k1, u) (generated code, ``ChainDynamics.torch_step``)."""
        if self.integrator not in ("euler", "runge_kutta2"):
            raise ValueError(f"integrator must be 'euler' or 'runge_kutta2', got {self.integrator!r}")
        return self.dynamics.torch_step(x, u, self.dt, self.integrator)

    def _step_one(self, x, u, check: bool):
        """``step`` of one float64 CPU state through the plain-float path, or None where it
        does not apply (a batch, another dtype or device, autograd or functorch tensors,
        tracing by torch.compile, a chain without a closed-form solve) or where the input
        is bad (``check``: the caller's validation raises the error)."""
        if (type(x) is not torch.Tensor or type(u) is not torch.Tensor or x.dtype != torch.float64
                or u.dtype != torch.float64 or x.requires_grad or u.requires_grad or not x.is_cpu or not u.is_cpu):
            return None
        shape, n = x.shape, self.n_states
        if shape == (1, n) and u.shape == (1, self.n_actions):
            batched = True
        elif shape == (n,) and u.shape == (self.n_actions,):
            batched = False
        else:
            return None
        if not self._has_scalar or _functorch_wrapped(x) or _functorch_wrapped(u) or torch.compiler.is_compiling():
            return None
        xs, us = x.tolist(), u.tolist()
        if batched:
            xs, us = xs[0], us[0]
        if check and not all(map(math.isfinite, xs + us)):
            return None
        try:
            # looked up per call: dt and integrator are plain attributes a caller may change
            out = self.dynamics.scalar(self.dt, self.integrator)(xs, us, 1)
        except (ValueError, ZeroDivisionError, OverflowError):   # math.sin(inf) and the like: torch gives inf/nan
            return None
        return torch.from_numpy(np.array([out] if batched else out))

    def step_columns(self, x: torch.Tensor, u: torch.Tensor, compiled: bool = False) -> torch.Tensor:
        """:meth:`step` of states stored column-major: ``x`` (n, B), ``u`` (m, B) -> (n, B).

        For long batched rollouts that keep their states as one contiguous row per coordinate
        (transpose once, step many times): every operation then reads contiguous memory, and
        with ``compiled=True`` (``torch.compile``, ~15 s to build once per process, dtype and
        batch size) the whole step runs as one fused loop, near the FLOP limit of
        ``benchmarks/dynamics.py``. Eager results equal :meth:`step` on ``x.T`` bit for bit;
        compiled ones agree to rounding. No input validation; at most 3 joint coordinates.
        """
        if self.integrator not in ("euler", "runge_kutta2"):
            raise ValueError(f"integrator must be 'euler' or 'runge_kutta2', got {self.integrator!r}")
        if x.dim() != 2 or u.dim() != 2 or x.shape[0] != self.n_states or u.shape[0] != self.n_actions \
                or x.shape[1] != u.shape[1]:
            raise ValueError(f"x must be ({self.n_states}, B) and u ({self.n_actions}, B), "
                             f"got {tuple(x.shape)} and {tuple(u.shape)}")
        return self.dynamics.torch_step_columns(x, u, self.dt, self.integrator, compiled=compiled)

    def step_single(self, x, u, steps: int = 1, bound: float | None = None) -> list[float] | None:
        """``steps`` integrator steps of one state, on plain Python floats (no torch, no numpy).

        ``x`` (n,) and ``u`` (m,) are sequences of floats (lists, tuples, 1-D float arrays),
        ``u`` held over the steps. Returns the state as a list, or None as soon as a
        coordinate leaves [-bound, bound] or is NaN, when ``bound`` is given. No input
        validation. The formula is the batched one written out for one state
        (``ChainDynamics.scalar``); it agrees with :meth:`step` on a batch to rounding
        (tested to 1e-12 for every spec). Chains of more than 3 joint coordinates (no
        closed-form solve) step through torch here.
        """
        if not self._has_scalar:
            return self._step_single_torch(x, u, steps, bound)
        return self.dynamics.scalar(self.dt, self.integrator, bound)(x, u, steps)

    def _step_single_torch(self, x, u, steps: int, bound: float | None) -> list[float] | None:
        xt = torch.tensor([list(x)], dtype=torch.float64)
        ut = torch.tensor([list(u)], dtype=torch.float64)
        for _ in range(steps):
            xt = self._step_torch(xt, ut)
            if bound is not None and not bool((xt.abs() <= bound).all()):
                return None
        return xt[0].tolist()

    def reward_single(self, x) -> float:
        """:meth:`reward` of one state given as a sequence of floats, as a float (the thesis' tip height on
        Python floats, ``ChainDynamics.tip_height_single``; other kinds through the numpy path)."""
        return self.reward_function.single(x)

    def rollout(self, x0: torch.Tensor, controls: torch.Tensor) -> torch.Tensor:
        """States (B, T+1, n) from x0 (B, n) under controls (B, T, m), differentiable.

        Every control step is checked up front (shape, finite values), not only the first.
        """
        if not isinstance(x0, torch.Tensor) or not isinstance(controls, torch.Tensor):
            raise ValueError("x0 and controls must be torch tensors (use torch.as_tensor)")
        if x0.dim() != 2 or controls.dim() != 3 or controls.shape[0] != x0.shape[0] or controls.shape[1] < 1 \
                or controls.shape[2] != self.n_actions:
            raise ValueError(f"x0 must be (B, {self.n_states}) and controls (B, T >= 1, {self.n_actions}), "
                             f"got {tuple(x0.shape)} and {tuple(controls.shape)}")
        check_array("x0", x0, self.n_states)
        check_array("controls", controls.reshape(-1, self.n_actions), self.n_actions)
        states = [x0]
        for t in range(controls.shape[1]):
            states.append(self.step_unchecked(states[-1], controls[:, t]))
        return torch.stack(states, dim=1)

    def energy(self, x):
        """Total mechanical energy of states x (numpy or torch, batched)."""
        return self.dynamics.energy(x)

    # ------------------------------------------------------- goal, reward, errors
    def state_error(self, x):
        """x - goal with angle coordinates wrapped to [-pi, pi) (numpy or torch); a new array."""
        if isinstance(x, torch.Tensor):
            goal = torch.as_tensor(self.goal, dtype=x.dtype, device=x.device)
        else:
            goal = self.goal
        return control.wrap_angles(x - goal, self._angle_index)

    def reward(self, x):
        """Per-decision reward of states x (numpy or torch, batched): the spec's ``reward.kind`` as a
        :class:`~hybridctl.systems.rewards.Reward` (thesis eq. 3.1's tip height or a variant), chosen once
        when the system is built (``reward_function``)."""
        return self.reward_function(x)

    def sample_initial_states(self, n: int, generator: np.random.Generator | None = None) -> np.ndarray:
        """n initial states from the spec's uniform distribution (nominal + U(low, high))."""
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        rng = generator if generator is not None else np.random.default_rng()
        return self.initial_state.sample(n, rng)

    def nudged_nominal_state(self, nudge: float = 1e-3) -> np.ndarray:
        """The spec's nominal initial state (hanging down) with its first angle moved by ``nudge`` rad.

        The exact bottom is an equilibrium where energy swing-ups output zero; the demo,
        the command line's default start and the benchmarks start here instead.
        """
        x0 = self.initial_state.nominal.copy()
        x0[self.angle_indices[0]] += nudge
        return x0

    # --------------------------------------------------------------------- Drake
    def state_unit(self, i: int) -> str:
        """The unit of state coordinate ``i``: rad or rad/s for angles (the spec's ``state.angles``), m or m/s
        for the other positions (a cart, a prismatic joint) and their rates."""
        n_q = self.n_states // 2
        unit = "rad" if i % n_q in self.angle_indices else "m"
        return f"{unit}/s" if i >= n_q else unit

    @property
    def action_unit(self) -> str:
        """The unit of the action, as the spec gives it for ``action.limit`` (N m, N); empty if it gives none."""
        return self.spec.units.get("action.limit", "")

    def save_spec(self, path, *, overwrite: bool = False):
        """Write this system as a complete spec TOML file (every value with its source; the goal it uses, its
        source saying where it was moved to the nearest equilibrium), atomically; an existing file is refused
        unless ``overwrite``. ``systems.load(path)`` builds the same dynamics and LQR (:mod:`.spec_writer`)."""
        from .spec_writer import save_spec
        return save_spec(self, path, overwrite=overwrite)

    def drake_plant(self):
        """A fresh Drake plant (AcrobotPlant, PendulumPlant or continuous MultibodyPlant).

        AcrobotPlant and PendulumPlant keep parameters in the Context; this plant's
        ``CreateDefaultContext()`` (and :meth:`drake_context`) writes the spec's parameters
        there. A Diagram's context is made in C++ with Drake's defaults: in a Diagram of
        your own, call :meth:`apply_drake_parameters` on the plant's subcontext
        (``hybridctl.drake``'s builders do it for you).
        """
        plant, _ = _plants().make_plant(self)
        return plant

    def drake_context(self, plant):
        """A Context of ``plant`` (from :meth:`drake_plant`) holding the spec's parameters."""
        context = plant.CreateDefaultContext()
        self.apply_drake_parameters(plant, context)
        return context

    def apply_drake_parameters(self, plant, context) -> None:
        """Write the spec's parameters into ``context``, a Context of ``plant`` (in a Diagram:
        ``plant.GetMyMutableContextFromRoot(root_context)``). Nothing to write for a
        MultibodyPlant, whose model holds them."""
        _plants().make_plant_parameter_setter(self, plant)(context)

    def to_drake_state(self, x: np.ndarray) -> np.ndarray:
        """Our state convention -> the Drake plant's (differs only in the acrobot's th1)."""
        return np.asarray(x, dtype=float) + self.drake_state_offset()

    def from_drake_state(self, x_drake: np.ndarray) -> np.ndarray:
        """The Drake plant's state convention -> ours."""
        return np.asarray(x_drake, dtype=float) - self.drake_state_offset()

    def drake_state_offset(self) -> np.ndarray:
        """x_drake - x: Drake's AcrobotPlant measures the first link angle from hanging down
        (zero for the multibody family, whose state is the MultibodyPlant's)."""
        offset = np.zeros(self.n_states)
        if self.chain is not None:
            offset[int(self.chain.has_cart)] = self.chain.angle_offset
        return offset

    def drake_input_matrix(self, plant) -> np.ndarray:
        """S with the Drake plant's actuation input = S u: the identity, except for a multibody model
        whose spec actuates a subset (or another order) of the model's JointActuators. It depends on the
        model alone, so it is worked out once (``drake_derivatives`` asks for it at every state)."""
        if self._input_matrix is None:
            self._input_matrix = _plants().input_matrix(self, plant)
        return self._input_matrix

    def drake_input(self, plant, u) -> np.ndarray:
        """The Drake plant's actuation input for our action ``u``."""
        return self.drake_input_matrix(plant) @ np.asarray(u, dtype=float)

    def drake_derivatives(self, plant, context, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Time derivatives from the Drake plant at one state (our convention) and input."""
        context.SetContinuousState(self.to_drake_state(x))
        _plants().actuation_port(plant).FixValue(context, self.drake_input(plant, u))
        return plant.EvalTimeDerivatives(context).CopyToVector()

    def lqr(self, Q: np.ndarray | None = None, R: np.ndarray | None = None):
        """(K, S) of the continuous-time LQR about the goal, u = -K (x - goal).

        Linearises the Drake plant with ``Linearize`` and calls Drake's
        ``LinearQuadraticRegulator``. Defaults: the spec's Q and R.
        """
        from pydrake.systems.controllers import LinearQuadraticRegulator
        from pydrake.systems.primitives import Linearize

        Q = self.Q if Q is None else np.atleast_2d(np.asarray(Q, dtype=float))
        R = self.R if R is None else np.atleast_2d(np.asarray(R, dtype=float))
        if Q.shape != (self.n_states,) * 2:
            raise ValueError(f"Q must be {self.n_states}x{self.n_states}, got {Q.shape}")
        if R.shape != (self.n_actions,) * 2:
            raise ValueError(f"R must be {self.n_actions}x{self.n_actions}, got {R.shape}")
        key = (Q.tobytes(), R.tobytes())
        if key not in self._lqr_cache:
            plant = self.drake_plant()
            context = self.drake_context(plant)
            context.SetContinuousState(self.to_drake_state(self.goal))
            port = _plants().actuation_port(plant)
            port.FixValue(context, np.zeros(port.size()))
            xdot = plant.EvalTimeDerivatives(context).CopyToVector()
            if np.abs(xdot).max() > EQUILIBRIUM_XDOT:
                raise ValueError(f"{self.name}: the goal {self.goal.tolist()} is not an equilibrium with u = 0, nor "
                                 f"near one (xdot = {xdot.tolist()}); see systems.nearest_equilibrium")
            from pydrake.systems.framework import OutputPortSelection
            linear = Linearize(plant, context, input_port_index=port.get_index(),
                               output_port_index=OutputPortSelection.kNoOutput)
            try:
                K, S = LinearQuadraticRegulator(linear.A(), linear.B() @ self.drake_input_matrix(plant), Q, R)
            except RuntimeError as exc:  # Drake's Riccati solver: not stabilizable / not detectable
                raise ValueError(self._lqr_failure(str(exc))) from None
            if not (np.isfinite(K).all() and np.isfinite(S).all()):
                raise ValueError(self._lqr_failure("the gain K or cost-to-go S is not finite"))
            self._lqr_cache[key] = (np.asarray(K), np.asarray(S))
        K, S = self._lqr_cache[key]
        return K.copy(), S.copy()

    def _lqr_failure(self, reason: str) -> str:
        """The one-line message of an LQR about the goal that cannot be solved: what to change."""
        reason = reason.splitlines()[0] if reason else "no solution"
        where = self.spec.path.name + "".join(f", {k}={v!r}" for k, v in self.spec.overrides.items())
        return (f"{self.name} ({where}): no LQR about the goal with these parameters ({reason}); "
                f"check the spec's params (gravity, masses, lengths, inertias) and lqr.Q / lqr.R "
                f"(Q must weigh every unstable state, e.g. the spec's default)")


def _rebuild_system(spec: Spec) -> System:
    """The System an unpickled spec describes (:meth:`System.__reduce__`). A multibody spec records its
    model file's sha256: a file that changed since is refused, naming it, rather than giving another plant."""
    recorded = spec.values.get("model.file_sha256")
    system = System(spec)
    found = system.spec.values.get("model.file_sha256")
    if recorded is not None and found != recorded:
        raise ValueError(f"{spec.name}: its model file {spec.get('model.file')} changed since the system was "
                         f"pickled (sha256 {recorded[:12]}... then, {str(found)[:12]}... now)")
    return system


def multibody_request(spec: Spec):
    """The :class:`~hybridctl.systems.symbolic.ModelRequest` of a multibody spec (its model file resolved
    next to the spec, in the package's models/, or as a package://drake/ URL)."""
    from .symbolic import ModelRequest, resolve_source
    try:
        source = resolve_source(spec.get("model.file"), spec.path.parent)
    except ModelError as exc:
        raise spec.error("model.file", str(exc)) from None
    tip = spec.get("model.tip_point", None)
    return ModelRequest(source=source, actuated=tuple(spec.get("model.actuated_joints", ())),
                        gravity=float(spec.get("params.gravity")) if spec.has("params.gravity") else None,
                        tip_body=spec.get("model.tip_body", None),
                        tip_point=tuple(float(t) for t in tip) if tip is not None else (0.0, 0.0, 0.0))
