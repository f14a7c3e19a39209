"""Type and limit checks for the learners' config dataclasses, read from their annotations and field names.

Every learner's ``validate()`` calls :func:`check_types` first, so a value of the wrong type
(``lr="fast"``, ``seed=1.5``, ``hidden=None``) or a non-finite number (``reward_shift=nan``)
is named before any work starts; each ``validate()`` then checks its ranges. :func:`check_types`
also applies the upper limits of :mod:`hybridctl.limits` by field name, the same for every
config (``torch_threads``, ``num_envs``, hidden sizes and their networks' memory, ``seed``), and
refuses a Ray address with a local backend. A message names the field and the command-line
flag ``hybridctl train`` makes of it (``SACConfig.torch_threads (--torch-threads)``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
import math
import types
import typing

import numpy as np
import torch

from ..limits import (MAX_CONFIG_INTEGER, MAX_EVAL_EPISODES, MAX_HIDDEN_UNITS, MAX_NUM_ENVS, MAX_SIMULATION_STEPS,
                      MAX_TOTAL_STEPS, MAX_UPDATES, check_at_most, check_fits_memory, cpu_count)

__all__ = ["check_types", "check_limits", "check_fields", "checkpoint_minutes", "describe_type", "MAX_SEED"]

MAX_SEED = 2**63 - 1
"""The largest seed: torch.manual_seed and numpy's generators take a 64-bit integer."""
NETWORK_BYTES_PER_PARAMETER = 14 * 4
"""Bytes one float32 weight of a learner's hidden layers costs in training: SAC's actor, two critics
and their two targets (5 copies), gradients of the three trained networks (3) and Adam's two
moments of each (6)."""
FIELD_LIMITS: dict[str, tuple[typing.Callable[[], int], str]] = {
    "torch_threads": (cpu_count, "cores this process may use"),
    "num_envs": (lambda: MAX_NUM_ENVS, "environments of one batched env"),
    "hidden_size": (lambda: MAX_HIDDEN_UNITS, "units of one hidden layer"),
    "seed": (lambda: MAX_SEED, "the largest 64-bit seed"),
    "total_steps": (lambda: MAX_TOTAL_STEPS, "env steps of one training run"),
    "exploration_steps": (lambda: MAX_TOTAL_STEPS, "env steps of one training run"),
    "epochs": (lambda: MAX_UPDATES, "epochs of one training run"),
    "updates": (lambda: MAX_UPDATES, "updates of one training run"),
    "apg_iterations": (lambda: MAX_UPDATES, "iterations of one epoch"),
    "eval_episodes": (lambda: MAX_EVAL_EPISODES, "episodes of one evaluation"),
    "episode_steps": (lambda: MAX_SIMULATION_STEPS, "time steps of one episode"),
    "horizon": (lambda: MAX_SIMULATION_STEPS, "time steps of one episode"),
}
"""Upper limits by config field name (every learner's config): (limit(), what it bounds). Every other
integer field is at most MAX_CONFIG_INTEGER."""


def describe_type(hint) -> str:
    """A readable name of an annotation ("a number or None", "a tuple of integers")."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join("None" if a is type(None) else describe_type(a) for a in args)
    if origin in (tuple, list):
        return f"a {origin.__name__} of {describe_type(args[0]).removeprefix('a ').removeprefix('an ')}s"
    return {bool: "true or false", int: "an integer", float: "a finite number", str: "a string",
            dict: "a dict"}.get(hint, getattr(hint, "__name__", str(hint)))


def _matches(value, hint) -> bool:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is typing.Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in args)
    if hint is type(None):
        return value is None
    if origin in (tuple, list):
        return isinstance(value, (tuple, list)) and all(_matches(v, args[0]) for v in value)
    if hint is bool:
        return isinstance(value, (bool, np.bool_))
    if hint is int:
        return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if hint is float:
        return (isinstance(value, (int, float, np.number)) and not isinstance(value, (bool, np.bool_))
                and math.isfinite(value))
    if isinstance(hint, type):
        return isinstance(value, hint)
    return True  # an annotation this checker does not know: leave it to validate()


def check_types(config) -> None:
    """Raise ValueError naming the first field of a config dataclass whose value does not match
    its annotation (floats must also be finite); then :func:`check_limits`."""
    hints = typing.get_type_hints(type(config))
    cls = type(config).__name__
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if not _matches(value, hints.get(f.name, typing.Any)):
            raise ValueError(f"{cls}.{f.name} must be {describe_type(hints[f.name])}, got {value!r}")
    check_limits(config)


def field_name(config, name: str) -> str:
    """How a message names a config field: ``SACConfig.num_envs (--num-envs)``, the flag of ``hybridctl train``."""
    return f"{type(config).__name__}.{name} (--{name.replace('_', '-')})"


def _integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_limits(config) -> None:
    """Raise LimitError naming the first field of ``config`` above its limit (:data:`FIELD_LIMITS`,
    hidden widths at most MAX_HIDDEN_UNITS, hidden layers whose training memory exceeds the
    memory budget), or ValueError for a Ray address with a local backend. Fields a config does
    not have, and values of the wrong type (reported by :func:`check_types`), are skipped."""
    values = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    for name, value in values.items():
        if _integer(value):
            limit, why = FIELD_LIMITS.get(name, (lambda: MAX_CONFIG_INTEGER, "an integer setting"))
            check_at_most(field_name(config, name), int(value), limit(), why=why, force_flag=None)
    for name, widths in values.items():
        if name.split("_")[-1] == "hidden" and isinstance(widths, (tuple, list)) and all(map(_integer, widths)):
            for width in widths:
                check_at_most(field_name(config, name), int(width), MAX_HIDDEN_UNITS, why="units of one hidden "
                              "layer", force_flag=None)
            weights = sum(int(a) * int(b) for a, b in zip(widths, widths[1:]))
            check_fits_memory(field_name(config, name), weights * NETWORK_BYTES_PER_PARAMETER, "the network")
    if _integer(values.get("hidden_size")) and _integer(values.get("hidden_layers")):
        weights = int(values["hidden_layers"]) * int(values["hidden_size"]) ** 2
        check_fits_memory(f"{field_name(config, 'hidden_size')} x {field_name(config, 'hidden_layers')}",
                          weights * NETWORK_BYTES_PER_PARAMETER, "the networks in training")
    backend = values.get("backend")
    if values.get("address") is not None and isinstance(backend, str) and backend != "ray":
        raise ValueError(f"{field_name(config, 'address')} applies to backend 'ray' only, not {backend!r}")


def check_fields(config, integers_from_1: Iterable[str] = (), integers_from_0: Iterable[str] = (),
                 positive: Iterable[str] = (), unit_interval: Iterable[str] = (),
                 non_negative: Iterable[str] = ()) -> None:
    """Raise ValueError naming the first field of ``config`` that is not an integer >= 1 / >= 0,
    a finite number > 0, a number in [0, 1], or a finite number >= 0 (the checks every learner's
    ``validate`` repeats)."""
    cls = type(config).__name__
    for minimum, names in ((1, integers_from_1), (0, integers_from_0)):
        for name in names:
            value = getattr(config, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
                raise ValueError(f"{cls}.{name} must be an integer >= {minimum}, got {value!r}")
    for name in positive:
        value = getattr(config, name)
        if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{cls}.{name} must be a finite number > 0, got {value!r}")
    for name in unit_interval:
        value = getattr(config, name)
        if not (isinstance(value, (int, float, np.number)) and 0.0 <= value <= 1.0):
            raise ValueError(f"{cls}.{name} must be in [0, 1], got {value!r}")
    for name in non_negative:
        value = getattr(config, name)
        if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{cls}.{name} must be a finite number >= 0, got {value!r}")


def checkpoint_minutes(config) -> float:
    """``config.checkpoint_minutes`` (0 when the config has none), ValueError unless a finite number >= 0."""
    minutes = getattr(config, "checkpoint_minutes", 0.0)
    if (not isinstance(minutes, (int, float, np.number)) or isinstance(minutes, bool) or not math.isfinite(minutes)
            or minutes < 0):
        raise ValueError(f"{type(config).__name__}.checkpoint_minutes must be a finite number >= 0 "
                         f"(0: no checkpoints by time), got {minutes!r}")
    return float(minutes)


def check_device_available(name: str, device: torch.device) -> None:
    """Raise ValueError naming ``name`` when ``device`` is a CUDA device this machine does not have."""
    if device.type != "cuda":
        return
    if not torch.cuda.is_available():
        raise ValueError(f"{name} is {str(device)!r}, but CUDA is not available here (torch {torch.__version__}, "
                         f"{'built without CUDA' if torch.version.cuda is None else 'no GPU found'}); use 'cpu'")
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise ValueError(f"{name} is {str(device)!r}, but this machine has {torch.cuda.device_count()} CUDA "
                         f"device(s): use 'cuda:0' to 'cuda:{torch.cuda.device_count() - 1}'")


DEVICE_TYPES = ("cpu", "cuda")
"""The torch device types hybridctl runs on; torch knows more (meta, mps, xla, ...), which fail deep inside."""


def check_device(name: str, value, available: bool = True) -> torch.device:
    """``value`` (a name such as "cuda:1", or a torch.device) as a torch device: the one check of every
    ``--device`` flag and config ``device`` field. ValueError naming ``name`` unless it is cpu, cuda or
    cuda:N (:data:`DEVICE_TYPES`), and (``available``) for a CUDA device this machine lacks
    (:func:`check_device_available`)."""
    try:
        device = value if isinstance(value, torch.device) else torch.device(value)
    except (RuntimeError, TypeError, ValueError):
        device = None
    if device is None or device.type not in DEVICE_TYPES or (device.type == "cpu" and device.index not in (None, 0)):
        raise ValueError(f"{name} must be a torch device hybridctl runs on (cpu, cuda or cuda:N), got {value!r}")
    if available:
        check_device_available(name, device)
    return device


def check_device_field(config, available: bool = True) -> torch.device:
    """``config.device`` as a torch device (:func:`check_device`, the message naming ``Config.device``)."""
    return check_device(f"{type(config).__name__}.device", config.device, available)
