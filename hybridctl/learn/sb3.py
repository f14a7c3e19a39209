"""Stable-Baselines3 checkpoints read WITHOUT unpickling (thesis Ch. 6: random search over SB3 weights).

An SB3 2.x ``model.save("agent.zip")`` writes a zip holding::

    data                       JSON; entries that JSON cannot hold carry ":serialized:" (base64
                               cloudpickle, NEVER decoded here) next to plain-text fields
                               (``observation_space``: ``_shape``, ``dtype``, ``low``, ``high``;
                               ``policy_class``: ``__module__``; ``policy_kwargs``: the repr of
                               each entry, e.g. ``activation_fn``)
    policy.pth                 the policy state dict (read with ``torch.load(weights_only=True)``)
    *.optimizer.pth, pytorch_variables.pth, _stable_baselines3_version, system_info.txt

:func:`load_sb3` reads only the plain JSON/text fields and the state dict and rebuilds the
deterministic (maximum-likelihood) action path of an ``MlpPolicy`` with Box spaces as
:class:`SB3Policy`, a plain ``torch.nn.Module`` whose parameter names are the SB3 keys.
Neither ``pickle`` nor ``cloudpickle`` is ever called on the zip, and this module imports
without stable-baselines3 installed. A zip is someone else's data: every entry is read in
chunks and stopped at ``hybridctl.limits`` (a zip bomb is not inflated), all entries are
checked before anything is built, tensors must be real floating point, and a class named in
the JSON (``policy_class``'s module, ``activation_fn``, ``optimizer_class``,
``features_extractor_class``) must be one of the known ones (:data:`POLICY_CLASSES`,
:data:`CLASS_KWARGS`). :meth:`SB3Agent.save_zip` writes a NEW zip built from what was parsed
(a fixed entry list, the JSON without the input's ":serialized:" payloads, the classes and
spaces re-serialised from known names), so that SB3's own ``PPO.load`` etc. predicts the
fine-tuned actions and never meets a pickle of the input's.

``VecNormalize.save`` writes a pickle; observation statistics are read here from an ``.npz``
(:class:`Normalizer`). A ``.pkl`` is unpickled only with ``trust=True``.

>>> agent = load_sb3("runs/ppo-pendulum/model.zip")      # finds vecnormalize.npz beside it
>>> action, _ = agent.predict(obs)                        # == model.predict(norm(obs), deterministic=True)
>>> names = agent.policy.parameter_names("action")        # what the random search perturbs
>>> agent.save_zip("runs/ppo-pendulum/finetuned.zip")     # PPO.load reads it
"""

from __future__ import annotations

import base64
import io
import json
import math
import pickle
import re
import zipfile
import zlib
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from .. import io as _io
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
NORMALIZER_NPZ = "vecnormalize.npz"
NORMALIZER_PKL = "vecnormalize.pkl"
NPZ_KEYS = ("mean", "var", "count", "clip_obs", "epsilon")

_TRUST_HINT = ("it is a pickle, which can run any code when loaded: pass trust=True (CLI --trust) if you made it, "
               "or convert it once to .npz with Normalizer.from_pkl(path, trust=True).save_npz('vecnormalize.npz')")


# --- observation normalisation ----------------------------------------------------------------------

class Normalizer:
    """Frozen ``VecNormalize`` observation statistics: ``clip((obs - mean) / sqrt(var + eps), -clip, clip)``.

    Calling it equals SB3's ``VecNormalize.normalize_obs`` (computed in float64, returned as
    float32; with ``norm_obs=False`` the observation is returned unchanged).
    """

    def __init__(self, mean, var, count: float, clip_obs: float, epsilon: float, norm_obs: bool = True,
                 source: str = "statistics"):
        mean = np.asarray(mean, dtype=np.float64)
        var = np.asarray(var, dtype=np.float64)
        if mean.shape != var.shape:
            raise CheckpointError(f"{source}: 'mean' has shape {mean.shape} but 'var' has shape {var.shape}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
            raise CheckpointError(f"{source}: 'mean' and 'var' must be finite and 'var' >= 0")
        scalars = {"count": count, "clip_obs": clip_obs, "epsilon": epsilon}
        for key, value in scalars.items():
            value = np.asarray(value)
            if value.size != 1 or not np.isfinite(value).all():
                raise CheckpointError(f"{source}: {key!r} must be one finite number, got {value!r}")
            scalars[key] = float(value.reshape(()))
        self.mean, self.var = mean, var
        self.count, self.clip_obs, self.epsilon = scalars["count"], scalars["clip_obs"], scalars["epsilon"]
        self.norm_obs = bool(np.asarray(norm_obs).reshape(()))
        self.mean.flags.writeable = False
        self.var.flags.writeable = False

    @property
    def shape(self) -> tuple[int, ...]:
        """The observation shape the statistics are for."""
        return self.mean.shape

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` (one observation or a batch) normalised exactly as ``VecNormalize.normalize_obs``."""
        if not self.norm_obs:
            return np.array(obs, copy=True)
        obs = np.asarray(obs)
        return np.clip((obs - self.mean) / np.sqrt(self.var + self.epsilon), -self.clip_obs, self.clip_obs
                       ).astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        """The statistics as plain JSON values (lists and numbers)."""
        return {"type": "vecnormalize_obs", "mean": self.mean.tolist(), "var": self.var.tolist(), "count": self.count,
                "clip_obs": self.clip_obs, "epsilon": self.epsilon, "norm_obs": self.norm_obs}

    def save_npz(self, path: str | Path) -> Path:
        """Write the statistics to ``path`` (.npz, no pickles) atomically: a temporary file, then a rename."""
        arrays = {"mean": self.mean, "var": self.var, "count": np.float64(self.count),
                  "clip_obs": np.float64(self.clip_obs), "epsilon": np.float64(self.epsilon),
                  "norm_obs": np.bool_(self.norm_obs)}
        return _io.atomic_write(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def from_npz(cls, path: str | Path) -> "Normalizer":
        """Read statistics from an ``.npz`` with keys mean, var, count, clip_obs, epsilon (optional norm_obs).

        Raises :class:`CheckpointError` naming the file and the missing or damaged key.
        """
        path = Path(path)
        if not path.is_file():
            raise CheckpointError(f"{path}: no such normalisation file (an .npz with keys {', '.join(NPZ_KEYS)})")
        try:
            with np.load(path, allow_pickle=False) as npz:
                arrays = {key: npz[key] for key in npz.files}
        except Exception as exc:  # BadZipFile, ValueError (object arrays), OSError, EOFError
            raise CheckpointError(f"{path} is not a readable .npz of normalisation statistics: {exc}") from exc
        missing = [key for key in NPZ_KEYS if key not in arrays]
        if missing:
            raise CheckpointError(f"{path} has no key {missing[0]!r} (has {sorted(arrays)}; needs "
                                  f"{', '.join(NPZ_KEYS)}, optional norm_obs)")
        return cls(arrays["mean"], arrays["var"], arrays["count"], arrays["clip_obs"], arrays["epsilon"],
                   arrays.get("norm_obs", True), source=str(path))

    @classmethod
    def from_vecnormalize(cls, vec_normalize) -> "Normalizer":
        """The current observation statistics of a live SB3 ``VecNormalize`` (Box observations only)."""
        rms = vec_normalize.obs_rms
        if isinstance(rms, dict):
            raise CheckpointError("VecNormalize with Dict observations is not supported (Box observations only)")
        return cls(rms.mean, rms.var, rms.count, vec_normalize.clip_obs, vec_normalize.epsilon,
                   vec_normalize.norm_obs, source=type(vec_normalize).__name__)

    @classmethod
    def from_pkl(cls, path: str | Path, trust: bool = False) -> "Normalizer":
        """Statistics from a ``VecNormalize.save`` pickle: refused unless ``trust=True`` (it unpickles)."""
        path = Path(path)
        if not trust:
            raise CheckpointError(f"{path} refused: {_TRUST_HINT}")
        if not path.is_file():
            raise CheckpointError(f"{path}: no such VecNormalize file")
        import pickle  # trusted by the caller; needs stable-baselines3 installed (the pickle names its class)

        with open(path, "rb") as f:
            return cls.from_vecnormalize(pickle.load(f))


TRAINING_NPZ_KEYS = ("ret_mean", "ret_var", "ret_count", "clip_reward", "gamma", "norm_reward")
"""What a ``vecnormalize.npz`` holds beside the observation statistics (:data:`NPZ_KEYS`) when it was
written to resume training (:func:`save_vecnormalize`): the return statistics and reward settings."""
_OLD_KEYS = {"obs_mean": "mean", "obs_var": "var", "obs_count": "count"}
"""Key names of the Table 3.1 driver's files before they shared this format (read, never written)."""


def save_vecnormalize(vec_normalize, path: str | Path, steps: int | None = None) -> Path:
    """A live SB3 ``VecNormalize``'s state to ``path`` (.npz, no pickle, atomic): the observation statistics
    under the keys :meth:`Normalizer.from_npz` reads (so :func:`load_sb3` and fine-tuning use the file as it
    is), the return statistics and settings a resumed training needs (:data:`TRAINING_NPZ_KEYS`), and
    ``steps`` (the env steps the statistics are at) when given. :func:`load_vecnormalize` reads it back."""
    obs = Normalizer.from_vecnormalize(vec_normalize)
    arrays = {"mean": obs.mean, "var": obs.var, "count": np.float64(obs.count), "clip_obs": np.float64(obs.clip_obs),
              "epsilon": np.float64(obs.epsilon), "norm_obs": np.bool_(obs.norm_obs),
              "ret_mean": np.asarray(vec_normalize.ret_rms.mean, dtype=np.float64),
              "ret_var": np.asarray(vec_normalize.ret_rms.var, dtype=np.float64),
              "ret_count": np.float64(vec_normalize.ret_rms.count),
              "clip_reward": np.float64(vec_normalize.clip_reward), "gamma": np.float64(vec_normalize.gamma),
              "norm_reward": np.bool_(vec_normalize.norm_reward)}
    if steps is not None:
        arrays["steps"] = np.int64(steps)
    return _io.atomic_write(path, lambda f: np.savez(f, **arrays))


def load_vecnormalize(path: str | Path, venv, training: bool = True):
    """A ``VecNormalize`` around ``venv`` with the state :func:`save_vecnormalize` wrote to ``path``;
    ``(vec_normalize, steps)`` (``steps`` None when the file has none).

    ``training=False`` freezes the statistics and leaves rewards unnormalised (evaluation). A file
    without the return statistics (observation statistics only) is refused for training. Needs
    stable-baselines3; nothing is unpickled.
    """
    from stable_baselines3.common.vec_env import VecNormalize

    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            d = {_OLD_KEYS.get(key, key): npz[key] for key in npz.files}
    except Exception as exc:  # missing, BadZipFile, object arrays
        raise CheckpointError(f"{path} is not a readable .npz of VecNormalize statistics: {exc}") from exc
    obs = Normalizer(d.get("mean"), d.get("var"), d.get("count"), d.get("clip_obs"), d.get("epsilon"),
                     d.get("norm_obs", True), source=str(path)) if all(k in d for k in NPZ_KEYS) else None
    missing = [k for k in (*NPZ_KEYS, *(TRAINING_NPZ_KEYS if training else ())) if k not in d]
    if obs is None or missing:
        raise CheckpointError(f"{path} has no key {missing[0]!r}" + (" (a file to resume training from needs the "
                              "return statistics too)" if training else ""))
    vn = VecNormalize(venv, training=training, norm_obs=obs.norm_obs,
                      norm_reward=bool(d.get("norm_reward", False)) and training, clip_obs=obs.clip_obs,
                      clip_reward=float(d.get("clip_reward", 10.0)), gamma=float(d.get("gamma", 0.99)),
                      epsilon=obs.epsilon)
    vn.obs_rms.mean, vn.obs_rms.var, vn.obs_rms.count = obs.mean.copy(), obs.var.copy(), obs.count
    if "ret_mean" in d:
        vn.ret_rms.mean, vn.ret_rms.var = d["ret_mean"].copy(), d["ret_var"].copy()
        vn.ret_rms.count = float(d["ret_count"])
    return vn, (int(d["steps"]) if "steps" in d else None)


# --- the policy --------------------------------------------------------------------------------------

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


def _linear_indices(state: dict[str, torch.Tensor], prefix: str) -> list[int]:
    """The Sequential indices ``i`` with a ``{prefix}.{i}.weight`` entry, sorted."""
    pattern = re.compile(rf"^{re.escape(prefix)}\.(\d+)\.weight$")
    return sorted(int(m.group(1)) for key in state if (m := pattern.match(key)))


def _linear(state: dict[str, torch.Tensor], key: str, in_dim: int, source: str) -> nn.Linear:
    """An ``nn.Linear`` shaped after ``{key}.weight`` / ``{key}.bias`` (its input must be ``in_dim``)."""
    weight = state.get(f"{key}.weight")
    if weight is None or weight.ndim != 2:
        raise CheckpointError(f"{source}: no 2-d tensor {key}.weight")
    if weight.shape[1] != in_dim:
        raise CheckpointError(f"{source}: {key}.weight has shape {tuple(weight.shape)}; its input must be {in_dim}")
    bias = state.get(f"{key}.bias")
    if bias is not None and tuple(bias.shape) != (weight.shape[0],):
        raise CheckpointError(f"{source}: {key}.bias has shape {tuple(bias.shape)}, not ({weight.shape[0]},)")
    return nn.Linear(weight.shape[1], weight.shape[0], bias=bias is not None, dtype=weight.dtype)


def _mlp(state, prefix: str, in_dim: int, activation: str, last, source: str) -> tuple[nn.Sequential, int]:
    """SB3's ``create_mlp`` layout: Linear at 0, 2, 4, ... with the activation between; ``last`` after the final one."""
    indices = _linear_indices(state, prefix)
    if indices != list(range(0, 2 * len(indices), 2)):
        raise CheckpointError(f"{source}: the Linear layers of {prefix} sit at {indices}, not 0, 2, 4, ...")
    layers: list[nn.Module] = []
    for k, i in enumerate(indices):
        layer = _linear(state, f"{prefix}.{i}", in_dim, source)
        in_dim = layer.out_features
        layers.append(layer)
        if k < len(indices) - 1:
            layers.append(ACTIVATIONS[activation]())
        elif last is not None:
            layers.append(last())
    return nn.Sequential(*layers), in_dim


class SB3Policy(nn.Module):
    """The deterministic action path of an SB3 ``MlpPolicy`` (Box spaces), rebuilt from its state dict.

    ``forward(obs_normalized[..., obs_dim]) -> action[..., act_dim]`` in env units, as
    ``model.predict(obs, deterministic=True)`` (the mode of the action distribution):

    - PPO/A2C: ``action_net(mlp_extractor.policy_net(obs))`` (also with gSDE, whose ``log_std``
      is a matrix), then clipped to [low, high]; with ``squash_output`` tanh and unscaled instead.
    - SAC/TQC: ``tanh(actor.mu(actor.latent_pi(obs)))`` unscaled to [low, high] (gSDE: ``actor.mu``
      ends in ``Hardtanh(-clip_mean, clip_mean)``, ``clip_mean`` from policy_kwargs, default 2).
    - TD3/DDPG: ``actor.mu(obs)`` (ends in tanh) unscaled to [low, high].

    The layer sizes (net_arch) come from the state-dict shapes. The activation is the one named
    in ``policy_kwargs`` or else SB3's default: Tanh for PPO/A2C, ReLU for SAC/TQC/TD3/DDPG.

    Parameters are named with their SB3 keys (``action_net.weight``, ``actor.mu.4.bias``) and keep the
    checkpoint's dtype. The module holds the whole ActorCriticPolicy (PPO/A2C: value net and log_std
    too), the whole SAC/TQC ``actor`` and the TD3/DDPG ``actor.mu``; the other tensors (critics,
    targets) are kept aside unchanged for :meth:`sb3_state_dict`. It is plain Linear layers and
    activations, so ``torch.func.functional_call`` and ``vmap`` work on it.
    """

    def __init__(self, state_dict: dict[str, torch.Tensor], algo: str, obs_dim: int, action_low, action_high,
                 activation: str | None = None, squash_output: bool = False, clip_mean: float = 2.0,
                 source: str = POLICY_ENTRY):
        super().__init__()
        if algo not in SB3_ALGORITHMS:
            raise ValueError(f"algo {algo!r} is not one of {SB3_ALGORITHMS}")
        self.algo, self.family = algo, FAMILY[algo]
        self.activation = activation or DEFAULT_ACTIVATION[algo]
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation {self.activation!r} is not one of {sorted(ACTIVATIONS)}")
        self.obs_dim = int(obs_dim)
        low = torch.as_tensor(np.asarray(action_low, dtype=np.float32).reshape(-1))
        high = torch.as_tensor(np.asarray(action_high, dtype=np.float32).reshape(-1))
        self.act_dim = low.numel()
        self.register_buffer("action_low", low, persistent=False)
        self.register_buffer("action_high", high, persistent=False)
        self._original = {key: value.detach().clone() for key, value in state_dict.items()}
        state = self._original
        act = self.activation
        if self.family == "actor_critic":
            self.squash_output = bool(squash_output)
            self.mlp_extractor = nn.Module()
            self.mlp_extractor.policy_net, pi_dim = _mlp(state, "mlp_extractor.policy_net", obs_dim, act,
                                                         ACTIVATIONS[act], source)
            self.mlp_extractor.value_net, vf_dim = _mlp(state, "mlp_extractor.value_net", obs_dim, act,
                                                         ACTIVATIONS[act], source)
            self.action_net = _linear(state, "action_net", pi_dim, source)
            self.value_net = _linear(state, "value_net", vf_dim, source)
            log_std = state.get("log_std")
            if log_std is None:
                raise CheckpointError(f"{source}: no 'log_std' tensor")
            self.log_std = nn.Parameter(torch.zeros_like(log_std))
            self._last = "action_net."
            own = ("mlp_extractor.", "action_net.", "value_net.", "log_std")
        elif self.family == "squashed":
            self.squash_output = True
            self.actor = nn.Module()
            self.actor.latent_pi, pi_dim = _mlp(state, "actor.latent_pi", obs_dim, act, ACTIVATIONS[act], source)
            if "actor.mu.0.weight" in state:  # gSDE: mu = Sequential(Linear, Hardtanh(-clip_mean, clip_mean))
                self.actor.mu = nn.Sequential(_linear(state, "actor.mu.0", pi_dim, source),
                                              nn.Hardtanh(-clip_mean, clip_mean))
                self._last = "actor.mu.0."
            else:
                self.actor.mu = _linear(state, "actor.mu", pi_dim, source)
                self._last = "actor.mu."
            if "actor.log_std.weight" in state:
                self.actor.log_std = _linear(state, "actor.log_std", pi_dim, source)
            elif "actor.log_std" in state:  # gSDE: a parameter matrix
                self.actor.log_std = nn.Parameter(torch.zeros_like(state["actor.log_std"]))
            else:
                raise CheckpointError(f"{source}: no actor.log_std tensor")
            own = ("actor.",)
        else:
            self.squash_output = True
            self.actor = nn.Module()
            self.actor.mu, _ = _mlp(state, "actor.mu", obs_dim, act, nn.Tanh, source)
            last = _linear_indices(state, "actor.mu")
            if not last:
                raise CheckpointError(f"{source}: no actor.mu.<i>.weight tensors (a TD3/DDPG actor)")
            self._last = f"actor.mu.{last[-1]}."
            own = ("actor.",)
        path_net = self.mlp_extractor.policy_net if self.family == "actor_critic" else (
            self.actor.latent_pi if self.family == "squashed" else self.actor.mu[:-2])
        self.net_arch = [m.out_features for m in path_net if isinstance(m, nn.Linear)]
        mine = self.state_dict()
        stray = [key for key in state if key.startswith(own) and key not in mine]
        if stray:
            raise CheckpointError(f"{source}: tensors {stray[:4]} do not fit an {algo} MlpPolicy")
        try:
            self.load_state_dict({key: state[key] for key in mine}, strict=True)
        except (KeyError, RuntimeError) as exc:
            raise CheckpointError(f"{source}: the state dict does not fit an {algo} MlpPolicy: {exc}") from exc
        out = self.action_net.out_features if self.family == "actor_critic" else self._mean_layer().out_features
        if out != self.act_dim:
            raise CheckpointError(f"{source}: the policy outputs {out} actions but the action space has {self.act_dim}")

    def _mean_layer(self) -> nn.Linear:
        for name, module in self.named_modules():
            if f"{name}." == self._last:
                return module
        raise AssertionError(self._last)

    def _unscale(self, scaled: torch.Tensor) -> torch.Tensor:
        # as SB3's BasePolicy.unscale_action: low + 0.5 * (a + 1) * (high - low)
        return self.action_low + 0.5 * (scaled + 1.0) * (self.action_high - self.action_low)

    def forward(self, obs_normalized: torch.Tensor) -> torch.Tensor:
        """The deterministic action in env units for (normalised) observations ``[..., obs_dim]``."""
        if self.family == "actor_critic":
            mean = self.action_net(self.mlp_extractor.policy_net(obs_normalized))
            if self.squash_output:
                return self._unscale(torch.tanh(mean))
            return torch.clamp(mean, self.action_low, self.action_high)
        if self.family == "squashed":
            return self._unscale(torch.tanh(self.actor.mu(self.actor.latent_pi(obs_normalized))))
        return self._unscale(self.actor.mu(obs_normalized))

    def parameter_names(self, select: str = "action") -> list[str]:
        """The names (of ``named_parameters()``) a fine-tuner perturbs, for ``select`` in :data:`SELECTIONS`.

        - ``"action"``: the deterministic action path: PPO/A2C ``mlp_extractor.policy_net.*`` and
          ``action_net.*`` (not the value net nor log_std); SAC/TQC ``actor.latent_pi.*`` and
          ``actor.mu.*`` (not ``actor.log_std``); TD3/DDPG ``actor.mu.*``.
        - ``"all"`` (the thesis author's code): PPO/A2C every policy parameter (value net and
          log_std too); SAC/TQC every ``actor.*`` parameter; TD3/DDPG ``actor.mu.*``.
        - ``"last"``: only the last Linear layer of the action path (ablation).
        """
        names = [name for name, _ in self.named_parameters()]
        if select == "all":
            return names
        if select == "last":
            return [name for name in names if name.startswith(self._last)]
        if select == "action":
            keep = {"actor_critic": ("mlp_extractor.policy_net.", "action_net."),
                    "squashed": ("actor.latent_pi.", "actor.mu."), "deterministic": ("actor.mu.",)}[self.family]
            return [name for name in names if name.startswith(keep)]
        raise ValueError(f"select {select!r} is not one of {SELECTIONS}")

    def sb3_state_dict(self) -> dict[str, torch.Tensor]:
        """The full original ``policy.pth`` dict (same keys, same order) with this module's current values."""
        mine = self.state_dict()
        return {key: (mine[key] if key in mine else value).detach().clone().contiguous()
                for key, value in self._original.items()}


# --- reading the zip ----------------------------------------------------------------------------------

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
        ``PPO.load(out_path)`` etc. reads it and predicts this agent's actions.
        """
        entries = {DATA_ENTRY: json.dumps(self.sb3_data(), indent=4).encode("utf-8")}
        if self._parts["variables"] is not None:
            entries[VARIABLES_ENTRY] = _torch_bytes(self._parts["variables"])
        entries[POLICY_ENTRY] = _torch_bytes(self.policy.sb3_state_dict())
        for name, state in self._parts["optimizers"].items():
            entries[name] = _torch_bytes(state)
        if self._parts["version"] is not None:
            entries[VERSION_ENTRY] = self._parts["version"].encode("ascii")

        def write(f):
            with zipfile.ZipFile(f, "w", zipfile.ZIP_DEFLATED) as zout:
                for name, payload in entries.items():
                    zout.writestr(name, payload)

        return _io.atomic_write(out_path, write)

    def sb3_data(self) -> dict:
        """The ``data`` JSON of :meth:`save_zip`.

        Kept: the input's plain JSON fields (with ":"-keys stripped at any depth), except ``env``
        (SB3 would ``gym.make`` it) and the ``*_class`` fields (SB3 picks its defaults). A serialized
        constant schedule (``ConstantSchedule(val=0.2)``) becomes its number, a pickled ``target_entropy``
        (SB3's "auto") ``-prod(action shape)``; other pickled fields are dropped (SB3 keeps its defaults,
        e.g. ``train_freq``, and rebuilds buffers on ``learn``). Rebuilt by us:
        ``policy_class`` (:data:`POLICY_CLASSES`), the two Boxes and ``policy_kwargs`` (its plain fields
        and the known classes of :data:`CLASS_KWARGS`), each pickled from objects made here.
        """
        data = {}
        for key, value in self._parts["data"].items():
            if key == "env" or key.endswith("_class") or key in _REBUILT:
                continue
            if isinstance(value, dict) and ":serialized:" in value:
                constant = _constant_schedule(value)
                if key == "target_entropy":  # only SB3's "auto" is stored pickled (a numpy float): -act_dim
                    constant = -float(math.prod(self.action_space.shape))
                if constant is not None:
                    data[key] = constant
                continue
            data[key] = _strip(value)
        module, name = POLICY_CLASSES[self.algo]
        data["policy_class"] = _serialized(_ClassRef(module, name), "<class 'abc.ABCMeta'>", {"__module__": module})
        for key, box in (("observation_space", self.observation_space), ("action_space", self.action_space)):
            data[key] = _serialized(box, str(type(box)), _box_fields(box))
        kwargs = dict(self.meta["policy_kwargs"])
        classes = self.meta["policy_kwargs_classes"]
        objects = {key: CLASS_OBJECTS[key][name] for key, name in classes.items() if key != "features_extractor_class"}
        if objects:  # FlattenExtractor is MlpPolicy's default: not written
            shown = {**kwargs, **{key: str(obj) for key, obj in objects.items()}}
            data["policy_kwargs"] = _serialized({**kwargs, **objects}, "<class 'dict'>", shown)
        else:
            data["policy_kwargs"] = kwargs
        return data


_REBUILT = ("policy_class", "observation_space", "action_space", "policy_kwargs")
"""``data`` fields :meth:`SB3Agent.sb3_data` writes itself."""
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


def _read_normalizer(path: Path, normalizer: str | Path | Normalizer | None, trust: bool) -> Normalizer | None:
    if isinstance(normalizer, Normalizer):
        return normalizer
    if normalizer is not None:
        normalizer = Path(normalizer)
        if normalizer.suffix == ".pkl":
            return Normalizer.from_pkl(normalizer, trust=trust)
        return Normalizer.from_npz(normalizer)
    npz, pkl = path.parent / NORMALIZER_NPZ, path.parent / NORMALIZER_PKL
    if npz.exists():
        return Normalizer.from_npz(npz)
    if pkl.exists():
        if not trust:
            raise CheckpointError(f"{pkl} (beside {path.name}) holds the observation normalisation but {_TRUST_HINT}")
        return Normalizer.from_pkl(pkl, trust=True)
    return None


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
    norm = _read_normalizer(path, normalizer, trust)
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
