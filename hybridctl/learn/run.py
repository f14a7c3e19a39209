"""One training run in progress: the run context, the loop of update-counting learners, guards.

A learner (:class:`hybridctl.learn.base.Learner`) writes only its algorithm, inside
:func:`training_run` (which its base ``learn`` opens); this module gives the run (it knows the
learner only as :class:`LearnerInTraining`, what a run reads and writes on it, so ``base``
imports ``run`` and never the other way round):

* :func:`training_run` -- the context of one ``learn`` call: the folder lock, torch threads,
  ``resume`` (newest checkpoint in ``out``; another algorithm's or plant's, an incomplete one
  or a missing replay / gate data file is an error unless ``force``), the run log
  (:class:`~hybridctl.learn.runlog.RunLog`), one progress bar, callbacks
  (:mod:`hybridctl.learn.callbacks`), checkpoints by steps and by wall time
  (``config.checkpoint_minutes``), the final checkpoint on success (none after an error: the
  last good one stays intact);
* :class:`Run` -- what the algorithm's loop calls: ``advance``, ``log``, ``after_update``,
  ``checkpoint_if_due``, and :meth:`Run.updates`, the whole loop of a learner that counts updates;
* :func:`check_finite` -- the NaN guard (FloatingPointError before a bad step is applied);
* :class:`EvalResult` -- what ``evaluate`` returns: typed fields and a plain dict;
* :func:`seeded` -- seeded initialisation that leaves the global torch RNG as it was.
"""

from __future__ import annotations

import contextlib
import math
import time
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

import numpy as np
import torch

from ..io import locked_folder
from ..systems.compiled import CompileGarbage
from . import checkpoint as ckpt
from .callbacks import CallbackList, progress_bar
from .checkpoint import PROGRESS_FILE, CheckpointError
from .config_check import checkpoint_minutes
from .runlog import RunLog

__all__ = ["Run", "training_run", "LearnerInTraining", "EvalResult", "check_finite", "seeded", "set_torch_threads", "EVAL_SEED"]

EVAL_SEED = 12345
"""The seed of every learner's held-out evaluation (``evaluate``), apart from the training seeds."""


class LearnerInTraining(Protocol):
    """What a run reads and writes on its learner (:class:`hybridctl.learn.base.Learner` and its subclasses)."""

    config: Any
    log_key: str
    log_columns: tuple[str, ...]
    log_int_columns: tuple[str, ...]
    log_float_format: str | None
    log_rows: list[dict]
    history: list[dict]                 # rows of the update-counting learners (Run.updates)
    wall_time: float
    checkpointer: Any

    @property
    def progress_count(self) -> int: ...

    def plot_curves(self, log: RunLog) -> None: ...

    def _checkpoint_with_data(self) -> bool: ...


# ============================================================================ seeding and threads


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Run a block (network initialisation) on the global CPU torch RNG seeded with ``seed``,
    then put the global RNG back as it was: a learner's seed never leaks into the caller's.

    Tensors made inside without a device are made on the CPU whatever the default device:
    initial weights come from the CPU generator, so one seed gives the same weights on every
    device, and the learner moves them to its own (``.to(device)``)."""
    with torch.random.fork_rng(devices=[]), torch.device("cpu"):
        torch.manual_seed(int(seed))
        yield


def set_torch_threads(threads: int | None) -> int:
    """``torch.set_num_threads(threads or 1)``; returns the previous count.

    Learners call it before any work of their own: the tiny networks here gain nothing
    from more threads, and the gate warm start ran 10x slower with the default count
    on a shared 2-core machine (175 s instead of 18 s).
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(int(threads or 1))
    return previous


# ============================================================================ the NaN guard


def check_finite(name: str, value, where: str) -> None:
    """Raise FloatingPointError if ``value`` (a loss, parameters: tensor, array, number or
    an iterable of tensors) has a NaN/Inf. ``where`` says when (e.g. "at env step 1200").

    Learners call it before applying a step, so the bad step never reaches the weights,
    and the run context writes no checkpoint after the error: the last good one stays.
    """
    if isinstance(value, torch.Tensor):  # a scalar loss: one item() (~1 us) instead of two kernels (~10 us)
        finite = math.isfinite(value.item()) if value.numel() == 1 else bool(torch.isfinite(value).all())
    elif isinstance(value, (np.ndarray, float, int, np.generic)):
        finite = bool(np.all(np.isfinite(value)))
    elif isinstance(value, Iterable):
        value = list(value)
        finite = all(bool(torch.isfinite(v).all()) for v in value)
    else:
        raise TypeError(f"check_finite: cannot check a {type(value).__name__}")
    if not finite:  # the message shows a single number, else says "non-finite"
        if isinstance(value, torch.Tensor):
            shown = float(value.detach().reshape(-1)[0]) if value.numel() == 1 else "non-finite"
        elif isinstance(value, list):
            shown = "non-finite"
        else:
            shown = float(np.reshape(value, -1)[0]) if np.size(value) == 1 else "non-finite"
        raise FloatingPointError(f"{name} became {shown} {where}; training stopped before applying it. "
                                 f"The last good checkpoint (if any) is left intact.")


# ============================================================================ evaluation results


class EvalResult(dict):
    """What ``evaluate`` returns: a plain dict (``result["mean_return"]``, ``result.update(...)``,
    ``json.dumps(result)`` all work) with the common statistics also as attributes.

    Keys always present: ``episodes``, ``mean_return``, ``std_return``, ``min_return``,
    ``success_rate`` (None where the env has no success test) and ``returns``; a
    learner adds its own (``seed``, ``deterministic``, ARS: ``steps``, ``dimension``, ...).
    """

    FIELDS = ("episodes", "mean_return", "std_return", "min_return", "success_rate", "returns")

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        missing = [k for k in self.FIELDS if k not in self]
        if missing:
            raise ValueError(f"EvalResult needs {missing}")

    @classmethod
    def from_returns(cls, returns, success_rate: float | None = None, first: dict | None = None,
                     **extra) -> "EvalResult":
        """Statistics of the episode ``returns``, with ``success_rate`` (None: the env has no success test).

        ``first``: keys placed before the statistics (e.g. episodes, seed), ``extra`` after.
        Means are numpy's over float64 returns; None when there are no returns.
        """
        r = np.asarray(returns, dtype=np.float64)
        stats = {"mean_return": float(r.mean()) if r.size else None,
                 "std_return": float(r.std()) if r.size else None,
                 "min_return": float(r.min()) if r.size else None,
                 "success_rate": None if success_rate is None else float(success_rate)}
        head = dict(first or {})
        head.setdefault("episodes", int(r.size))
        return cls({**head, **stats, "returns": r.tolist(), **extra})

    def to_dict(self) -> dict:
        """A plain dict copy."""
        return dict(self)

    episodes = property(lambda self: self["episodes"], doc="Number of episodes run.")
    mean_return = property(lambda self: self["mean_return"], doc="Mean episode return.")
    std_return = property(lambda self: self["std_return"], doc="Standard deviation of the returns.")
    min_return = property(lambda self: self["min_return"], doc="Smallest return.")
    success_rate = property(lambda self: self["success_rate"], doc="Share of episodes that passed the success test.")
    returns = property(lambda self: self["returns"], doc="Every episode's return.")


CURVES_EVERY_S = 30.0
"""Seconds between redraws of ``training_curves.png`` at periodic checkpoints (the final one always draws)."""


@contextlib.contextmanager
def training_run(learner: LearnerInTraining, out: str | Path | None, resume: bool, progress: bool, callback, total: int,
                 unit: str = "step", desc: str | None = None, force: bool = False) -> Iterator["Run"]:
    """The context of one ``learn`` call (see :class:`Run`).

    On entry: the lock of ``out`` (:func:`hybridctl.io.locked_folder`: another process
    writing it is refused, naming its pid), torch threads, ``resume`` (restore the newest of
    ``out/checkpoint`` and ``out/final``; a warning and the learner's current state
    when there is none; an incomplete or damaged one, one of another algorithm or plant, is an
    error unless ``force``; so is a checkpoint whose counter is beyond the budget ``total``:
    the run would "finish" untrained; the counters' type and range are checked as
    progress.json is read, :data:`hybridctl.learn.checkpoint.SCHEMAS`), the run log, the
    progress bar, ``on_training_start``.
    During the run: a checkpoint ``out/checkpoint`` at least every
    ``config.checkpoint_minutes`` of wall time (:meth:`Run.checkpoint_if_due`; 0: by the
    learner's step cadence only). On a normal exit: the final checkpoint
    ``out/final``, the curves, ``on_training_end``. On an error: files closed, no
    checkpoint written.
    """
    out = Path(out) if out is not None else None
    minutes = checkpoint_minutes(learner.config)
    if resume and out is None:
        raise ValueError("learn(resume=True) needs out=, the run folder to resume")
    with contextlib.ExitStack() as held:
        if out is not None:  # another process writing the folder is refused (nests under train's lock)
            held.enter_context(locked_folder(out, "out"))
        previous_threads = set_torch_threads(getattr(learner.config, "torch_threads", 1))
        try:
            yield from _training_run(learner, out, resume, progress, callback, total, unit, desc, force, minutes)
        finally:
            torch.set_num_threads(previous_threads)


def _training_run(learner: LearnerInTraining, out: Path | None, resume: bool, progress: bool, callback, total: int,
                  unit: str, desc: str | None, force: bool, minutes: float) -> Iterator["Run"]:
    """The body of :func:`training_run` in its locked log folder (a generator: it yields the :class:`Run` once)."""
    run = None
    try:
        if resume:
            found = ckpt.newest_checkpoint([out / "checkpoint", out / "final"], learner.log_key,
                                           strict=not force)
            if found is None:
                warnings.warn(f"resume=True but no checkpoint in {out}; starting from the learner's current "
                              f"state ({learner.log_key} {learner.progress_count})", stacklevel=4)
            else:
                learner.checkpointer.restore(found, bulky=True, force=force)
                check_budget(learner, found, total, unit)
        log = None
        if out is not None:
            log = RunLog(out, learner.log_columns, learner.log_key, learner.progress_count, learner.log_int_columns,
                         learner.log_float_format, tensorboard=bool(getattr(learner.config, "tensorboard", False)),
                         fallback_rows=learner.log_rows)
            learner.log_rows = list(log.rows)
        run = Run(learner, out, log, CallbackList.of(callback),
                  progress_bar(progress, total, learner.progress_count, unit, desc), checkpoint_seconds=60.0 * minutes)
        run.callbacks.on_training_start(learner)
        yield run
        if out is not None:
            run.checkpoint("final")
        run.callbacks.on_training_end(learner)
    finally:
        if run is not None:
            run.close()


def check_budget(learner: LearnerInTraining, found: Path, total: int, unit: str) -> None:
    """Refuse a resume whose checkpoint counted more than the run's budget ``total`` allows (one
    round of ``num_envs`` env steps over it is a finished run): it would "finish" untrained."""
    slack = int(getattr(learner.config, "num_envs", 1) or 1) if learner.log_key == "env_steps" else 0
    if learner.progress_count > int(total) + slack:
        raise CheckpointError(f"{found / PROGRESS_FILE}: {learner.log_key!r} is {learner.progress_count:,}, beyond "
                              f"this run's budget of {int(total):,} {unit}s; resume with a larger budget or "
                              f"start a new run")


class Run:
    """One training run in progress: what a learner's loop calls.

    ``advance(n)`` after each step (progress bar, ``on_step``), ``after_update()`` after
    each update round, ``log(row)`` for a progress row, ``checkpoint()`` for
    ``log_dir/checkpoint``; ``stopped`` turns True when a callback returned False.
    """

    def __init__(self, learner: LearnerInTraining, log_dir: Path | None, log: RunLog | None, callbacks: CallbackList, bar,
                 checkpoint_seconds: float = 0.0):
        self.learner, self.log_dir, self.logger, self.callbacks, self.bar = learner, log_dir, log, callbacks, bar
        self.stopped = False
        self.checkpoint_seconds = float(checkpoint_seconds)
        self._last_checkpoint = time.monotonic()
        self._last_curves: float | None = None   # when training_curves.png was last drawn
        self._compile_garbage = CompileGarbage()   # full GC passes skip what a compile left (settled per update)

    def checkpoint_due(self) -> bool:
        """Whether ``checkpoint_seconds`` of wall time passed since the run began or last checkpointed."""
        return self.checkpoint_seconds > 0 and time.monotonic() - self._last_checkpoint >= self.checkpoint_seconds

    def checkpoint_if_due(self, by_steps: bool = False) -> Path | None:
        """Write ``log_dir/checkpoint`` when the learner's step cadence says so (``by_steps``) or the
        time cadence is due (a kill then loses at most ``checkpoint_minutes``); else nothing."""
        if by_steps or self.checkpoint_due():
            return self.checkpoint()
        return None

    def advance(self, n: int, **postfix) -> None:
        """``n`` steps done: move the bar (with ``postfix`` shown), call ``on_step``."""
        self.bar.update(n)
        if postfix:
            self.bar.set_postfix(postfix, refresh=False)
        if self.callbacks.on_step(self.learner) is False:
            self.stopped = True

    def after_update(self, **postfix) -> None:
        """An update round done: call ``on_update`` (False stops the run)."""
        self._compile_garbage.settle()
        if postfix:
            self.bar.set_postfix(postfix, refresh=False)
        if self.callbacks.on_update(self.learner) is False:
            self.stopped = True

    def log(self, row: dict) -> None:
        """Record a progress row in ``learner.log_rows`` and write it (when the run has a log folder)."""
        self.learner.log_rows.append(row)
        if self.logger is not None:
            self.logger.write(row)

    def checkpoint(self, name: str = "checkpoint") -> Path | None:
        """Write ``log_dir/name`` (with the bulky files if the config says so) and the curves."""
        self._last_checkpoint = time.monotonic()
        if self.log_dir is None:
            return None
        path = self.learner.checkpointer.save(self.log_dir / name, include_bulky=self.learner._checkpoint_with_data())
        # the curves take ~1.5 s to draw: at most every CURVES_EVERY_S on periodic checkpoints (a run
        # checkpointing every second spent 94 % of its time drawing), always for the final one
        now = time.monotonic()
        due = name != "checkpoint" or self._last_curves is None or now - self._last_curves >= CURVES_EVERY_S
        if self.logger is not None and due:
            self.learner.plot_curves(self.logger)
            self._last_curves = now
        self.callbacks.on_checkpoint(self.learner, path)
        return path

    def updates(self, target: int, train: Callable[[], dict], rollouts: int, every: int,
                postfix: Callable[[dict], dict]) -> None:
        """The loop of a learner that counts whole updates (ARS epochs, fine-tuning updates).

        Until the learner's ``progress_count`` reaches ``target`` or a callback stops the run: ``train()``
        returns the update's row (with ``episode_steps``, the mean episode length); the loop adds
        the learner's ``wall_time`` and ``steps_per_s`` (over ``rollouts`` episodes), appends it to
        ``history``, logs it, advances the bar (``postfix(row)``: its fields) and checkpoints every
        ``every`` updates, or when ``checkpoint_minutes`` have passed (not after the last update,
        which the run's ``final/`` follows).
        """
        learner = self.learner
        while learner.progress_count < target and not self.stopped:
            start = time.perf_counter()
            row = train()
            took = time.perf_counter() - start
            learner.wall_time += took
            row.update(wall_time=learner.wall_time, steps_per_s=row["episode_steps"] * rollouts / max(took, 1e-9))
            learner.history.append(row)
            self.log(row)
            self.advance(1, **postfix(row))
            self.after_update()
            by_count = learner.progress_count % every == 0
            if by_count or learner.progress_count < target:
                self.checkpoint_if_due(by_count)

    def close(self) -> None:
        """Close the bar and the log; the collector walks every object again."""
        self._compile_garbage.release()
        self.bar.close()
        if self.logger is not None:
            self.logger.close()
