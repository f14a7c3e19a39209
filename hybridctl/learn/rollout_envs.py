"""Envs of the rollouts from ids: :func:`make_env` (a hybridctl system name maps to its swing-up env), and
:func:`recorded_env_id` / :func:`recorded_env_kwargs` for ids and keyword arguments read from files (data, never
an import)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import gymnasium as gym

from ..envs import env_id
from ..systems import known_systems
from . import checkpoint as ckpt

# An env id read from a FILE (a checkpoint's config.json) is data, never an import:
# gymnasium.make("module:Env-v0") imports `module` before it looks the id up. An id the user passes
# directly (ARS("mymod:Env-v0"), an env on the command line) is the user's own choice and is not checked.
ACCEPTED_IDS = ("a hybridctl system name or an id already registered in gymnasium.registry, "
                "without a 'module:' part")
"""What :func:`recorded_env_id` accepts, as the error messages say it."""


def _shown_value(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def recorded_env_id(value: Any, file: str | Path, key: str = "env") -> str:
    """``value`` (``file``'s ``key``) if it is a safe env id to hand to ``gymnasium.make``.

    Accepted: a hybridctl system name or an id already in ``gymnasium.registry`` (a dict lookup:
    nothing is imported, neither ``gym.make`` nor ``gym.spec`` is called), without a ``module:``
    part. Raises :class:`~hybridctl.learn.checkpoint.CheckpointError` naming the file, the key and
    what is accepted otherwise (a non-string too).
    """
    if not isinstance(value, str):
        raise ckpt.CheckpointError(f"{file}: {key!r} must be a string ({ACCEPTED_IDS}), got "
                                   f"{type(value).__name__} {_shown_value(value)}")
    if ":" in value:
        raise ckpt.CheckpointError(f"{file}: {key!r} is {_shown_value(value)}, whose 'module:' part would import "
                                   f"code named by a file; accepted: {ACCEPTED_IDS} (pass such an id yourself, "
                                   f"e.g. env=..., if you trust its module)")
    if value in known_systems(strict=False) or value in gym.registry:
        return value
    raise ckpt.CheckpointError(f"{file}: {key!r} is {_shown_value(value)}, not {ACCEPTED_IDS} (pass env=... to "
                               f"use another env)")


def recorded_env_kwargs(value: Any, file: str | Path, key: str = "env_kwargs") -> dict | None:
    """``value`` (``file``'s ``key``) if it is None or safe keyword arguments of an env
    (:func:`hybridctl.learn.checkpoint_schema.check_env_kwargs`).

    Raises :class:`~hybridctl.learn.checkpoint.CheckpointError` naming the file and the key otherwise.
    """
    return ckpt.check_env_kwargs(value, file, key)   # known keys, plain values, render_mode never "human"


def make_env(env: str | Callable[[], gym.Env], env_kwargs: dict | None = None,
             max_steps: int | None = None) -> gym.Env:
    """A gymnasium env from an id (hybridctl system names map to their swing-up env) or a factory.

    ``max_steps`` replaces an id's time limit (e.g. 10,000-step robustness episodes); a factory's
    env keeps its own, and rollouts stop at ``max_steps`` anyway.
    """
    if callable(env):
        return env()
    name = env_id(env) if env in known_systems() else env
    kwargs = dict(env_kwargs or {})
    if max_steps is not None:
        kwargs["max_episode_steps"] = max_steps
    return gym.make(name, **kwargs)
