"""SB3's ``VecNormalize`` statistics without its pickle: the frozen :class:`Normalizer` read from an ``.npz``,
and a live ``VecNormalize`` saved to / restored from one (:func:`save_vecnormalize`, :func:`load_vecnormalize`).

``VecNormalize.save`` writes a pickle; observation statistics are read here from an ``.npz``. A
``.pkl`` is unpickled only with ``trust=True``.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np

from .. import io as _io
from .checkpoint import CheckpointError

NORMALIZER_NPZ = "vecnormalize.npz"
NORMALIZER_PKL = "vecnormalize.pkl"
NPZ_KEYS = ("mean", "var", "count", "clip_obs", "epsilon")

_TRUST_HINT = ("it is a pickle, which can run any code when loaded: pass trust=True (CLI --trust) if you made it, "
               "or convert it once to .npz with Normalizer.from_pkl(path, trust=True).save_npz('vecnormalize.npz')")


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



def read_normalizer(path: Path, normalizer: str | Path | Normalizer | None, trust: bool) -> Normalizer | None:
    """The observation statistics of the SB3 zip at ``path``: ``normalizer`` as given (a Normalizer, an .npz,
    a .pkl with ``trust``), else ``vecnormalize.npz`` beside the zip (a ``vecnormalize.pkl`` there only with
    ``trust``), else None."""
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
