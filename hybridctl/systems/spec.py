"""Loading and validating the declarative system specs in ``systems/*.toml``.

A spec value is either a plain TOML value or a table ``{ value = ..., source = ... }``
(optionally with ``units``). Angles may be written as strings of pi, e.g. ``"pi/2"``,
``"-pi"`` or ``"2*pi"``. Every value is validated here, and an error names the key
and the file, so a typo in a spec never reaches the dynamics.
"""

from __future__ import annotations

import math
import numbers
import os
import re
import tomllib
import warnings
from importlib import resources
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..limits import MAX_SIMULATION_STEPS, MAX_SPEC_BYTES, MAX_SPEC_FILES, MIN_DT
from .initial_state import InitialStateSection, warn_absolute_offsets

# Specs and robot models ship inside the package (``hybridctl/data``; the repository's top-level
# ``systems/`` and ``models/`` are links to them), so an installed wheel finds them.
DATA_DIR = Path(str(resources.files("hybridctl") / "data"))
SPEC_DIR = DATA_DIR / "systems"
MODELS_DIR = DATA_DIR / "models"
USER_SPEC_ENV = "HYBRIDCTL_SYSTEMS"
"""Environment variable: folders (separated by ``os.pathsep``) with more ``NAME.toml`` specs."""

INTEGRATORS = ("euler", "runge_kutta2")
REWARD_KINDS = ("tip_height", "quadratic", "tip_height_centered", "upright_centered")
# upright_centered (hybridctl, see System.reward) has the optional settings reward.position_scale and
# reward.speed_scale (> 0; default 1 m and 1 m/s)
CENTERED_REWARD_SETTINGS = ("reward.position_scale", "reward.speed_scale")
# thesis Ch. 7 (analytic policy gradients): see System.reward; their settings reward.alive_bonus,
# reward.velocity_penalty, reward.position_weight, reward.linear_velocity_weight and reward.cost_to_go_weight
# are optional (default 0) and >= 0
CH7_REWARD_KINDS = ("angle_squared", "angle_cosine", "tip_distance")
CH7_REWARD_SETTINGS = ("reward.alive_bonus", "reward.velocity_penalty", "reward.position_weight",
                       "reward.linear_velocity_weight", "reward.cost_to_go_weight")
REWARD_KINDS = REWARD_KINDS + CH7_REWARD_KINDS

SYSTEM_NAME = re.compile(r"[a-z0-9][a-z0-9_-]{0,63}")
"""A system's name (``system.name``, else the spec file's stem): it becomes part of file and folder
names and of records, so it is a plain identifier, never a path."""

PHYSICAL_RANGES = {
    # key: (lowest, highest, why): SI units. The dynamics and the LQR solve are well conditioned across
    # these ranges; outside them a typo (1e30 for 1e3) trains to nothing or overflows float64.
    "params.gravity": (0.0, 300.0, "m/s^2; the Sun's surface gravity is 274"),
    "params.link_mass": (1e-3, 1e4, "kg: 1 g to 10 t"),
    "params.cart_mass": (1e-3, 1e4, "kg: 1 g to 10 t"),
    "params.link_length": (1e-3, 100.0, "m: 1 mm to 100 m"),
    "params.link_com": (0.0, 100.0, "m from the joint"),
    "params.link_inertia": (0.0, 1e6, "kg m^2 about the centre of mass"),
    "params.joint_damping": (0.0, 1e4, "N m s/rad or N s/m"),
    "action.limit": (1e-6, 1e6, "N m or N"),
}
"""Plausible physical ranges of a spec's parameters (inclusive), each with why."""

_PI_EXPR = re.compile(r"^\s*(-)?\s*(?:(\d+(?:\.\d*)?)\s*\*\s*)?pi\s*(?:/\s*(\d+(?:\.\d*)?))?\s*$")


class SpecError(ValueError):
    """A system spec is missing a key or holds a value out of range."""


def spec_dirs() -> list[Path]:
    """Folders searched for ``NAME.toml``: those in ``$HYBRIDCTL_SYSTEMS`` first, then the shipped specs."""
    extra = [Path(p).expanduser() for p in os.environ.get(USER_SPEC_ENV, "").split(os.pathsep) if p]
    for folder in extra:
        if not folder.is_dir():
            raise SpecError(f"{USER_SPEC_ENV} names {folder}, which is not a folder")
    return [*extra, SPEC_DIR]


def spec_path(name: str) -> Path | None:
    """The spec file of system ``name`` (the first found in :func:`spec_dirs`), or None (also for no system name)."""
    if not SYSTEM_NAME.fullmatch(name):
        return None
    for folder in spec_dirs():
        path = folder / f"{name}.toml"
        if path.is_file():
            return path
    return None


def known_systems(strict: bool = True) -> list[str]:
    """Names of the systems with a spec file: the shipped ones and those in ``$HYBRIDCTL_SYSTEMS``.

    ``strict=False`` skips a ``$HYBRIDCTL_SYSTEMS`` entry that is not a folder instead of raising
    (the gymnasium registration at import time; loading a system still reports it).
    """
    try:
        folders = spec_dirs()
    except SpecError:
        if strict:
            raise
        folders = [SPEC_DIR]
    return sorted({name for folder in folders for name in _spec_names(folder)})


def _spec_names(folder: Path) -> list[str]:
    """The system names of the first MAX_SPEC_FILES ``*.toml`` files in ``folder``; a file whose stem is not a
    system name (``a b;rm -rf.toml``) is skipped with a warning, so it breaks no other system's command."""
    paths = sorted(folder.glob("*.toml"))[:MAX_SPEC_FILES]
    for path in (p for p in paths if not SYSTEM_NAME.fullmatch(p.stem)):   # warnings shows each message once
        warnings.warn(f"skipped spec file {path}: {path.stem!r} is not a system name ([a-z0-9][a-z0-9_-], at "
                      f"most 64 characters)", stacklevel=3)
    return [p.stem for p in paths if SYSTEM_NAME.fullmatch(p.stem)]


def parse_number(raw: Any, where: str) -> float:
    """Parse a number or a pi expression such as ``"-pi/2"``; ``where`` names the key."""
    if isinstance(raw, bool):
        raise SpecError(f"{where}: expected a number, got {raw!r}")
    if isinstance(raw, numbers.Real):
        if not math.isfinite(raw):
            raise SpecError(f"{where}: must be a finite number, got {raw!r}")
        return float(raw)
    if isinstance(raw, str):
        match = _PI_EXPR.match(raw)
        if match:
            sign = -1.0 if match.group(1) else 1.0
            factor = float(match.group(2)) if match.group(2) else 1.0
            divisor = float(match.group(3)) if match.group(3) else 1.0
            if divisor == 0.0:
                raise SpecError(f"{where}: divides by zero in {raw!r}; write a multiple of pi like 'pi/2'")
            value = sign * factor * math.pi / divisor
            if not math.isfinite(value):  # a factor of 400 digits
                raise SpecError(f"{where}: must be a finite number, got {raw!r}")
            return value
    raise SpecError(f"{where}: expected a number or a multiple of pi like 'pi/2', got {raw!r}")


def _parse_tree(raw: Any, where: str) -> Any:
    """Numbers, pi expressions and (nested) lists of them -> floats / float arrays."""
    if isinstance(raw, list):
        items = [_parse_tree(item, f"{where}[{i}]") for i, item in enumerate(raw)]
        try:
            return np.array(items, dtype=float)
        except ValueError:  # ragged: [[1], [1, 2]]
            raise SpecError(f"{where}: nested lists must all have the same length, got {raw!r}") from None
    return parse_number(raw, where)


@dataclass
class Spec:
    """A parsed spec: ``values`` maps 'section.key' to a parsed value, ``sources`` to its source."""

    name: str
    path: Path
    values: dict[str, Any]
    sources: dict[str, str] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    overrides: dict[str, Any] = field(default_factory=dict)
    overridden: dict[str, str] = field(default_factory=dict)  # full key -> "override k=v", for error messages

    def get(self, key: str, default: Any = ...) -> Any:
        """Value of 'section.key'; raises SpecError naming the file when missing."""
        if key in self.values:
            return self.values[key]
        if default is not ...:
            return default
        raise SpecError(f"{self.path}: missing required key '{key}'")

    def has(self, key: str) -> bool:
        """Whether 'section.key' is present."""
        return key in self.values

    def error(self, key: str, message: str) -> SpecError:
        """An error that names the key and where its value came from: the spec file, or an override."""
        if key in self.overridden:
            return SpecError(f"{self.overridden[key]} ('{key}' of {self.name}): {message}")
        return SpecError(f"{self.path}: '{key}' {message}")


_STRING_KEYS = {
    "system.name", "system.description", "system.source", "model.family", "model.base",
    "model.drake", "integrator.method", "reward.kind", "initial_state.distribution",
    "swingup.controller", "model.file", "model.tip_body",
}
_LIST_OF_STRING_KEYS = {"state.names", "action.names"}
_INT_LIST_KEYS = {"state.angles"}
_INT_OR_NAME_LIST_KEYS = {"model.actuated_joints"}  # chain: joint indices; multibody: joint names
FAMILIES = ("chain", "multibody")
MULTIBODY_PARAMS = ("params.gravity",)
"""The only [params] a multibody spec may set: the model file holds the rest of the physics."""
_INT_KEYS = {"success.lookback"}


def parse_value(full: str, entry: Any, where: str) -> Any:
    """One spec value, type-checked by its key: the same rules for the file and for overrides.

    ``where`` prefixes the error ("<file>: 'params.link_mass'" or "override link_mass=-1.0").
    """
    if full in _STRING_KEYS:
        if not isinstance(entry, str):
            raise SpecError(f"{where}: must be a string, got {entry!r}")
        return entry
    if full in _LIST_OF_STRING_KEYS:
        if not (isinstance(entry, (list, tuple)) and all(isinstance(s, str) for s in entry)):
            raise SpecError(f"{where}: must be a list of strings, got {entry!r}")
        return list(entry)
    if full in _INT_LIST_KEYS:
        if not (isinstance(entry, (list, tuple)) and all(isinstance(i, int) and not isinstance(i, bool)
                                                         for i in entry)):
            raise SpecError(f"{where}: must be a list of integers, got {entry!r}")
        return list(entry)
    if full in _INT_OR_NAME_LIST_KEYS:
        if isinstance(entry, (list, tuple)) and all(isinstance(s, str) for s in entry):
            return list(entry)
        if not (isinstance(entry, (list, tuple)) and all(isinstance(i, int) and not isinstance(i, bool)
                                                         for i in entry)):
            raise SpecError(f"{where}: must be a list of joint indices (chain) or joint names (multibody), "
                            f"got {entry!r}")
        return list(entry)
    if full in _INT_KEYS:
        if isinstance(entry, float) and entry.is_integer():
            entry = int(entry)
        if not isinstance(entry, int) or isinstance(entry, bool):
            raise SpecError(f"{where}: must be an integer, got {entry!r}")
        return entry
    if isinstance(entry, np.ndarray):
        entry = entry.tolist()
    if isinstance(entry, tuple):
        entry = list(entry)
    return _parse_tree(entry, where)


def _flatten(doc: dict, path: Path) -> Spec:
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    units: dict[str, str] = {}
    for section, table in doc.items():
        if not isinstance(table, dict):
            raise SpecError(f"{path}: top-level key '{section}' must be a [table]")
        for key, entry in table.items():
            full = f"{section}.{key}"
            if isinstance(entry, dict):
                if "value" not in entry:
                    raise SpecError(f"{path}: '{full}' is a table without 'value'")
                if "source" in entry:
                    sources[full] = str(entry["source"])
                if "units" in entry:
                    units[full] = str(entry["units"])
                entry = entry["value"]
            values[full] = parse_value(full, entry, f"{path}: '{full}'")
    return Spec(name=str(values.get("system.name", path.stem)), path=path, values=values,
                sources=sources, units=units)


def _apply_overrides(spec: Spec, overrides: dict[str, Any]) -> None:
    """Override values by 'section.key' or by a bare key that is unique across sections.

    Each value is type-checked like the file's (:func:`parse_value`) and must keep the
    file value's shape (a list stays a list of as many entries); :func:`validate` then
    range-checks it, and every error names the override, not the file.
    """
    for key, value in overrides.items():
        full = key.replace("__", ".")
        if full not in spec.values and full in OPTIONAL_DEFAULTS:   # an optional key the file leaves out
            spec.values[full] = OPTIONAL_DEFAULTS[full]
        if full not in spec.values:
            matches = [k for k in spec.values if k.split(".", 1)[1] == full]
            if not matches:
                matches = [k for k in OPTIONAL_DEFAULTS if k.split(".", 1)[1] == full]
                for k in matches:
                    spec.values.setdefault(k, OPTIONAL_DEFAULTS[k])
            if len(matches) != 1:
                known = ", ".join(sorted({k.split(".", 1)[1] for k in spec.values}))
                what = "is ambiguous (give it as section__key)" if matches else "is not a key of this spec"
                raise SpecError(f"override '{key}' {what}; keys of {spec.name}: {known}")
            full = matches[0]
        where = f"override {key}={value!r} ('{full}' of {spec.name})"
        old = spec.values[full]
        new = parse_value(full, value, where)
        if isinstance(old, np.ndarray) and np.shape(new) != old.shape:
            raise SpecError(f"{where}: must have the file value's shape {old.shape} "
                            f"(e.g. {old.tolist()}), got shape {np.shape(new)}")
        if isinstance(old, float) and np.ndim(new) != 0:
            raise SpecError(f"{where}: must be a single number, got {value!r}")
        spec.values[full] = new
        spec.sources[full] = "user override"
        spec.overridden[full] = f"override {key}={value!r}"


def spec_from_document(doc: dict, path: Path, **overrides: Any) -> Spec:
    """A validated spec from a TOML-shaped ``doc`` (sections of keys, values or {value, source}),
    as if read from ``path`` (errors name it): ``systems.from_drake`` builds one in memory."""
    spec = _flatten(doc, Path(path))
    _apply_overrides(spec, overrides)
    spec.overrides = dict(overrides)
    validate(spec)
    return spec


def read_spec(name_or_path: str | Path, **overrides: Any) -> Spec:
    """Read, override and validate a spec by system name or by path to a TOML file.

    ``[initial_state]``: starts are ``nominal + U(low, high)``, so ``low`` and ``high`` are offsets from
    ``nominal`` (one finite number per state, low <= high, refused in one line otherwise), not absolute
    states; a coordinate whose [low, high] holds its nonzero nominal but not 0 is warned about."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = spec_path(str(name_or_path))
        if path is None:
            raise KeyError(
                f"unknown system '{name_or_path}'; known systems: {', '.join(known_systems())}")
    elif not path.is_file():
        raise SpecError(f"{path}: no such spec file")
    spec = _flatten(_read_toml(path), path)
    _apply_overrides(spec, overrides)
    spec.overrides = dict(overrides)  # so worker processes can rebuild the same System
    validate(spec)
    return spec


def _read_toml(path: Path) -> dict:
    """The TOML document of a spec file, or a one-line SpecError naming the file.

    The size is checked before reading (:data:`~hybridctl.limits.MAX_SPEC_BYTES`); a binary file,
    invalid TOML and nesting too deep for the parser (``[[[[...``) are refused alike.
    """
    size = path.stat().st_size
    if size > MAX_SPEC_BYTES:
        raise SpecError(f"{path}: a spec file is at most {MAX_SPEC_BYTES:,} bytes, this one has {size:,}")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpecError(f"{path}: not a text file (not UTF-8 at byte {exc.start}); a spec is TOML text") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML: {exc}") from exc
    except RecursionError:  # tomllib recurses once per nested array or inline table
        raise SpecError(f"{path}: not valid TOML: arrays or tables nested too deeply") from None
    return doc


def _require_positive(spec: Spec, key: str, allow_zero: bool = False) -> None:
    value = np.asarray(spec.get(key), dtype=float)
    bad = (value < 0) if allow_zero else (value <= 0)
    if not np.all(np.isfinite(value)) or np.any(bad):
        rule = ">= 0" if allow_zero else "> 0"
        raise spec.error(key, f"must be finite and {rule}, got {spec.get(key)!r}")


def _require_in_range(spec: Spec, key: str) -> None:
    """Every entry of ``key`` within its :data:`PHYSICAL_RANGES` row."""
    low, high, why = PHYSICAL_RANGES[key]
    value = np.asarray(spec.get(key), dtype=float)
    if np.any(value < low) or np.any(value > high):
        raise spec.error(key, f"must lie in [{low:g}, {high:g}] ({why}), got {np.asarray(spec.get(key)).tolist()}")


def _check_name(spec: Spec) -> None:
    """``system.name`` (or the file's stem, where the spec sets none) is a plain identifier."""
    name = spec.get("system.name", spec.name)
    if not SYSTEM_NAME.fullmatch(name):
        key = "system.name" if spec.has("system.name") else "the file name"
        raise spec.error("system.name", f"must be a plain name of lower-case letters, digits, '_' and '-' "
                                        f"(at most 64, as [a-z0-9_-]+), got {name!r} ({key})")


def validate(spec: Spec) -> None:
    """Check every value's range and every shape; raise SpecError naming the key and file.

    A multibody spec's shapes depend on its model file: here its own keys and every value that
    does not depend on the model are checked; ``System`` checks the shapes (:func:`validate_shapes`)
    once Drake has read the model.
    """
    family = spec.get("model.family")
    if family not in FAMILIES:
        raise spec.error("model.family", f"must be one of {FAMILIES}, got {family!r}")
    _check_name(spec)
    if family == "multibody":
        _validate_multibody_keys(spec)
        _validate_values(spec)
        return
    n_q, n_actions = _validate_chain(spec)
    validate_shapes(spec, n_q, n_actions)
    _validate_values(spec)


def _validate_multibody_keys(spec: Spec) -> None:
    """[model] of a multibody spec: a model file, actuated joints by name, an optional tip point."""
    spec.get("model.file")
    for key in spec.values:
        if key.startswith("params.") and key not in MULTIBODY_PARAMS:
            raise spec.error(key, f"is not used by the multibody family: the model file holds the robot's "
                                  f"physics (a multibody spec's [params] may set only {', '.join(MULTIBODY_PARAMS)})")
    for key in ("model.base", "model.angle_offset", "model.drake"):
        if spec.has(key):
            raise spec.error(key, "belongs to the chain family; a multibody spec names its model with model.file")
    actuated = spec.get("model.actuated_joints", None)
    if actuated is not None and (not actuated or not all(isinstance(j, str) for j in actuated)):
        raise spec.error("model.actuated_joints", f"must list joint names of the model (or be left out: every "
                                                  f"JointActuator of the model), got {actuated!r}")
    if spec.has("model.tip_point"):
        point = np.asarray(spec.get("model.tip_point"))
        if point.shape != (3,) or not spec.has("model.tip_body"):
            raise spec.error("model.tip_point", "must be 3 numbers (x, y, z in the body frame of model.tip_body)")


def _validate_chain(spec: Spec) -> tuple[int, int]:
    """The chain family's keys; returns (joint coordinates, actions)."""
    if spec.has("model.file"):
        raise spec.error("model.file", "belongs to the multibody family (model.family = 'multibody')")
    base = spec.get("model.base")
    if base not in ("fixed", "cart"):
        raise spec.error("model.base", f"must be 'fixed' or 'cart', got {base!r}")
    n_links = len(np.atleast_1d(spec.get("params.link_mass")))
    for key in ("params.link_mass", "params.link_length"):
        _require_positive(spec, key)
    for key in ("params.link_com", "params.link_inertia", "params.joint_damping", "params.gravity"):
        _require_positive(spec, key, allow_zero=True)
    for key in ("params.link_length", "params.link_com", "params.link_inertia"):
        if len(np.atleast_1d(spec.get(key))) != n_links:
            raise spec.error(key, f"must have one entry per link ({n_links})")
    n_q = n_links + (1 if base == "cart" else 0)
    if base == "cart":
        _require_positive(spec, "params.cart_mass")
    if len(np.atleast_1d(spec.get("params.joint_damping"))) != n_q:
        raise spec.error("params.joint_damping", f"must have one entry per joint ({n_q})")
    actuated = spec.get("model.actuated_joints")
    if not actuated or any(not isinstance(j, int) or not 0 <= j < n_q for j in actuated):
        raise spec.error("model.actuated_joints", f"must list joint indices in 0..{n_q - 1}")
    return n_q, len(actuated)


def validate_shapes(spec: Spec, n_q: int, n_actions: int) -> None:
    """Every value whose shape follows from the joint coordinates ``n_q`` and the actions ``n_actions``."""
    n = 2 * n_q
    names = spec.get("state.names")
    if len(names) != n:
        raise spec.error("state.names", f"must name {n} states, got {len(names)}")
    for key in ("state.goal", "initial_state.nominal", "initial_state.low", "initial_state.high"):
        value = np.asarray(spec.get(key))
        if value.shape != (n,) or not np.all(np.isfinite(value)):
            raise spec.error(key, f"must be {n} finite numbers, got {spec.get(key)!r}")
    if np.any(spec.get("initial_state.low") > spec.get("initial_state.high")):
        raise spec.error("initial_state.low", "must be <= initial_state.high elementwise")
    warn_absolute_offsets(spec)
    for idx in spec.get("state.angles"):
        if not 0 <= idx < n_q:
            raise spec.error("state.angles", f"index {idx} is not a position index (0..{n_q - 1})")
    if len(spec.get("action.names")) != n_actions:
        raise spec.error("action.names", f"must name {n_actions} actions")
    Q = np.atleast_2d(spec.get("lqr.Q"))
    R = np.atleast_2d(spec.get("lqr.R"))
    if Q.shape != (n, n) or not np.allclose(Q, Q.T) or np.linalg.eigvalsh(Q).min() < -1e-12:
        raise spec.error("lqr.Q", f"must be a symmetric positive semidefinite {n}x{n} matrix")
    if R.shape != (n_actions, n_actions) or not np.allclose(R, R.T) or np.linalg.eigvalsh(R).min() <= 0:
        raise spec.error("lqr.R", f"must be a symmetric positive definite {n_actions}x{n_actions} matrix")
    for key in ("gate.warm_near", "gate.warm_far"):
        if spec.has(key):
            value = np.asarray(spec.get(key))
            if value.shape != (n,) or not np.all(np.isfinite(value)) or np.any(value <= 0):
                raise spec.error(key, f"must be {n} finite numbers > 0 (a spread per state), got {spec.get(key)!r}")


def _validate_values(spec: Spec) -> None:
    """The checks that do not depend on the model's size: ranges, periods, rewards, gate, success."""
    if spec.has("action.limit") or spec.get("model.family") == "chain":
        _require_positive(spec, "action.limit")
    for key in PHYSICAL_RANGES:  # after the sign and shape checks, which say more about a wrong value
        if spec.has(key):
            _require_in_range(spec, key)
    if spec.get("integrator.method") not in INTEGRATORS:
        raise spec.error("integrator.method", f"must be one of {INTEGRATORS}")
    for key in ("integrator.dt", "control.period", "control.swingup_period", "episode.duration"):
        _require_positive(spec, key)
        if spec.get(key) < MIN_DT:
            raise spec.error(key, f"must be at least {MIN_DT:g} s (hybridctl.limits.MIN_DT), got {spec.get(key)!r}")
    dt = spec.get("integrator.dt")
    steps = spec.get("episode.duration") / dt
    if steps > MAX_SIMULATION_STEPS:
        raise spec.error("episode.duration", f"is {steps:.3g} steps of integrator.dt ({dt}), above the limit of "
                                             f"{MAX_SIMULATION_STEPS:,} (hybridctl.limits.MAX_SIMULATION_STEPS)")
    for key in ("control.period", "control.swingup_period", "episode.duration"):
        ratio = spec.get(key) / dt
        if abs(ratio - round(ratio)) > 1e-9:
            raise spec.error(key, f"must be a whole multiple of integrator.dt ({dt}), got {spec.get(key)}")
    if spec.get("reward.kind") not in REWARD_KINDS:
        raise spec.error("reward.kind", f"must be one of {REWARD_KINDS}")
    for key in CH7_REWARD_SETTINGS:  # Ch. 7 reward settings (optional)
        if spec.has(key):
            _require_positive(spec, key, allow_zero=True)
    for key in CENTERED_REWARD_SETTINGS:
        if spec.has(key):
            _require_positive(spec, key)
    _require_positive(spec, "success.eps")
    if spec.get("success.lookback") < 1:
        raise spec.error("success.lookback", "must be >= 1")
    on, off = spec.get("gate.on"), spec.get("gate.off")
    if not 0.0 < off < on < 1.0:
        raise spec.error("gate.on", f"needs 0 < gate.off < gate.on < 1, got off={off}, on={on}")
    _require_positive(spec, "gate.cost_scale")
    for key in [k for k in spec.values if k.startswith("swingup.") and k != "swingup.controller"]:
        # energy-shaping gains: the Lyapunov argument needs k_energy > 0 and k_p, k_d >= 0
        _require_positive(spec, key, allow_zero=key != "swingup.k_energy")
    if spec.has("gate.label_horizon"):
        _require_positive(spec, "gate.label_horizon")


# ----------------------------------------------------------------- typed sections
# What the rest of hybridctl reads from a spec, as typed, validated values: code
# outside ``systems`` reads ``system.gate.on``, never ``spec.get("gate.on")``.

THESIS_LABEL_HORIZON = 2.5
"""s: the thesis labels gate data by 2.5 s LQR rollouts (implementation notes, Ch. 3).
The default of ``gate.label_horizon`` for a spec that does not set it."""

OPTIONAL_DEFAULTS = {
    "gate.label_horizon": THESIS_LABEL_HORIZON,
    "reward.alive_bonus": 0.0,        # thesis Ch. 7 reward settings: off unless a spec sets them
    "reward.velocity_penalty": 0.0,
    "reward.position_weight": 0.0,
    "reward.linear_velocity_weight": 0.0,
    "reward.cost_to_go_weight": 0.0,
    "reward.position_scale": 1.0,     # upright_centered settings (m, m/s)
    "reward.speed_scale": 1.0,
}
"""Optional spec keys and the value a spec that does not set them has. One source for the
readers and for checkpoint plant records: a key added to the specs after a checkpoint was
written is no difference while it holds this value."""


@dataclass(frozen=True)
class GateSection:
    """``[gate]``: hysteresis thresholds, gate-label horizon, cost-to-go scale, warm-start spreads.

    ``warm_near`` / ``warm_far`` are None when the spec gives none (no gate learning then).
    """

    on: float
    off: float
    cost_scale: float
    label_horizon: float
    warm_near: np.ndarray | None
    warm_far: np.ndarray | None
    system: str = ""

    def spread(self, which: str) -> np.ndarray:
        """``warm_near`` or ``warm_far``; ValueError naming the key when the spec has none."""
        value = getattr(self, which)
        if value is None:
            raise ValueError(f"gate learning needs 'gate.{which}' (a spread per state) in the spec of "
                             f"{self.system or 'this system'}; systems with one: those whose spec sets it "
                             f"(acrobot, cartpole)")
        return value


@dataclass(frozen=True)
class SuccessSection:
    """``[success]``: the thesis success test's eps and lookback b (eq. 3.2)."""

    eps: float
    lookback: int


@dataclass(frozen=True)
class SwingupSection:
    """``[swingup]``: the hand-designed swing-up's name (None when the spec has none) and gains."""

    controller: str | None
    gains: dict


def typed_sections(spec: Spec) -> dict:
    """The typed sections of a validated spec: gate, success, initial_state, swingup."""
    def optional_spread(key):
        return np.asarray(spec.get(key), dtype=float).copy() if spec.has(key) else None

    gate = GateSection(
        on=float(spec.get("gate.on")), off=float(spec.get("gate.off")),
        cost_scale=float(spec.get("gate.cost_scale")),
        label_horizon=float(spec.get("gate.label_horizon", OPTIONAL_DEFAULTS["gate.label_horizon"])),
        warm_near=optional_spread("gate.warm_near"), warm_far=optional_spread("gate.warm_far"), system=spec.name)
    success = SuccessSection(eps=float(spec.get("success.eps")), lookback=int(spec.get("success.lookback")))
    initial = InitialStateSection(*(np.asarray(spec.get(f"initial_state.{k}"), dtype=float).copy()
                                    for k in ("nominal", "low", "high")))
    gains = {k.split(".", 1)[1]: float(v) for k, v in spec.values.items()
             if k.startswith("swingup.") and k != "swingup.controller"}
    swingup = SwingupSection(controller=spec.get("swingup.controller", None), gains=gains)
    return {"gate": gate, "success": success, "initial_state": initial, "swingup": swingup}
