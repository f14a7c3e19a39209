"""Stable-Baselines3 checkpoints read WITHOUT unpickling (thesis Ch. 6: random search over SB3 weights).

An SB3 2.x ``model.save("agent.zip")`` zip (its entries: :mod:`hybridctl.learn.sb3_zip`) holds JSON
with cloudpickled entries beside plain-text fields, and the policy's state dict.

:func:`load_sb3` reads only the plain JSON/text fields and the state dict and rebuilds the
deterministic (maximum-likelihood) action path of an ``MlpPolicy`` with Box spaces as
:class:`SB3Policy`, a plain ``torch.nn.Module`` whose parameter names are the SB3 keys.
Neither ``pickle`` nor ``cloudpickle`` is ever called on the zip, and this module imports
without stable-baselines3 installed. A zip is someone else's data: the reading,
bounded and checked before anything is built, is :mod:`hybridctl.learn.sb3_zip`; the policy module
:mod:`hybridctl.learn.sb3_policy`. :meth:`SB3Agent.save_zip` writes a NEW zip built from what was parsed
(a fixed entry list, the JSON without the input's ":serialized:" payloads, the classes and
spaces re-serialised from known names; :mod:`hybridctl.learn.sb3_export`), so that SB3's own
``PPO.load`` etc. predicts the fine-tuned actions and never meets a pickle of the input's.

``VecNormalize.save`` writes a pickle; observation statistics are read from an ``.npz``
(:class:`~hybridctl.learn.sb3_normalizer.Normalizer`). A ``.pkl`` is unpickled only with ``trust=True``.

>>> agent = load_sb3("runs/ppo-pendulum/model.zip")      # finds vecnormalize.npz beside it
>>> action, _ = agent.predict(obs)                        # == model.predict(norm(obs), deterministic=True)
>>> names = agent.policy.parameter_names("action")        # what the random search perturbs
>>> agent.save_zip("runs/ppo-pendulum/finetuned.zip")     # PPO.load reads it
"""


from __future__ import annotations

import json
import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from .checkpoint import CheckpointError
from .sb3_export import sb3_data, write_zip
from .sb3_normalizer import Normalizer, read_normalizer
from .sb3_policy import SB3Policy
from .sb3_zip import (DATA_ENTRY, DEFAULT_ACTIVATION, EXTRACTORS, FAMILY, POLICY_ENTRY, POLICY_MODULES,
                      SB3_ALGORITHMS, _box_from_json, _detect_algo, _number, _optimizers, _policy_kwargs,
                      _policy_module, _read_entries, _state_dict, _strip, _variables, _version)

__all__ = ["SB3Agent", "load_sb3", "silent_logger"]


class SB3Agent:
    """An SB3 checkpoint read without unpickling: the policy module, the normaliser, the spaces.

    Attributes: ``algo`` (one of :data:`SB3_ALGORITHMS`), ``policy`` (:class:`SB3Policy`),
    ``normalizer`` (:class:`Normalizer` or None), ``observation_space`` / ``action_space``
    (gymnasium Boxes rebuilt from the JSON's plain fields), ``meta`` (the plain JSON fields used),
    ``path`` (the zip).

    Box bounds are parsed from numpy's text of the arrays (numpy's print precision); :meth:`check_env`
    compares bounds with a relative tolerance of 1e-5 for that reason.
    """

    def __init__(self, path: Path, algo: str, policy: SB3Policy, normalizer: Normalizer | None,
                 observation_space: gym.spaces.Box, action_space: gym.spaces.Box, meta: dict, parts: dict):
        self.path, self.algo, self.policy, self.normalizer = path, algo, policy, normalizer
        self.observation_space, self.action_space, self.meta = observation_space, action_space, meta
        self._parts = parts  # what was parsed from the zip: data (JSON), variables, optimizers, version

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        """``(action, None)`` for raw env observations (one or a batch), like SB3's ``model.predict``.

        The normaliser (if any) is applied first, so this equals
        ``model.predict(vec_normalize.normalize_obs(obs), deterministic=True)``.
        """
        if not deterministic:
            raise ValueError("SB3Agent.predict gives the deterministic (maximum-likelihood) action only: "
                             "fine-tuning uses maximum-likelihood actions (pass deterministic=True)")
        obs = np.asarray(obs)
        shape = self.observation_space.shape
        if obs.shape == shape:
            single = True
        elif obs.shape[1:] == shape:
            single = False
        else:
            raise ValueError(f"observation shape {obs.shape} is neither {shape} nor (n, *{shape}) ({self.path})")
        if self.normalizer is not None:
            obs = self.normalizer(obs)
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, self.policy.obs_dim)
        with torch.no_grad():
            action = self.policy(x).cpu().numpy().reshape((-1, *self.action_space.shape))
        return (action[0] if single else action), None

    def check_env(self, env) -> None:
        """Raise ``ValueError`` naming both spaces when ``env``'s observation or action space is not the checkpoint's."""
        for name, mine in (("observation", self.observation_space), ("action", self.action_space)):
            theirs = getattr(env, f"{name}_space", None)
            fits = (isinstance(theirs, gym.spaces.Box) and theirs.shape == mine.shape
                    and np.allclose(theirs.low, mine.low, rtol=1e-5, atol=1e-7, equal_nan=True)
                    and np.allclose(theirs.high, mine.high, rtol=1e-5, atol=1e-7, equal_nan=True))
            if not fits:
                raise ValueError(f"the env's {name} space {theirs!r} (low {getattr(theirs, 'low', None)}, high "
                                 f"{getattr(theirs, 'high', None)}) differs from the checkpoint's {mine!r} (low "
                                 f"{mine.low}, high {mine.high}) of {self.path}")

    def save_zip(self, out_path: str | Path) -> Path:
        """Write an SB3 zip of this agent (atomically), built from what was parsed, never copied from the input.

        The entries are a fixed list with names chosen here: ``data`` (:meth:`sb3_data`: the plain JSON
        fields, every ":serialized:" payload of the input dropped, the classes and spaces SB3 needs
        re-serialised from known names and the parsed Boxes), ``pytorch_variables.pth`` and the
        optimizer states (if the input had them; re-saved from their ``weights_only`` load),
        ``policy.pth`` (``torch.save`` of ``policy.sb3_state_dict()``) and the SB3 version. SB3's own
        ``PPO.load(out_path)`` etc. reads it and predicts this agent's actions
        (:func:`hybridctl.learn.sb3_export.write_zip`).
        """
        return write_zip(self, out_path)

    def sb3_data(self) -> dict:
        """The ``data`` JSON of :meth:`save_zip` (:func:`hybridctl.learn.sb3_export.sb3_data`)."""
        return sb3_data(self)



def silent_logger():
    """A Stable-Baselines3 logger that writes nothing, for ``model.set_logger`` before ``learn``: SB3's own
    (``verbose=0``) still makes an empty ``SB3-<date>`` folder in the temporary directory on every call."""
    from stable_baselines3.common.logger import Logger

    return Logger(folder=None, output_formats=[])


def load_sb3(path: str | Path, normalizer: str | Path | Normalizer | None = None, trust: bool = False,
             algo: str | None = None) -> SB3Agent:
    """Read an SB3 ``.zip`` (PPO, A2C, SAC, TD3, DDPG; TQC of sb3-contrib) without unpickling anything.

    Args:
        path: the ``model.save`` zip.
        normalizer: an ``.npz`` of :class:`Normalizer` statistics (or a Normalizer); None looks for
            ``vecnormalize.npz`` beside the zip (a ``vecnormalize.pkl`` there without an npz is
            refused unless ``trust``).
        trust: allow unpickling a VecNormalize ``.pkl`` (never the zip).
        algo: override the algorithm found from the JSON (``policy_class.__module__`` and the
            algorithm's fields) or the state-dict keys; one of :data:`SB3_ALGORITHMS`.

    Raises :class:`CheckpointError` naming the file and the entry (and key): a missing file, not a
    zip, an entry that inflates past its limit (``hybridctl.limits.MAX_JSON_BYTES`` for text,
    ``MAX_ZIP_ENTRY_BYTES`` for others and all together; at most ``MAX_ZIP_ENTRIES`` entries), no
    ``data`` or ``policy.pth``, damaged JSON, a bad JSON field we read (``_shape``, ``dtype``,
    ``clip_mean``, ``squash_output``), an unknown class name, a tensor that is not real floating
    point, a state dict that does not fit, a damaged ``pytorch_variables.pth`` or optimizer state.
    """
    path = Path(path)
    if algo is not None and algo not in SB3_ALGORITHMS:
        raise ValueError(f"algo {algo!r} is not one of {SB3_ALGORITHMS}")
    if not path.is_file():
        raise CheckpointError(f"{path}: no such file (an SB3 .zip written by model.save)")
    entries = _read_entries(path)  # every entry, bounded, before anything is built or trained
    for entry in (DATA_ENTRY, POLICY_ENTRY):
        if entry not in entries:
            raise CheckpointError(f"{path} has no {entry!r} entry (entries: {sorted(entries)[:10]})")
    try:
        data = json.loads(entries[DATA_ENTRY].decode("utf-8"))
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise CheckpointError(f"{path}: entry {DATA_ENTRY!r} is not valid JSON: {str(exc)[:120]}") from exc
    if not isinstance(data, dict):
        raise CheckpointError(f"{path}: entry {DATA_ENTRY!r} is not a JSON object")
    state = _state_dict(entries, path)
    parts = {"variables": _variables(entries, path), "optimizers": _optimizers(entries, path),
             "version": _version(entries)}
    source = f"{path}: entry {POLICY_ENTRY!r}"
    module = _policy_module(data)
    if module is not None and module not in POLICY_MODULES:
        raise CheckpointError(f"{path}: entry {DATA_ENTRY!r} key 'policy_class' names module {module[:80]!r}, not "
                              f"one of {POLICY_MODULES} (an MlpPolicy of {', '.join(SB3_ALGORITHMS)})")
    found, how = _detect_algo(data, state)
    if algo is None:
        if found is None:
            raise CheckpointError(f"{path}: cannot tell the algorithm from {DATA_ENTRY!r} or {POLICY_ENTRY!r}; "
                                  f"pass algo= (one of {SB3_ALGORITHMS})")
        algo = found
    else:
        how = "algo= argument"
    where = f"{path}: entry {DATA_ENTRY!r}"
    observation_space = _box_from_json(data, "observation_space", str(path))
    action_space = _box_from_json(data, "action_space", str(path))
    policy_kwargs, classes = _policy_kwargs(data, where)
    if classes.get("features_extractor_class", "FlattenExtractor") not in EXTRACTORS:  # pragma: no cover - checked
        raise CheckpointError(f"{where}: features_extractor_class is not supported (MlpPolicy only)")
    activation = classes.get("activation_fn", DEFAULT_ACTIVATION[algo])
    squash = policy_kwargs.get("squash_output", False) if FAMILY[algo] == "actor_critic" else True
    if not isinstance(squash, bool):
        raise CheckpointError(f"{where}: policy_kwargs['squash_output'] must be true or false, got {squash!r:.60}")
    clip_mean = _number(policy_kwargs.get("clip_mean", 2.0), f"{where}: policy_kwargs['clip_mean']", positive=True)
    obs_dim = int(math.prod(observation_space.shape))
    policy = SB3Policy(state, algo, obs_dim, action_space.low, action_space.high, activation=activation,
                       squash_output=squash, clip_mean=clip_mean, source=source)
    norm = read_normalizer(path, normalizer, trust)
    if norm is not None and norm.norm_obs and norm.shape != observation_space.shape:
        raise CheckpointError(f"the normalisation statistics have shape {norm.shape} but {path} observes "
                              f"{observation_space.shape}")
    meta = {"algo": algo, "algo_from": how, "sb3_version": parts["version"],
            "policy_module": module, "policy_kwargs": policy_kwargs, "policy_kwargs_classes": classes,
            "activation": activation, "use_sde": data.get("use_sde"),
            "squash_output": squash, "num_timesteps": data.get("num_timesteps"),
            "net_arch": policy.net_arch,
            "observation_space": _strip(data["observation_space"]), "action_space": _strip(data["action_space"])}
    parts["data"] = data
    return SB3Agent(path, algo, policy, norm, observation_space, action_space, meta, parts)
