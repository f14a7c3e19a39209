"""Env ids and env kwargs read from a FILE (a checkpoint's config.json): data, never an import.

``gymnasium.make("module:Env-v0")`` imports ``module`` before it looks the id up, so an id
recorded in a file someone else wrote could run any code on this machine. An id read from a
file is therefore accepted only when it is a hybridctl system name or an id already in
``gymnasium.registry`` (a dict lookup: nothing is imported, ``gym.make`` and ``gym.spec`` are
not called), and never with a ``module:`` part. An id the user passes directly (``ARS("mymod:Env-v0")``,
an env on the command line) is the user's own choice and is not checked here.

>>> env = recorded_env_id(meta.get("env"), folder / "config.json")      # CheckpointError if unsafe
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym

from ..systems import known_systems
from .checkpoint import CheckpointError

ACCEPTED_IDS = ("a hybridctl system name or an id already registered in gymnasium.registry, "
                "without a 'module:' part")
"""What :func:`recorded_env_id` accepts, as the error messages say it."""


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def recorded_env_id(value: Any, file: str | Path, key: str = "env") -> str:
    """``value`` (``file``'s ``key``) if it is a safe env id to hand to ``gymnasium.make``.

    Raises :class:`CheckpointError` naming the file, the key and what is accepted: a non-string,
    an id with a ``module:`` part (its module would be imported) or an id that is neither a
    hybridctl system nor registered in gymnasium (making it could import its package).
    """
    if not isinstance(value, str):
        raise CheckpointError(f"{file}: {key!r} must be a string ({ACCEPTED_IDS}), got {type(value).__name__} "
                              f"{_shown(value)}")
    if ":" in value:
        raise CheckpointError(f"{file}: {key!r} is {_shown(value)}, whose 'module:' part would import code named "
                              f"by a file; accepted: {ACCEPTED_IDS} (pass such an id yourself, e.g. env=..., "
                              f"if you trust its module)")
    if value in known_systems(strict=False) or value in gym.registry:
        return value
    raise CheckpointError(f"{file}: {key!r} is {_shown(value)}, not {ACCEPTED_IDS} (pass env=... to use "
                          f"another env)")


def recorded_env_kwargs(value: Any, file: str | Path, key: str = "env_kwargs") -> dict | None:
    """``value`` (``file``'s ``key``) if it is None or an object with string keys (the env's keyword arguments).

    Raises :class:`CheckpointError` naming the file and the key otherwise.
    """
    if value is None:
        return None
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise CheckpointError(f"{file}: {key!r} must be null or an object of keyword arguments, got "
                              f"{type(value).__name__} {_shown(value)}")
    return value
