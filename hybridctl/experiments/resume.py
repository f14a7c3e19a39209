"""The resume policy of a training run: which config fields a resume may change, and the refusal of the rest.

A resumed run takes from the command line how long to train and how to record, checkpoint, evaluate
and parallelise it (:data:`RESUME_APPLIED`); a changed value of any other field (learning rates,
gamma, sizes, seed, ...) would make it another run, so the resume is refused naming the field
(``force`` applies it anyway).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any, Callable

__all__ = ["RESUME_APPLIED", "resume_changes", "describe_refused", "resume_settings"]

RESUME_APPLIED = ("total_steps", "epochs", "checkpoint_every", "checkpoint_minutes", "log_every", "tensorboard",
                  "save_replay", "torch_threads", "backend", "workers", "address", "eval_episodes")
"""Config fields a resumed run takes from the command line: how long to train and how to record,
checkpoint, evaluate and parallelise it. They do not change the algorithm's math. Every other
field (learning rates, gamma, network sizes, batch sizes, seed, num_envs, ...) does: a resume
with another value refuses, naming the field (``force`` applies it anyway). The APG family's
former ``ray_address`` is ``address`` (an old checkpoint's recorded ``ray_address`` is read as
``address`` when it loads), so no setting given today has the old name."""


def resume_changes(recorded: dict, settings: dict, applied: Iterable[str] = RESUME_APPLIED
                   ) -> tuple[dict, list[tuple[str, Any, Any]]]:
    """Split the ``settings`` given for a resume against the checkpoint's ``recorded`` config.

    Returns (the settings to apply: the ``applied`` fields and those equal to the recorded
    value, the changed math fields as (field, recorded value, given value)).
    """
    applied = set(applied)
    take, refused = {}, []
    for name, value in settings.items():
        old = recorded.get(name, _MISSING_SETTING)
        same = old is not _MISSING_SETTING and _same_value(old, value)
        if name in applied or same:
            take[name] = value
        else:
            refused.append((name, None if old is _MISSING_SETTING else old, value))
    return take, refused


_MISSING_SETTING = object()


def _same_value(a, b) -> bool:
    """Equal as JSON would store them (2e6 == 2000000, a tuple == a list)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same_value(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool) \
            and not isinstance(b, bool):
        return float(a) == float(b)
    return a == b


def describe_refused(found, refused: list[tuple[str, Any, Any]]) -> str:
    """The error text of a resume with changed math settings, naming each field and both values."""
    fields = "; ".join(f"{name}: recorded {old!r}, given {new!r}" for name, old, new in refused)
    return (f"--resume from {found} with changed settings that change the algorithm: {fields}. A resumed run keeps "
            f"its recorded values for these (only {', '.join(RESUME_APPLIED)} may change); drop them, start a new run "
            f"(another --out, or --overwrite), or pass --force to apply them anyway")


def resume_settings(found: Path, recorded: dict, settings: dict, force: bool, report: Callable[[str], None]) -> dict:
    """The ``settings`` a resume from ``found`` applies (see :data:`RESUME_APPLIED`):
    run settings always, math settings equal to the recorded ones; changed math settings raise
    ValueError naming each field with its recorded and given value, unless ``force`` (applied,
    and reported)."""
    take, refused = resume_changes(recorded, settings)
    if refused and not force:
        raise ValueError(describe_refused(found, refused))
    for name, old, new in refused:
        report(f"--force: resuming with {name}={new!r} (the checkpoint's run had {old!r})")
        take[name] = new
    return take
