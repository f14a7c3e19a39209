"""Reading a generated-model cache entry and checking it against Drake (a cache file, edited or
stale, must not change the physics).

:func:`read_cache_entry` reads ``$HYBRIDCTL_CACHE/multibody/KEY.json`` with its size and nesting checked on the
bytes before they are parsed, then every count, length and number (``MultibodyModel.from_json``).
:func:`check_values` compares its polynomials with Drake's float MultibodyPlant of the same model at random
states; ``symbolic.check_against_drake`` compares its structure first and calls it. Neither imports pydrake:
the plant comes in as an argument.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from ..limits import MAX_MODEL_CACHE_BYTES, MAX_MODEL_CACHE_DEPTH
from .multibody import ModelError, MultibodyModel

CACHE_ERRORS = (ValueError, OSError, ArithmeticError, RecursionError, TypeError, KeyError, IndexError, MemoryError,
                RuntimeError)
"""What reading or checking a cache entry may raise on odd data (ModelError is a ValueError; json's errors
too; OverflowError and ZeroDivisionError are ArithmeticErrors; Drake's are RuntimeErrors): derived anew."""

_JSON_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')


def read_cache_entry(path: Path) -> MultibodyModel:
    """A cache file as a :class:`MultibodyModel`, its size and nesting checked on the bytes before they are
    parsed (:data:`~hybridctl.limits.MAX_MODEL_CACHE_BYTES`, :data:`~hybridctl.limits.MAX_MODEL_CACHE_DEPTH`),
    then every count, length and number (``MultibodyModel.from_json``); ModelError says what is wrong."""
    size = path.stat().st_size
    if size > MAX_MODEL_CACHE_BYTES:
        raise ModelError(f"{size:,} bytes, above the limit of {MAX_MODEL_CACHE_BYTES:,} "
                         f"(hybridctl.limits.MAX_MODEL_CACHE_BYTES)")
    data = path.read_bytes()[:MAX_MODEL_CACHE_BYTES]
    codes = np.frombuffer(_JSON_STRING.sub(b'""', data), dtype=np.uint8)   # brackets inside strings do not nest
    depth = np.cumsum((codes == ord("[")).astype(np.int32) + (codes == ord("{")) - (codes == ord("]"))
                      - (codes == ord("}")))
    if depth.size and depth.max() > MAX_MODEL_CACHE_DEPTH:
        raise ModelError(f"nests {int(depth.max()):,} deep, above the limit of {MAX_MODEL_CACHE_DEPTH} "
                         f"(hybridctl.limits.MAX_MODEL_CACHE_DEPTH)")
    return MultibodyModel.from_json(json.loads(data), where="the entry")


CHECK_STATES = 3
"""Random states at which a cache entry is compared with Drake's plant."""
CHECK_RTOL, CHECK_ATOL = 1e-9, 1e-12
"""A cache entry's values may differ from Drake's by CHECK_RTOL times the largest of Drake's values of the
same kind (mass matrix, bias, gravity, energies, points) plus CHECK_ATOL: rounding is ~1e-15 of it."""


def check_values(model: MultibodyModel, plant, revolute, moving, tip_body: str | None, tip_point, rng=None) -> None:
    """Raise ModelError unless ``model``'s polynomials have the degrees Drake's equations have and equal
    ``plant``'s M, C v, tau_g, energies, tip point (of ``tip_body``, if any) and origins of the ``moving`` bodies
    at :data:`CHECK_STATES` states drawn afresh each time (fixed states could be matched by a tampered entry)."""
    n = len(revolute)
    _check_degrees(model, revolute)
    rng = np.random.default_rng() if rng is None else rng
    q = np.where(revolute, rng.uniform(-np.pi, np.pi, (CHECK_STATES, n)), rng.uniform(-1, 1, (CHECK_STATES, n)))
    v = rng.uniform(-3, 3, (CHECK_STATES, n))
    context = plant.CreateDefaultContext()
    body = plant.GetBodyByName(tip_body) if tip_body is not None else None
    drake = {"mass matrix entries": [], "bias terms": [], "gravity terms": [], "energies": [], "points": []}
    for qs, vs in zip(q, v):
        plant.SetPositions(context, qs)
        plant.SetVelocities(context, vs)
        M = plant.CalcMassMatrix(context)
        drake["mass matrix entries"].append([M[i, k] for i in range(n) for k in range(i, n)])
        drake["bias terms"].append(plant.CalcBiasTerm(context))
        drake["gravity terms"].append(plant.CalcGravityGeneralizedForces(context))
        drake["energies"].append([plant.CalcKineticEnergy(context), plant.CalcPotentialEnergy(context)])
        tip = [] if body is None else plant.CalcPointsPositions(
            context, body.body_frame(), np.reshape(tip_point, (3, 1)), plant.world_frame())[:, 0]
        drake["points"].append([*tip, *(x for b in moving for x in plant.EvalBodyPoseInWorld(context, b).translation())])
    ours = {"mass matrix entries": model.mass, "bias terms": model.bias, "gravity terms": model.gravity,
            "energies": (model.kinetic, model.potential), "points": (*model.tip, *model.body_origins)}
    variables = np.concatenate([np.sin(q), np.cos(q), q, v], axis=1)
    for kind, polys in ours.items():
        expected = np.asarray(drake[kind], dtype=float).reshape(CHECK_STATES, -1)
        got = _evaluate(polys, variables)
        tolerance = CHECK_RTOL * (np.abs(expected).max(initial=0.0)) + CHECK_ATOL
        with np.errstate(all="ignore"):
            error = np.abs(got - expected).max(initial=0.0)
        if not error <= tolerance:       # NaN fails too
            raise ModelError(f"its {kind} differ from Drake's MultibodyPlant at a random state by {error:.3g} "
                             f"(tolerance {tolerance:.3g})")


def _check_degrees(model: MultibodyModel, revolute) -> None:
    """The degrees Drake's equations have, so that agreement at a few states is agreement everywhere (a tiny
    v^16 term would pass at the checked states and explode at fast ones): an angle q_i only through s_i, c_i,
    a prismatic q_i at most squared and never in a sine; v nowhere in M, tau_g, the potential energy and
    the points, and C v and the kinetic energy quadratic in v."""
    n = len(revolute)
    trig = [16 if r else 0 for r in revolute]            # |s|, |c| <= 1: any power stays bounded
    allowed = np.array(trig + trig + [0 if r else 2 for r in revolute] + [2] * n)
    groups = {"mass matrix entries": (model.mass, 0), "gravity terms": (model.gravity, 0),
              "energies": ((model.potential,), 0), "points": ((*model.tip, *model.body_origins), 0),
              "bias terms": (model.bias, 2), "kinetic energy": ((model.kinetic,), 2)}
    for kind, (polys, v_degree) in groups.items():
        exponents = np.array([e for p in polys for _, e in p], dtype=np.int64).reshape(-1, 4 * n)
        bad = (exponents > allowed).any(axis=1) | (exponents[:, 3 * n:].sum(axis=1) != v_degree)
        if bad.any():
            raise ModelError(f"its {kind} have a term of exponents {exponents[bad][0].tolist()} (s, c, q, v), "
                             f"which Drake's equations never have")


def _evaluate(polys, variables: np.ndarray) -> np.ndarray:
    """(states, polynomials): each polynomial of terms (coefficient, exponents) at each row of ``variables``."""
    lengths = [len(p) for p in polys]
    if not sum(lengths):
        return np.zeros((len(variables), len(polys)))
    coefficients = np.array([c for p in polys for c, _ in p], dtype=float)
    exponents = np.array([e for p in polys for _, e in p], dtype=np.int64)
    owner = np.repeat(np.arange(len(polys)), lengths)
    with np.errstate(all="ignore"):
        terms = coefficients * np.prod(variables[:, None, :] ** exponents[None], axis=2)
    return np.stack([np.bincount(owner, weights=row, minlength=len(polys)) for row in terms])


_WARNED: set[tuple[str, str]] = set()   # (model file, warning): each said once per process


def warn_unenforced(plant, source: str) -> None:
    """One warning line per model file (once per process) for what a model file states and neither engine applies:
    an actuator's gear ratio != 1 (MJCF ``gear``, URDF ``<mechanicalReduction>``: Drake keeps it for reflected
    rotor inertia only, applies u as joint torque and clamps it to the effort limit, as the generated dynamics do),
    and joint position limits (MJCF ``range``, URDF/SDF ``<limit lower upper>``: Drake's continuous-time plant
    does not enforce them, nor do the generated dynamics). Takes the finalized plant; imports no pydrake."""
    import warnings
    mjcf = source.lower().endswith(".xml")
    limit_word = "ctrlrange" if mjcf else "effort limit"
    gear_word = "gear" if mjcf else "mechanical reduction"
    range_word = "range" if mjcf else "<limit lower upper>"
    said = []
    for index in plant.GetJointActuatorIndices():
        actuator = plant.get_joint_actuator(index)
        gear = float(actuator.default_gear_ratio())
        if gear != 1.0:
            e = float(actuator.effort_limit())
            said.append(f"actuator {actuator.name()!r} ({gear_word}): gear {gear:g} is not applied: Drake and the "
                        f"generated dynamics apply u as joint torque within {limit_word} [{-e:g}, {e:g}]")
    for index in plant.GetJointIndices():
        joint = plant.get_joint(index)
        if joint.num_positions() != 1:
            continue
        low, high = float(joint.position_lower_limits()[0]), float(joint.position_upper_limits()[0])
        if np.isfinite(low) or np.isfinite(high):
            unit = "m" if joint.type_name() == "prismatic" else "rad"
            said.append(f"joint {joint.name()!r} ({range_word}) has position limits [{low:.6g}, {high:.6g}] {unit}; "
                        f"neither Drake's continuous plant nor the generated dynamics enforce them")
    for text in said:
        if (source, text) not in _WARNED:
            _WARNED.add((source, text))
            warnings.warn(f"model file {source}: {text}", UserWarning, stacklevel=4)
