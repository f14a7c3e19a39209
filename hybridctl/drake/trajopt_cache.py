"""The collocation swing-up's cache (:mod:`hybridctl.drake.trajopt`): ``.npz`` files named by a hash of everything
that determines them, read with ``allow_pickle=False`` after their array headers were checked, written atomically."""

from __future__ import annotations

import hashlib
import json
import os
import warnings
import zipfile
from pathlib import Path

import numpy as np

from .. import io
from ..limits import MAX_TRAJOPT_ROWS
from ..systems import System
from ..systems import plants as _plants

CACHE_ENV = "HYBRIDCTL_CACHE"
"""Environment variable of the cache root (shared with the multibody model cache); ``trajopt/`` below it."""

DEFAULT_CACHE = Path("runs") / "trajopt"
"""The cache folder when ``$HYBRIDCTL_CACHE`` is not set, relative to the working folder."""

CACHE_FORMAT = 2
"""Version of the cached arrays and of the problem they solve; part of every cache key, so a new layout or problem
never reads an old file (2: a multibody model's prismatic joints are bounded, ``trajopt.rail_bounds``)."""



def cache_folder() -> Path:
    """The cache folder: ``$HYBRIDCTL_CACHE/trajopt`` when the variable is set, else ``runs/trajopt``."""
    root = os.environ.get(CACHE_ENV)
    return Path(root) / "trajopt" if root else DEFAULT_CACHE


def _model_identity(system: System) -> str:
    """What fixes the Drake model beyond the spec's values: the rendered SDF of a chain on a
    MultibodyPlant, the model file's hash of the multibody family, else Drake's example plant's name."""
    if system.family == "multibody":
        from ..systems.symbolic import model_hash
        return model_hash(system.model_request)
    kind = system.drake_model or ""
    if kind.startswith("multibody:"):
        return hashlib.sha256(_plants.render_model(system).encode()).hexdigest()
    return kind


def _drake_version() -> str:
    try:
        from importlib.metadata import version
        return version("drake")
    except Exception:  # noqa: BLE001 - a source build of Drake has no distribution metadata
        return "unknown"


def cache_key(system: System, settings: dict, **extra) -> str:
    """sha256 (hex, 20 characters) of everything that determines a cached result: the spec's values,
    the Drake model, ``settings`` (a dict of the settings that matter), Drake's version and ``extra``."""
    record = {"format": CACHE_FORMAT, "system": system.name, "spec": io.to_jsonable(system.spec.values),
              "model": _model_identity(system), "settings": settings, "drake": _drake_version(), **extra}
    text = json.dumps(io.to_jsonable(record), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def load_npz(path: Path, key: str, shapes: dict[str, tuple]) -> dict | None:
    """The arrays of a cache file, or None if it is missing; a file that is unreadable, holds another
    key, or arrays of other shapes or non-finite values is reported (warning) and treated as missing.
    ``shapes`` gives each array's shape, -1 for any length."""
    if not path.exists():
        return None
    try:
        _check_npz_headers(path, shapes)      # sizes from the headers, before np.load allocates them
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.asarray(data[name]) for name in (*shapes, "key")}
        if str(arrays["key"]) != key:
            raise ValueError(f"holds key {arrays['key']}, not {key}")
        for name, shape in shapes.items():
            array = arrays[name]
            if array.ndim != len(shape) or any(s not in (-1, a) for s, a in zip(shape, array.shape)):
                raise ValueError(f"array {name!r} has shape {array.shape}, expected {shape}")
            if array.dtype.kind == "f" and not np.isfinite(array).all():
                raise ValueError(f"array {name!r} is not finite")
        return arrays
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        warnings.warn(f"trajopt cache {path} cannot be used ({reason}); recomputing it", stacklevel=3)
        return None


def _check_npz_headers(path: Path, shapes: dict[str, tuple]) -> None:
    """ValueError unless each array's .npy header in the zip ``path`` claims ``shapes`` (-1: any length up to
    ``limits.MAX_TRAJOPT_ROWS``) and a plain dtype: read without reading (or allocating) any array data."""
    with zipfile.ZipFile(path) as archive:
        for name, shape in shapes.items():
            with archive.open(f"{name}.npy") as f:      # KeyError when missing
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                claimed, _, dtype = read(f)
            if dtype.hasobject:
                raise ValueError(f"array {name!r} holds Python objects")
            if len(claimed) != len(shape) or any(s not in (-1, a) or a > MAX_TRAJOPT_ROWS
                                                 for s, a in zip(shape, claimed)):
                raise ValueError(f"array {name!r} has shape {claimed}, expected {shape} (-1: at most "
                                 f"{MAX_TRAJOPT_ROWS:,}, limits.MAX_TRAJOPT_ROWS)")


def save_npz(path: Path, key: str, arrays: dict) -> None:
    """Write ``arrays`` and ``key`` to ``path`` atomically (plain arrays only: loadable without pickle)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    io.atomic_write(path, lambda f: np.savez(f, key=np.asarray(key), **{k: np.asarray(v) for k, v in arrays.items()}))
