"""What a checkpoint was trained on: the system record of config.json, and the checks against it.

:func:`system_record` records a hybridctl system (name, spec overrides, the resolved spec values
and their hash); :func:`env_record` a gymnasium env (id and kwargs). :func:`check_plant` refuses a
checkpoint trained on another plant, naming each differing value (``force``: a warning).
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

from ..io import to_jsonable
from ..systems import load as load_system
from ..systems.spec import OPTIONAL_DEFAULTS
from .checkpoint_schema import CONFIG_FILE, FORCE_HINT, CheckpointError, _shown_short

def spec_hash(values: dict) -> str:
    """SHA-256 (first 16 hex digits) of the canonical JSON of resolved spec values (sorted keys,
    numpy arrays as lists, no whitespace): equal for equal plants, whatever the override spelling."""
    text = json.dumps(to_jsonable(values), sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def system_record(system) -> dict:
    """config.json's ``system``: name, spec overrides, the resolved spec values and their hash."""
    spec = getattr(system, "spec", None)
    values = to_jsonable(dict(getattr(spec, "values", {}) or {}))
    return {"name": system.name, "overrides": to_jsonable(dict(getattr(spec, "overrides", {}) or {})),
            "spec_hash": spec_hash(values), "spec_values": values}


def _shown(value) -> str:
    return json.dumps(to_jsonable(value))


TRAINING_ONLY_SECTIONS = ("reward.", "initial_state.", "episode.")
"""Spec keys that shape training but not the plant or its controllers: the reward, the
distribution episodes start from and how long training episodes last. A deployed policy
(:func:`hybridctl.learn.load_controller`) ignores them; resuming a run does not."""

GATE_SECTION = "gate."
"""Spec keys only a learned gate uses (its cost feature's scale, its warm-start spreads and
labels): ignored when only the swing-up policy of a checkpoint is deployed."""


def plant_differences(found: Path, recorded: dict | None, system,
                      ignore: tuple[str, ...] = ()) -> tuple[list[str], bool]:
    """How the system a checkpoint at ``found`` recorded (config.json ``system``) differs from ``system``.

    Returns (one line per difference, whether the whole spec could be compared). A
    checkpoint without ``spec_hash`` (written before it was recorded) is compared by system
    name and spec overrides only. Keys starting with a prefix in ``ignore`` (e.g.
    :data:`TRAINING_ONLY_SECTIONS`) are not compared.
    """
    recorded = recorded or {}
    name = recorded.get("name")
    if name != system.name:
        return [f"checkpoint {found} was trained on system {name!r}, but this system is {system.name!r}"], True
    current = system_record(system)
    complete = "spec_hash" in recorded
    if not complete:  # an old checkpoint: what its overrides make of today's spec is all there is to compare
        try:
            saved_values = system_record(load_system(name, **(recorded.get("overrides") or {})))["spec_values"]
        except (ValueError, KeyError, TypeError) as exc:
            return [f"checkpoint {found} was trained on {name} with spec overrides "
                    f"{_shown(recorded.get('overrides'))}, which no longer apply ({exc})"], False
    elif recorded["spec_hash"] == current["spec_hash"]:
        return [], True
    else:
        saved_values = recorded.get("spec_values") or {}
    lines = []
    for key in sorted(set(saved_values) | set(current["spec_values"])):
        if key.startswith(ignore) if ignore else False:
            continue
        # a key the other side lacks holds its optional default (a spec key added after the checkpoint)
        absent = OPTIONAL_DEFAULTS.get(key, "(absent)")
        old, new = saved_values.get(key, absent), current["spec_values"].get(key, absent)
        if old != new:
            lines.append(f"checkpoint {found} was trained on {name} with {key}={_shown(old)}; this system has "
                         f"{_shown(new)}")
    if not complete:
        return [f"{line} (an old checkpoint: only its spec overrides are recorded)" for line in lines], False
    return lines, True  # hashes that differ only by optional keys at their defaults: the same plant



def recorded_system(found: Path, name: str, overrides: dict):
    """The system a checkpoint at ``found`` records (its name and spec overrides in config.json), or
    :class:`CheckpointError` naming the file when that system is unknown here or its overrides do
    not apply (the spec's own message says which value)."""
    try:
        return load_system(name, **overrides)
    except KeyError as exc:
        raise CheckpointError(f"{found / CONFIG_FILE}: {exc.args[0] if exc.args else exc}") from None
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{found / CONFIG_FILE}: the recorded system {name!r} with overrides "
                              f"{_shown_short(overrides)} does not load: {exc}") from None


def check_plant(found: Path, recorded: dict | None, system, force: bool = False,
                ignore: tuple[str, ...] = ()) -> None:
    """Raise :class:`CheckpointError` naming what differs when the checkpoint at ``found`` was trained
    on another plant than ``system`` (``force``: warn instead). An old checkpoint without a spec
    hash is checked by name and overrides, with a warning that nothing more can be checked.
    Keys starting with a prefix in ``ignore`` are not compared."""
    lines, complete = plant_differences(found, recorded, system, ignore)
    if lines:
        message = "; ".join(lines)
        if not force:
            raise CheckpointError(f"{message} ({FORCE_HINT})")
        warnings.warn(f"force: loading anyway: {message}", stacklevel=3)
    if not complete:
        warnings.warn(f"checkpoint {found} records no spec hash (written before hybridctl recorded one): only the "
                      f"system name and spec overrides were checked, nothing more can be checked", stacklevel=3)


def env_record(env_id: str, kwargs: dict | None = None) -> dict:
    """config.json's ``system`` for a gymnasium env: its id and keyword arguments (``kind`` "gymnasium")."""
    return {"name": env_id, "kind": "gymnasium", "kwargs": to_jsonable(dict(kwargs or {}))}
