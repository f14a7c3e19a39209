"""Benchmark systems: specs, batched torch dynamics, Drake plants and LQR.

>>> from hybridctl import systems
>>> acrobot = systems.load("acrobot")
>>> K, S = acrobot.lqr()                     # Drake's LinearQuadraticRegulator
>>> xdot = acrobot.derivatives(x, u)         # torch, batched (B, n), (B, m) -> (B, n)
>>> x_next = acrobot.step(x, u)              # one step of the spec's integrator

A system's parameters live in its spec (``systems/NAME.toml``) only; everything
here derives from it. :class:`System` lives in :mod:`hybridctl.systems.system`, its rewards in
:mod:`hybridctl.systems.rewards`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from . import control
from . import equilibrium
from .equilibrium import GOAL_TOLERANCE, EquilibriumError
from .multibody import ModelError
from .spec import (GateSection, InitialStateSection, SpecError, Spec, SuccessSection, SwingupSection, known_systems,
                   read_spec, spec_from_document)
from .switched import (AlwaysGate, CostToGoGate, EnergySwingup, Gate, LearnedGate, NeverGate, Rollout, SwitchedController,
                       TrajoptSwingup, ZeroSwingup, closed_loop_rollout)
from .system import System, check_array

__all__ = ["System", "load", "from_drake", "known_systems", "SpecError", "ModelError", "Spec", "check_array", "control",
           "GateSection", "SuccessSection", "InitialStateSection", "SwingupSection", "SwitchedController",
           "closed_loop_rollout", "Rollout", "Gate", "LearnedGate", "CostToGoGate", "AlwaysGate", "NeverGate",
           "EnergySwingup", "ZeroSwingup", "TrajoptSwingup", "nearest_equilibrium", "EquilibriumError"]


def load(name: str, **overrides: Any) -> System:
    """Load a system by name (``systems/NAME.toml``) or path, with optional overrides.

    Overrides are given by key, bare (``dt=0.005``) when unique across the spec or
    as ``section__key`` (``integrator__dt=0.005``). Unknown names raise KeyError
    listing the known systems; out-of-range values raise SpecError naming the key
    and the file.
    """
    return System(read_spec(name, **overrides))


_FROM_DRAKE = "hybridctl.systems.from_drake default"


def from_drake(model_file: str, goal, Q, R, *, name: str | None = None, actuated_joints=None,
               action_limit: float | None = None, gravity: float | None = None, tip_body: str | None = None,
               tip_point=None, nominal=None, settings: dict | None = None, **overrides: Any) -> System:
    """A :class:`System` straight from a URDF/SDF file, without writing a spec.

    ``model_file``: a path or a ``package://drake/`` URL. ``goal``: the state to balance at (Drake's
    coordinates: positions then velocities), ``Q`` / ``R``: the LQR weights. ``actuated_joints``:
    joint names in action order (default: every JointActuator of the model); ``action_limit``:
    default the actuators' effort limit (one above it is allowed: Drake's plant, and the generated
    dynamics with it, clamp each actuator's input to its effort limit); ``gravity``: m/s^2 (default Drake's 9.81); ``tip_body`` /
    ``tip_point``: the point whose height the tip rewards use; ``nominal``: the initial state
    (default all zeros). Every other section gets a default recorded with the source
    "hybridctl.systems.from_drake default" (Euler, dt = control period = 0.01 s, swing-up
    decisions every 0.1 s, 10 s episodes, reward ``angle_cosine``, success within 0.1 over the
    last 10 states, gate 0.9 / 0.5 with cost scale 1); change any by key as in
    :func:`load` (``dt=0.005``, ``gate__cost_scale=50``). ``settings``: ``{"section.key": (value, source)}``,
    values set with the source that chose them (``hybridctl fit`` records its measurements so). The result
    equals a spec file with the same values (``[model] family = "multibody"``).
    """
    def entry(value, source=_FROM_DRAKE):
        if isinstance(value, np.ndarray):
            value = value.tolist()
        return {"value": value, "source": source}

    goal = np.asarray(goal, dtype=float)
    if goal.ndim != 1 or goal.size % 2:
        raise ValueError(f"goal must be a state (positions then velocities), got shape {goal.shape}")
    nominal = np.zeros_like(goal) if nominal is None else np.asarray(nominal, dtype=float)
    path = Path(model_file)
    stem = re.sub(r"[^a-z0-9_-]", "_", path.stem.lower()).strip("_-") or "robot"
    # a URL, or a file found from here, is kept as an absolute reference; any other name is looked up
    # among the package's models (resolve_source)
    found = not str(model_file).startswith("package://") and path.expanduser().is_file()
    model = {"family": "multibody", "file": str(path.expanduser().resolve()) if found else str(model_file)}
    if actuated_joints is not None:
        model["actuated_joints"] = list(actuated_joints)
    if tip_body is not None:
        model["tip_body"] = tip_body
        model["tip_point"] = entry(list(tip_point if tip_point is not None else (0.0, 0.0, 0.0)), "from_drake argument")
    doc = {
        "system": {"name": name or stem[:64], "description": f"from_drake({model_file!r})"},
        "model": model,
        "state": {"goal": entry(goal, "from_drake argument")},
        "action": {} if action_limit is None else {"limit": entry(float(action_limit), "from_drake argument")},
        "integrator": {"method": entry("euler"), "dt": entry(0.01)},
        "control": {"period": entry(0.01), "swingup_period": entry(0.1)},
        "episode": {"duration": entry(10.0)},
        "reward": {"kind": entry("angle_cosine")},
        "initial_state": {"distribution": "uniform", "nominal": entry(nominal),
                          "low": entry(np.zeros_like(goal)), "high": entry(np.zeros_like(goal))},
        "lqr": {"Q": entry(np.atleast_2d(np.asarray(Q, dtype=float)), "from_drake argument"),
                "R": entry(np.atleast_2d(np.asarray(R, dtype=float)), "from_drake argument")},
        "success": {"eps": entry(0.1), "lookback": entry(10)},
        "gate": {"on": entry(0.9), "off": entry(0.5), "cost_scale": entry(1.0)},
    }
    if gravity is not None:
        doc["params"] = {"gravity": entry(float(gravity), "from_drake argument")}
    for full, (value, source) in (settings or {}).items():
        section, key = full.split(".", 1)
        doc.setdefault(section, {})[key] = entry(np.asarray(value) if isinstance(value, (list, tuple)) else value,
                                                 str(source))
    base = Path(model["file"]) if found else Path.cwd() / path.name   # where errors say the values come from
    return System(spec_from_document(doc, base, **overrides))


def nearest_equilibrium(system_or_model, x, *, tolerance: float = GOAL_TOLERANCE, check_drake: bool = True):
    """The equilibrium (u = 0) nearest to state ``x``: ``(x_eq, distance)``, the max-norm of the move.

    ``system_or_model``: a :class:`System`, a spec name or path (:func:`load`), or a URDF/SDF/MJCF file
    (:func:`from_drake`, built with ``goal = x``). Solves qdd(q, v = 0, u = 0) = 0 from the given q on
    the generated dynamics (Levenberg-Marquardt) and checks the answer on Drake's plant. Raises
    :class:`EquilibriumError` (one line) where none lies within ``tolerance``. A system's goal within
    ``GOAL_TOLERANCE`` (1e-2) of an equilibrium is moved there when it is built, with one warning.
    """
    system = system_or_model
    if not isinstance(system, System):
        ref = str(system_or_model)
        if ref.lower().endswith((".urdf", ".sdf", ".xml")):
            import warnings
            from .symbolic import ModelRequest, load_model, resolve_source
            n = np.asarray(x, dtype=float).size
            n_u = load_model(ModelRequest(source=resolve_source(ref))).n_u      # cached: from_drake reads it again
            with warnings.catch_warnings():     # its goal is x, moved or not: the caller gets the answer instead
                warnings.simplefilter("ignore")
                system = from_drake(ref, goal=x, Q=np.eye(n), R=np.eye(n_u), action_limit=1.0)
        else:
            system = load(ref)
    return equilibrium.nearest_equilibrium(system, x, tolerance=tolerance, check_drake=check_drake)
