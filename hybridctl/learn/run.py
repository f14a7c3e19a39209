"""The training skeleton every learner stands on: run log, checkpoints, resume, callbacks, guards.

A learner (SAC, SSAC, ARS; next: analytic policy gradients, ARS fine-tuning of deep
RL policies) subclasses :class:`Learner`, declares what its checkpoint holds ONCE (a
tuple of :class:`Saved` entries), and writes only its algorithm: the loop inside
``with self.run(...) as run:``. The skeleton does the rest:

* :class:`RunLog` -- ``progress.csv`` with the learner's columns (replaced on a fresh
  run, truncated to the checkpoint's rows on resume, a clear error for a log without
  the key column), TensorBoard scalars when ``torch.utils.tensorboard`` imports;
* :class:`Checkpointer` -- one atomic checkpoint directory (see
  :mod:`hybridctl.learn.checkpoint`) written from the declared state: ``model.pt``
  (``torch.load(weights_only=True)``), ``config.json`` (written once, from
  :meth:`Learner.checkpoint_meta`), ``normalization.json``, ``progress.json`` and the
  bulky files (replay, gate data) that only a resumed run needs;
* :meth:`Learner.run` -- the run context: torch threads, ``resume=True`` (newest
  checkpoint in ``log_dir``; another algorithm's or plant's, an incomplete one or a
  missing replay / gate data file is an error unless ``force``), the log, one progress
  bar, callbacks, checkpoints by wall time (``config.checkpoint_minutes``, through
  :meth:`Run.checkpoint_if_due`), the final checkpoint on success (none after an error:
  the last good one stays intact);
* :func:`resume_changes` -- the resume policy: which config fields a resume may change
  (:data:`RESUME_APPLIED`) and which it refuses;
* :func:`check_finite` -- the NaN guard (FloatingPointError before a bad step is applied);
* :class:`EvalResult` -- what ``evaluate`` returns: typed fields and a plain dict;
* :class:`Callback` -- hooks that receive the learner;
* :func:`seeded` -- seeded initialisation that leaves the global torch RNG as it was.

>>> class MyLearner(Learner):
...     algorithm_name, log_key = "MINE", "epoch"
...     log_columns = ("epoch", "env_steps", "mean_return")
...     saved = (Saved("theta", "theta", "array"), Saved("epoch", "epoch", file=PROGRESS_FILE, load=int))
...     def learn(self, epochs, log_dir=None, resume=False, progress=True, callback=None):
...         with self.run(log_dir, resume, progress, callback, total=epochs, unit="epoch") as run:
...             while self.epoch < epochs and not run.stopped:
...                 ...                                   # the algorithm
...                 run.advance(1)
...                 run.log({"epoch": self.epoch, ...})
...         return self
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import math
import time
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from io import StringIO
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from ..io import locked_folder
from . import checkpoint as ckpt
from .checkpoint import CONFIG_FILE, MODEL_FILE, NORMALIZATION_FILE, PROGRESS_FILE, CheckpointError

__all__ = ["Learner", "Saved", "check_fields", "RESUME_APPLIED", "resume_changes", "describe_refused",
           "checkpoint_minutes", "Checkpointer", "RunLog", "Run", "Callback", "CallbackList", "EvalResult",
           "check_finite", "progress_bar", "seeded", "set_torch_threads", "MODEL_FILE", "PROGRESS_FILE"]

PROGRESS_CSV = "progress.csv"
EVAL_SEED = 12345
"""The seed of every learner's held-out evaluation (``evaluate``), apart from the training seeds."""
CURVES_PNG = "training_curves.png"


# ============================================================================ seeding and threads


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Run a block (network initialisation) on the global torch RNG seeded with ``seed``,
    then put the global RNG back as it was: a learner's seed never leaks into the caller's."""
    with torch.random.fork_rng(devices=[]):
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


# ============================================================================ config checks


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


# ============================================================================ resuming with changed settings

RESUME_APPLIED = ("total_steps", "epochs", "checkpoint_every", "checkpoint_minutes", "log_every", "tensorboard",
                  "save_replay", "torch_threads", "backend", "workers", "address", "ray_address", "eval_episodes")
"""Config fields a resumed run takes from the command line: how long to train and how to record,
checkpoint, evaluate and parallelise it. They do not change the algorithm's math. Every other
field (learning rates, gamma, network sizes, batch sizes, seed, num_envs, ...) does: a resume
with another value refuses, naming the field (``force`` applies it anyway)."""


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


def checkpoint_minutes(config) -> float:
    """``config.checkpoint_minutes`` (0 when the config has none), ValueError unless a finite number >= 0."""
    minutes = getattr(config, "checkpoint_minutes", 0.0)
    if (not isinstance(minutes, (int, float, np.number)) or isinstance(minutes, bool) or not math.isfinite(minutes)
            or minutes < 0):
        raise ValueError(f"{type(config).__name__}.checkpoint_minutes must be a finite number >= 0 "
                         f"(0: no checkpoints by time), got {minutes!r}")
    return float(minutes)


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


# ============================================================================ callbacks


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


# ============================================================================ progress bar


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


# ============================================================================ run log


class RunLog:
    """``progress.csv`` in a log folder (and TensorBoard scalars in ``tb/`` when available).

    Opening it keeps the rows of the existing file whose ``key`` column is at most
    ``upto`` (the learner's counter: the rows a resumed checkpoint had seen) and drops
    the rest; ``upto == 0`` starts a fresh file. A file without the key column is not a
    log of this learner: ValueError. The header is the learner's ``columns``.
    """

    def __init__(self, log_dir: str | Path, columns: tuple[str, ...], key: str, upto: int,
                 int_columns: tuple[str, ...] = (), float_format: str | None = ".6g", tensorboard: bool = False,
                 fallback_rows: Iterable[dict] = ()):
        self.dir = Path(log_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.columns, self.key, self.int_columns = tuple(columns), key, set(int_columns) | {key}
        self.float_format = float_format
        self.path = self.dir / PROGRESS_CSV
        self.rows = self._kept_rows(upto, fallback_rows)
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=self.columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(self._cells(r) for r in self.rows)
        tmp.replace(self.path)
        self._fh = open(self.path, "a", newline="")
        self._csv = csv.DictWriter(self._fh, fieldnames=self.columns, extrasaction="ignore")
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
                self.tb = SummaryWriter(str(self.dir / "tb"))
            except Exception:  # noqa: BLE001 - tensorboard is optional
                self.tb = None

    def _kept_rows(self, upto: int, fallback_rows: Iterable[dict]) -> list[dict]:
        if upto == 0:
            return []
        if not self.path.is_file():  # a new folder for a learner that trained before: its rows so far
            return [dict(r) for r in fallback_rows if r.get(self.key, math.inf) <= upto]
        text = self.path.read_text()
        if text and not text.endswith("\n"):  # a row cut short by a kill: dropped (its key may be cut too)
            text = text[:text.rfind("\n") + 1]
        with StringIO(text, newline="") as fh:
            reader = csv.DictReader(fh)
            if self.key not in (reader.fieldnames or []):
                raise ValueError(f"{self.path} has no {self.key!r} column: not a progress log of this learner; "
                                 f"move it or pick another log_dir")
            rows = []
            for r in reader:
                try:
                    if int(float(r[self.key])) <= upto:
                        rows.append({k: float(v) if v not in ("", None) else math.nan for k, v in r.items()})
                except (TypeError, ValueError):
                    continue
        return rows

    def _cells(self, row: dict) -> dict:
        out = {}
        for k in self.columns:
            v = row.get(k, math.nan)
            if k in self.int_columns and isinstance(v, (int, float, np.number)) and math.isfinite(v):
                out[k] = int(v)
            else:
                out[k] = format(v, self.float_format) if isinstance(v, float) and self.float_format else v
        return out

    def write(self, row: dict) -> None:
        """Append one row (missing columns empty) and flush; TensorBoard gets every finite number."""
        self._csv.writerow(self._cells(row))
        self._fh.flush()
        if self.tb is not None:
            for k, v in row.items():
                if k != self.key and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(f"train/{k}", v, row[self.key])

    def close(self) -> None:
        """Close the CSV file and the TensorBoard writer."""
        self._fh.close()
        if self.tb is not None:
            self.tb.close()


# ============================================================================ declared checkpoint state


@dataclass(frozen=True)
class Saved:
    """One entry of a learner's checkpoint: where it lives in which file, and how it is restored.

    ``key``: dotted path inside the file (``"extra.gate"`` is ``model["extra"]["gate"]``);
    ``""`` means the entry is the whole file. ``attr``: dotted attribute path on the
    learner (``"stats.sum"``). ``kind``:

    * ``"state"``: an object with ``state_dict`` / ``load_state_dict`` (modules, optimizers, buffers);
    * ``"rng"``: a ``torch.Generator`` (``get_state`` / ``set_state``);
    * ``"param"``: a tensor restored in place (``log_alpha``: the optimizer holds it);
    * ``"tensor"``: a tensor attribute replaced on load;
    * ``"array"``: a numpy array stored as a tensor, restored as a float64 copy;
    * ``"value"``: a number / list / dict (JSON in progress.json), with optional converters.

    ``bulky`` entries (replay, gate data) are written only with ``include_bulky`` and
    read only on resume. ``restore=False``: written for readers, never read back.
    ``optional``: missing on disk (older checkpoints) or None on the learner is fine.
    """

    key: str
    attr: str
    kind: str = "value"
    file: str = MODEL_FILE
    bulky: bool = False
    optional: bool = False
    restore: bool = True
    save: Callable | None = None
    load: Callable | None = None


def _get_attr(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _set_attr(obj, path: str, value) -> None:
    *parents, last = path.split(".")
    for part in parents:
        obj = getattr(obj, part)
    setattr(obj, last, value)


def _put(tree: dict, key: str, value) -> None:
    if key == "":
        tree.update(value)
        return
    *parents, last = key.split(".")
    for part in parents:
        tree = tree.setdefault(part, {})
    tree[last] = value


_MISSING = object()


def _take(tree: dict, key: str):
    if key == "":
        return tree
    for part in key.split("."):
        if not isinstance(tree, dict) or part not in tree:
            return _MISSING
        tree = tree[part]
    return tree


class Checkpointer:
    """Writes and restores a learner's checkpoint directory from its declared ``saved`` entries."""

    def __init__(self, learner: "Learner"):
        self.learner = learner

    def save(self, path: str | Path, include_bulky: bool = False) -> Path:
        """Write the checkpoint directory ``path`` atomically (the old one stays until the new is complete)."""
        learner = self.learner
        learner.before_checkpoint()

        def write(d: Path) -> None:
            files: dict[str, dict] = {MODEL_FILE: {"format": ckpt.FORMAT_VERSION}, PROGRESS_FILE: {}}
            for item in learner.saved:
                if item.bulky and not include_bulky:
                    continue
                value = _get_attr(learner, item.attr)
                if value is None:
                    if item.optional:
                        continue
                    raise CheckpointError(f"{learner.algorithm_name}: {item.attr} is None, cannot save {item.key!r}")
                _put(files.setdefault(item.file, {}), item.key, self._dump(item, value))
            for name, content in files.items():
                if name.endswith(".json"):
                    ckpt.write_json(d / name, content)
                else:
                    torch.save(content, d / name)
            ckpt.write_json(d / CONFIG_FILE, {**learner.checkpoint_meta(), "format": ckpt.FORMAT_VERSION,
                                              "files": sorted({*files, CONFIG_FILE, NORMALIZATION_FILE}),
                                              "versions": ckpt.versions()})
            ckpt.write_json(d / NORMALIZATION_FILE, learner.normalization())

        return ckpt.write_checkpoint_dir(path, write)

    @staticmethod
    def _dump(item: Saved, value):
        if item.save is not None:
            value = item.save(value)
        if item.kind == "state":
            return value.state_dict()
        if item.kind == "rng":
            return value.get_state()
        if item.kind in ("param", "tensor"):
            return value.detach().clone()
        if item.kind == "array":
            return torch.as_tensor(np.asarray(value))
        return value

    def restore(self, path: str | Path, bulky: bool = False, force: bool = False) -> Path:
        """Load the entries of the checkpoint at ``path`` (bulky ones too if ``bulky``) into the learner.

        Every file an entry lives in is read and checked: a missing, damaged or incomplete
        one raises :class:`CheckpointError` naming it (and the entry it lacks), as does a
        checkpoint written by another algorithm or on another plant
        (:meth:`Learner.check_checkpoint`). ``force``: another algorithm or plant is loaded
        with a warning (what the classes share), and a resume continues without a missing
        or damaged bulky file (replay, gate data), saying so.
        """
        learner = self.learner
        found = ckpt.resolve_checkpoint_dir(path)
        meta = ckpt.read_json(found / CONFIG_FILE)
        if not isinstance(meta, dict) or not isinstance(meta.get("config", {}), dict):
            raise CheckpointError(f"{found / CONFIG_FILE} is damaged: expected an object with 'algorithm' and "
                                  f"'config'")
        ckpt.check_algorithm(found, meta.get("algorithm"), learner.compatible_algorithms, learner.algorithm_name,
                             force)
        normalization = ckpt.read_json(found / NORMALIZATION_FILE)
        if not isinstance(normalization, dict) or "type" not in normalization:
            raise CheckpointError(f"{found / NORMALIZATION_FILE} is damaged: expected an object with 'type'")
        learner.check_checkpoint(found, meta, normalization, force=force)
        cache: dict[str, Any] = {}
        for item in learner.saved:
            if not item.restore or (item.bulky and not bulky):
                continue
            if item.file not in cache:
                cache[item.file] = self._read(found, item.file, force, meta)
            content = cache[item.file]
            if content is None:  # a bulky file that was not saved
                continue
            value = _take(content, item.key)
            if value is _MISSING:
                if item.optional:
                    continue
                raise CheckpointError(f"{found / item.file} lacks {item.key!r}")
            try:
                self._load(item, value)
            except CheckpointError:
                raise
            except (RuntimeError, KeyError, ValueError, TypeError, AttributeError) as exc:
                raise CheckpointError(f"{found / item.file}: {item.key or 'its content'!r} does not fit this "
                                      f"{learner.algorithm_name} ({type(exc).__name__}: {exc})") from exc
        learner.after_restore(found, meta, bulky)
        return found

    def missing_bulky(self, found: Path, meta: dict) -> list[tuple[str, bool]]:
        """The bulky files (replay, gate data) the checkpoint at ``found`` lacks, each with whether it
        should be there: config.json's ``files`` lists what was written (older checkpoints: the
        bulky files are expected unless their config had ``save_replay`` False)."""
        written = meta.get("files")
        out = []
        for name in dict.fromkeys(i.file for i in self.learner.saved if i.bulky):
            if not (found / name).is_file():
                expected = name in written if isinstance(written, list) else \
                    bool((meta.get("config") or {}).get("save_replay", True))
                out.append((name, expected))
        return out

    def check_resumable(self, path: str | Path, force: bool = False) -> Path:
        """Raise :class:`CheckpointError` when a resume from ``path`` would lack a replay / gate data
        file the checkpoint should hold (``force``: no error; the resume then says so)."""
        found = ckpt.resolve_checkpoint_dir(path)
        meta = ckpt.read_json(found / CONFIG_FILE)
        for name, expected in self.missing_bulky(found, meta if isinstance(meta, dict) else {}):
            if expected and not force:
                raise CheckpointError(self._missing_message(found, name))
        return found

    def _missing_message(self, found: Path, name: str) -> str:
        return (f"cannot resume from {found}: missing file {name!r} ({', '.join(self._entries(name))}); a resumed run "
                f"without it would not be the same run. --force (force=True) resumes without it")

    def _entries(self, name: str) -> list[str]:
        return [i.attr.lstrip("_") for i in self.learner.saved if i.file == name]

    def _read(self, found: Path, name: str, force: bool = False, meta: dict | None = None):
        path = found / name
        bulky = name not in ckpt.REQUIRED_FILES
        keys = self._entries(name)
        if not path.is_file():
            if not bulky:
                raise CheckpointError(f"checkpoint {found} is incomplete: missing file {name!r}")
            expected = dict(self.missing_bulky(found, meta or {})).get(name, True)
            if not expected:  # saved without it on purpose (save_replay=False, save(include_replay=False))
                warnings.warn(f"{found} was saved without {name} (save_replay=False or save(include_replay=False)): "
                              f"the resumed run starts without {', '.join(keys)}", stacklevel=4)
                return None
            if not force:
                raise CheckpointError(self._missing_message(found, name))
            warnings.warn(f"force: {found} has no {name}: the resumed run starts without {', '.join(keys)}",
                          stacklevel=4)
            return None
        try:
            content = ckpt.read_json(path) if name.endswith(".json") else ckpt.load_tensors(
                path, getattr(self.learner, "device", "cpu"))
            if not isinstance(content, dict):
                raise CheckpointError(f"{path} is damaged: expected a dict, got {type(content).__name__}")
        except CheckpointError as exc:
            if not (bulky and force):
                raise
            warnings.warn(f"force: {exc}; the resumed run starts without {', '.join(keys)}", stacklevel=4)
            return None
        return content

    def _load(self, item: Saved, value) -> None:
        learner = self.learner
        if item.kind == "state":
            target = _get_attr(learner, item.attr)
            if item.optional and (target is None or not value):  # e.g. no alpha optimizer (fixed alpha)
                return
            target.load_state_dict(value)
            return
        if item.kind == "rng":
            _get_attr(learner, item.attr).set_state(value.cpu())
            return
        if item.kind == "param":
            with torch.no_grad():
                _get_attr(learner, item.attr).copy_(value)
            return
        if item.kind == "tensor":
            current = _get_attr(learner, item.attr)
            value = value.to(dtype=current.dtype, device=current.device)
        elif item.kind == "array":
            value = value.double().numpy().copy()
        if item.load is not None:
            value = item.load(value)
        _set_attr(learner, item.attr, value)


# ============================================================================ the learner base


class Learner:
    """Base of every learner: declared checkpoint state, ``save``, the run context.

    A subclass sets ``algorithm_name``, ``config`` (a dataclass with ``torch_threads``
    where torch does work), ``log_key`` (its counter column: ``env_steps``, ``epoch``)
    and ``log_columns``, ``saved`` (its :class:`Saved` entries), the property
    :attr:`progress_count` (the counter's value) and overrides the hooks it needs:
    :meth:`checkpoint_meta`, :meth:`normalization`, :meth:`check_checkpoint`,
    :meth:`before_checkpoint`, :meth:`after_restore`, :meth:`plot_curves`,
    :meth:`extend_log_columns`.
    """

    algorithm_name = "Learner"
    compatible_algorithms: tuple[str, ...] = ()   # checkpoints this class restores (default: its own)
    log_key = "env_steps"
    log_columns: tuple[str, ...] = ("env_steps",)
    log_int_columns: tuple[str, ...] = ()
    log_float_format: str | None = ".6g"   # None: full precision (repr)
    saved: tuple[Saved, ...] = ()
    log_rows: list[dict]                   # progress rows so far (set by the subclass's __init__)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "compatible_algorithms" not in cls.__dict__:
            cls.compatible_algorithms = (cls.algorithm_name,)
        # a subclass's hook appends its columns to the inherited ones (each column once)
        cls.log_columns = tuple(dict.fromkeys(cls.extend_log_columns(tuple(cls.log_columns))))

    @classmethod
    def extend_log_columns(cls, columns: tuple[str, ...]) -> tuple[str, ...]:
        """Hook: the progress.csv columns of this class (a subclass appends its own)."""
        return columns

    # ------------------------------------------------------------------ counters and hooks
    @property
    def progress_count(self) -> int:
        """The value of the ``log_key`` counter (env steps, epochs)."""
        raise NotImplementedError

    def checkpoint_meta(self) -> dict:
        """config.json: algorithm, config and what a loader needs to rebuild the learner."""
        return {"algorithm": self.algorithm_name, "config": dataclasses.asdict(self.config)}

    def normalization(self) -> dict:
        """normalization.json: the observation normalisation ({"type": "none"} when there is none)."""
        return {"type": "none"}

    def check_checkpoint(self, found: Path, meta: dict, normalization: dict, force: bool = False) -> None:
        """Hook: raise CheckpointError when the checkpoint at ``found`` does not fit this learner
        (another plant, normalisation); ``force``: warn instead where loading can go on."""

    def before_checkpoint(self) -> None:
        """Hook: bring the declared state up to date before it is written."""

    def after_restore(self, found: Path, meta: dict, bulky: bool) -> None:
        """Hook: after the declared state was restored (e.g. restart the env's episodes)."""

    def plot_curves(self, log: RunLog) -> None:
        """Hook: write training curves into the log folder (default: none)."""

    # ------------------------------------------------------------------ save
    @property
    def checkpointer(self) -> Checkpointer:
        """The :class:`Checkpointer` of this learner."""
        return Checkpointer(self)

    def save(self, path: str | Path, include_replay: bool = False) -> Path:
        """Write a checkpoint directory atomically; ``include_replay`` adds the bulky files
        (replay buffers, gate data) that a resumed run needs."""
        return self.checkpointer.save(path, include_bulky=include_replay)

    def _checkpoint_with_data(self) -> bool:
        """Whether checkpoints written by ``learn`` include the bulky files (config ``save_replay``)."""
        return bool(getattr(self.config, "save_replay", True))

    def run_updates(self, run: "Run", target: int, train: Callable[[], dict], rollouts: int, every: int,
                    postfix: Callable[[dict], dict]) -> None:
        """The loop of a learner that counts whole updates (ARS epochs, fine-tuning updates).

        Until ``progress_count`` reaches ``target`` or a callback stops the run: ``train()``
        returns the update's row (with ``episode_steps``, the mean episode length); the loop adds
        the learner's ``wall_time`` and ``steps_per_s`` (over ``rollouts`` episodes), appends it to
        ``history``, logs it, advances the bar (``postfix(row)``: its fields) and checkpoints every
        ``every`` updates, or when ``checkpoint_minutes`` have passed (not after the last update,
        which the run's ``final/`` follows).
        """
        while self.progress_count < target and not run.stopped:
            start = time.perf_counter()
            row = train()
            took = time.perf_counter() - start
            self.wall_time += took
            row.update(wall_time=self.wall_time, steps_per_s=row["episode_steps"] * rollouts / max(took, 1e-9))
            self.history.append(row)
            run.log(row)
            run.advance(1, **postfix(row))
            run.after_update()
            by_count = self.progress_count % every == 0
            if by_count or self.progress_count < target:
                run.checkpoint_if_due(by_count)

    # ------------------------------------------------------------------ the run context
    @contextlib.contextmanager
    def run(self, log_dir: str | Path | None, resume: bool, progress: bool, callback, total: int,
            unit: str = "step", desc: str | None = None, force: bool = False) -> Iterator["Run"]:
        """The context of one ``learn`` call (see :class:`Run`).

        On entry: the lock of ``log_dir`` (:func:`hybridctl.io.locked_folder`: another process
        writing it is refused, naming its pid), torch threads, ``resume`` (restore the newest of
        ``log_dir/checkpoint`` and ``log_dir/final``; a warning and the learner's current state
        when there is none; an incomplete or damaged one, one of another algorithm or plant, is an
        error unless ``force``; so is a checkpoint whose counter is beyond the budget ``total``:
        the run would "finish" untrained; the counters' type and range are checked as
        progress.json is read, :data:`hybridctl.learn.checkpoint.SCHEMAS`), the run log, the
        progress bar, ``on_training_start``.
        During the run: a checkpoint ``log_dir/checkpoint`` at least every
        ``config.checkpoint_minutes`` of wall time (:meth:`Run.checkpoint_if_due`; 0: by the
        learner's step cadence only). On a normal exit: the final checkpoint
        ``log_dir/final``, the curves, ``on_training_end``. On an error: files closed, no
        checkpoint written.
        """
        log_dir = Path(log_dir) if log_dir is not None else None
        minutes = checkpoint_minutes(self.config)
        if resume and log_dir is None:
            raise ValueError("learn(resume=True) needs the log_dir of the run to resume")
        with contextlib.ExitStack() as held:
            if log_dir is not None:  # another process writing the folder is refused (nests under train's lock)
                held.enter_context(locked_folder(log_dir, "log_dir"))
            previous_threads = set_torch_threads(getattr(self.config, "torch_threads", 1))
            try:
                yield from self._run(log_dir, resume, progress, callback, total, unit, desc, force, minutes)
            finally:
                torch.set_num_threads(previous_threads)

    def _run(self, log_dir: Path | None, resume: bool, progress: bool, callback, total: int, unit: str,
             desc: str | None, force: bool, minutes: float) -> Iterator["Run"]:
        """The body of :meth:`run` in its locked log folder (a generator: it yields the :class:`Run` once)."""
        run = None
        try:
            if resume:
                found = ckpt.newest_checkpoint([log_dir / "checkpoint", log_dir / "final"], self.log_key,
                                               strict=not force)
                if found is None:
                    warnings.warn(f"resume=True but no checkpoint in {log_dir}; starting from the learner's current "
                                  f"state ({self.log_key} {self.progress_count})", stacklevel=4)
                else:
                    self.checkpointer.restore(found, bulky=True, force=force)
                    self.check_budget(found, total, unit)
            log = None
            if log_dir is not None:
                log = RunLog(log_dir, self.log_columns, self.log_key, self.progress_count, self.log_int_columns,
                             self.log_float_format, tensorboard=bool(getattr(self.config, "tensorboard", False)),
                             fallback_rows=self.log_rows)
                self.log_rows = list(log.rows)
            run = Run(self, log_dir, log, CallbackList.of(callback),
                      progress_bar(progress, total, self.progress_count, unit, desc), checkpoint_seconds=60.0 * minutes)
            run.callbacks.on_training_start(self)
            yield run
            if log_dir is not None:
                run.checkpoint("final")
            run.callbacks.on_training_end(self)
        finally:
            if run is not None:
                run.close()

    def check_budget(self, found: Path, total: int, unit: str) -> None:
        """Refuse a resume whose checkpoint counted more than the run's budget ``total`` allows (one
        round of ``num_envs`` env steps over it is a finished run): it would "finish" untrained."""
        slack = int(getattr(self.config, "num_envs", 1) or 1) if self.log_key == "env_steps" else 0
        if self.progress_count > int(total) + slack:
            raise CheckpointError(f"{found / PROGRESS_FILE}: {self.log_key!r} is {self.progress_count:,}, beyond "
                                  f"this run's budget of {int(total):,} {unit}s; resume with a larger budget or "
                                  f"start a new run")


CURVES_EVERY_S = 30.0
"""Seconds between redraws of ``training_curves.png`` at periodic checkpoints (the final one always draws)."""


class Run:
    """One training run in progress: what a learner's loop calls.

    ``advance(n)`` after each step (progress bar, ``on_step``), ``after_update()`` after
    each update round, ``log(row)`` for a progress row, ``checkpoint()`` for
    ``log_dir/checkpoint``; ``stopped`` turns True when a callback returned False.
    """

    def __init__(self, learner: Learner, log_dir: Path | None, log: RunLog | None, callbacks: CallbackList, bar,
                 checkpoint_seconds: float = 0.0):
        self.learner, self.log_dir, self.logger, self.callbacks, self.bar = learner, log_dir, log, callbacks, bar
        self.stopped = False
        self.checkpoint_seconds = float(checkpoint_seconds)
        self._last_checkpoint = time.monotonic()
        self._last_curves: float | None = None   # when training_curves.png was last drawn

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

    def close(self) -> None:
        """Close the bar and the log."""
        self.bar.close()
        if self.logger is not None:
            self.logger.close()
