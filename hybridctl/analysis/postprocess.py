"""Reward post-processing by trajectory dimension (thesis Sec. 4.2.5, eq. 4.4-4.5; Ch. 6 eq. 6.1-6.2).

A post-processor turns an episode's return R and its states into

    R* = R / D      (eq. 4.4 / 6.1, form "divide", for positive returns)
    R* = R * D      (eq. 6.2, form "multiply", for negative returns)

so that lower-dimensional closed-loop behaviour earns more. ``D`` by kind:

=============  ==============================================================
identity       D = 1 (the thesis' "no post-processing" baseline)
mesh-lower     lower mesh dimension of the states after T_r steps, clipped
               to [1, n_states / 2] (eq. 4.5)
mesh-upper     upper mesh dimension, clipped likewise
mesh-mean      mean of lower and upper, clipped (what Ch. 6 trains on)
madogram       variation estimator p = 1 of the states after T_r (Sec. 4.2.4)
variogram      variation estimator p = 2
=============  ==============================================================

Too-short episodes (fewer than ``min_points`` states after the transient, e.g. a
hopper that fell) cannot be measured: they get the worst value, ``n_states / 2``
for the mesh kinds and 2 for the variation kinds, so that falling early is never
rewarded (the thesis' clipping "weeds out trajectories that terminate very early").
The returned ``info["reason"]`` says when and why that happened.

>>> pp = PostProcessor("mesh-lower")
>>> new_return, info = pp(states, episode_return)     # info: dimension, raw_dimension, reason
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .mesh import INITIAL_BOX_SIZE, SCALE_FACTOR, mesh_dimension
from .variation import variation_dimension

KINDS = ("identity", "mesh-lower", "mesh-upper", "mesh-mean", "madogram", "variogram")
FORMS = ("divide", "multiply", "auto")
TRANSIENT_STEPS = 200   # T_r, thesis Sec. 4.2.5
MIN_POINTS = 10         # hybridctl: fewest states after T_r for a dimension (a mesh curve needs a few)


@dataclass(frozen=True)
class PostProcessor:
    """Dimension-based reward post-processor (see the module docstring for the kinds and forms).

    ``transient_steps``: states dropped from the start (T_r = 200). ``form``: "divide"
    (eq. 4.4), "multiply" (eq. 6.2) or "auto" (divide a return >= 0, multiply a negative one).
    ``mean`` / ``std``: normalisation for the mesh kinds (default: the trajectory's own; the
    thesis used the policy's running statistics). ``legacy``: the author's variation code.
    ``scale_factor`` / ``initial_box``: the mesh's f and d0 (Ch. 4: 1.5 and 0.01; the Ch. 6
    author's code: 1.2 and 1). ``clip_low``: the lower clip of a mesh dimension (Ch. 4: 1;
    the Ch. 6 code: 0). A dimension of 0 cannot divide a return: the divide form then uses
    the worst value, so that standing still is never rewarded without bound.
    """

    kind: str = "identity"
    transient_steps: int = TRANSIENT_STEPS
    form: str = "divide"
    min_points: int = MIN_POINTS
    mean: tuple | None = None
    std: tuple | None = None
    legacy: bool = False
    scale_factor: float = SCALE_FACTOR
    initial_box: float = INITIAL_BOX_SIZE
    clip_low: float = 1.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"post-processor kind must be one of {KINDS}, got {self.kind!r}")
        if self.form not in FORMS:
            raise ValueError(f"post-processor form must be one of {FORMS}, got {self.form!r}")
        if not (isinstance(self.transient_steps, (int, np.integer)) and self.transient_steps >= 0):
            raise ValueError(f"transient_steps must be an integer >= 0, got {self.transient_steps!r}")
        if not (isinstance(self.min_points, (int, np.integer)) and self.min_points >= 3):
            raise ValueError(f"min_points must be an integer >= 3, got {self.min_points!r}")
        if not (isinstance(self.scale_factor, (int, float)) and np.isfinite(self.scale_factor)
                and self.scale_factor > 1):
            raise ValueError(f"scale_factor must be a finite number > 1, got {self.scale_factor!r}")
        if not (isinstance(self.initial_box, (int, float)) and np.isfinite(self.initial_box) and self.initial_box > 0):
            raise ValueError(f"initial_box must be a finite number > 0, got {self.initial_box!r}")
        if not (isinstance(self.clip_low, (int, float)) and 0 <= self.clip_low <= 1):
            raise ValueError(f"clip_low must be in [0, 1], got {self.clip_low!r}")

    def dimension(self, states) -> tuple[float, dict]:
        """(D, info) for one episode's states, shape (n_steps, n_states). D is finite and >= 1."""
        if self.kind == "identity":
            return 1.0, {"dimension": 1.0, "raw_dimension": None, "reason": ""}
        x = np.asarray(states, dtype=np.float64)
        if x.ndim != 2:
            raise ValueError(f"states must have shape (n_steps, n_states), got shape {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{self.kind} post-processor: states contain NaN or inf; cannot compute a dimension")
        mesh = self.kind.startswith("mesh")
        worst = x.shape[1] / 2 if mesh else 2.0
        tail = x[self.transient_steps:]
        if tail.shape[0] < self.min_points:
            reason = (f"episode too short: {x.shape[0]} states, {tail.shape[0]} after the first "
                      f"{self.transient_steps} (need {self.min_points}); worst value {worst:g} used")
            return worst, {"dimension": worst, "raw_dimension": None, "reason": reason}
        if mesh:
            md = mesh_dimension(tail, f=self.scale_factor, d0=self.initial_box, mean=self.mean, std=self.std)
            raw = {"mesh-lower": md.lower, "mesh-upper": md.upper, "mesh-mean": (md.lower + md.upper) / 2}[self.kind]
            value = float(np.clip(raw, self.clip_low, worst))
            reason = md.note
        else:
            raw = variation_dimension(tail, 1.0 if self.kind == "madogram" else 2.0, legacy=self.legacy)
            value, reason = raw, ""
        return value, {"dimension": value, "raw_dimension": raw, "reason": reason}

    def __call__(self, states, episode_return: float) -> tuple[float, dict]:
        """(post-processed return, info) for one episode."""
        if isinstance(episode_return, (bool, np.bool_)) or not isinstance(episode_return, (int, float, np.number)) \
                or not np.isfinite(episode_return):
            raise ValueError(f"episode_return must be a finite number, got {episode_return!r}")
        dim, info = self.dimension(states)
        form = self.form if self.form != "auto" else ("divide" if episode_return >= 0 else "multiply")
        if form == "divide" and dim <= 0:  # clip_low 0 and a constant trajectory: no division by zero
            worst = np.asarray(states).shape[1] / 2 if self.kind.startswith("mesh") else 2.0
            dim = worst
            info.update(dimension=worst, reason=(info["reason"] + "; " if info["reason"] else "")
                        + f"dimension 0 cannot divide a return: worst value {worst:g} used")
        info["form"] = form
        info["raw_return"] = float(episode_return)
        return (episode_return / dim if form == "divide" else episode_return * dim), info

    def to_dict(self) -> dict:
        """JSON-ready settings (for checkpoints)."""
        return asdict(self)
