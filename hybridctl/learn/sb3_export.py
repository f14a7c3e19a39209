"""Writing an SB3 zip that SB3's own ``PPO.load`` etc. reads, built from what was parsed, never copied.

:meth:`hybridctl.learn.sb3.SB3Agent.save_zip` calls :func:`write_zip`: a fixed entry list, the
JSON without the input's ":serialized:" payloads (:func:`sb3_data`), the classes and spaces
re-serialised from known names, so SB3 predicts the fine-tuned actions and never meets a pickle
of the input's.
"""

from __future__ import annotations

import base64
import io
import json
import math
import pickle
import re
import zipfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from .. import io as _io
from .sb3_zip import (ACTIVATIONS, DATA_ENTRY, OPTIMIZERS, POLICY_CLASSES, POLICY_ENTRY, VARIABLES_ENTRY,
                      VERSION_ENTRY, _strip)

__all__ = ["write_zip", "sb3_data"]


def write_zip(agent, out_path: str | Path) -> Path:
    """Write an SB3 zip of ``agent`` (an :class:`~hybridctl.learn.sb3.SB3Agent`) atomically, built from what
    was parsed, never copied from the input.

    The entries are a fixed list with names chosen here: ``data`` (:func:`sb3_data`: the plain JSON
    fields, every ":serialized:" payload of the input dropped, the classes and spaces SB3 needs
    re-serialised from known names and the parsed Boxes), ``pytorch_variables.pth`` and the
    optimizer states (if the input had them; re-saved from their ``weights_only`` load),
    ``policy.pth`` (``torch.save`` of ``policy.sb3_state_dict()``) and the SB3 version. SB3's own
    ``PPO.load(out_path)`` etc. reads it and predicts the agent's actions.
    """
    entries = {DATA_ENTRY: json.dumps(sb3_data(agent), indent=4).encode("utf-8")}
    if agent._parts["variables"] is not None:
        entries[VARIABLES_ENTRY] = _torch_bytes(agent._parts["variables"])
    entries[POLICY_ENTRY] = _torch_bytes(agent.policy.sb3_state_dict())
    for name, state in agent._parts["optimizers"].items():
        entries[name] = _torch_bytes(state)
    if agent._parts["version"] is not None:
        entries[VERSION_ENTRY] = agent._parts["version"].encode("ascii")

    def write(f):
        with zipfile.ZipFile(f, "w", zipfile.ZIP_DEFLATED) as zout:
            for name, payload in entries.items():
                zout.writestr(name, payload)

    return _io.atomic_write(out_path, write)


def sb3_data(agent) -> dict:
    """The ``data`` JSON of :func:`write_zip`.

    Kept: the input's plain JSON fields (with ":"-keys stripped at any depth), except ``env``
    (SB3 would ``gym.make`` it) and the ``*_class`` fields (SB3 picks its defaults). A serialized
    constant schedule (``ConstantSchedule(val=0.2)``) becomes its number, a pickled ``target_entropy``
    (SB3's "auto") ``-prod(action shape)``; other pickled fields are dropped (SB3 keeps its defaults,
    e.g. ``train_freq``, and rebuilds buffers on ``learn``). Rebuilt by us:
    ``policy_class`` (:data:`POLICY_CLASSES`), the two Boxes and ``policy_kwargs`` (its plain fields
    and the known classes of :data:`CLASS_KWARGS`), each pickled from objects made here.
    """
    data = {}
    for key, value in agent._parts["data"].items():
        if key == "env" or key.endswith("_class") or key in _REBUILT:
            continue
        if isinstance(value, dict) and ":serialized:" in value:
            constant = _constant_schedule(value)
            if key == "target_entropy":  # only SB3's "auto" is stored pickled (a numpy float): -act_dim
                constant = -float(math.prod(agent.action_space.shape))
            if constant is not None:
                data[key] = constant
            continue
        data[key] = _strip(value)
    module, name = POLICY_CLASSES[agent.algo]
    data["policy_class"] = _serialized(_ClassRef(module, name), "<class 'abc.ABCMeta'>", {"__module__": module})
    for key, box in (("observation_space", agent.observation_space), ("action_space", agent.action_space)):
        data[key] = _serialized(box, str(type(box)), _box_fields(box))
    kwargs = dict(agent.meta["policy_kwargs"])
    classes = agent.meta["policy_kwargs_classes"]
    objects = {key: CLASS_OBJECTS[key][name] for key, name in classes.items() if key != "features_extractor_class"}
    if objects:  # FlattenExtractor is MlpPolicy's default: not written
        shown = {**kwargs, **{key: str(obj) for key, obj in objects.items()}}
        data["policy_kwargs"] = _serialized({**kwargs, **objects}, "<class 'dict'>", shown)
    else:
        data["policy_kwargs"] = kwargs
    return data


_REBUILT = ("policy_class", "observation_space", "action_space", "policy_kwargs")
"""``data`` fields :func:`sb3_data` writes itself."""
CLASS_OBJECTS = {"activation_fn": ACTIVATIONS, "optimizer_class": OPTIMIZERS}
"""The classes written for the class-valued ``policy_kwargs`` (by reference: a module and a name)."""


class _ClassRef:
    """A class named by module and name, pickled as a bare reference (SB3 need not be installed to write it)."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name


class _Pickler(pickle._Pickler):  # the pure-Python pickler: its dispatch table can take _ClassRef
    """Pickles plain values, numpy arrays, Boxes and classes by reference; a :class:`_ClassRef` as GLOBAL."""

    dispatch = pickle._Pickler.dispatch.copy()

    def _save_class_ref(self, obj: _ClassRef) -> None:
        self.write(pickle.GLOBAL + f"{obj.module}\n{obj.name}\n".encode("ascii"))

    dispatch[_ClassRef] = _save_class_ref


def _serialized(obj: Any, type_text: str, plain: dict) -> dict:
    """SB3's JSON form of a non-JSON value: ``{":type:", ":serialized:" (base64 pickle), plain fields}``."""
    buffer = io.BytesIO()
    _Pickler(buffer, protocol=4).dump(obj)
    return {":type:": type_text, ":serialized:": base64.b64encode(buffer.getvalue()).decode("ascii"), **plain}


def _box_fields(box: gym.spaces.Box) -> dict:
    """The plain fields of a Box, as SB3 writes them for humans and :func:`_box_from_json` reads them."""
    def text(array):
        return np.array2string(array, threshold=array.size + 1, floatmode="unique", max_line_width=1 << 30)
    return {"dtype": str(box.dtype), "_shape": list(box.shape), "low": text(box.low), "high": text(box.high)}


def _constant_schedule(entry: dict) -> float | None:
    """The value of a serialized ``FloatSchedule(ConstantSchedule(val=x))`` from its plain text, else None."""
    match = re.fullmatch(r"ConstantSchedule\(val=([-+0-9.eE]+)\)", str(entry.get("value_schedule", "")))
    try:
        value = float(match.group(1)) if match else None
    except ValueError:
        return None
    return value if value is not None and math.isfinite(value) else None


def _torch_bytes(obj: Any) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()
