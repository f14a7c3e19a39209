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


def load_controller(path: str | Path, system) -> tuple[DeterministicPolicy, GateNet | None, dict]:
    """The deterministic swing-up policy and (SSAC) the gate of a checkpoint directory.

    Args:
        path: a checkpoint directory (``final/``, ``checkpoint/``) or a run folder
            holding ``final/``.
        system: the ``System`` it must have been trained on (checked by name).

    Returns (policy, gate or None for SAC, the checkpoint's config.json dict).
    Raises :class:`CheckpointError` naming the missing file or the mismatch.
    """
    path = Path(path)
    if path.is_dir() and not (path / ckpt.CONFIG_FILE).exists() and (path / "final").is_dir():
        path = path / "final"
    found = ckpt.resolve_checkpoint_dir(path)
    meta = ckpt.read_json(found / ckpt.CONFIG_FILE)
    trained_on = meta.get("system", {}).get("name")
    if trained_on != system.name:
        raise ckpt.CheckpointError(f"checkpoint {found} was trained on system {trained_on!r}, "
                                   f"not {system.name!r}")
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
    model = ckpt.load_tensors(found / ckpt.MODEL_FILE)
    if "actor" not in model:
        raise ckpt.CheckpointError(f"{found / ckpt.MODEL_FILE} lacks 'actor'")
    transform = ObsTransform(cfg.get("obs_transform", "none"), obs_dim, system.angle_indices)
    actor = Actor(transform, action_dim, scale, layers, width, cfg.get("log_std_min", -20.0),
                  cfg.get("log_std_max", 2.0))
    actor.load_state_dict(model["actor"])
    policy = DeterministicPolicy(actor)
    gate = None
    if meta.get("algorithm") == "SSAC":
        gate_state = model.get("extra", {}).get("gate")
        if gate_state is None:
            raise ckpt.CheckpointError(f"{found / ckpt.MODEL_FILE} is an SSAC checkpoint without gate weights")
        hidden = tuple(meta.get("gate", {}).get("hidden", GateConfig.hidden))
        gate = GateNet(system, hidden, cost_feature=bool(cfg.get("gate_cost_feature", True)))
        gate.load_state_dict(gate_state)
        gate.eval()
        for p in gate.parameters():
            p.requires_grad_(False)
    return policy, gate, meta
