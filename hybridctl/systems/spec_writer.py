"""A built :class:`~hybridctl.systems.system.System` written back as a complete spec TOML file.

``System.save_spec(path)`` calls :func:`save_spec`: every value the system was built from (the spec's,
the overrides', the defaults ``from_drake`` and the model file filled in), each as ``{ value, source }``
(and ``units`` where the spec had them), floats written so that they read back bit for bit. The goal is the
one the system uses: where it was moved to the nearest equilibrium its source says so. The model file is
written relative to the spec's folder where it lies inside it, else as an absolute path or its
``package://drake/`` URL. ``systems.load(path)`` of the file builds the same dynamics and LQR.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .. import io
from .spec import SpecError

_BARE = {"system.name", "system.description", "model.family"}
"""Keys written as plain values, as the shipped specs write them (what the system is, not a physical value)."""
_DERIVED = {"model.file_sha256"}
"""Keys the system computes when built (the model file's hash, recomputed on load): not written."""
DEFAULT_SOURCE = "hybridctl.systems.from_drake default"


def _toml(value: Any) -> str:
    """One TOML value: a string, an integer, a float that reads back bit for bit, or a (nested) list."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)       # a JSON string without \u surrogates is a TOML one
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    number = float(value)
    if math.isnan(number):
        return "nan"
    if math.isinf(number):
        return "inf" if number > 0 else "-inf"
    return repr(number)                                     # the shortest text that reads back to the same float


def _model_file(system, folder: Path) -> str:
    source = system.model_request.source
    if source.startswith("package://"):
        return source
    try:
        return Path(source).resolve().relative_to(folder.resolve()).as_posix()
    except ValueError:                                     # outside the spec's folder: where it is
        return str(Path(source).resolve())


def spec_document(system, path: Path) -> str:
    """The TOML text of ``system``'s spec as a file at ``path`` (the model file relative to its folder)."""
    spec = system.spec
    values = dict(spec.values)
    sources = dict(spec.sources)
    stated = np.asarray(spec.get("state.goal"), dtype=float)
    if not np.array_equal(stated, system.goal):
        distance = float(np.abs(system.goal - stated).max())
        values["state.goal"] = system.goal
        sources["state.goal"] = (f"{sources.get('state.goal', 'the spec')}: {_toml(stated)} moved {distance:.3g} to "
                                 f"the nearest equilibrium with u = 0 (hybridctl.systems.nearest_equilibrium)")
    if system.model_request is not None:
        values["model.file"] = _model_file(system, path.parent)
        sources.setdefault("model.file", f"{spec.path.name}: the model file ({system.model_request.source})")
    sections: dict[str, list[str]] = {}
    from_file = spec.path.suffix == ".toml"
    for full, value in values.items():
        if full in _DERIVED:
            continue
        section, key = full.split(".", 1)
        if full in _BARE:
            line = f"{key} = {_toml(value)}"
        else:
            source = sources.get(full, spec.path.name if from_file else
                                 "from_drake argument" if section == "model" else DEFAULT_SOURCE)
            units = f", units = {_toml(spec.units[full])}" if full in spec.units else ""
            line = f"{key} = {{ value = {_toml(value)}{units}, source = {_toml(source)} }}"
        sections.setdefault(section, []).append(line)
    made = spec.path if from_file else spec.get("system.description", spec.path)
    head = (f"# {system.name}: written by hybridctl System.save_spec from {made}; every value with its source.\n"
            f"# systems.load(this file) builds the same dynamics and LQR.\n")
    return head + "".join(f"\n[{section}]\n" + "\n".join(lines) + "\n" for section, lines in sections.items())


def save_spec(system, path, *, overwrite: bool = False) -> Path:
    """Write ``system``'s complete spec to ``path`` (a ``.toml`` file) through :func:`hybridctl.io.atomic_write_text`;
    an existing file is refused in one line unless ``overwrite``. Returns the path."""
    path = Path(path).expanduser()
    if path.suffix != ".toml":
        raise SpecError(f"{path}: a spec file ends in .toml")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    if not path.parent.is_dir():
        raise SpecError(f"{path}: no such folder {path.parent}")
    return io.atomic_write_text(path, spec_document(system, path))
