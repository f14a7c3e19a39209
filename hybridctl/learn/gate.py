"""The learned gate of SSAC (thesis Sec. 3.3, Algorithm 2): a classifier of the LQR's basin.

The gate G(s) in [0, 1] says whether the LQR can take over from state s. It is a
4-32-32-1 ReLU MLP with a sigmoid output (thesis appendix), trained with a
weighted binary cross-entropy whose positive-class weight
c_w = (n_total / n_positive) * w, w = 0.01 (thesis eq. 3.3), which makes it
conservative: a false "LQR can take over" costs an episode, a false "cannot" only
delays the hand-over. Labels come from LQR rollouts (warm start) and, during
SSAC, from the episodes in which the LQR acted.

Two deliberate differences from the thesis, both control knowledge handed to
the network instead of learned by it: it sees the wrapped state error (angles in
[-pi, pi)) scaled per coordinate, so a turn of 2 pi is the same state to the gate
as to the LQR; and it gets log(1 + V / scale) with V = (x - goal)' S (x - goal)
the LQR cost-to-go as an extra input. The LQR's basin is a thin sliver of the
sampled states (V < ~260 for the acrobot, errors of ~0.02 rad), which a raw-state
4-32-32-1 MLP did not carve out in our tests (it never handed over).

:func:`learned_gate_from_basin` is the warm start without the spec's spreads: it measures the LQR's
basin (:func:`measure_basin`), samples around it, fits on LQR-rollout labels only and says whether
the gate works on held-out states (the fallback is the cost-to-go gate). SSAC's refits on episode
outcomes (Alg. 4 line 8) are what made the furuta's and the reaction wheel's gates hand back or never
hand over (results/your_robot/learned_gate/diagnosis.json).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from torch.func import functional_call, grad_and_value

from ..systems import System
from ..systems.compiled import LazyCompiled
from ..systems.control import cost_to_go, lqr_rollouts_balanced, wrap_angles
from ..systems.switched import SwitchedController, ZeroSwingup, closed_loop_rollout
from .config_check import check_types
from .optim import FusedAdamStep, adam, set_grads
from .config_check import check_fields
from .run import check_finite, seeded


@dataclass
class GateConfig:
    """Every hyperparameter of gate learning, with its source."""

    hidden: tuple[int, ...] = (32, 32)        # thesis appendix Ch. 3: two hidden layers of 32, ReLU
    positive_weight: float = 0.01             # thesis eq. 3.3: w in c_w = n_t / n_p * w
    label_eps: float = 0.2                    # implementation notes: gate labels within 0.2 (L2)
    label_lookback: int = 10                  # implementation notes: last 10 states
    label_horizon: float | None = None        # None: the spec's gate.label_horizon (default: the thesis' 2.5 s,
    #                                           systems.spec.THESIS_LABEL_HORIZON)
    warm_samples: int = 100_000               # hybridctl: 2.5e7 LQR steps, ~1 min on 2 cores (thesis: 1e6 steps)
    warm_fit_steps: int = 3000                # hybridctl: Adam steps on the warm-start data
    refit_steps: int = 500                    # hybridctl: Adam steps per SSAC refit on all gate data
    batch_size: int = 4096                    # hybridctl: minibatches drawn from the whole data set
    cost_feature: bool = True                 # hybridctl: log(1 + V / gate.cost_scale) as an extra input
    lr: float = 1e-3                          # hybridctl; thesis "initial gate learning rate" 1e-5 (too slow here)
    seed: int = 0
    extra: dict = field(default_factory=dict)

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        check_types(self)
        check_fields(self, positive=("positive_weight", "label_eps", "lr"),
                     integers_from_1=("label_lookback", "batch_size"),
                     integers_from_0=("warm_fit_steps", "refit_steps", "seed"))
        if not self.hidden or any(h < 1 for h in self.hidden):
            raise ValueError(f"GateConfig.hidden must be a non-empty tuple of layer widths >= 1, got {self.hidden!r}")
        if self.warm_samples < 2:
            raise ValueError(f"GateConfig.warm_samples must be an integer >= 2, got {self.warm_samples!r}")
        if self.label_horizon is not None and self.label_horizon <= 0:
            raise ValueError(f"GateConfig.label_horizon must be None (the spec's) or > 0, got {self.label_horizon!r}")

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        data = asdict(self)
        data["hidden"] = list(self.hidden)
        return data


class GateNet(torch.nn.Module):
    """Gate classifier: states (B, n) -> probabilities (B, 1) that the LQR can take over.

    Features are the wrapped state error divided by ``feature_scale`` (by default
    the spec's ``gate.warm_far`` spread, so features are O(1)) and, with
    ``cost_feature``, log(1 + V / cost_scale) of the LQR cost-to-go V (``cost_scale`` by
    default the spec's ``gate.cost_scale``).

    The net is built on the CPU whatever torch's default device (initial weights from the
    CPU RNG, so one seed gives the same gate on every device) and then moved to ``device``
    (None: it stays on the CPU).
    """

    def __init__(self, system: System, hidden: tuple[int, ...] = GateConfig.hidden,
                 feature_scale: np.ndarray | None = None, cost_feature: bool = True,
                 device: str | torch.device | None = None, cost_scale: float | None = None):
        super().__init__()
        with torch.device("cpu"):
            self._build(system, hidden, feature_scale, cost_feature, cost_scale)
        if device is not None:
            self.to(device)

    def _build(self, system: System, hidden: tuple[int, ...], feature_scale, cost_feature: bool,
               cost_scale: float | None = None) -> None:
        """The buffers and layers of :meth:`__init__` (made on the CPU); ``cost_scale`` None: the spec's
        ``gate.cost_scale`` (both scales are buffers: a loaded state dict brings its own)."""
        self.system_name = system.name
        self.gate_on = system.gate.on  # the hand-over threshold of the system's hysteresis (gate_metrics)
        scale = system.gate.spread("warm_far") if feature_scale is None else np.asarray(feature_scale, float)
        self.register_buffer("feature_scale", torch.as_tensor(scale, dtype=torch.float32))
        self.register_buffer("goal", torch.as_tensor(system.goal, dtype=torch.float32))
        # kept as a buffer: checkpoints' gate state dicts hold it
        self.register_buffer("angle_mask", torch.zeros(system.n_states, dtype=torch.bool))
        self.angle_mask[system.angle_indices] = True
        self.angle_indices = list(system.angle_indices)
        self.cost_feature = bool(cost_feature)
        S = system.lqr()[1] / (system.gate.cost_scale if cost_scale is None else float(cost_scale))
        self.register_buffer("S_scaled", torch.as_tensor(S, dtype=torch.float32))
        layers, width = [], system.n_states + int(self.cost_feature)
        for h in hidden:
            layers += [torch.nn.Linear(width, h), torch.nn.ReLU()]
            width = h
        layers.append(torch.nn.Linear(width, 1))
        self.net = torch.nn.Sequential(*layers)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Wrapped state error, scaled, and optionally log(1 + V / scale)."""
        err = wrap_angles(x.to(self.goal.dtype) - self.goal, self.angle_indices)  # a new tensor: wrapped in place
        features = err / self.feature_scale
        if self.cost_feature:
            cost = cost_to_go(err, self.S_scaled).unsqueeze(-1)
            features = torch.cat([features, torch.log1p(cost)], dim=-1)
        return features

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """Pre-sigmoid outputs (B, 1)."""
        return self.net(self.features(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Probabilities (B, 1)."""
        return torch.sigmoid(self.logits(x))

    def numpy_forward(self, x: np.ndarray) -> np.ndarray:
        """The same probabilities for numpy states (..., n) -> (..., 1), in numpy at the net's dtype.

        The Drake ``Gate`` calls it at every control period on one state, where torch's
        per-call overhead was most of the loop's time. The same formulas as :meth:`forward`
        (``wrap_angles``, ``cost_to_go``); in float32 the two differ by rounding (the
        cost-to-go feature, a sum with cancellation, by up to ~1e-5 relative). The numpy
        copies of the weights are refreshed whenever a parameter or buffer changed (a refit).
        """
        layers, goal, scale, S = self._numpy_copies()
        err = wrap_angles(np.asarray(x, dtype=goal.dtype) - goal, self._angle_columns)
        h = err / scale
        if self.cost_feature:
            h = np.concatenate([h, np.log1p(cost_to_go(err, S))[..., None]], axis=-1)
        last = len(layers) - 1
        for i, (w, b) in enumerate(layers):
            h = h @ w + b
            if i < last:
                h = np.maximum(h, 0)
        return 1.0 / (1.0 + np.exp(-h))

    def _numpy_copies(self):
        """(layers [(W^T, b)], goal, feature_scale, S_scaled) as numpy, cached while no parameter or
        buffer changed in place (optimiser steps and ``load_state_dict`` do; a parameter replaced by a
        new tensor object is not seen: call ``numpy_forward`` on a fresh GateNet then)."""
        tensors = self.__dict__.get("_numpy_tensors")
        if tensors is None or [t._version for t in tensors] != self._numpy_key:
            if any(not isinstance(m, (torch.nn.Linear, torch.nn.ReLU)) for m in self.net):
                raise TypeError("GateNet.numpy_forward needs the net built by GateNet (Linear and ReLU layers)")
            tensors = [*self.parameters(), *self.buffers()]
            # host copies of a gate on any device (the Drake blocks run on the CPU)
            layers = [(m.weight.detach().cpu().numpy().T.copy(), m.bias.detach().cpu().numpy().copy())
                      for m in self.net if isinstance(m, torch.nn.Linear)]
            buffers = [getattr(self, name).detach().cpu().numpy().copy()
                       for name in ("goal", "feature_scale", "S_scaled")]
            idx = list(self.angle_indices)
            contiguous = bool(idx) and idx == list(range(idx[0], idx[-1] + 1))
            self._angle_columns = slice(idx[0], idx[-1] + 1) if contiguous else idx
            self._numpy = (layers, *buffers)
            self._numpy_tensors, self._numpy_key = tensors, [t._version for t in tensors]
        return self._numpy


def warm_start_states(system: System, n: int, rng: np.random.Generator, near=None, far=None) -> np.ndarray:
    """Thesis Algorithm 2 samples: half goal + U(-near, near), half goal + U(-far, far); ``near`` / ``far``
    None: the spec's ``gate.warm_near`` / ``gate.warm_far`` (:func:`basin_spreads` derives them from a basin)."""
    if n < 2:
        raise ValueError(f"n must be >= 2, got {n}")
    near = system.gate.spread("warm_near") if near is None else np.asarray(near, dtype=float)
    far = system.gate.spread("warm_far") if far is None else np.asarray(far, dtype=float)
    half = n // 2
    states = np.concatenate([rng.uniform(-near, near, size=(half, system.n_states)),
                             rng.uniform(-far, far, size=(n - half, system.n_states))])
    return system.goal + states


def label_horizon(system: System, config: GateConfig) -> float:
    """Seconds of LQR rollout behind a gate label: the config's, else the system's ``gate.label_horizon``
    (whose default is the thesis' 2.5 s)."""
    if config.label_horizon is not None:
        return float(config.label_horizon)
    return system.gate.label_horizon


def label_states(system: System, states, config: GateConfig, K=None,
                 device: str | torch.device | None = None) -> np.ndarray:
    """Labels 1 where the saturated LQR from that state balances (config's eps and lookback,
    :func:`label_horizon` seconds). The rollouts run on ``device`` (None: a torch ``states``'
    device, else the CPU); the labels come back as a numpy bool array."""
    return lqr_rollouts_balanced(system, states, label_horizon(system, config), eps=config.label_eps,
                                 lookback=config.label_lookback, K=K, device=device)


def positive_class_weight(labels, positive_weight: float) -> float:
    """Thesis eq. 3.3: c_w = (n_total / n_positive) * positive_weight (1 without positives)."""
    n_pos = int(labels.sum()) if isinstance(labels, torch.Tensor) else int(np.asarray(labels, dtype=bool).sum())
    return (len(labels) / n_pos) * positive_weight if n_pos else 1.0


def gate_loss(gate: GateNet, states: torch.Tensor, labels: torch.Tensor, c_w: float) -> torch.Tensor:
    """Thesis eq. 3.3: BCE on the gate's logits with the positive class weighted by ``c_w``."""
    logits = gate.logits(states)
    return _weighted_bce(logits, labels, torch.tensor(c_w, device=logits.device))


def _weighted_bce(logits: torch.Tensor, labels: torch.Tensor, c_w: torch.Tensor) -> torch.Tensor:
    """Eq. 3.3's loss on logits (B, 1) and bool labels (B,), shared by the eager and compiled fits."""
    return torch.nn.functional.binary_cross_entropy_with_logits(logits.squeeze(-1), labels.float(), pos_weight=c_w)


def fit_gate(gate: GateNet, states, labels, steps: int, lr: float = 1e-3, positive_weight: float = 0.01,
             batch_size: int = 4096, generator: torch.Generator | None = None,
             optimizer: torch.optim.Optimizer | None = None, class_weight: float | None = None,
             compiled: bool = False) -> list[float]:
    """Adam on minibatches drawn from the whole gate data set (the thesis refits on all of it).

    The class weight c_w is ``class_weight`` if given, else eq. 3.3 on the whole data
    set's class balance. ``compiled``: each step's loss and gradient is one ``torch.compile``-d
    graph (the same numbers up to float32 rounding; the minibatches are the same draws), with
    a fused Adam step; SSAC refits this way when it trains compiled. Returns the losses.

    The fit runs on the gate's device: ``states`` and ``labels`` (numpy or torch, on any device)
    are copied there once, and the minibatch rows are drawn there, from ``generator`` (which must
    be on that device; None: torch's default generator of the device). Each step reads its loss
    back once (the NaN guard and the returned losses).
    """
    device = _module_device(gate)
    x = _as_device_tensor(states, torch.float32, device)
    y = _as_device_tensor(labels, torch.bool, device)
    if x.shape[0] != y.shape[0] or x.shape[0] == 0:
        raise ValueError(f"states and labels must be non-empty and of equal length, got {x.shape[0]} and {y.shape[0]}")
    c_w = positive_class_weight(y, positive_weight) if class_weight is None else class_weight
    optimizer = optimizer or (adam(gate.parameters(), lr) if compiled else torch.optim.Adam(gate.parameters(), lr=lr))
    step = _CompiledGateStep(gate, optimizer, c_w) if compiled else None
    losses = []
    gate.train()
    for i in range(steps):
        rows = torch.randint(len(y), (min(batch_size, len(y)),), generator=generator, device=device)
        xb, yb = x.index_select(0, rows), y.index_select(0, rows)  # = x[rows], y[rows], 2.5x faster
        if step is not None:
            loss = step(xb, yb)
        else:
            loss = gate_loss(gate, xb, yb, c_w)
            value = loss.item()  # the step's one read-back: checked here, returned below
            check_finite("gate loss", value, f"at fit step {i}")
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            loss = value
        losses.append(loss)
    gate.eval()
    return losses


def _module_device(module) -> torch.device:
    """The device of a module's first parameter or buffer (the CPU for one without tensors, or a
    plain callable)."""
    tensors = [*getattr(module, "parameters", lambda: [])(), *getattr(module, "buffers", lambda: [])()]
    return tensors[0].device if tensors else torch.device("cpu")


def _as_device_tensor(values, dtype: torch.dtype | None, device: torch.device) -> torch.Tensor:
    """``values`` (numpy, a sequence or a torch tensor on any device) as a ``dtype`` tensor on ``device``
    (None: the values' own dtype)."""
    if isinstance(values, torch.Tensor):
        return values.detach().to(device=device, dtype=dtype)
    return torch.as_tensor(np.asarray(values), dtype=dtype, device=device)


def _gate_grads(params: dict, gate: GateNet, x: torch.Tensor, y: torch.Tensor, c_w: torch.Tensor):
    """Gradient and value of :func:`gate_loss` with respect to ``params`` (the gate's parameters,
    all in ``gate.net``; the features use buffers only)."""
    def loss_of(params):
        net_params = {name.removeprefix("net."): value for name, value in params.items()}
        return _weighted_bce(functional_call(gate.net, net_params, (gate.features(x),)), y, c_w)
    return grad_and_value(loss_of)(params)


COMPILED_GATE_GRADS = LazyCompiled(_gate_grads, True, strict=False, name="the gate's fit step")
"""The compiled gradient of :func:`gate_loss` (a failed compile falls back to eager with a warning)."""


class _CompiledGateStep:
    """One compiled gate fit step: BCE loss and its gradient in one graph, then a fused Adam step.

    One compiled function serves every gate (torch.compile guards on the gate's layout, not on
    the object, so refits and new gates of the same layout reuse it); c_w is passed as a tensor
    (a new class weight does not compile again)."""

    def __init__(self, gate: GateNet, optimizer: torch.optim.Optimizer, c_w: float):
        self.gate = gate
        self.params = list(gate.parameters())
        self.detached = {k: v.detach() for k, v in gate.named_parameters()}
        self.c_w = torch.tensor(float(c_w), dtype=torch.float32, device=self.params[0].device)
        self.grads = COMPILED_GATE_GRADS
        self.adam_step = FusedAdamStep(optimizer)

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> float:
        """One step on the minibatch ``x``, ``y``; returns its loss (read back once, for the NaN guard)."""
        grads, loss = self.grads(self.detached, self.gate, x, y, self.c_w)
        value = loss.item()
        check_finite("gate loss", value, "in a compiled fit step")
        set_grads(self.params, [grads[k] for k in self.detached])
        self.adam_step()
        return value


def gate_metrics(gate: torch.nn.Module, states, labels, on: float | None = None) -> dict:
    """How the gate's hand-over decision (p > on) compares with the labels.

    ``on``: the hand-over threshold; None: the system's ``gate.on`` (a :class:`GateNet`
    knows it; a gate with a ``system``, e.g. ``CostToGoGate``, reads it there).

    ``false_handover_rate``: share of predicted hand-overs whose LQR rollout fails
    (what the conservative weighting keeps small); ``recall``: share of
    balanceable states the gate hands over.
    """
    if on is None:
        on = getattr(gate, "gate_on", None)
        if on is None and getattr(gate, "system", None) is not None:
            on = gate.system.gate.on
        if on is None:
            raise ValueError(f"gate_metrics needs on= for a {type(gate).__name__} (no system to read gate.on from)")
    with torch.no_grad():  # on the gate's device; one host copy of the probabilities
        x = _as_device_tensor(states, None, _module_device(gate))  # the states' own dtype, as before
        p = gate(x).reshape(-1).cpu().numpy()
    labels = labels.cpu() if isinstance(labels, torch.Tensor) else labels
    y = np.asarray(labels, dtype=bool)
    handover = p > on
    return {
        "n": int(len(y)), "positives": int(y.sum()),
        "handovers": int(handover.sum()),
        "false_handover_rate": float((handover & ~y).sum() / max(handover.sum(), 1)),
        "recall": float((handover & y).sum() / max(y.sum(), 1)),
        "accuracy": float(((p > 0.5) == y).mean()),
    }


def warm_start_gate(system: System, config: GateConfig | None = None, progress: bool = False,
                    device: str | torch.device = "cpu"):
    """Thesis Algorithm 2: sample states, label them by LQR rollouts, fit a GateNet.

    The rollouts, the gate and its fit run on ``device`` (the gate's initial weights come from
    the seed on the CPU, as on every device, and are moved there; the minibatches are drawn by a
    generator on ``device``). Returns (gate on ``device``, states and labels as numpy, info) so
    SSAC keeps the data for later refits.
    """
    config = config or GateConfig()
    config.validate()
    rng = np.random.default_rng(config.seed)
    states = warm_start_states(system, config.warm_samples, rng)
    labels = label_states(system, states, config, device=device)
    if labels.sum() == 0:
        raise RuntimeError(f"no warm-start state of {system.name} was balanced by the LQR; widen gate.warm_near")
    with seeded(config.seed):  # initial weights from the seed; the caller's global torch RNG is left alone
        gate = GateNet(system, tuple(config.hidden), cost_feature=config.cost_feature)
    gate.to(device)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    losses = fit_gate(gate, states, labels, config.warm_fit_steps, config.lr, config.positive_weight,
                      config.batch_size, generator)
    info = {"positive_fraction": float(labels.mean()), "final_loss": losses[-1],
            **gate_metrics(gate, states, labels, system.gate.on)}
    return gate, states, labels, info


# ------------------------------------------------------------------ a learned gate from the measured basin
BASIN_FAR_FACTOR = 4.0
"""The far warm-start spread is this many times the near one (the box of the cost-to-go level 16 V*)."""
BASIN_GATE_CONFIG = GateConfig(warm_fit_steps=4000, lr=3e-3)
""":func:`learned_gate_from_basin`'s default fit: 4000 Adam steps at SSAC's gate learning rate (the rest
GateConfig's: eq. 3.3 with w = 0.01, labels within 0.2 over the last 10 steps of the spec's label horizon)."""
WORKS_MAX_FALSE_HANDOVER = 0.01
""":func:`learned_gate_from_basin` fails when its held-out false hand-over rate is measurably above this: the
lower end of its 95 % Wilson interval exceeds it (few hand-overs, as on the acrobot's held-out mix, give wide
intervals; one failing rollout in 56 hand-overs is no measured failure)."""
WORKS_MIN_BASIN_HANDOVER = 0.5
"""... or when it hands over, or the switched controller with it balances, less than this share of held-out
states inside the measured basin (V < V*)."""


def basin_ellipsoid_states(system: System, level: float, n: int, rng: np.random.Generator, S=None,
                           low: float = 0.0) -> np.ndarray:
    """``n`` states goal + e with e uniform in the ellipsoid e' S e < ``level`` (S: the LQR's cost-to-go
    matrix); ``low`` > 0: the cost-to-go level log-uniform in [low * level, level] instead (for measuring)."""
    S = system.lqr()[1] if S is None else np.asarray(S, dtype=float)
    u = rng.normal(size=(n, system.n_states))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    if low > 0:
        radius = np.sqrt(np.exp(rng.uniform(np.log(low), 0.0, size=(n, 1))))
    else:
        radius = rng.uniform(size=(n, 1)) ** (1.0 / system.n_states)
    err = np.linalg.solve(np.linalg.cholesky(S).T, (u * radius).T).T * np.sqrt(level)
    return system.goal + err


def measure_basin(system: System, n_samples: int = 8000, seed: int = 0, config: GateConfig | None = None,
                  device: str | torch.device = "cpu") -> dict:
    """The LQR's basin as a cost-to-go level V*, measured on samples shaped like it.

    States are drawn in the ellipsoids e' S e < V (S: the LQR's cost-to-go matrix) with V log-uniform over
    three decades below V_max, the level whose ellipsoid just spans +-pi in some angle; each is labelled as the
    gate's data (:func:`label_states`, the config's eps, lookback and horizon); V* is the smallest (wrapped)
    cost-to-go of a failing sample. Unlike :func:`~hybridctl.systems.control.lqr_basin_level`, whose samples
    fill a given box, it needs no spread, and every level is sampled in every direction: a box much narrower
    than the ellipsoid in some coordinate (the spec's speeds) overstates V* (furuta: 23.9 from the spec's
    box, of whose ellipsoid the LQR balanced 59 %; 2.6 here). Returns lqr_basin_level's keys (``level``,
    ``gate_scale``, ``success_rate``, ``success_below_kx``) and ``sampling``, ``v_max``, ``label_eps``.
    """
    config = config or GateConfig()
    if n_samples < 10:
        raise ValueError(f"n_samples must be >= 10, got {n_samples}")
    S = system.lqr()[1]
    inverse = np.diag(np.linalg.inv(S))
    columns = list(system.angle_indices) or list(range(system.n_states))
    v_max = float(max(np.pi ** 2 / inverse[i] for i in columns))
    states = basin_ellipsoid_states(system, v_max, n_samples, np.random.default_rng(seed), S, low=1e-3)
    ok = label_states(system, states, config, device=device)
    V = cost_to_go(system.state_error(states), S)
    level = float(V[~ok].min()) if (~ok).any() else float(V.max())
    rates = {f"success_below_{k}x": float(ok[V < k * level].mean()) if np.any(V < k * level) else None
             for k in (1, 2, 4)}
    return {"level": level, "gate_scale": level / np.log(1 / system.gate.on), "n_samples": int(n_samples),
            "horizon": label_horizon(system, config), "seed": int(seed), "success_rate": float(ok.mean()), **rates,
            "sampling": "cost-to-go ellipsoids", "v_max": v_max, "label_eps": config.label_eps}


def basin_spreads(system: System, level: float, far_factor: float = BASIN_FAR_FACTOR, S=None):
    """Warm-start spreads (near, far) from a basin level V*: near is the half-width of the box around the
    ellipsoid e' S e < V* (sqrt(V* (S^-1)_ii) per coordinate), far ``far_factor`` times it; angles at most pi."""
    if not level > 0:
        raise ValueError(f"the basin level must be > 0, got {level!r}")
    S = system.lqr()[1] if S is None else np.asarray(S, dtype=float)
    near = np.sqrt(level * np.diag(np.linalg.inv(S)))
    far = far_factor * near
    angles = list(system.angle_indices)
    near[angles], far[angles] = np.minimum(near[angles], np.pi), np.minimum(far[angles], np.pi)
    return near, far


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a proportion ``successes / n`` (95 % for z = 1.96); (0, 1) for n = 0."""
    if n == 0:
        return 0.0, 1.0
    p, z2 = successes / n, z * z
    centre, half = (p + z2 / (2 * n)) / (1 + z2 / n), z * np.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return float(max(centre - half, 0.0)), float(min(centre + half, 1.0))


def learned_gate_from_basin(system: System, *, seed: int = 0, samples: int = 40_000, basin: dict | None = None,
                            config: GateConfig | None = None, device: str | torch.device = "cpu"):
    """A learned gate whose warm start (thesis Alg. 2) samples around the measured LQR basin, with its verdict.

    1. The basin level V*: ``basin["level"]`` (a dict of :func:`measure_basin` or
       :func:`~hybridctl.systems.control.lqr_basin_level`), else :func:`measure_basin` on ``samples // 8`` states.
    2. Spreads from V* (:func:`basin_spreads`): near = the box around the ellipsoid V < V*, far = 4 times it.
    3. ``samples`` states (half near, half far) labelled by saturated-LQR rollouts only (:func:`label_states`;
       no episode outcomes, which taught SSAC's gates to hand back), fitted by eq. 3.3 (``config``: a
       :class:`GateConfig`, default :data:`BASIN_GATE_CONFIG`; its ``warm_samples`` and ``seed`` are replaced).
       The net's features: the error scaled by the far spread and log(1 + V / V*).
    4. Held-out checks on fresh states: ``samples // 4`` of the near / far mix, and ``samples // 16`` uniform in
       V < V*, from which the switched controller (zero swing-up, the spec's hysteresis) also runs for the
       label horizon.

    Returns ``(gate, info)``: the :class:`GateNet` on ``device`` and a JSON-ready dict: ``works`` (False when
    the gate measurably fails: the held-out false hand-over rate's 95 % Wilson interval lies above
    :data:`WORKS_MAX_FALSE_HANDOVER`, or ``basin_handover`` or ``closed_loop_balanced`` is below
    :data:`WORKS_MIN_BASIN_HANDOVER`, or no sample balanced), ``criterion`` (that rule in words); on the held-out
    mix ``n``, ``positives``, ``handovers``, ``recall``, ``false_handover_rate``, ``false_handover_interval``; in
    the basin ``basin_handover`` (share handed over), ``basin_positive_fraction`` (of their LQR labels),
    ``closed_loop_balanced`` (share the switched controller balanced); and ``basin`` (the dict used), ``level``,
    ``near``, ``far``, ``positive_fraction`` (of the training labels), ``class_weight`` (eq. 3.3's c_w),
    ``final_loss``, ``samples``, ``seed``, ``seconds``.
    """
    start = time.perf_counter()
    config = dataclasses.replace(config or BASIN_GATE_CONFIG, warm_samples=int(samples), seed=int(seed))
    config.validate()
    basin = dict(basin) if basin is not None else measure_basin(system, max(samples // 8, 2000), seed, config, device)
    level = float(basin["level"])
    near, far = basin_spreads(system, level)
    states = warm_start_states(system, samples, np.random.default_rng([seed, 1]), near, far)
    labels = label_states(system, states, config, device=device)
    with seeded(seed):
        gate = GateNet(system, tuple(config.hidden), feature_scale=far, cost_feature=config.cost_feature,
                       cost_scale=level)
    gate.to(device)
    info = {"basin": basin, "level": level, "near": near.tolist(), "far": far.tolist(), "samples": int(samples),
            "seed": int(seed), "positive_fraction": float(labels.mean()),
            "class_weight": positive_class_weight(labels, config.positive_weight), "final_loss": None}
    if labels.any():
        generator = torch.Generator(device=device).manual_seed(seed)
        losses = fit_gate(gate, states, labels, config.warm_fit_steps, config.lr, config.positive_weight,
                          config.batch_size, generator)
        info["final_loss"] = losses[-1] if losses else None
    info.update(_held_out_checks(system, gate, config, level, near, far, max(samples // 4, 2), seed, device))
    info["works"] = bool(labels.any() and info["false_handover_interval"][0] <= WORKS_MAX_FALSE_HANDOVER
                         and min(info["basin_handover"], info["closed_loop_balanced"]) >= WORKS_MIN_BASIN_HANDOVER)
    info["criterion"] = (f"the held-out false hand-over rate is not measurably above {WORKS_MAX_FALSE_HANDOVER} "
                         f"(its 95 % Wilson interval reaches down to it), and basin_handover and "
                         f"closed_loop_balanced are >= {WORKS_MIN_BASIN_HANDOVER}")
    info["seconds"] = time.perf_counter() - start
    return gate, info


def _held_out_checks(system: System, gate: GateNet, config: GateConfig, level: float, near, far, n: int,
                     seed: int, device) -> dict:
    """:func:`learned_gate_from_basin`'s checks on fresh states: the gate's metrics on ``n`` states of the
    near / far mix, its hand-overs on ``n // 4`` states in V < V*, and the switched controller run from there."""
    rng = np.random.default_rng([seed, 2])
    mix = warm_start_states(system, n, rng, near, far)
    metrics = gate_metrics(gate, mix, label_states(system, mix, config, device=device), system.gate.on)
    inside = basin_ellipsoid_states(system, level, max(n // 4, 2), rng)
    in_basin = gate_metrics(gate, inside, label_states(system, inside, config, device=device), system.gate.on)
    controller = SwitchedController.for_system(system, swingup=ZeroSwingup(), gate=gate)
    steps = int(round(label_horizon(system, config) / controller.decision_period))
    with torch.no_grad():
        final = closed_loop_rollout(system, controller, inside, steps, record=False, device=device).final
    balanced = torch.linalg.norm(system.state_error(final), dim=-1) < config.label_eps
    false = int(round(metrics["false_handover_rate"] * metrics["handovers"]))
    return {**{k: metrics[k] for k in ("n", "positives", "handovers", "recall", "false_handover_rate")},
            "false_handover_interval": list(wilson_interval(false, metrics["handovers"])),
            "basin_handover": in_basin["handovers"] / max(in_basin["n"], 1),
            "basin_positive_fraction": in_basin["positives"] / max(in_basin["n"], 1),
            "closed_loop_balanced": float(balanced.float().mean())}
