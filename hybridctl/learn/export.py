"""Trained checkpoints as plain torch modules for Drake blocks (no replay buffers, no optimizers).

>>> from hybridctl.learn import load_controller
>>> policy, gate, meta = load_controller("models/policies/ssac-acrobot", system)
>>> build_hybrid_diagram(system, swingup=policy, gate=gate)
"""

from __future__ import annotations

from pathlib import Path

import torch

from . import checkpoint as ckpt
from .gate import GateConfig, GateNet
from .networks import Actor, DeterministicPolicy, ObsTransform


def load_controller(path: str | Path, system, force: bool = False,
                    with_gate: bool = True) -> tuple[DeterministicPolicy, GateNet | None, dict]:
    """The deterministic swing-up policy and (SSAC) the gate of a checkpoint directory.

    Args:
        path: a checkpoint directory (``final/``, ``checkpoint/``) or a run folder
            holding ``final/``.
        system: the ``System`` it must have been trained on: the same system name and
            resolved spec values (:func:`~hybridctl.learn.checkpoint.check_plant`; a
            checkpoint written before the spec hash was recorded is checked by name and
            spec overrides, with a warning). The reward and the initial-state distribution
            (:data:`~hybridctl.learn.checkpoint.TRAINING_ONLY_SECTIONS`) may differ: a deployed
            policy does not see them.
        force: load a checkpoint trained on another plant anyway (with a warning).
        with_gate: False when only the swing-up policy is deployed (beside the spec's
            cost-to-go gate): the checkpoint's gate is not loaded, and the spec's ``gate``
            section (which only a learned gate reads) may differ too.

    Returns (policy, gate or None for SAC or ``with_gate=False``, the checkpoint's config.json dict).
    Raises :class:`CheckpointError` naming the missing or damaged file (model.pt and its keys,
    config.json, normalization.json) or what differs from ``system``.
    """
    path = Path(path)
    if path.is_dir() and not (path / ckpt.CONFIG_FILE).exists() and (path / "final").is_dir():
        path = path / "final"
    found = ckpt.resolve_checkpoint_dir(path)
    meta = ckpt.read_meta(found)
    if meta.get("algorithm") not in ("SAC", "SSAC"):
        raise ckpt.CheckpointError(f"checkpoint {found} was written by {meta.get('algorithm')}, not SAC or SSAC: "
                                   f"it holds no swing-up policy and gate")
    ignore = ckpt.TRAINING_ONLY_SECTIONS + (() if with_gate else (ckpt.GATE_SECTION,))
    ckpt.check_plant(found, meta.get("system"), system, force, ignore=ignore)
    cfg = meta.get("config", {})
    try:
        obs_dim, action_dim = int(meta["obs_dim"]), int(meta["action_dim"])
        scale = torch.as_tensor(meta["action_scale"], dtype=torch.float32)
        layers, width = int(cfg["hidden_layers"]), int(cfg["hidden_size"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ckpt.CheckpointError(f"{found / ckpt.CONFIG_FILE} lacks {exc} (not a hybridctl SAC/SSAC checkpoint?)")
    if (obs_dim, action_dim) != (system.n_states, system.n_actions):
        raise ckpt.CheckpointError(f"checkpoint {found} has obs/action dims {obs_dim}/{action_dim}, "
                                   f"{system.name} has {system.n_states}/{system.n_actions}")
    model = ckpt.read_model(found / ckpt.MODEL_FILE, ("actor",))
    transform = ObsTransform(cfg.get("obs_transform", "none"), obs_dim, system.angle_indices)
    normalization = ckpt.read_json(found / ckpt.NORMALIZATION_FILE)
    if ckpt.to_jsonable(normalization) != ckpt.to_jsonable(transform.describe()):
        raise ckpt.CheckpointError(f"{found / ckpt.NORMALIZATION_FILE} says {normalization}, but config.json's "
                                   f"obs_transform {cfg.get('obs_transform', 'none')!r} on {system.name} means "
                                   f"{transform.describe()}: the checkpoint is damaged")
    actor = Actor(transform, action_dim, scale, layers, width, cfg.get("log_std_min", -20.0),
                  cfg.get("log_std_max", 2.0))
    try:
        actor.load_state_dict(model["actor"])
    except (RuntimeError, KeyError, TypeError) as exc:
        raise ckpt.CheckpointError(f"{found / ckpt.MODEL_FILE}: 'actor' does not fit a {layers} x {width} policy "
                                   f"of {obs_dim} states ({exc})") from exc
    policy = DeterministicPolicy(actor)
    gate = None
    if meta.get("algorithm") == "SSAC" and with_gate:
        gate_state = model.get("extra", {}).get("gate")
        if gate_state is None:
            raise ckpt.CheckpointError(f"{found / ckpt.MODEL_FILE} is an SSAC checkpoint without gate weights")
        hidden = tuple(meta.get("gate", {}).get("hidden", GateConfig.hidden))
        gate = GateNet(system, hidden, cost_feature=bool(cfg.get("gate_cost_feature", True)))
        try:
            gate.load_state_dict(gate_state)
        except (RuntimeError, KeyError, TypeError) as exc:
            raise ckpt.CheckpointError(f"{found / ckpt.MODEL_FILE}: the gate weights do not fit ({exc})") from exc
        gate.eval()
        for p in gate.parameters():
            p.requires_grad_(False)
    return policy, gate, meta
