"""Reading a Stable-Baselines3 zip WITHOUT unpickling: the entries, bounded, and the plain JSON fields.

An SB3 2.x ``model.save("agent.zip")`` writes a zip holding::

    data                       JSON; entries that JSON cannot hold carry ":serialized:" (base64
                               cloudpickle, NEVER decoded here) next to plain-text fields
                               (``observation_space``: ``_shape``, ``dtype``, ``low``, ``high``;
                               ``policy_class``: ``__module__``; ``policy_kwargs``: the repr of
                               each entry, e.g. ``activation_fn``)
    policy.pth                 the policy state dict (read with ``torch.load(weights_only=True)``)
    *.optimizer.pth, pytorch_variables.pth, _stable_baselines3_version, system_info.txt

A zip is someone else's data: every entry is read in chunks and stopped at ``hybridctl.limits``
(a zip bomb is not inflated), all entries are checked before anything is built, tensors must be
real floating point, and a class named in the JSON (``policy_class``'s module, ``activation_fn``,
``optimizer_class``, ``features_extractor_class``) must be one of the known ones
(:data:`POLICY_CLASSES`, :data:`CLASS_KWARGS`). :func:`hybridctl.learn.sb3.load_sb3` puts the
pieces together; the policy module is :mod:`hybridctl.learn.sb3_policy`, the writer
:mod:`hybridctl.learn.sb3_export`.
"""

from __future__ import annotations

import io
import math
import re
import zipfile
import zlib
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from .. import limits
from .checkpoint import CheckpointError

SB3_ALGORITHMS = ("ppo", "a2c", "sac", "td3", "ddpg", "tqc")
"""The algorithms whose ``MlpPolicy`` :func:`load_sb3` rebuilds (``tqc`` is sb3-contrib's)."""

SELECTIONS = ("action", "all", "last")
"""The parameter selections of :meth:`SB3Policy.parameter_names`."""

FAMILY = {"ppo": "actor_critic", "a2c": "actor_critic", "sac": "squashed", "tqc": "squashed",
          "td3": "deterministic", "ddpg": "deterministic"}
"""How each algorithm's policy acts: ActorCriticPolicy (PPO, A2C), squashed Gaussian actor
(SAC, TQC), deterministic tanh actor (TD3, DDPG)."""

DEFAULT_ACTIVATION = {"ppo": "Tanh", "a2c": "Tanh", "sac": "ReLU", "tqc": "ReLU", "td3": "ReLU", "ddpg": "ReLU"}
"""SB3's default ``activation_fn`` per algorithm, used when ``policy_kwargs`` does not name one."""

ACTIVATIONS = {"Tanh": nn.Tanh, "ReLU": nn.ReLU, "ELU": nn.ELU, "LeakyReLU": nn.LeakyReLU, "GELU": nn.GELU,
               "SiLU": nn.SiLU, "Sigmoid": nn.Sigmoid, "Softplus": nn.Softplus, "Mish": nn.Mish}
"""Activation classes accepted by name (the text SB3 writes: ``<class 'torch.nn...ReLU'>``), default arguments."""

DATA_ENTRY = "data"
POLICY_ENTRY = "policy.pth"
VERSION_ENTRY = "_stable_baselines3_version"
SYSTEM_INFO_ENTRY = "system_info.txt"
VARIABLES_ENTRY = "pytorch_variables.pth"
OPTIMIZER_ENTRIES = ("policy.optimizer.pth", "actor.optimizer.pth", "critic.optimizer.pth", "ent_coef_optimizer.pth")
"""The optimizer state dicts SB3 writes (PPO/A2C: policy; SAC/TQC/TD3/DDPG: actor, critic; SAC/TQC: ent_coef)."""
TEXT_ENTRIES = (DATA_ENTRY, VERSION_ENTRY, SYSTEM_INFO_ENTRY)
"""Entries read as text, bounded by :data:`hybridctl.limits.MAX_JSON_BYTES` (the others by MAX_ZIP_ENTRY_BYTES)."""
PYTORCH_VARIABLES = ("log_ent_coef", "ent_coef_tensor")
"""The names SB3 stores in ``pytorch_variables.pth`` (SAC/TQC's entropy coefficient); no other is read."""
MAX_SPACE_ELEMENTS = 1_000_000
"""Elements of an observation or action Box read from a zip (``_shape``); an MlpPolicy of more is not
readable within :data:`hybridctl.limits.MAX_ZIP_ENTRY_BYTES` anyway (stated here: limits.py has no cap for it)."""

POLICY_CLASSES = {"ppo": ("stable_baselines3.common.policies", "ActorCriticPolicy"),
                  "a2c": ("stable_baselines3.common.policies", "ActorCriticPolicy"),
                  "sac": ("stable_baselines3.sac.policies", "SACPolicy"),
                  "td3": ("stable_baselines3.td3.policies", "TD3Policy"),
                  "ddpg": ("stable_baselines3.td3.policies", "TD3Policy"),
                  "tqc": ("sb3_contrib.tqc.policies", "TQCPolicy")}
"""The ``MlpPolicy`` class of each algorithm (module, name): the only ``policy_class`` modules a zip may name,
and the class :meth:`SB3Agent.save_zip` writes (by name; nothing of the input's pickle is kept)."""
POLICY_MODULES = tuple(sorted({module for module, _ in POLICY_CLASSES.values()}))

OPTIMIZERS = {"Adam": torch.optim.Adam, "AdamW": torch.optim.AdamW, "RMSprop": torch.optim.RMSprop,
              "SGD": torch.optim.SGD}
"""Optimizer classes a zip's ``policy_kwargs['optimizer_class']`` may name (A2C's default is RMSprop)."""
EXTRACTORS = ("FlattenExtractor",)
"""Features extractors a zip's ``policy_kwargs['features_extractor_class']`` may name (MlpPolicy's)."""
CLASS_KWARGS = {"activation_fn": ("torch.nn.modules.activation", ACTIVATIONS),
                "optimizer_class": ("torch.optim", OPTIMIZERS),
                "features_extractor_class": ("stable_baselines3.common.torch_layers", EXTRACTORS)}
"""The ``policy_kwargs`` entries that name a class, with the module prefix and names accepted for each.
Any other entry must be plain JSON (a class or function there is refused)."""


def _class_name(key: str, text: Any, where: str) -> str:
    """The class named by SB3's text ``<class 'torch.nn.modules.activation.ReLU'>`` (or a bare name) of
    ``policy_kwargs[key]``, if it is one of the known classes of :data:`CLASS_KWARGS` (nothing is imported)."""
    prefix, known = CLASS_KWARGS[key]
    pattern = r"\s*(?:<class '([A-Za-z_][\w.]*)'>|([A-Za-z_]\w*))\s*"
    match = re.fullmatch(pattern, text) if isinstance(text, str) else None
    dotted = (match.group(1) or match.group(2)) if match else ""
    module, _, name = dotted.rpartition(".")
    if name in known and (not module or module == prefix or module.startswith(prefix + ".")):
        return name
    raise CheckpointError(f"{where}: policy_kwargs[{key!r}] is {str(text)[:80]!r}, not one of {sorted(known)} "
                          f"(of {prefix})")


def _strip(value: Any) -> Any:
    """``value`` with every key starting with ':' (":serialized:", ":type:") removed, at any depth."""
    if isinstance(value, dict):
        return {key: _strip(item) for key, item in value.items() if not str(key).startswith(":")}
    if isinstance(value, list):
        return [_strip(item) for item in value]
    return value


def _policy_kwargs(data: dict, where: str) -> tuple[dict, dict[str, str]]:
    """(the plain ``policy_kwargs`` fields, {key: known class name} for the class-valued ones).

    A class or function named anywhere else (SB3 writes its text, ``<class ...>`` / ``<function ...>``)
    is refused: we would have to unpickle it to use it.
    """
    kwargs = _strip(data.get("policy_kwargs") or {})
    if not isinstance(kwargs, dict):
        raise CheckpointError(f"{where}: data['policy_kwargs'] is not an object")
    classes = {}
    for key, value in kwargs.items():
        if key in CLASS_KWARGS:
            classes[key] = _class_name(key, value, where)
        elif isinstance(value, str) and value.lstrip().startswith("<"):
            raise CheckpointError(f"{where}: policy_kwargs[{key!r}] is {value[:80]!r}, an object that cannot be "
                                  f"read without unpickling; only {sorted(CLASS_KWARGS)} may name classes")
    return {k: v for k, v in kwargs.items() if k not in classes}, classes


def _number(value: Any, where: str, positive: bool = False) -> float:
    """``value`` as a finite float (``positive``: > 0); CheckpointError naming ``where`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (positive and value <= 0):
        raise CheckpointError(f"{where} must be a finite {'positive ' if positive else ''}number, got {value!r:.60}")
    return float(value)



def _parse_array(text: Any, shape: tuple[int, ...], dtype: np.dtype, where: str) -> np.ndarray:
    """A numpy ``str()`` of an array (``'[-1. -1. -8.]'``, nested for 2-d, ``inf``) parsed back."""
    if isinstance(text, (int, float)):
        return np.full(shape, text, dtype=dtype)
    if isinstance(text, bool) or not isinstance(text, str) or "..." in text:
        raise CheckpointError(f"{where} is {text!r}: not a full array repr (summarised reprs cannot be read back)")
    try:
        values = np.array([float(token) for token in text.replace("[", " ").replace("]", " ").split()])
    except ValueError as exc:
        raise CheckpointError(f"{where} is not an array repr: {text!r}") from exc
    if values.size == 1:
        return np.full(shape, values[0], dtype=dtype)
    if values.size != math.prod(shape):
        raise CheckpointError(f"{where} has {values.size} values, the shape {shape} needs {math.prod(shape)}")
    return values.reshape(shape).astype(dtype)


def _box_from_json(data: dict, field: str, source: str) -> gym.spaces.Box:
    """The gymnasium Box of ``data[field]`` rebuilt from its plain fields (_shape, dtype, low, high)."""
    entry = data.get(field)
    where = f"{source}: data[{field!r}]"
    if not isinstance(entry, dict):
        raise CheckpointError(f"{where} is missing or not an object")
    kind = str(entry.get(":type:", ""))
    if "spaces.box.Box" not in kind:
        raise CheckpointError(f"{where} is a {kind or 'non-space'}; only Box spaces are supported")
    try:
        shape = entry["_shape"]
        if not isinstance(shape, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
                                                  for n in shape) or math.prod(shape) > MAX_SPACE_ELEMENTS:
            raise CheckpointError(f"{where}['_shape'] is {str(shape)[:60]}: it must be a list of sizes >= 0 with at "
                                  f"most {MAX_SPACE_ELEMENTS:,} elements in all")
        shape = tuple(shape)
        dtype = entry.get("dtype", "float32")
        if dtype not in ("float16", "float32", "float64"):
            raise CheckpointError(f"{where}['dtype'] is {str(dtype)[:40]!r}, not float16, float32 or float64")
        dtype = np.dtype(dtype)
        low = _parse_array(entry["low"], shape, dtype, f"{where}['low']")
        high = _parse_array(entry["high"], shape, dtype, f"{where}['high']")
    except KeyError as exc:
        raise CheckpointError(f"{where} lacks the plain field {exc} (needs _shape, dtype, low, high)") from exc
    try:
        return gym.spaces.Box(low=low, high=high, shape=shape, dtype=dtype)
    except (ValueError, TypeError, AssertionError) as exc:
        raise CheckpointError(f"{where} is not a valid Box: {exc}") from exc


def _policy_module(data: dict) -> str | None:
    """The plain ``__module__`` text beside the pickled ``policy_class`` (e.g. 'stable_baselines3.sac.policies')."""
    entry = data.get("policy_class")
    module = entry.get("__module__") if isinstance(entry, dict) else None
    return module if isinstance(module, str) else None


def _detect_algo(data: dict, state: dict[str, torch.Tensor]) -> tuple[str | None, str]:
    """The algorithm from ``policy_class.__module__`` and algorithm fields, else from state-dict keys."""
    module = _policy_module(data)
    ddpg_like = data.get("policy_delay") == 1 and data.get("target_noise_clip") == 0.0
    if isinstance(module, str):
        if module.startswith("sb3_contrib.tqc"):
            return "tqc", f"policy_class.__module__ = {module!r}"
        if ".sac." in module:
            return "sac", f"policy_class.__module__ = {module!r}"
        if ".td3." in module or ".ddpg." in module:
            return ("ddpg" if ddpg_like else "td3"), f"policy_class.__module__ = {module!r}, policy_delay, target_noise_clip"
        if module == "stable_baselines3.common.policies":
            ppo = "clip_range" in data or "n_epochs" in data
            return ("ppo" if ppo else "a2c"), f"policy_class.__module__ = {module!r}, clip_range/n_epochs"
    if "action_net.weight" in state:
        ppo = "clip_range" in data or "n_epochs" in data
        return ("ppo" if ppo else "a2c"), "state-dict keys (action_net), clip_range/n_epochs"
    if "actor.latent_pi.0.weight" in state or "actor.mu.weight" in state:
        quantiles = state.get("critic.qf0.4.weight")
        tqc = quantiles is not None and quantiles.shape[0] > 1
        return ("tqc" if tqc else "sac"), "state-dict keys (actor.latent_pi, critic outputs)"
    if "actor_target.mu.0.weight" in state:
        return ("ddpg" if ddpg_like or "critic.qf1.0.weight" not in state else "td3"), "state-dict keys (actor_target)"
    return None, "nothing recognised"


_ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, RuntimeError, ValueError)
"""What zipfile raises for a damaged, encrypted or oddly compressed entry (CRC, truncation, method)."""


def _read_entry(archive: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, limit: int, what: str) -> bytes:
    """One entry's bytes, read in chunks and stopped past ``limit`` (a zip bomb never inflates further)."""
    chunks, size = [], 0
    try:
        with archive.open(info) as stream:
            while (chunk := stream.read(1 << 20)) and size <= limit:
                size += len(chunk)
                chunks.append(chunk)
    except _ZIP_ERRORS as exc:
        raise CheckpointError(f"{path}: entry {info.filename!r} cannot be read: {exc}") from exc
    if size > limit:
        raise CheckpointError(f"{path}: entry {info.filename!r} inflates past {limit:,} bytes, {what}; the zip is "
                              f"damaged or a zip bomb")
    return b"".join(chunks)


def _read_entries(path: Path) -> dict[str, bytes]:
    """Every entry of the zip at ``path`` (name -> bytes), each bounded, all read before anything is used.

    Text entries (:data:`TEXT_ENTRIES`) are bounded by ``limits.MAX_JSON_BYTES``, the others by
    ``limits.MAX_ZIP_ENTRY_BYTES``, all together by ``MAX_ZIP_ENTRY_BYTES`` too; at most
    ``limits.MAX_ZIP_ENTRIES`` entries, each name once.
    """
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise CheckpointError(f"{path} is not a zip file (an SB3 checkpoint is the .zip of model.save): {exc}") from exc
    entries: dict[str, bytes] = {}
    with archive:
        infos = archive.infolist()
        if len(infos) > limits.MAX_ZIP_ENTRIES:
            raise CheckpointError(f"{path} holds {len(infos):,} entries, above the limit of "
                                  f"{limits.MAX_ZIP_ENTRIES:,} (an SB3 zip holds about 8)")
        total = 0
        for info in infos:
            if info.filename in entries:
                raise CheckpointError(f"{path} holds the entry {info.filename!r} twice: the zip is damaged")
            text = info.filename in TEXT_ENTRIES
            limit = limits.MAX_JSON_BYTES if text else limits.MAX_ZIP_ENTRY_BYTES
            what = ("the limit of one text entry (hybridctl.limits.MAX_JSON_BYTES)" if text
                    else "the limit of one entry (hybridctl.limits.MAX_ZIP_ENTRY_BYTES)")
            if limits.MAX_ZIP_ENTRY_BYTES - total < limit:
                limit, what = limits.MAX_ZIP_ENTRY_BYTES - total, (
                    f"what is left of the limit of {limits.MAX_ZIP_ENTRY_BYTES:,} bytes for all entries together "
                    f"(hybridctl.limits.MAX_ZIP_ENTRY_BYTES)")
            entries[info.filename] = _read_entry(archive, info, path, limit, what)
            total += len(entries[info.filename])
    return entries


def _torch_entry(entries: dict[str, bytes], name: str, path: Path) -> Any:
    """``torch.load(weights_only=True)`` of one entry (tensors and plain containers only; nothing else unpickles)."""
    try:
        return torch.load(io.BytesIO(entries[name]), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged file
        raise CheckpointError(f"{path}: entry {name!r} is not readable with torch.load(weights_only=True): "
                              f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from exc


def _state_dict(entries: dict[str, bytes], path: Path) -> dict[str, torch.Tensor]:
    """The policy state dict: string keys to real floating-point tensors (no bool, integer or complex)."""
    state = _torch_entry(entries, POLICY_ENTRY, path)
    source = f"{path}: entry {POLICY_ENTRY!r}"
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise CheckpointError(f"{source} is not a dict of tensors")
    for key, value in state.items():
        if not value.is_floating_point():
            raise CheckpointError(f"{source}: tensor {key!r} has dtype {value.dtype}; a policy's weights are "
                                  f"real floating point (float16, bfloat16, float32, float64)")
    return state


def _variables(entries: dict[str, bytes], path: Path) -> dict[str, torch.Tensor] | None:
    """``pytorch_variables.pth`` (SAC/TQC's entropy coefficient) if present: known names, float tensors."""
    if VARIABLES_ENTRY not in entries:
        return None
    found = _torch_entry(entries, VARIABLES_ENTRY, path)
    if not isinstance(found, dict) or not all(k in PYTORCH_VARIABLES and isinstance(v, torch.Tensor)
                                              and v.is_floating_point() for k, v in found.items()):
        raise CheckpointError(f"{path}: entry {VARIABLES_ENTRY!r} must map names of {PYTORCH_VARIABLES} to "
                              f"floating-point tensors, got {str(found)[:80]}")
    return found


def _optimizers(entries: dict[str, bytes], path: Path) -> dict[str, dict]:
    """The optimizer state dicts present (``{"state": {...}, "param_groups": [...]}``), checked and kept."""
    found = {}
    for name in OPTIMIZER_ENTRIES:
        if name in entries:
            state = _torch_entry(entries, name, path)
            if not (isinstance(state, dict) and isinstance(state.get("state"), dict)
                    and isinstance(state.get("param_groups"), list)
                    and all(isinstance(group, dict) for group in state["param_groups"])):
                raise CheckpointError(f"{path}: entry {name!r} is not an optimizer state dict (state, param_groups)")
            found[name] = state
    return found


def _version(entries: dict[str, bytes]) -> str | None:
    """The SB3 version text if it looks like a version (``2.9.2``), else None."""
    text = entries.get(VERSION_ENTRY, b"").decode("utf-8", "replace").strip()
    return text if re.fullmatch(r"[0-9][0-9A-Za-z.+-]{0,39}", text) else None
