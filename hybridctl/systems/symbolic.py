"""From a URDF/SDF file to a :class:`~hybridctl.systems.multibody.MultibodyModel` through Drake.

Drake parses the file into a continuous-time ``MultibodyPlant`` and its symbolic twin
(``ToSymbolic``) writes M(q), C(q, v) v, tau_g(q), the energies and the tip point's position
as ``pydrake.symbolic.Expression``s. ``pydrake.symbolic.to_sympy`` hands them to sympy, where
sin q_i and cos q_i become variables s_i, c_i, every float becomes the exact rational it
stands for, and each entry is reduced modulo s_i^2 + c_i^2 - 1 (a Groebner basis: the
remainder is canonical, of degree <= 1 in each s_i). The result is a polynomial with a
handful of terms per entry (the acrobot's M_00 is 2.663 + 2 c_1), converted back to floats.

Imported only when a multibody system is built (pydrake and sympy are heavy). The result is
cached as JSON (:func:`cache_folder`), keyed by a hash of the model file's bytes and every
setting that changes it; a cache file is read as data and checked, never executed.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .. import io
from ..limits import MAX_DERIVE_SECONDS, MAX_MODEL_BYTES, MAX_MODEL_INERTIA, MAX_MODEL_LENGTH, MAX_MODEL_MASS
from . import model_files
from . import model_check
from .multibody import MAX_JOINTS, MAX_TERMS, ModelError, MultibodyModel

CACHE_ENV = "HYBRIDCTL_CACHE"
"""Environment variable: the folder of hybridctl's caches (default ``~/.cache/hybridctl``)."""

MAX_EXPRESSION_CHARS = 5_000_000
"""Most characters of Drake's symbolic expressions (M, C v, tau_g, energies, tip) that are handed
to sympy: above it the reduction takes minutes and the generated code would be too large to run
fast. The 2-link acrobot's are about 4,000 characters."""

FORMAT = 3  # bumped when the model record or the reduction changes, so old cache files are not used
SUPPORTED_JOINTS = ("revolute", "prismatic", "weld")


@dataclass(frozen=True)
class ModelRequest:
    """Everything that determines a generated model: the file and the spec's choices."""

    source: str                    # a file path or a package://drake/ URL
    actuated: tuple[str, ...] = ()  # joint names in action order; () = every JointActuator, in model order
    gravity: float | None = None   # m/s^2 along -z; None = Drake's default 9.81
    tip_body: str | None = None    # body whose point ``tip_point`` is the tip (tip-height rewards)
    tip_point: tuple[float, float, float] = (0.0, 0.0, 0.0)


def resolve_source(ref: str, base: Path | None = None) -> str:
    """The file path or URL Drake reads for the spec's ``model.file`` value ``ref``.

    ``package://drake/...``: pydrake's own models (``package://drake_models`` downloads from
    the internet and is refused). Otherwise a path: absolute, or relative to ``base`` (the
    spec's folder), else inside the package's ``models/`` folder.
    """
    from .spec import MODELS_DIR

    if ref.startswith("package://"):
        if not ref.startswith("package://drake/"):
            raise ModelError(f"model file {ref!r}: only package://drake/ URLs (pydrake's own models) can be "
                             f"read offline; give a path to a file instead")
        return ref
    path = Path(ref).expanduser()
    candidates = [path] if path.is_absolute() else [*(([base / path]) if base else []), MODELS_DIR / path]
    for candidate in candidates:
        if candidate.is_file():
            return str(candidate.resolve())
        if candidate.exists():   # a FIFO, a device, a folder: never opened
            model_files.regular_file(candidate, MAX_MODEL_BYTES, f"model file {ref!r} ({candidate})")
    where = " or ".join(str(c) for c in candidates)
    raise ModelError(f"model file {ref!r}: no such file ({where})")


def _packages() -> dict[str, str]:
    """The packages a model may name files in (``package://NAME/``): pydrake's own models only."""
    from pydrake.multibody.parsing import PackageMap
    return {"drake": PackageMap().GetPath("drake")}


def _source_path(source: str) -> Path:
    if source.startswith("package://"):
        package, _, rest = source[len("package://"):].partition("/")
        return Path(_packages()[package]) / rest
    return Path(source)


def _file_bytes(source: str) -> bytes:
    """The model file's bytes (for the cache key): a regular file, its size checked before and while reading."""
    try:
        return model_files.read_bounded(_source_path(source), MAX_MODEL_BYTES, f"model file {source}")
    except ModelError as exc:
        raise ModelError(f"{exc} (hybridctl.limits.MAX_MODEL_BYTES)" if "above the limit" in str(exc)
                         else str(exc)) from None


def scan_files(request: ModelRequest) -> model_files.ModelScan:
    """Check every file the model names before Drake opens any (:func:`~hybridctl.systems.model_files.scan_model`)."""
    return model_files.scan_model(_source_path(request.source), _packages())


def parse_plant(request: ModelRequest, plant=None):
    """A finalized continuous-time MultibodyPlant of the model (``plant``: one to fill, e.g. from
    ``AddMultibodyPlantSceneGraph``), its structure checked; ModelError names the file and what to change.
    Every file the model names is checked first (:func:`scan_files`): Drake opens them."""
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    scan_files(request)
    plant = MultibodyPlant(0.0) if plant is None else plant
    parser = Parser(plant)
    try:
        if request.source.startswith("package://"):
            parser.AddModels(url=request.source)
        else:
            parser.AddModels(file_name=request.source)
    except RuntimeError as exc:  # the parser's own message names the file and line
        raise ModelError(f"model file {request.source} does not parse: {_first_lines(str(exc))}") from None
    if request.gravity is not None:
        plant.mutable_gravity_field().set_gravity_vector([0.0, 0.0, -float(request.gravity)])
    plant.Finalize()
    check_structure(plant, request)
    model_check.warn_unenforced(plant, request.source)
    return plant


def _first_lines(text: str, count: int = 3) -> str:
    return " ".join(line.strip() for line in text.strip().splitlines()[:count])


def check_structure(plant, request: ModelRequest) -> None:
    """Refuse what the generated dynamics cannot express, naming the joint or the file."""
    src = request.source
    if plant.num_positions() != plant.num_velocities():
        floating = [plant.get_body(b).name() for b in plant.GetFloatingBaseBodies()] \
            if hasattr(plant, "GetFloatingBaseBodies") else []
        raise ModelError(f"model file {src}: has a floating base or a quaternion joint "
                         f"({plant.num_positions()} positions, {plant.num_velocities()} velocities"
                         f"{'; free bodies: ' + ', '.join(floating) if floating else ''}); weld the root link to "
                         f"'world' (a <joint type=\"fixed\">) and use revolute or prismatic joints")
    for index in range(plant.num_joints()):
        joint = plant.get_joint(_joint_index(index))
        kind = joint.type_name()
        if kind not in SUPPORTED_JOINTS:
            raise ModelError(f"model file {src}: joint {joint.name()!r} is of type {kind!r}; the generated "
                             f"dynamics support {', '.join(SUPPORTED_JOINTS)} joints (a floating base or a "
                             f"ball joint has no such coordinates: weld it, or split it into revolute joints)")
    n = plant.num_positions()
    if n == 0:
        raise ModelError(f"model file {src}: has no joint coordinates (nothing moves)")
    if n > MAX_JOINTS:
        raise ModelError(f"model file {src}: {n} joint coordinates, above the limit of {MAX_JOINTS} "
                         f"(hybridctl.systems.multibody.MAX_JOINTS)")
    if plant.num_actuators() == 0:
        raise ModelError(f"model file {src}: has no actuators; add a <transmission> (URDF) or a joint "
                         f"<limit><effort> > 0 (SDF) for each actuated joint")
    check_physics(plant, request)


def check_physics(plant, request: ModelRequest) -> None:
    """Refuse numbers no robot has, before code is generated from them: a body's mass (finite, >= 0, at
    most :data:`~hybridctl.limits.MAX_MODEL_MASS`) and inertia (physically valid: positive semidefinite,
    triangle inequality; moments at most MAX_MODEL_INERTIA), every fixed frame offset (joint origins;
    |x| at most MAX_MODEL_LENGTH), finite joint limits and damping, and a positive definite mass matrix."""
    from pydrake.multibody.tree import FrameIndex, JointActuatorIndex

    src = request.source
    for i in range(1, plant.num_bodies()):
        body = plant.get_body(_body_index(i))
        mass = float(body.default_mass())
        if not (np.isfinite(mass) and 0.0 <= mass <= MAX_MODEL_MASS):
            raise ModelError(f"model file {src}: body {body.name()!r} has mass {mass:g} kg; a mass must be finite, "
                             f">= 0 and at most {MAX_MODEL_MASS:g} kg (hybridctl.limits.MAX_MODEL_MASS)")
        inertia = np.asarray(body.default_rotational_inertia().CopyToFullMatrix3())
        if not np.isfinite(inertia).all() or not np.isfinite(np.asarray(body.default_com())).all():
            raise ModelError(f"model file {src}: body {body.name()!r} has a non-finite inertia or centre of mass")
        moments = np.linalg.eigvalsh((inertia + inertia.T) / 2)
        if not body.default_spatial_inertia().IsPhysicallyValid() or moments.max() > MAX_MODEL_INERTIA:
            raise ModelError(f"model file {src}: body {body.name()!r} has principal moments of inertia "
                             f"{', '.join(f'{m:g}' for m in moments)} kg m^2 (about its origin); an inertia must be "
                             f"positive semidefinite, obey the triangle inequality (each moment at most the sum of "
                             f"the other two) and be at most {MAX_MODEL_INERTIA:g} (hybridctl.limits.MAX_MODEL_INERTIA)")
    for i in range(plant.num_frames()):
        frame = plant.get_frame(FrameIndex(i))
        offset = np.asarray(frame.GetFixedPoseInBodyFrame().translation())
        if not (np.isfinite(offset).all() and np.abs(offset).max() <= MAX_MODEL_LENGTH):
            raise ModelError(f"model file {src}: frame {frame.name()!r} (of body {frame.body().name()!r}) is at "
                             f"{offset.tolist()} m; an offset (a joint origin) must be finite and at most "
                             f"{MAX_MODEL_LENGTH:g} m (hybridctl.limits.MAX_MODEL_LENGTH)")
    for index in range(plant.num_joints()):
        joint = plant.get_joint(_joint_index(index))
        values = [*joint.position_lower_limits(), *joint.position_upper_limits(), *joint.velocity_lower_limits(),
                  *joint.velocity_upper_limits(), *np.atleast_1d(joint.default_damping_vector())]
        if any(np.isnan(values)) or not np.isfinite(np.atleast_1d(joint.default_damping_vector())).all():
            raise ModelError(f"model file {src}: joint {joint.name()!r} has a NaN limit or a non-finite damping")
    for i in range(plant.num_actuators()):
        actuator = plant.get_joint_actuator(JointActuatorIndex(i))
        if np.isnan(actuator.effort_limit()) or actuator.effort_limit() <= 0:
            raise ModelError(f"model file {src}: actuator {actuator.name()!r} has effort limit "
                             f"{actuator.effort_limit():g}; it must be > 0 (inf: none)")
    context = plant.CreateDefaultContext()
    M = plant.CalcMassMatrix(context)
    lowest = np.linalg.eigvalsh(M).min() if np.isfinite(M).all() else np.nan
    if not lowest > 1e-12 * max(1.0, float(np.abs(M).max())):
        raise ModelError(f"model file {src}: its mass matrix at q = 0 is singular or not positive definite "
                         f"(lowest eigenvalue {lowest:g}): a moving body without mass or inertia")


def _joint_index(i: int):
    from pydrake.multibody.tree import JointIndex
    return JointIndex(i)


def actuator_selection(plant, request: ModelRequest) -> tuple[np.ndarray, tuple[str, ...]]:
    """(S, joint names): Drake's actuation vector is S u for our action u (one column per action)."""
    from pydrake.multibody.tree import JointActuatorIndex

    actuators = [plant.get_joint_actuator(JointActuatorIndex(i)) for i in range(plant.num_actuators())]
    by_joint = {a.joint().name(): k for k, a in enumerate(actuators)}
    names = request.actuated or tuple(a.joint().name() for a in actuators)
    selection = np.zeros((len(actuators), len(names)))
    for column, name in enumerate(names):
        if name not in by_joint:
            raise ModelError(f"model file {request.source}: model.actuated_joints names {name!r}, which has no "
                             f"actuator; joints with one: {', '.join(sorted(by_joint)) or 'none'}")
        selection[by_joint[name], column] = 1.0
    if len(set(names)) != len(names):
        raise ModelError(f"model file {request.source}: model.actuated_joints names a joint twice: {list(names)}")
    return selection, tuple(names)


def effort_limits(plant, request: ModelRequest) -> np.ndarray:
    """The effort limits of the actuated joints' actuators (inf where the model sets none)."""
    from pydrake.multibody.tree import JointActuatorIndex

    selection, _ = actuator_selection(plant, request)
    limits = np.array([plant.get_joint_actuator(JointActuatorIndex(i)).effort_limit()
                       for i in range(plant.num_actuators())])
    return selection.T @ limits


def coordinates(plant) -> tuple[list[str], list[bool], np.ndarray]:
    """Names of the positions (joint names), whether each is an angle, and each velocity's damping."""
    names = [""] * plant.num_positions()
    revolute = [False] * plant.num_positions()
    damping = np.zeros(plant.num_velocities())
    for index in range(plant.num_joints()):
        joint = plant.get_joint(_joint_index(index))
        if joint.num_positions() == 0:
            continue
        names[joint.position_start()] = joint.name()
        revolute[joint.position_start()] = joint.type_name() == "revolute"
        damping[joint.velocity_start()] = float(joint.default_damping())
    return names, revolute, damping


# ============================================================================ symbolic -> polynomials
def derive(request: ModelRequest) -> MultibodyModel:
    """The model's polynomial equations from Drake's symbolic plant (no cache; see :func:`load_model`)."""
    with _Deadline(request.source, MAX_DERIVE_SECONDS) as deadline:
        return _derive(request, deadline)


class _Deadline:
    """The wall-time limit of one derivation: :meth:`check` between stages and entries, and (in the main
    thread, where no other timer is set) a SIGALRM that interrupts sympy mid-entry. ModelError names it."""

    def __init__(self, source: str, seconds: float):
        self.source, self.seconds = source, float(seconds)
        self.started = time.perf_counter()
        self.previous = None

    def __enter__(self) -> "_Deadline":
        import signal
        import threading
        if (hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()
                and signal.getitimer(signal.ITIMER_REAL)[0] == 0
                and signal.getsignal(signal.SIGALRM) in (signal.SIG_DFL, signal.SIG_IGN, None)
                and 0 < self.seconds < float("inf")):
            self.previous = signal.signal(signal.SIGALRM, lambda *_: self.fail())
            signal.setitimer(signal.ITIMER_REAL, self.seconds)
        return self

    def __exit__(self, *exc) -> None:
        if self.previous is not None:
            import signal
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self.previous)

    def check(self) -> None:
        if time.perf_counter() - self.started > self.seconds:
            self.fail()

    def fail(self):
        raise ModelError(f"model file {self.source}: deriving its equations took more than {self.seconds:g} s "
                         f"(hybridctl.limits.MAX_DERIVE_SECONDS): too large to generate code for; fewer joints "
                         f"or bodies would do")


def _derive(request: ModelRequest, deadline: _Deadline) -> MultibodyModel:
    import sympy
    from pydrake.symbolic import MakeVectorVariable, to_sympy

    started = deadline.started
    plant = parse_plant(request)
    deadline.check()
    selection, actuated = actuator_selection(plant, request)
    names, revolute, damping = coordinates(plant)
    n = plant.num_positions()
    symbolic = plant.ToSymbolic()
    context = symbolic.CreateDefaultContext()
    q, v = MakeVectorVariable(n, "q"), MakeVectorVariable(n, "v")
    symbolic.SetPositions(context, q)
    symbolic.SetVelocities(context, v)
    size = [0]

    def measured(new: list) -> list:
        """``new``, its characters counted towards MAX_EXPRESSION_CHARS as Drake makes them: a large model is
        refused before Drake's next, larger stage (a 12-joint chain's kinetic energy alone takes minutes)."""
        for entry in new:
            size[0] += len(entry.to_string())
            if size[0] > MAX_EXPRESSION_CHARS:
                raise ModelError(f"model file {request.source}: Drake's symbolic equations have {size[0]:,} "
                                 f"characters, above the limit of {MAX_EXPRESSION_CHARS:,} (hybridctl.systems."
                                 f"symbolic.MAX_EXPRESSION_CHARS): too large to generate code for; fewer joints or "
                                 f"bodies would do")
        deadline.check()
        return list(new)

    M = symbolic.CalcMassMatrix(context)
    deadline.check()
    entries = measured([M[i, k] for i in range(n) for k in range(i, n)])
    entries += measured([*symbolic.CalcBiasTerm(context), *symbolic.CalcGravityGeneralizedForces(context)])
    entries += measured([symbolic.CalcKineticEnergy(context), symbolic.CalcPotentialEnergy(context)])
    if request.tip_body is not None:
        if not symbolic.HasBodyNamed(request.tip_body):
            bodies = sorted(plant.get_body(_body_index(i)).name() for i in range(1, plant.num_bodies()))
            raise ModelError(f"model file {request.source}: model.tip_body {request.tip_body!r} is not a body of "
                             f"the model; its bodies: {', '.join(bodies)}")
        body = symbolic.GetBodyByName(request.tip_body)
        point = np.asarray(request.tip_point, dtype=float).reshape(3, 1)
        tip = symbolic.CalcPointsPositions(context, body.body_frame(), point, symbolic.world_frame())
        entries += measured([tip[k, 0] for k in range(3)])
    # every moving body's origin in the world (drawings, view boxes) and its parent body
    moving = [plant.get_body(_body_index(i)) for i in range(1, plant.num_bodies())]
    moving = [b for b in moving if not _welded_to_world(plant, b)]
    body_names = [b.name() for b in moving]
    parents = []
    for body in moving:
        parent = _parent_body(plant, body)
        parents.append(body_names.index(parent) if parent in body_names else -1)
    n_tip = len(entries) - (n * (n + 1) // 2 + 2 * n + 2)
    origin = np.zeros((3, 1))
    for body in moving:
        where = symbolic.CalcPointsPositions(context, symbolic.GetBodyByName(body.name()).body_frame(), origin,
                                             symbolic.world_frame())
        entries += measured([where[k, 0] for k in range(3)])
    size = size[0]
    s, c = sympy.symbols(f"s0:{n}"), sympy.symbols(f"c0:{n}")
    qs, vs = sympy.symbols(f"q0:{n}"), sympy.symbols(f"v0:{n}")
    memo = {**{q[i].get_id(): qs[i] for i in range(n)}, **{v[i].get_id(): vs[i] for i in range(n)}}
    trig = {**{sympy.sin(qs[i]): s[i] for i in range(n)}, **{sympy.cos(qs[i]): c[i] for i in range(n)}}
    generators = (*s, *c, *qs, *vs)
    circle = [s[i] ** 2 + c[i] ** 2 - 1 for i in range(n) if revolute[i]]
    polys, count = [], 0
    for index, entry in enumerate(entries):
        deadline.check()
        polys.append(_polynomial(sympy, to_sympy(entry, memo=memo), trig, generators, circle, revolute, qs,
                                 request.source))
        count += len(polys[-1])
        if count > MAX_TERMS:
            raise ModelError(f"model file {request.source}: the equations have more than {MAX_TERMS:,} terms "
                             f"(hybridctl.systems.multibody.MAX_TERMS): too large to generate code for")
    n_mass = n * (n + 1) // 2
    B = plant.MakeActuationMatrix() @ selection
    first_body = n_mass + 2 * n + 2 + n_tip
    model = MultibodyModel(
        positions=tuple(names), velocities=tuple(f"{name}_dot" for name in names), actuators=actuated,
        revolute=tuple(revolute), mass=tuple(polys[:n_mass]), bias=tuple(polys[n_mass:n_mass + n]),
        gravity=tuple(polys[n_mass + n:n_mass + 2 * n]), kinetic=polys[n_mass + 2 * n],
        potential=polys[n_mass + 2 * n + 1], tip=tuple(polys[n_mass + 2 * n + 2:first_body]),
        bodies=tuple(body_names), body_parents=tuple(parents), body_origins=tuple(polys[first_body:]),
        actuation=tuple(tuple(float(b) for b in row) for row in B), damping=tuple(float(d) for d in damping),
        info={"generation_seconds": time.perf_counter() - started, "terms": count, "expression_chars": size,
              # None where the model sets no limit (JSON has no infinity)
              "effort_limits": [float(e) if np.isfinite(e) else None for e in effort_limits(plant, request)],
              **({"tip_body_index": body_names.index(request.tip_body)} if request.tip_body in body_names else {})})
    return model


def _welded_to_world(plant, body) -> bool:
    """Whether ``body`` is fixed to the world (welds all the way down): it never moves."""
    while True:
        joint = _inboard_joint(plant, body)
        if joint is None:
            return True
        if joint.num_positions() > 0:
            return False
        body = joint.parent_body()
        if body.index() == plant.world_body().index():
            return True


def _inboard_joint(plant, body):
    for index in range(plant.num_joints()):
        joint = plant.get_joint(_joint_index(index))
        if joint.child_body().index() == body.index():
            return joint
    return None


def _parent_body(plant, body) -> str | None:
    """The name of the nearest moving ancestor of ``body`` (None: the world or a welded base)."""
    joint = _inboard_joint(plant, body)
    while joint is not None:
        parent = joint.parent_body()
        if parent.index() == plant.world_body().index() or _welded_to_world(plant, parent):
            return None
        return parent.name()
    return None


def _body_index(i: int):
    from pydrake.multibody.tree import BodyIndex
    return BodyIndex(i)


def _polynomial(sympy, expression, trig, generators, circle, revolute, qs, source) -> tuple:
    """One entry as terms (float coefficient, exponents): exact rationals, reduced modulo the circles."""
    expression = expression.xreplace(trig)
    expression = expression.xreplace({f: sympy.Rational(float(f)) for f in expression.atoms(sympy.Float)})
    leftover = [qs[i] for i in range(len(qs)) if revolute[i] and expression.has(qs[i])]
    try:
        if leftover:
            raise sympy.PolynomialError(f"{leftover} outside sin/cos")
        if circle:
            _, expression = sympy.reduced(expression, circle, *generators, order="lex", domain="QQ")
        poly = sympy.Poly(expression, *generators, domain="QQ")
    except (sympy.PolynomialError, sympy.polys.polyerrors.GeneratorsError, sympy.polys.polyerrors.CoercionFailed) as exc:
        raise ModelError(f"model file {source}: an equation is not a polynomial in sin q, cos q, q and v "
                         f"({str(exc).splitlines()[0][:200]}); the generated dynamics cannot express it") from None
    return tuple((float(coefficient), tuple(int(k) for k in exponents))
                 for exponents, coefficient in poly.terms() if coefficient != 0)


# ============================================================================ the cache
def cache_folder() -> Path:
    """Where generated models are cached: ``$HYBRIDCTL_CACHE/multibody`` or ``~/.cache/hybridctl/multibody``."""
    root = os.environ.get(CACHE_ENV) or os.path.join(os.path.expanduser("~"), ".cache", "hybridctl")
    return Path(root) / "multibody"


def model_hash(request: ModelRequest) -> str:
    """sha256 of the model file's bytes: what a checkpoint records to notice a changed model."""
    return hashlib.sha256(_file_bytes(request.source)).hexdigest()


def cache_key(request: ModelRequest, file_hash: str | None = None) -> str:
    """The cache key: the model file's bytes (``file_hash``, :func:`model_hash`; read when not given), its
    location, every setting, the format and Drake's version."""
    import pydrake
    settings = {"format": FORMAT, "source": request.source, "actuated": list(request.actuated),
                "gravity": request.gravity, "tip_body": request.tip_body, "tip_point": list(request.tip_point),
                "file": file_hash or model_hash(request), "drake": getattr(pydrake, "__version__", "")}
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:32]


def load_model(request: ModelRequest, use_cache: bool = True) -> MultibodyModel:
    """The generated model of ``request``: from the cache when it holds it, else derived and cached.

    ``info`` says ``cached``, ``generation_seconds`` (of the derivation, when it ran now) and
    ``file_sha256`` (:func:`model_hash`, read once here). A cache entry is read as data with every
    size checked before it is used (``model_check.read_cache_entry``), then compared with Drake's float
    MultibodyPlant of the same request at random states (:func:`check_against_drake`, about 1 ms);
    an entry that fails either is derived anew and replaced, with a one-line warning.
    """
    file_hash = model_hash(request)
    key = cache_key(request, file_hash)
    path = cache_folder() / f"{key}.json"
    if use_cache and path.is_file():
        plant = parse_plant(request)      # outside the try: a bad model file is the user's error, not the cache's
        try:
            model = model_check.read_cache_entry(path)
            check_against_drake(model, plant, request)
            return _with_info(model, cached=True, cache_file=str(path), key=key, file_sha256=file_hash)
        except model_check.CACHE_ERRORS as exc:
            reason = str(exc).splitlines()[0][:300] if isinstance(exc, ModelError) else \
                f"{type(exc).__name__}: {(str(exc).splitlines() or [''])[0][:200]}"
            warnings.warn(f"model cache {path}: {reason}; derived anew from {request.source}", UserWarning,
                          stacklevel=2)
    model = derive(request)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        io.write_json(path, model.to_json())
    except OSError:  # a read-only home: generate every time
        pass
    return _with_info(model, cached=False, cache_file=str(path), key=key, file_sha256=file_hash)


def check_against_drake(model: MultibodyModel, plant, request: ModelRequest, rng=None) -> None:
    """Raise ModelError unless ``model`` is what :func:`derive` makes of ``request``: the structure (names,
    angles, B, damping, effort limits, bodies) equal to ``plant``'s (:func:`parse_plant`), and M, C v,
    tau_g, the energies, the tip and the body origins equal to Drake's float values at :data:`CHECK_STATES`
    states drawn afresh each time (:func:`~hybridctl.systems.model_check.check_values`)."""
    selection, actuated = actuator_selection(plant, request)
    names, revolute, damping = coordinates(plant)
    moving = [b for b in (plant.get_body(_body_index(i)) for i in range(1, plant.num_bodies()))
              if not _welded_to_world(plant, b)]
    bodies = tuple(b.name() for b in moving)
    parents = tuple(bodies.index(p) if p in bodies else -1 for p in (_parent_body(plant, b) for b in moving))
    efforts = tuple(float(e) for e in effort_limits(plant, request))
    structure = {"positions": tuple(names), "velocities": tuple(f"{x}_dot" for x in names), "actuators": actuated,
                 "revolute": tuple(revolute), "damping": tuple(float(d) for d in damping), "bodies": bodies,
                 "body_parents": parents, "effort limits": efforts, "tip points": 3 if request.tip_body else 0,
                 "actuation": tuple(tuple(float(b) for b in row) for row in plant.MakeActuationMatrix() @ selection)}
    found = {**{k: getattr(model, k) for k in structure if hasattr(model, k)}, "effort limits": model.effort,
             "tip points": len(model.tip)}
    for key, value in structure.items():
        if found[key] != value:
            raise ModelError(f"its {key} {str(found[key])[:80]} are not Drake's {str(value)[:80]}")
    if request.tip_body is not None and not plant.HasBodyNamed(request.tip_body):
        raise ModelError(f"its tip body {request.tip_body!r} is not a body of the model")
    if model.info.get("tip_body_index") != (bodies.index(request.tip_body) if request.tip_body in bodies else None):
        raise ModelError(f"its tip_body_index is not that of body {request.tip_body!r}")
    model_check.check_values(model, plant, revolute, moving, request.tip_body, request.tip_point, rng)


def _with_info(model: MultibodyModel, **info) -> MultibodyModel:
    from dataclasses import replace
    return replace(model, info={**model.info, **info})
