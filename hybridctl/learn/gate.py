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
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from torch.func import functional_call, grad_and_value

from ..systems import System
from ..systems.compiled import LazyCompiled
from ..systems.control import cost_to_go, lqr_rollouts_balanced, wrap_angles
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
    ``cost_feature``, log(1 + V / gate.cost_scale) of the LQR cost-to-go V.

    The net is built on the CPU whatever torch's default device (initial weights from the
    CPU RNG, so one seed gives the same gate on every device) and then moved to ``device``
    (None: it stays on the CPU).
    """

    def __init__(self, system: System, hidden: tuple[int, ...] = GateConfig.hidden,
                 feature_scale: np.ndarray | None = None, cost_feature: bool = True,
                 device: str | torch.device | None = None):
        super().__init__()
        with torch.device("cpu"):
            self._build(system, hidden, feature_scale, cost_feature)
        if device is not None:
            self.to(device)

    def _build(self, system: System, hidden: tuple[int, ...], feature_scale, cost_feature: bool) -> None:
        """The buffers and layers of :meth:`__init__` (made on the CPU)."""
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
        S = system.lqr()[1] / system.gate.cost_scale
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


def warm_start_states(system: System, n: int, rng: np.random.Generator) -> np.ndarray:
    """Thesis Algorithm 2 samples: half goal + U(-warm_near, warm_near), half goal + U(-warm_far, warm_far)."""
    if n < 2:
        raise ValueError(f"n must be >= 2, got {n}")
    near, far = system.gate.spread("warm_near"), system.gate.spread("warm_far")
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
