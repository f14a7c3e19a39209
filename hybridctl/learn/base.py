"""The one learner contract, as Stable-Baselines3's ``BaseAlgorithm``: ``learn``, ``evaluate``, ``save``, ``load``.

Every learner (SAC, SSAC, ARS, the APG family, fine-tuning) subclasses :class:`Learner`, declares
what its checkpoint holds ONCE (a tuple of :class:`~hybridctl.learn.checkpoint.Saved` entries) and
writes only its algorithm (:meth:`Learner.train`, the loop inside the run) and its evaluation
rollouts (:meth:`Learner.run_evaluation`). The base gives every learner the same calls:

* ``learn(total=None, *, out=None, resume=False, force=False, callback=None, progress=True,
  backend=None)`` -- train until the learner's counter reaches ``total`` (env steps, epochs or
  updates: ``budget_field`` names the config field of the default), in the run context of
  :func:`hybridctl.learn.run.training_run` (run log, checkpoints by steps and by time, resume,
  callbacks, progress bar, the final checkpoint);
* ``evaluate(episodes=None, *, seed=EVAL_SEED, **options)`` -- held-out episodes, an
  :class:`~hybridctl.learn.run.EvalResult`;
* ``save(path, include_replay=False)`` and ``Learner.load(path, *, system=None, force=False,
  **overrides)`` -- one checkpoint directory, one ``config.json`` schema (algorithm, format,
  ``system`` record, config, versions, files; the counters in ``progress.json``) read through
  :func:`~hybridctl.learn.checkpoint.read_meta` (older layouts upgraded) and
  :func:`~hybridctl.learn.checkpoint.config_from_meta` (a dropped field loads with a warning);
* ``controller(system=None)`` -- the :class:`~hybridctl.systems.SwitchedController` its policy drives
  a system with (a learner that drives none keeps the default, an error). A class that sets
  ``algorithm_name`` registers itself (:mod:`hybridctl.learn.registry`), so
  :func:`hybridctl.learn.load_controller` turns its checkpoints into controllers by config.json's
  ``algorithm``, for named controllers, balance maps and fine-tuning alike.

>>> class MyLearner(Learner):
...     algorithm_name, config_class, budget_field, unit = "MINE", MyConfig, "epochs", "epoch"
...     log_key, log_columns = "epoch", ("epoch", "mean_return")
...     saved = (Saved("theta", "theta", "array"), Saved("epoch", "epoch", file=PROGRESS_FILE, load=int))
...     def train(self, run, target, backend):
...         while self.epoch < target and not run.stopped:
...             ...                                   # the algorithm
...             run.advance(1)
...             run.log({"epoch": self.epoch, ...})
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
import numpy as np

from . import checkpoint as ckpt
from .checkpoint import Checkpointer, Saved
from .registry import no_swingup, register_learner
from .run import EVAL_SEED, EvalResult, Run, training_run
from .runlog import RunLog

__all__ = ["Learner", "DEFAULT_EVAL_EPISODES"]

DEFAULT_EVAL_EPISODES = 100
"""Episodes of ``evaluate()`` for a learner whose config names none (thesis Sec. 3.4 / 6.3: 100 trials)."""


class Learner:
    """Base of every learner: the ``learn`` / ``evaluate`` / ``save`` / ``load`` contract.

    A subclass sets ``algorithm_name``, ``config_class`` and ``config`` (a dataclass with
    ``torch_threads`` where torch does work), ``budget_field`` (the config field holding
    ``learn``'s default total) and ``unit``, ``log_key`` (its counter column: ``env_steps``,
    ``epoch``) and ``log_columns``, ``saved`` (its :class:`Saved` entries), the property
    :attr:`progress_count` (the counter's value), :meth:`train` (the algorithm),
    :meth:`run_evaluation` (its evaluation rollouts) and :meth:`from_checkpoint` (build the
    learner a checkpoint then restores), and overrides the hooks it needs:
    :meth:`system_record`, :meth:`checkpoint_extra`, :meth:`normalization`,
    :meth:`check_checkpoint`, :meth:`before_checkpoint`, :meth:`after_restore`,
    :meth:`plot_curves`, :meth:`extend_log_columns`, :meth:`run_description`.
    """

    algorithm_name = "Learner"
    config_class: type | None = None
    compatible_algorithms: tuple[str, ...] = ()   # checkpoints this class restores (default: its own)
    budget_field = "total_steps"                   # the config field of learn()'s default total
    unit = "step"                                  # what the counter counts (progress bar, messages)
    log_key = "env_steps"
    log_columns: tuple[str, ...] = ("env_steps",)
    log_int_columns: tuple[str, ...] = ()
    log_float_format: str | None = ".6g"   # None: full precision (repr)
    saved: tuple[Saved, ...] = ()
    log_rows: list[dict]                   # progress rows so far (set by the subclass's __init__)

    controller_aliases: tuple[str, ...] = ()
    """Lower-case kinds of named controllers ``KIND:PATH`` beside the algorithm's name (APG: its methods)."""
    train_names: tuple[str, ...] | None = None
    """The names ``hybridctl train NAME`` and :func:`~hybridctl.experiments.train_and_evaluate` run this learner
    under (None: its ``algorithm_name`` in lower case; ``()``: none, as fine-tuning, which has its own command).
    Read from the registry (:func:`~hybridctl.learn.registry.trainable_learners`): no other file lists them."""
    train_order = 100
    """Where its names come in ``hybridctl train``'s list (lower first; SAC, SSAC, ARS, the APG family: 0-3)."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "compatible_algorithms" not in cls.__dict__:
            cls.compatible_algorithms = (cls.algorithm_name,)
        # a subclass's hook appends its columns to the inherited ones (each column once)
        cls.log_columns = tuple(dict.fromkeys(cls.extend_log_columns(tuple(cls.log_columns))))
        if "algorithm_name" in cls.__dict__:   # the class that names an algorithm loads its checkpoints
            register_learner(cls.algorithm_name, cls, tuple(cls.controller_aliases))

    @classmethod
    def extend_log_columns(cls, columns: tuple[str, ...]) -> tuple[str, ...]:
        """Hook: the progress.csv columns of this class (a subclass appends its own)."""
        return columns

    # ------------------------------------------------------------------ learn
    def learn(self, total: int | None = None, *, out: str | Path | None = None, resume: bool = False,
              force: bool = False, callback=None, progress: bool = True, backend=None) -> "Learner":
        """Train until the learner's counter (``log_key``) reaches ``total`` in all.

        Args:
            total: the run's total (not an increment) in the learner's ``unit``: env steps
                (SAC, SSAC), epochs (ARS, the APG family) or updates (fine-tuning); default the
                config's ``budget_field``. A resumed run or a second call continues until the
                learner has done that many in all.
            out: the run folder: ``progress.csv``, the checkpoints ``checkpoint/`` (every
                ``checkpoint_every`` and at least every ``checkpoint_minutes`` of wall time) and
                ``final/``, training curves. None: no files.
            resume: first restore the newest checkpoint in ``out`` (networks, optimizers,
                counters, RNG states and, if saved, the replay / gate data); without one, a
                warning and the learner's current state.
            force: resume from a checkpoint of another algorithm or plant, or without its
                replay / gate data file (each with a warning).
            callback: a :class:`~hybridctl.learn.callbacks.Callback`, a list of them, or a plain
                ``f(learner)`` called after every update; False stops training.
            progress: show a tqdm bar.
            backend: an open parallel backend (:func:`hybridctl.parallel.make_backend`) for the
                learners whose rollouts run on one (ARS, fine-tuning, the APG family's population
                split); default: the config's backend, opened for the run. A learner without
                parallel rollouts refuses one.

        Raises FloatingPointError if training diverges (the last checkpoint stays intact);
        CheckpointError for a resume from an unfit checkpoint.
        """
        target = self.budget(total)
        if backend is not None and not self.uses_backend:
            raise ValueError(f"{self.algorithm_name}.learn(backend=...): {self.algorithm_name} runs no parallel "
                             f"rollouts; leave backend None")
        with training_run(self, out, resume, progress, callback, target, self.unit, self.run_description(),
                          force) as run:
            self.train(run, target, backend)
        return self

    uses_backend = False
    """Whether :meth:`train` runs its rollouts on a parallel backend (``learn(backend=...)``)."""
    takes_gym_envs = False
    """Whether the learner trains on gymnasium env ids as well as hybridctl systems (ARS)."""
    takes_spec = False
    """Whether a training run may give spec overrides (``hybridctl train --spec``) for a new run."""
    warm_starts = False
    """Whether a training run may start from another run's checkpoint (``hybridctl train --init``)."""
    init_keeps_data = False
    """Whether ``--init`` also restores the checkpoint's bulky files (replay buffers, gate data), as a resume does."""
    record_evaluation: dict = {}
    """The ``evaluate`` options of the evaluation a training run records in ``eval.json``."""

    @classmethod
    def run_label(cls, config) -> str:
        """The learner's name in a run's account ("SAC", "papg")."""
        return cls.algorithm_name

    def training_record(self) -> dict:
        """What ``eval.json`` records of the training beside the evaluation: counters and wall time."""
        return {self.log_key: self.progress_count, "train_wall_time_s": self.wall_time}

    def budget(self, total: int | None) -> int:
        """``total`` (default the config's ``budget_field``) as an integer >= 1, else ValueError naming it."""
        value = getattr(self.config, self.budget_field) if total is None else total
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise ValueError(f"total ({self.budget_field}) must be an integer >= 1, got {value!r}")
        if value < 1:
            raise ValueError(f"total ({self.budget_field}) must be an integer >= 1, got {value!r}")
        return int(value)

    def train(self, run: Run, target: int, backend) -> None:
        """The algorithm: train inside ``run`` until ``progress_count`` reaches ``target`` or
        ``run.stopped`` (a subclass writes it; :meth:`Run.updates` is the loop of a learner
        that counts whole updates)."""
        raise NotImplementedError

    def run_description(self) -> str:
        """The progress bar's label."""
        return self.algorithm_name

    # ------------------------------------------------------------------ evaluate
    def evaluate(self, episodes: int | None = None, *, seed: int = EVAL_SEED, **options) -> EvalResult:
        """Held-out deterministic episodes of the trained policy (``episodes``: default the config's
        ``eval_episodes``, else :data:`DEFAULT_EVAL_EPISODES`; ``seed``: their initial
        conditions, :data:`~hybridctl.learn.run.EVAL_SEED` by default, apart from every training
        seed). ``options``: the learner's own (see its :meth:`run_evaluation`)."""
        n = getattr(self.config, "eval_episodes", DEFAULT_EVAL_EPISODES) if episodes is None else episodes
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f"episodes must be an integer >= 1, got {n!r}")
        return self.run_evaluation(int(n), int(seed), **options)

    def run_evaluation(self, episodes: int, seed: int, **options) -> EvalResult:
        """The evaluation rollouts of :meth:`evaluate` (a subclass writes them)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ counters and hooks
    @property
    def progress_count(self) -> int:
        """The value of the ``log_key`` counter (env steps, epochs)."""
        raise NotImplementedError

    def system_record(self) -> dict:
        """config.json's ``system``: what the learner trained on (a hybridctl system:
        :func:`~hybridctl.learn.checkpoint.system_record`; a gymnasium env:
        :func:`~hybridctl.learn.checkpoint.env_record`)."""
        return ckpt.system_record(self.system)

    def checkpoint_extra(self) -> dict:
        """Hook: what else config.json records for a loader (dimensions, the policy's architecture)."""
        return {}

    def checkpoint_meta(self) -> dict:
        """config.json, one schema for every learner: ``algorithm``, ``system`` (the record of what it
        trained on), ``config`` and the learner's extras (the checkpointer adds ``format``,
        ``files`` and ``versions``)."""
        return {"algorithm": self.algorithm_name, "system": self.system_record(),
                "config": dataclasses.asdict(self.config), **self.checkpoint_extra()}

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

    def warm_started(self) -> None:
        """Hook: this learner was loaded from another run's checkpoint to train on (``--init``), perhaps
        on another reward: forget what only held for that run's task (a best score it was ranked by)."""

    def plot_curves(self, log: RunLog) -> None:
        """Hook: write training curves into the log folder (default: none)."""

    # ------------------------------------------------------------------ save and load
    @property
    def checkpointer(self) -> Checkpointer:
        """The :class:`~hybridctl.learn.checkpoint.Checkpointer` of this learner."""
        return Checkpointer(self)

    def save(self, path: str | Path, include_replay: bool = False) -> Path:
        """Write a checkpoint directory atomically; ``include_replay`` adds the bulky files
        (replay buffers, gate data) that a resumed run needs."""
        return self.checkpointer.save(path, include_bulky=include_replay)

    def _checkpoint_with_data(self) -> bool:
        """Whether checkpoints written by ``learn`` include the bulky files (config ``save_replay``)."""
        return bool(getattr(self.config, "save_replay", True))

    @classmethod
    def load(cls, path: str | Path, *, system=None, force: bool = False, **overrides) -> "Learner":
        """Restore a checkpoint directory written by ``save`` or ``learn``.

        ``system``: what to run it on (default: the one config.json records; a system name, a
        :class:`~hybridctl.systems.System`, a vector env, or a gymnasium env id / factory for
        the learners that take one); it must be what the checkpoint was trained on.
        ``overrides`` replace config fields (e.g. ``num_envs``, ``epochs``; a learner's
        :data:`load_keywords` go to its constructor instead). Bulky files (replay,
        gate data) are not loaded (``learn(resume=True)`` does that).

        Raises :class:`~hybridctl.learn.checkpoint.CheckpointError` naming what differs for a
        checkpoint of another algorithm or plant, and naming the file for a missing or damaged
        one. ``force=True``: load another algorithm's or plant's anyway (with a warning).
        """
        fields = {f.name for f in dataclasses.fields(cls.config_class)}
        build = {k: overrides.pop(k) for k in list(overrides) if k not in fields and k in cls.load_keywords}
        unknown = sorted(set(overrides) - fields)
        if unknown:
            raise ValueError(f"{cls.algorithm_name}.load: {', '.join(unknown)} is not a {cls.config_class.__name__} "
                             f"field" + (f" nor one of {', '.join(cls.load_keywords)}" if cls.load_keywords else ""))
        found = ckpt.resolve_checkpoint_dir(path)
        meta = ckpt.read_meta(found)
        ckpt.check_algorithm(found, meta.get("algorithm"), cls.compatible_algorithms, cls.algorithm_name, force)
        ckpt.require_keys(found, meta, meta.get("algorithm") or cls.algorithm_name)
        config = ckpt.config_from_meta(cls.config_class, meta, overrides, found)
        agent = cls.from_checkpoint(found, meta, config, system, force, **build)
        agent.checkpointer.restore(found, bulky=False, force=force)
        return agent

    # ------------------------------------------------------------------ the controller
    def controller(self, system=None):
        """The :class:`~hybridctl.systems.SwitchedController` this learner's policy drives ``system`` with
        (default: the system it trained on): its swing-up, its gate, the LQR of ``system``. What
        :func:`hybridctl.learn.load_controller` returns for its checkpoints. A learner whose policy drives
        no hybridctl system keeps this default, which raises CheckpointError."""
        raise no_swingup(self.algorithm_name)

    @classmethod
    def drives_systems(cls) -> bool:
        """Whether :meth:`controller` is written (checked before a checkpoint is loaded for one)."""
        return cls.controller is not Learner.controller

    @classmethod
    def deploy_overrides(cls, config: dict) -> dict:
        """:meth:`load`'s overrides when a checkpoint (its recorded ``config``) is loaded only for its
        controller: the CPU, where a config has a device (Drake and the rollouts move their own copy)."""
        fields = {f.name for f in dataclasses.fields(cls.config_class)} if cls.config_class else set()
        return {"device": "cpu"} if "device" in fields else {}

    def fine_tuning_task(self) -> dict:
        """The spec overrides of the task the policy was trained on (reward, starts): what fine-tuning
        (:mod:`hybridctl.learn.finetune`) tunes its controller on; ValueError where it cannot be tuned
        inside the switched controller. Default: the overrides of the system it trained on."""
        spec = getattr(getattr(self, "system", None), "spec", None)
        return dict(getattr(spec, "overrides", None) or {})

    load_keywords: tuple[str, ...] = ()
    """Keywords of :meth:`load` that are not config fields but go to :meth:`from_checkpoint` (ARS's
    ``policy``: the custom torch module a checkpoint's weights belong to)."""

    @classmethod
    def from_checkpoint(cls, found: Path, meta: dict, config, system, force: bool, **build) -> "Learner":
        """Hook of :meth:`load`: the learner (with ``config``) whose state the checkpoint at ``found``
        then restores; ``system`` as :meth:`load` takes it (None: the recorded one)."""
        raise NotImplementedError
