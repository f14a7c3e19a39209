"""Type checks for the learners' config dataclasses, read from their annotations.

Every learner's ``validate()`` calls :func:`check_types` first, so a value of the wrong type
(``lr="fast"``, ``seed=1.5``, ``hidden=None``) or a non-finite number (``reward_shift=nan``)
is named before any work starts; each ``validate()`` then checks its ranges.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing

import numpy as np

__all__ = ["check_types", "describe_type"]


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
    its annotation (floats must also be finite)."""
    hints = typing.get_type_hints(type(config))
    cls = type(config).__name__
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if not _matches(value, hints.get(f.name, typing.Any)):
            raise ValueError(f"{cls}.{f.name} must be {describe_type(hints[f.name])}, got {value!r}")
