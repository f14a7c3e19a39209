"""Every checkpoint becomes a controller through the learner contract: a registry of learners by
``config.json``'s ``algorithm`` and :func:`load_controller`.

A learner registers itself where it is defined: a :class:`~hybridctl.learn.base.Learner` subclass
that sets ``algorithm_name`` in its own body is registered under that name when the class is made
(``Learner.__init_subclass__`` calls :func:`register_learner`), with its ``controller_aliases``
(the APG family's method names). :func:`load_controller` reads a checkpoint's ``config.json``
(:func:`~hybridctl.learn.checkpoint.read_meta`, the safe reader), looks its ``algorithm`` up here
(a name from a file is never imported: only a registered class is used), checks the plant it was
trained on against ``system`` as a deployed controller (the reward, the starts and the episode
length may differ: :data:`~hybridctl.learn.checkpoint.TRAINING_ONLY_SECTIONS`), loads the learner
on its recorded system (``cls.load``, with the class's :meth:`~hybridctl.learn.base.Learner.
deploy_overrides`) and asks it for ``learner.controller(system)``: a
:class:`~hybridctl.systems.SwitchedController`.

>>> from hybridctl import systems
>>> from hybridctl.learn import load_controller
>>> acrobot = systems.load("acrobot")
>>> controller = load_controller("models/policies/ssac-acrobot", acrobot)   # learned swing-up + learned gate
>>> swingup_only = load_controller("models/policies/ssac-acrobot", acrobot, gate="never")
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from . import checkpoint as ckpt
from ..systems.spec import known_systems
from ..systems.switched import AlwaysGate, CostToGoGate, LearnedGate, NeverGate, SwitchedController

__all__ = ["register_learner", "registered_learners", "trainable_learners", "learner_class", "checkpoint_kinds", "gate_of_kind",
           "load_deployed", "load_controller", "GATES", "KIND_GATES", "no_swingup"]

_LEARNERS: dict[str, type] = {}
_ALIASES: dict[str, str] = {}   # a lower-case controller kind -> the algorithm name it loads

GATES = ("checkpoint", "learned", "cost-to-go", "never", "always")
"""What :func:`load_controller`'s ``gate`` puts beside the checkpoint's swing-up: ``checkpoint`` the
learner's own (SSAC: its learned gate; SAC: none; the APG family: the spec's cost-to-go gate);
``learned`` the same, which must be a learned gate; ``cost-to-go`` the spec's cost-to-go gate with
the spec's hysteresis; ``never`` the swing-up alone; ``always`` the LQR alone."""

KIND_GATES = {"sac": "never", "ssac": "learned", "ssac-costgate": "cost-to-go", "checkpoint": "checkpoint"}
"""The ``KIND`` of a named controller ``KIND:PATH`` (or a fine-tuning source) that selects a gate variant.
Every other registered kind (an algorithm's name in lower case, an alias) is ``checkpoint``."""


def register_learner(algorithm: str, cls: type, aliases: tuple[str, ...] = ()) -> type:
    """Register ``cls`` as the learner whose checkpoints ``config.json`` names ``algorithm``; ``aliases``:
    further lower-case kinds of named controllers (``papg:PATH``). A class registered again under its
    name (a module reloaded) replaces itself; another class under a taken name is a ValueError.
    Returns ``cls`` (so it works as a decorator's body)."""
    if not isinstance(algorithm, str) or not algorithm or ":" in algorithm:
        raise ValueError(f"a learner's algorithm name must be a non-empty string without ':', got {algorithm!r}")
    known = _LEARNERS.get(algorithm)
    if known is not None and known is not cls and _qualified(known) != _qualified(cls):
        raise ValueError(f"algorithm {algorithm!r} is registered to {_qualified(known)}; {_qualified(cls)} needs "
                         f"another algorithm_name")
    _LEARNERS[algorithm] = cls
    for kind in (algorithm.lower(), *aliases):
        if kind in KIND_GATES and kind != algorithm.lower():
            raise ValueError(f"controller kind {kind!r} selects a gate variant; choose another alias")
        _ALIASES[kind] = algorithm
    return cls


def _qualified(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def registered_learners() -> dict[str, type]:
    """The registered learners by algorithm name (a copy)."""
    return dict(_LEARNERS)


def trainable_learners() -> dict[str, type]:
    """The registered learners by the names they train under (``hybridctl train NAME``): each one's
    ``train_names`` (default its algorithm name in lower case), ordered by its ``train_order``, then by
    registration. Only a learner with a ``config_class`` dataclass trains so (its fields are the flags); one
    without trains from Python alone. A name two learners claim raises ValueError naming both."""
    found: dict[str, type] = {}
    ranked = sorted(_LEARNERS.items(), key=lambda item: getattr(item[1], "train_order", 100))   # stable
    for algorithm, cls in ranked:
        config_class = getattr(cls, "config_class", None)
        if not (isinstance(config_class, type) and dataclasses.is_dataclass(config_class)):
            continue
        names = getattr(cls, "train_names", None)
        for name in (algorithm.lower(),) if names is None else names:
            if name in found and found[name] is not cls:
                raise ValueError(f"the training name {name!r} is claimed by {_qualified(found[name])} and "
                                 f"{_qualified(cls)}")
            found[name] = cls
    return found


def learner_class(algorithm) -> type:
    """The registered learner of ``algorithm``; CheckpointError naming it and the registered ones otherwise."""
    cls = _LEARNERS.get(algorithm) if isinstance(algorithm, str) else None
    if cls is None:
        raise ckpt.CheckpointError(f"no learner is registered for algorithm {algorithm!r}; registered: "
                                   f"{', '.join(sorted(_LEARNERS))}")
    return cls


def checkpoint_kinds() -> tuple[str, ...]:
    """Every ``KIND`` of a named checkpoint controller ``KIND:PATH``: the gate variants of :data:`KIND_GATES`,
    the registered algorithms in lower case and their aliases."""
    return tuple(dict.fromkeys([*KIND_GATES, *_ALIASES]))


def gate_of_kind(kind: str) -> str | None:
    """The ``gate`` of :func:`load_controller` a named controller's ``KIND`` asks for (None: not a checkpoint kind)."""
    if kind in KIND_GATES:
        return KIND_GATES[kind]
    return "checkpoint" if kind in _ALIASES else None


def no_swingup(algorithm: str) -> ckpt.CheckpointError:
    """The one-line error of a learner whose checkpoints drive no system."""
    return ckpt.CheckpointError(f"{algorithm} checkpoints hold no swing-up")


def _checkpoint_dir(path) -> Path:
    path = Path(path)
    if path.is_dir() and not (path / ckpt.CONFIG_FILE).exists() and (path / "final").is_dir():
        path = path / "final"
    return ckpt.resolve_checkpoint_dir(path)


def load_deployed(path, system, *, force: bool = False,
                  gate: str = "checkpoint") -> tuple[object, SwitchedController]:
    """(the :class:`~hybridctl.learn.base.Learner`, its :class:`~hybridctl.systems.SwitchedController` on
    ``system``) of a checkpoint: what :func:`load_controller` returns, and the learner it asked
    (fine-tuning also reads its training task)."""
    if gate not in GATES:
        raise ValueError(f"gate must be one of {GATES}, got {gate!r}")
    found = _checkpoint_dir(path)
    meta = ckpt.read_meta(found)
    algorithm = meta.get("algorithm")
    cls = learner_class(algorithm)
    if not cls.drives_systems():
        raise no_swingup(algorithm)
    record = meta.get("system")
    if isinstance(record, dict) and record.get("kind") != "gymnasium":   # a gymnasium env's learner checks its own
        ignore = ckpt.TRAINING_ONLY_SECTIONS + (() if gate in ("checkpoint", "learned") else (ckpt.GATE_SECTION,))
        ckpt.check_plant(found, record, system, force, ignore=ignore)
    # the learner is rebuilt on its recorded system by name where that name finds the spec it trained on; a robot
    # of the user's (a spec file, `hybridctl fit`'s system.toml, perhaps named like a shipped one) is built on
    # ``system``, whose plant check_plant just matched
    on = None
    if isinstance(record, dict) and record.get("kind") != "gymnasium" and not _name_finds_spec(record):
        on = system
    learner = cls.load(found, system=on, force=force, **cls.deploy_overrides(meta.get("config") or {}))
    controller = learner.controller(system)
    if gate == "learned" and not isinstance(controller.gate, LearnedGate):
        raise ValueError(f"{path} is a {algorithm} checkpoint without a learned gate (its controller's gate is "
                         f"{type(controller.gate).__name__}); use sac:{path} for its swing-up alone")
    if gate == "never":
        controller = controller.replace(gate=NeverGate())
    elif gate == "always":
        controller = controller.replace(gate=AlwaysGate())
    elif gate == "cost-to-go":   # the spec's gate with the spec's hysteresis, at the swing-up's own period
        controller = SwitchedController.for_system(system, swingup=controller.swingup, gate=CostToGoGate(system),
                                                   decision_period=controller.decision_period)
    return learner, controller


def _name_finds_spec(record: dict) -> bool:
    """Whether config.json's ``system`` record names a shipped spec that, with its recorded overrides, is the one
    it trained on (its ``spec_hash``; an old record without one: the name is all there is)."""
    from ..systems import load as load_system
    from .plant_record import system_record

    name = record.get("name")
    if name not in known_systems():
        return False
    if "spec_hash" not in record:
        return True
    try:
        return system_record(load_system(name, **(record.get("overrides") or {})))["spec_hash"] == record["spec_hash"]
    except (KeyError, TypeError, ValueError):
        return False


def load_controller(path, system, *, force: bool = False, gate: str = "checkpoint") -> SwitchedController:
    """The :class:`~hybridctl.systems.SwitchedController` of a checkpoint directory on ``system``.

    Args:
        path: a checkpoint directory (``final/``, ``checkpoint/``) or a run folder holding ``final/``.
        system: the :class:`~hybridctl.systems.System` it drives; it must be the plant the checkpoint
            was trained on (:func:`~hybridctl.learn.checkpoint.check_plant`); the reward, the starts and
            the episode length may differ (a deployed controller does not see them), and the spec's
            ``gate`` section too where the checkpoint's gate is not used (``gate`` other than
            ``checkpoint`` / ``learned``).
        force: load a checkpoint trained on another plant anyway (with a warning).
        gate: one of :data:`GATES`.

    The learner is the one registered for config.json's ``algorithm`` (:func:`register_learner`);
    ``learner.controller(system)`` makes the controller. Raises
    :class:`~hybridctl.learn.checkpoint.CheckpointError` naming the missing or damaged file, what differs
    from ``system``, an unregistered algorithm, or a learner whose checkpoints hold no swing-up.
    """
    return load_deployed(path, system, force=force, gate=gate)[1]
