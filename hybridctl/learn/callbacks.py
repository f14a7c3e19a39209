"""Callbacks a training run calls with the learner, and the progress bar.

A :class:`Callback`'s hooks receive the learner; ``on_step`` / ``on_update`` returning False stop
the run (the final checkpoint is still written). ``learn(callback=...)`` takes one, a list of them
or a plain function ``f(learner)`` called after every update (:meth:`CallbackList.of`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Callable

__all__ = ["Callback", "FunctionCallback", "CallbackList", "progress_bar"]


class Callback:
    """Hooks a training run calls with the learner. Return False from :meth:`on_step` or
    :meth:`on_update` to stop training (the final checkpoint is still written).

    SAC/SSAC: a step is one vector-env step, an update one update round. ARS: a step and
    an update are one epoch; fine-tuning: one update; the APG family: one epoch.
    """

    def on_training_start(self, learner) -> None:
        """Before the first step (after a resume's restore)."""

    def on_step(self, learner) -> bool | None:
        """After every env step (all envs) / epoch."""

    def on_update(self, learner) -> bool | None:
        """After every update round (SAC: ``steps_per_update`` env steps) / epoch."""

    def on_checkpoint(self, learner, path: Path) -> None:
        """After a checkpoint directory was written to ``path``."""

    def on_training_end(self, learner) -> None:
        """After the run ended normally (final checkpoint written)."""


class FunctionCallback(Callback):
    """A plain function ``f(learner) -> bool | None`` called after every update."""

    def __init__(self, function: Callable):
        self.function = function

    def on_update(self, learner):
        return self.function(learner)


class CallbackList(Callback):
    """Several callbacks in order; training stops when any of them returns False."""

    def __init__(self, callbacks: Iterable[Callback] = ()):
        self.callbacks = list(callbacks)

    @classmethod
    def of(cls, callback) -> "CallbackList":
        """None, a Callback, a plain function (``f(learner)``, after every update) or a list of them."""
        if callback is None:
            return cls()
        if isinstance(callback, CallbackList):
            return callback
        if isinstance(callback, Callback):
            return cls([callback])
        if callable(callback):
            return cls([FunctionCallback(callback)])
        return cls([c if isinstance(c, Callback) else FunctionCallback(c) for c in callback])

    def on_training_start(self, learner):
        for c in self.callbacks:
            c.on_training_start(learner)

    def on_step(self, learner):
        return False if any([c.on_step(learner) is False for c in self.callbacks]) else None

    def on_update(self, learner):
        return False if any([c.on_update(learner) is False for c in self.callbacks]) else None

    def on_checkpoint(self, learner, path):
        for c in self.callbacks:
            c.on_checkpoint(learner, path)

    def on_training_end(self, learner):
        for c in self.callbacks:
            c.on_training_end(learner)


class _NoBar:
    def update(self, n=1):
        pass

    def set_postfix(self, *args, **kwargs):
        pass

    def close(self):
        pass


def progress_bar(enabled: bool, total: int, initial: int = 0, unit: str = "step", desc: str | None = None):
    """A tqdm bar (or a silent stand-in with the same methods when ``enabled`` is False)."""
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit=unit, unit_scale=unit == "step", dynamic_ncols=True,
                smoothing=0.05, desc=desc)
