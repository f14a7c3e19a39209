"""Training runs as ``hybridctl train`` does them: build (or resume, or warm-start) a learner, train
it with checkpoints and logs in a run folder, evaluate it and write ``eval.json``.

>>> from hybridctl.experiments import train_and_evaluate
>>> run = train_and_evaluate("ssac", "acrobot", out="runs/ssac", settings={"total_steps": 200_000})
>>> run.evaluation["mean_return"], run.agent
"""

from __future__ import annotations

import contextlib
import os
import platform
import shutil
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import torch

from .. import io
from ..io import RunFolderError
from ..learn import ARSConfig, SACConfig, SSACConfig, trainable_learners   # importing learn registers every learner
from ..learn.apg import METHODS as APG_METHODS
from ..learn.apg import APGConfig
from ..learn.checkpoint import CheckpointError, newest_checkpoint, read_meta, system_record
from ..learn.config_check import checkpoint_minutes
from .resume import resume_settings
from ..systems import System, load


def machine() -> dict:
    """Where a run ran: platform, Python, CPU count, torch version and threads (for run records)."""
    return {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "torch": torch.__version__, "torch_threads": torch.get_num_threads()}


def training_algorithms() -> dict[str, type]:
    """Learner class by ``hybridctl train`` name, read from the learner registry
    (:func:`~hybridctl.learn.registry.trainable_learners`): ``sac``, ``ssac``, ``ars``, the APG family's ``apg``,
    ``shapg``, ``papg``, ``cem``, ``ce-apg`` (thesis Ch. 3, 4, 7), and any learner registered since (a
    :class:`~hybridctl.learn.base.Learner` subclass that names its ``algorithm_name``). Each has ``config_class``."""
    return trainable_learners()

SSAC_VARIANTS = ("hybridctl", "paper", "author")
"""Presets of :meth:`SSACConfig.variant`."""

DEFAULT_EVAL_EPISODES = {"sac": 100, "ssac": 100}
"""Episodes in ``eval.json`` when none are asked for (ARS: its config's ``eval_episodes``, 5)."""


@dataclass
class TrainingRun:
    """A finished :func:`train_and_evaluate`: the trained learner, its run folder and ``eval.json``."""

    agent: Any
    out: Path
    evaluation: dict = field(default_factory=dict)


def _silent(line: str) -> None:
    """A ``report`` that prints nothing."""


def learner_class(algorithm: str):
    """The learner class of ``algorithm``, a name of :func:`training_algorithms` (``"sac"``, ``"ssac"``, ``"ars"``
    and the APG family's ``"apg"``, ``"shapg"``, ``"papg"``, ``"cem"``, ``"ce-apg"``)."""
    known = training_algorithms()
    try:
        return known[algorithm]
    except KeyError:
        raise ValueError(f"unknown algorithm {algorithm!r}; known: {', '.join(known)}") from None


def make_config(algorithm: str, variant: str = "hybridctl", **settings) -> SACConfig | SSACConfig | ARSConfig:
    """The validated config of ``algorithm`` with ``settings`` replacing its defaults.

    ``variant`` (SSAC only) picks the preset the settings start from: ``"hybridctl"``,
    ``"paper"`` or ``"author"`` (:meth:`SSACConfig.variant`). Unknown fields and invalid
    values raise ValueError naming them.
    """
    config_class = learner_class(algorithm).config_class
    if algorithm in APG_METHODS:   # variant: the preset ("thesis" or "reduced"; "hybridctl" means "thesis")
        return APGConfig.preset("thesis" if variant == "hybridctl" else variant, method=algorithm, **settings)
    if algorithm != "ssac" and variant != "hybridctl":
        raise ValueError("--variant applies to ssac only")
    try:
        config = SSACConfig.variant(variant, **settings) if algorithm == "ssac" else config_class(**settings)
    except TypeError as exc:  # an unknown field name
        raise ValueError(f"{config_class.__name__}: {exc}") from exc
    config.validate()
    checkpoint_minutes(config)  # the skeleton's time cadence: a bad value fails before any work
    return config


def default_run_dir(algorithm: str, system: str, seed: int = 0) -> Path:
    """``runs/train/ALGO-SYSTEM-sSEED`` (a gymnasium id's ``/`` becomes ``_``)."""
    return Path(f"runs/train/{algorithm}-{system.replace('/', '_')}-s{seed}")


def newest_run_checkpoint(out: str | Path, strict: bool = False) -> Path | None:
    """The newest checkpoint of a run folder (``checkpoint/`` or ``final/``), None if it has none.

    ``strict``: one that exists but is incomplete or damaged raises CheckpointError naming it.
    """
    out = Path(out)
    return newest_checkpoint([out / "checkpoint", out / "final"], strict=strict)


TRAIN_MARKERS = ("checkpoint", "final", "progress.csv", "eval.json")
"""What makes a folder hold a training run."""
MESH_MARKERS = ("mesh.npz", "mfpt.json", "mesh_checkpoint.npz", "transition_matrix.npz")
"""What makes a folder hold a mesh run."""
RUN_OUTPUTS = (*TRAIN_MARKERS, *MESH_MARKERS, "tb", "training_curves.png", "sparsity.png", "cumulative_mass.png",
               "states.png", "mesh_sizes.png")
"""What ``overwrite`` removes from a run folder before a new run (nothing else is touched)."""
CHECKPOINT_DIRS = ("checkpoint", "final")
"""The checkpoint folders of a run folder."""
CHECKPOINT_FILES = ("model.pt", "config.json")
"""Files that make a folder a checkpoint (never a run folder: a run's outputs would mix with it)."""


def _held_runs(out: Path) -> list[str]:
    """The run outputs in ``out`` (checkpoint backups ``NAME.bak-*`` / ``.tmp-*`` count too)."""
    found = []
    for name in (*TRAIN_MARKERS, *MESH_MARKERS):
        if (out / name).exists() or any(out.glob(f"{name}.bak-*")):
            found.append(name)
    return found


def _within(inner: Path, outer: Path) -> bool:
    """Whether the resolved ``inner`` is ``outer`` or lies inside it."""
    return inner == outer or outer in inner.parents


def check_inputs(out: Path, inputs: Mapping[str, str | Path | None] | None) -> None:
    """Refuse an ``out`` that is, holds or lies inside one of the command's ``inputs`` ({flag: path}).

    Paths are compared resolved (symlinks and ``..`` followed), so ``--out D`` with
    ``--policy sb3:D/model.zip`` and ``--out R/final`` with ``--init R/final`` are both
    caught: the run would overwrite (or ``--overwrite`` delete) what it reads.
    """
    where = out.resolve()
    for flag, given in (inputs or {}).items():
        if given is None or not str(given):
            continue
        source = Path(given).resolve()
        if source == where:
            relation = "is"
        elif _within(source, where):
            relation = "holds"
        elif _within(where, source):
            relation = "lies inside"
        else:
            continue
        raise RunFolderError(f"--out {out} {relation} the {flag} input {given}: the run would overwrite what it "
                             f"reads; choose an --out outside it")


def checkpoint_folder(out: Path) -> str | None:
    """Why ``out`` is a checkpoint rather than a run folder (None if it is not one): it holds
    model.pt or config.json, or it is the ``checkpoint/`` or ``final/`` of a run folder."""
    for name in CHECKPOINT_FILES:
        if (out / name).exists():
            return f"holds {name}"
    if out.name in CHECKPOINT_DIRS and _held_runs(out.resolve().parent):
        return f"is the {out.name}/ checkpoint of the run in {out.parent}"
    return None


def _check_out(out: str | Path, resume: bool, overwrite: bool, inputs: Mapping | None) -> Path:
    """The checks of :func:`prepare_run_folder` that need neither the folder nor its lock."""
    out = io.folder_argument(out, "--out")
    if out.exists() and not out.is_dir():
        raise RunFolderError(f"--out {out} is a file, not a folder: give a folder for the run's outputs")
    if resume and overwrite:
        raise RunFolderError("--resume and --overwrite exclude each other: --resume continues the run in the folder, "
                             "--overwrite replaces it")
    check_inputs(out, inputs)
    reason = checkpoint_folder(out)
    if reason is not None:
        what = "--resume continues the run folder that holds it" if resume else "a run goes into a folder of its own"
        raise RunFolderError(f"--out {out} {reason}: it is a checkpoint, not a run folder; {what} (e.g. --out "
                             f"{out.parent if out.name in CHECKPOINT_DIRS else 'runs/NAME'})")
    held = io.input_held(out) if out.is_dir() and not _held_runs(out) else None  # a run's own model.zip is fine
    if held is not None:
        raise RunFolderError(f"--out {out} holds {held}: a run never writes beside an input; choose another --out "
                             f"(e.g. --out runs/NAME)")
    return out


def clear_run_outputs(out: Path, extra: tuple[str, ...] = ()) -> None:
    """Remove the run outputs (:data:`RUN_OUTPUTS`, their backups, and ``extra`` names) from ``out``."""
    for name in (*RUN_OUTPUTS, *extra):
        for path in [out / name, *out.glob(f"{name}.bak-*"), *out.glob(f"{name}.tmp-*")]:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.exists() or path.is_symlink():
                path.unlink()


def prepare_run_folder(out: str | Path, resume: bool = False, overwrite: bool = False,
                       markers: tuple[str, ...] = TRAIN_MARKERS, inputs: Mapping[str, str | Path | None] | None = None,
                       clear: bool = True) -> Path:
    """Check (and create) the folder of a new run, or of the run that ``resume`` continues.

    A folder that already holds a run (a checkpoint, ``final/``, ``progress.csv``, ``eval.json``,
    ``mesh.npz``, ``mfpt.json``, ...) is refused unless ``resume`` (continue that run; it must
    be a run of this kind, ``markers``) or ``overwrite`` (its run outputs, :data:`RUN_OUTPUTS`,
    are removed, here if ``clear``, else by the caller once the run's inputs are read). Also
    refused: an empty ``out``, a file, an ``out`` that is, holds or lies inside one of
    ``inputs`` (:func:`check_inputs`), and a checkpoint folder (:func:`checkpoint_folder`).
    Raises :class:`RunFolderError` naming the folder and what to do. It takes no lock: a run
    writing the folder uses :func:`open_run_folder`.
    """
    out = _check_out(out, resume, overwrite, inputs)
    held = _held_runs(out) if out.is_dir() else []
    if held and overwrite:
        if clear:
            clear_run_outputs(out)
    elif held and resume:
        other = [name for name in held if name not in markers]
        if other and not any(name in markers for name in held):
            raise RunFolderError(f"{out} holds another kind of run ({', '.join(other)}), not one that --resume can "
                                 f"continue; choose another --out, or --overwrite to replace it")
    elif held:
        raise RunFolderError(f"{out} already holds a run ({', '.join(held)}); pass --resume to continue that run, "
                             f"or --overwrite to replace it (or choose another --out)")
    out.mkdir(parents=True, exist_ok=True)
    return out


@dataclass
class RunFolder:
    """A run folder held locked by :func:`open_run_folder`: ``path``, and ``clear`` for ``--overwrite``."""

    path: Path
    overwrite: bool = False

    def clear(self, extra: tuple[str, ...] = ()) -> None:
        """With ``overwrite``: remove the old run's outputs (and ``extra`` names); call it only once the
        new run's inputs are read, so a failed start leaves the old run whole. Without: nothing."""
        if self.overwrite:
            clear_run_outputs(self.path, extra)
            self.overwrite = False


@contextlib.contextmanager
def open_run_folder(out: str | Path, resume: bool = False, overwrite: bool = False,
                    markers: tuple[str, ...] = TRAIN_MARKERS,
                    inputs: Mapping[str, str | Path | None] | None = None) -> Iterator[RunFolder]:
    """:func:`prepare_run_folder` under the folder's lock (:func:`hybridctl.io.locked_folder`), held
    for the ``with`` block: a second run on the folder is refused at once, naming the holder's pid.

    The checks run after the lock is taken, so of two runs started together one is refused by
    the lock and the other sees the folder as it is. ``overwrite`` removes nothing here: the
    caller calls :meth:`RunFolder.clear` after reading its inputs.
    """
    out = _check_out(out, resume, overwrite, inputs)   # before the folder is created or locked
    with io.locked_folder(out, "--out"):
        prepare_run_folder(out, resume, overwrite, markers, inputs, clear=False)
        yield RunFolder(out, overwrite)


def _input_file(text: str | Path | None) -> str | Path | None:
    """``text`` where it names an existing file or folder (a spec file given as SYSTEM), else None."""
    return text if text is not None and str(text) and Path(text).exists() else None


def _as_record(result) -> dict:
    """An evaluation result (a dict, a mapping or a dataclass) as a plain dict."""
    if isinstance(result, Mapping):
        return dict(result)
    if is_dataclass(result):
        return asdict(result)
    if hasattr(result, "keys"):
        return {key: result[key] for key in result.keys()}
    raise TypeError(f"cannot record an evaluation result of type {type(result).__name__}")


def train_and_evaluate(algorithm: str, system: str, out: str | Path | None = None, settings: dict | None = None,
                       variant: str | None = None, resume: bool = False, init: str | Path | None = None,
                       eval_episodes: int | None = None, progress: bool = True, command: str | None = None,
                       report: Callable[[str], None] | None = print, force: bool = False,
                       overwrite: bool = False, spec: dict | None = None, callback=None) -> TrainingRun:
    """Train ``algorithm`` on ``system``, checkpointing into ``out``; evaluate; write ``out/eval.json``.

    Args:
        algorithm: ``"sac"``, ``"ssac"`` (a system name) or ``"ars"`` (a gymnasium env id or a
            system name).
        out: the run folder (default :func:`numbered_run_dir`): ``progress.csv``, ``checkpoint/``,
            ``final/``, ``eval.json`` (and for SAC/SSAC ``training_curves.png``). A folder that
            already holds a run is refused unless ``resume`` or ``overwrite``
            (:func:`prepare_run_folder`); so are an empty ``out``, a checkpoint folder and an
            ``out`` that is, holds or lies inside ``init`` or a spec file given as ``system``.
            The folder is locked while the run writes it (:func:`open_run_folder`).
        settings: config fields to change (see :func:`make_config`). On ``resume`` the run
            settings (:data:`~hybridctl.experiments.resume.RESUME_APPLIED`: total_steps / epochs,
            checkpoint and log cadence, eval episodes, tensorboard, threads, backend) are
            applied; any other field given with another value than the checkpoint's refuses
            the resume, naming it (``force`` applies it anyway).
        variant: SSAC's preset (``"hybridctl"``, ``"paper"``, ``"author"``; None: hybridctl, or on
            resume the run's own); on resume another preset than the run's refuses (``force``).
        resume: continue from the run folder's newest checkpoint (a new run when it has none);
            a checkpoint of another algorithm or plant, or an incomplete or damaged one (also a
            missing replay.pt / gate_data.pt), refuses naming what differs or the file.
        init: ARS and the APG family: start from this checkpoint's policy and normalisation (the
            thesis trains ARS 750 identity epochs, then 250 with post-processing); SAC and SSAC: from its
            networks, optimisers, replay buffers and gate data (``hybridctl fit`` starts SSAC from its cloned
            swing-up so). Its counters go on, so the budget is the total. A checkpoint of another plant or
            reward needs ``force``.
        eval_episodes: deterministic episodes in ``eval.json`` (default SAC/SSAC 100, ARS the
            config's ``eval_episodes``).
        command: the command line, recorded in ``eval.json``.
        report: called with each line of the run's account (default ``print``; None: silent).
        force: resume despite another algorithm or plant, changed math settings, or a missing
            replay / gate data file (each said in a warning or a report line).
        overwrite: replace the run the folder holds (its run outputs are removed once the new
            run's inputs are read: a start that fails leaves the old run whole).
        spec: SAC/SSAC only: system spec overrides for a new run (``{"reward.kind":
            "upright_centered"}``; keys as :func:`hybridctl.systems.load` takes them). The
            checkpoint records them; on resume, values other than the recorded ones refuse
            (``force``: the checkpoint's are kept).
        callback: a :class:`~hybridctl.learn.callbacks.Callback` (or a function of the learner called per update)
            for :meth:`~hybridctl.learn.base.Learner.learn`; returning False stops the run, which still
            writes ``final/`` and is evaluated (``hybridctl fit`` stops its learner at its budget so).

    Raises:
        ValueError: a bad setting, an unknown system, a folder holding another run
        (:class:`RunFolderError`) or a refused resume; CheckpointError: an unreadable or
        mismatched checkpoint; FloatingPointError: training diverged (the last checkpoint
        stays intact).
    """
    report = report or _silent
    settings = dict(settings or {})
    algo = learner_class(algorithm)
    if init is not None and not algo.warm_starts:
        raise ValueError(f"--init applies to {', '.join(n for n, c in training_algorithms().items() if c.warm_starts)} "
                         "only")
    preset = variant if variant is not None else "hybridctl"
    config = make_config(algorithm, preset, **settings)   # bad settings fail before any work
    target, system_name = _training_target(algo, system, config, dict(spec or {}))
    out = _run_folder_of(out, algorithm, system, config.seed, resume, overwrite)
    inputs = {"SYSTEM spec": _input_file(system), **({"--init": init} if init is not None else {})}
    with open_run_folder(out, resume, overwrite, inputs=inputs) as folder:
        start = time.perf_counter()
        agent = _starting_learner(algo, algorithm, system, target, system_name, config, settings, variant, init, out,
                                  resume, force, bool(spec), report)
        folder.clear()   # --overwrite: only now that the new run's inputs are read
        agent.learn(out=out, resume=resume, force=force, progress=progress, callback=callback)
        record = _as_record(agent.evaluate(eval_episodes, **algo.record_evaluation))
        if command is not None:
            record["command"] = command
        record.update(agent.training_record())
        record["session_wall_time_s"] = time.perf_counter() - start
        io.write_json(out / "eval.json", record)
    return TrainingRun(agent, out, record)


def _training_target(algo, system: str, config, spec: dict):
    """What a new learner of class ``algo`` is built on, and the name its checkpoints record: a
    system (with the ``spec`` overrides; a name alone is loaded by the learner, with the config's
    reward) or, for a learner that takes gymnasium envs (ARS), the env id as given."""
    if spec and not algo.takes_spec:
        raise ValueError(f"--spec applies to {', '.join(n for n, c in training_algorithms().items() if c.takes_spec)} "
                         "only")
    if algo.takes_gym_envs:
        return system, system
    name = load(system).name  # a clear error for an unknown system name, before any work
    if spec and getattr(config, "reward", None) is not None:
        # --reward with --spec: the system is loaded here with the overrides, so the reward goes with them
        # (a name alone is loaded by the learner with config.reward as its reward.kind)
        spec.setdefault("reward.kind", config.reward)
    return (load(system, **spec) if spec else system), name  # a bad override fails here, naming the key


def _starting_learner(algo, algorithm: str, system: str, target, system_name: str, config, settings: dict,
                      variant: str | None, init, out: Path, resume: bool, force: bool, spec_given: bool,
                      report: Callable[[str], None]):
    """The learner a run starts with: resumed from ``out``'s newest checkpoint, warm-started from
    ``init``, or new."""
    found = newest_run_checkpoint(out, strict=not force) if resume else None
    if found is not None:
        return _resumed_learner(algo, algorithm, system, target, system_name, found, settings, variant, force,
                                spec_given, report)
    if resume:
        report(f"--resume: no checkpoint under {out}; starting a new run")
    if init is not None:
        agent = algo.load(init, system=_loaded_on(algo, system, target) or system, force=force, **settings)
        if algo.init_keeps_data:   # SAC / SSAC: the replay and gate data go on with the networks, as in a resume
            agent.checkpointer.check_resumable(init, force)
            agent.checkpointer.restore(init, bulky=True, force=force)
        agent.warm_started()
        report(f"starting from {init} ({agent.log_key} {agent.progress_count}); training to "
               f"{getattr(agent.config, agent.budget_field)} {agent.unit}s")
        return agent
    report(f"{algo.run_label(config)} on {system}: {config.describe_budget()}")
    return algo(target, config)


def _loaded_on(algo, system: str, target):
    """What a checkpoint is loaded on to go on training: a learner on gymnasium envs on the env as given (an id, or
    a spec file the recorded name cannot find); one on systems on the system given with spec overrides, on the spec
    file given (a robot of the user's, `hybridctl fit`'s system.toml: no shipped name finds it), else (None) on the
    recorded system with its spec overrides."""
    if algo.takes_gym_envs:
        return system
    if isinstance(target, System):
        return target
    return load(system) if str(system).endswith(".toml") else None


def _resumed_learner(algo, algorithm: str, system: str, target, system_name: str, found: Path, settings: dict,
                     variant: str | None, force: bool, spec_given: bool, report: Callable[[str], None]):
    """The learner of the checkpoint ``found`` with the run settings applied
    (:func:`~hybridctl.experiments.resume.resume_settings`): refused, naming what differs, when it
    was trained on another system, with other spec values or other math settings (``force``: go on)."""
    recorded = read_meta(found)
    trained_on = (recorded.get("system") or {}).get("name")
    if trained_on != system_name and not force:
        raise CheckpointError(f"cannot resume: checkpoint {found} was trained on system {trained_on!r}, not "
                              f"{system_name!r} (--force resumes it on its own system {trained_on!r})")
    if spec_given:
        _check_spec_on_resume(found, recorded, target, force, report)
    given = {**_preset_changes(algorithm, variant, recorded.get("config", {})), **settings}
    applied = resume_settings(found, recorded.get("config", {}), given, force, report)
    # a learner on gymnasium envs is loaded on the env as given (an id, or a spec file the recorded name
    # cannot find); one on systems on the recorded system with its spec overrides, or on the spec file given
    # (a robot of the user's, `hybridctl fit`'s system.toml: no shipped name finds it)
    agent = algo.load(found, system=_loaded_on(algo, system, target), force=force, **applied)
    agent.checkpointer.check_resumable(found, force)
    report(f"resuming {found} at {agent.log_key} {agent.progress_count}"
           + (f", training to {getattr(agent.config, agent.budget_field)}" if agent.budget_field in applied else ""))
    return agent


def _preset_changes(algorithm: str, variant: str | None, recorded: dict) -> dict:
    """The fields a preset given on resume (SSAC's ``--variant``, the APG family's ``--preset``) sets to other
    values than the run's own preset (its recorded ``variant_name``; without one, its recorded config), as if
    each were given."""
    if variant is None:
        return {}
    preset = asdict(make_config(algorithm, variant))
    run_variant = recorded.get("variant_name")
    base = asdict(make_config(algorithm, run_variant)) if run_variant else recorded
    return {k: v for k, v in preset.items() if base.get(k, v) != v}


MAX_NUMBERED_RUNS = 9999
"""The most numbered default run folders (``ALGO-SYSTEM-sSEED-N``) one setting may have."""


def numbered_run_dir(algorithm: str, system: str, seed: int = 0, resume: bool = False,
                     overwrite: bool = False) -> Path:
    """The run folder of a training command given no ``--out``, numbered as the RL Zoo numbers its runs:
    :func:`default_run_dir` for the first run of these settings, then ``...-2``, ``...-3`` for new runs beside
    it. ``resume`` and ``overwrite`` take the newest existing one (the unnumbered one if none holds a run)."""
    base = default_run_dir(algorithm, system, seed)
    held = [base] if _held_runs(base) else []
    for n in range(2, MAX_NUMBERED_RUNS + 1):
        numbered = base.with_name(f"{base.name}-{n}")
        if not numbered.exists():
            break
        if _held_runs(numbered):
            held.append(numbered)
    else:
        raise RunFolderError(f"{base.parent} holds {MAX_NUMBERED_RUNS} runs named {base.name}-N: give --out")
    if resume or overwrite:
        return held[-1] if held else base
    if not held:
        return base
    newest = held[-1]
    if newest == base:
        return base.with_name(f"{base.name}-2")
    return base.with_name(f"{base.name}-{int(newest.name.rsplit('-', 1)[1]) + 1}")


def _run_folder_of(out: str | Path | None, algorithm: str, system: str, seed: int, resume: bool = False,
                   overwrite: bool = False) -> Path:
    """The ``out`` argument as a Path (an empty one refused, naming --out), :func:`numbered_run_dir` if None."""
    if out is not None:
        return io.folder_argument(out, "--out")
    return numbered_run_dir(algorithm, system, seed, resume=resume, overwrite=overwrite)


def _check_spec_on_resume(found: Path, recorded: dict, plant, force: bool, report: Callable[[str], None]) -> None:
    """On resume, spec overrides given again must resolve to the checkpoint's plant values."""
    saved = (recorded.get("system") or {}).get("spec_values")
    now = system_record(plant)["spec_values"]
    differing = sorted(k for k in set(saved or {}) | set(now) if (saved or {}).get(k) != now.get(k))
    if saved is None or not differing:
        return
    text = f"checkpoint {found} was trained with other spec values: " + ", ".join(
        f"{k} {saved.get(k)!r} (given {now.get(k)!r})" for k in differing[:4])
    if not force:
        raise CheckpointError(f"cannot resume: {text}; --force keeps the checkpoint's")
    report(f"--force: {text}; keeping the checkpoint's")


