"""Deterministic policies for analytic policy gradients (thesis Ch. 7), as populations.

A population holds K members' parameters stacked along a leading dimension ([K, ...]),
so K members x N starts run as ONE batched computation (``torch.baddbmm``): one graph,
one backward, and each member's gradient lands in its own slice. Every policy has an
explicit recurrent state:

>>> pop = PolicyPopulation.gru(obs_dim=6, act_dim=1, action_limit=200.0, members=24)
>>> h = pop.initial_state(4)                    # [K, N, hidden] (stateless policies: [K, N, 0])
>>> action, h = pop(obs, h)                     # obs [K, N, obs_dim] -> action [K, N, act_dim]
>>> flat = pop.to_flat()                        # [K, P]; pop.from_flat(flat) writes it back (CEM)
>>> one = pop.member(3)                         # a Policy (K = 1) with member 3's parameters
>>> a, h1 = one(obs[0], one.initial_state(4))   # obs [N, obs_dim] -> action [N, act_dim]

Architectures (``kind``):

* ``"gru"`` -- the thesis' controller (Sec. 7.3.4, 7.3.6; implementation notes Ch. 7):
  Dense(w)-ReLU -> GRU cell (hidden = obs size) -> Dense(w)-ReLU -> Dense(w)-ReLU ->
  Dense(act)-tanh with w = 2^ceil(log2(4 obs)) (obs 4 -> 16: the thesis' "4x16x16x1").
  The GRU cell follows ``torch.nn.GRUCell`` (gates r, z, n in that order), so a member
  equals a GRUCell with the same weights.
* ``"mlp"`` -- Dense-ReLU layers of the given widths, then Dense(act)-tanh.
* ``"linear"`` -- tanh(W z + b).

Outputs are scaled to the actuator limit (``action_limit * tanh(.)``). Observations are
normalised by frozen ``obs_mean`` / ``obs_std`` buffers (shared by the members; the
learner updates them between APG runs, never inside one). Initialisation as the author's
code: every parameter zero, then perturbed by N(0, init_std^2) (init_std = 0.05).

Device: a population lives on ``device`` (default torch's default device); its initial
perturbation is always drawn on the CPU (from ``generator``, or the global CPU RNG) and then
moved, so one seed gives the same members on every device. Everything it makes afterwards
(recurrent states, copies, written parameters) follows its own device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["Layer", "PolicyPopulation", "Policy", "gru_width", "KINDS"]

KINDS = ("gru", "mlp", "linear")


def gru_width(obs_dim: int) -> int:
    """w = 2^ceil(log2(4 obs_dim)), the author's dense width (obs 4 -> 16, obs 6 -> 32, thesis Sec. 7.3.6)."""
    if obs_dim < 1:
        raise ValueError(f"obs_dim must be >= 1, got {obs_dim}")
    return 2 ** math.ceil(math.log2(4 * obs_dim))


@dataclass(frozen=True)
class Layer:
    """One layer: ``kind`` "dense" (activation "relu", "tanh" or "none") or "gru"; sizes in -> out."""

    kind: str
    n_in: int
    n_out: int
    activation: str = "none"

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """Parameter names and shapes of one member (torch.nn.Linear / GRUCell layout)."""
        if self.kind == "dense":
            return {"weight": (self.n_out, self.n_in), "bias": (self.n_out,)}
        h = self.n_out
        return {"weight_ih": (3 * h, self.n_in), "weight_hh": (3 * h, h), "bias_ih": (3 * h,), "bias_hh": (3 * h,)}


def _layers(kind: str, obs_dim: int, act_dim: int, hidden: tuple[int, ...] = ()) -> list[Layer]:
    if kind == "gru":
        w = gru_width(obs_dim)
        return [Layer("dense", obs_dim, w, "relu"), Layer("gru", w, obs_dim), Layer("dense", obs_dim, w, "relu"),
                Layer("dense", w, w, "relu"), Layer("dense", w, act_dim, "tanh")]
    if kind == "mlp":
        if not hidden or any(h < 1 for h in hidden):
            raise ValueError(f"an mlp policy needs positive hidden widths, got {hidden!r}")
        sizes = (obs_dim, *hidden)
        return [Layer("dense", a, b, "relu") for a, b in zip(sizes[:-1], sizes[1:])] + \
            [Layer("dense", sizes[-1], act_dim, "tanh")]
    if kind == "linear":
        return [Layer("dense", obs_dim, act_dim, "tanh")]
    raise ValueError(f"unknown policy kind {kind!r}; known: {', '.join(KINDS)}")


def _dense(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x [K, N, in] -> [K, N, out]: per-member x W^T + b, one batched matmul."""
    return torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))


class PolicyPopulation(torch.nn.Module):
    """K deterministic policies with stacked parameters [K, ...]; see the module docstring.

    ``forward(obs [K, N, obs_dim], state [K, N, hidden]) -> (action [K, N, act_dim], state)``.
    """

    def __init__(self, layers: list[Layer], members: int, action_limit: float, init_std: float = 0.05,
                 dtype: torch.dtype = torch.float64, generator: torch.Generator | None = None,
                 kind: str = "custom", hidden: tuple[int, ...] = (), device: str | torch.device | None = None):
        super().__init__()
        if members < 1:
            raise ValueError(f"members must be >= 1, got {members}")
        if not (math.isfinite(action_limit) and action_limit > 0):
            raise ValueError(f"action_limit must be a finite number > 0, got {action_limit!r}")
        if not (math.isfinite(init_std) and init_std >= 0):
            raise ValueError(f"init_std must be a finite number >= 0, got {init_std!r}")
        self.layers, self.members, self.action_limit = list(layers), int(members), float(action_limit)
        self.kind, self.hidden_sizes = kind, tuple(hidden)
        self.obs_dim, self.act_dim = layers[0].n_in, layers[-1].n_out
        self.hidden_dim = sum(layer.n_out for layer in layers if layer.kind == "gru")
        self.names: list[str] = []
        draw_on = generator.device if generator is not None else torch.device("cpu")
        device = torch.device(device) if device is not None else torch.get_default_device()
        for i, layer in enumerate(self.layers):
            for pname, shape in layer.shapes().items():
                name = f"l{i}_{pname}"
                # the author's initialisation: zero, then perturbed by N(0, init_std^2), drawn on the CPU
                # (or the generator's device) so a seed gives the same members wherever they then live
                value = torch.zeros((self.members, *shape), dtype=dtype, device=draw_on)
                if init_std > 0:
                    value += init_std * torch.randn(value.shape, dtype=dtype, generator=generator, device=draw_on)
                self.register_parameter(name, torch.nn.Parameter(value.to(device)))
                self.names.append(name)
        self.register_buffer("obs_mean", torch.zeros(self.obs_dim, dtype=dtype, device=device))
        self.register_buffer("obs_std", torch.ones(self.obs_dim, dtype=dtype, device=device))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def build(cls, kind: str, obs_dim: int, act_dim: int, action_limit: float, members: int = 1,
              hidden: tuple[int, ...] = (), **kwargs) -> "PolicyPopulation":
        """A population of ``kind`` ("gru", "mlp" with ``hidden`` widths, "linear")."""
        return cls(_layers(kind, obs_dim, act_dim, tuple(hidden)), members, action_limit, kind=kind,
                   hidden=tuple(hidden), **kwargs)

    @classmethod
    def gru(cls, obs_dim: int, act_dim: int, action_limit: float, members: int = 1, **kwargs) -> "PolicyPopulation":
        """The thesis' GRU controller (module docstring) for ``members`` members."""
        return cls.build("gru", obs_dim, act_dim, action_limit, members, **kwargs)

    # ------------------------------------------------------------------ parameters
    @property
    def n_params(self) -> int:
        """Parameters of one member (the length of a flat vector)."""
        return sum(getattr(self, n)[0].numel() for n in self.names)

    @property
    def dtype(self) -> torch.dtype:
        """The parameters' dtype."""
        return getattr(self, self.names[0]).dtype

    @property
    def device(self) -> torch.device:
        """The device of the parameters and buffers."""
        return self.obs_mean.device

    def stacked(self) -> list[torch.Tensor]:
        """The parameters [K, ...] in a fixed order (the order of :meth:`to_flat`)."""
        return [getattr(self, n) for n in self.names]

    def to_flat(self) -> torch.Tensor:
        """A detached copy of the parameters as one [K, P] matrix."""
        return torch.cat([p.detach().reshape(self.members, -1) for p in self.stacked()], dim=1).clone()

    def from_flat(self, flat: torch.Tensor) -> "PolicyPopulation":
        """Write a [K, P] matrix (or a [P] vector, given to every member) into the parameters."""
        flat = torch.as_tensor(flat, dtype=self.dtype, device=self.device)
        if flat.dim() == 1:
            flat = flat.expand(self.members, -1)
        if tuple(flat.shape) != (self.members, self.n_params):
            raise ValueError(f"flat parameters must be ({self.members}, {self.n_params}) or ({self.n_params},), "
                             f"got {tuple(flat.shape)}")
        offset = 0
        with torch.no_grad():
            for p in self.stacked():
                size = p[0].numel()
                p.copy_(flat[:, offset:offset + size].reshape(p.shape))
                offset += size
        return self

    def set_normalization(self, mean, std) -> None:
        """Freeze new observation statistics (std floored at 1e-8)."""
        with torch.no_grad():
            self.obs_mean.copy_(torch.as_tensor(mean, dtype=self.dtype, device=self.device))
            self.obs_std.copy_(torch.as_tensor(std, dtype=self.dtype, device=self.device).clamp_min(1e-8))

    def resized(self, members: int, flat: torch.Tensor | None = None) -> "PolicyPopulation":
        """A new population of ``members`` members with these layers and normalisation, on this one's
        device (parameters from ``flat`` [members, P] when given, else zero)."""
        new = PolicyPopulation(self.layers, members, self.action_limit, init_std=0.0, dtype=self.dtype,
                               kind=self.kind, hidden=self.hidden_sizes, device=self.device)
        new.set_normalization(self.obs_mean, self.obs_std)
        if flat is not None:
            new.from_flat(flat)
        return new

    def member(self, k: int) -> "Policy":
        """Member ``k`` as a single :class:`Policy` (a copy of its parameters)."""
        if not 0 <= k < self.members:
            raise IndexError(f"member {k} of a population of {self.members}")
        return Policy(self.resized(1, self.to_flat()[k:k + 1]))

    def describe(self) -> dict:
        """What rebuilds this architecture: kind, sizes, action limit (JSON-friendly)."""
        return {"kind": self.kind, "obs_dim": self.obs_dim, "act_dim": self.act_dim, "hidden": list(self.hidden_sizes),
                "action_limit": self.action_limit, "n_params": self.n_params, "hidden_state": self.hidden_dim}

    # ------------------------------------------------------------------ evaluation
    def initial_state(self, batch: int) -> torch.Tensor:
        """Zero recurrent state [K, batch, hidden] ([K, batch, 0] for stateless policies)."""
        return torch.zeros((self.members, batch, self.hidden_dim), dtype=self.dtype, device=self.device)

    def forward(self, obs: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Actions [K, N, act_dim] (scaled to the limit) and the next state for obs [K, N, obs_dim]."""
        x = (obs - self.obs_mean) / self.obs_std
        new_states, offset = [], 0
        for i, layer in enumerate(self.layers):
            if layer.kind == "dense":
                x = _dense(x, getattr(self, f"l{i}_weight"), getattr(self, f"l{i}_bias"))
                if layer.activation == "relu":
                    x = torch.relu(x)
                elif layer.activation == "tanh":
                    x = torch.tanh(x)
            else:
                h = state[..., offset:offset + layer.n_out]
                offset += layer.n_out
                x = self._gru(i, x, h)
                new_states.append(x)
        new_state = torch.cat(new_states, dim=-1) if new_states else state
        return self.action_limit * x, new_state

    def _gru(self, i: int, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """torch.nn.GRUCell for every member at once."""
        gi = _dense(x, getattr(self, f"l{i}_weight_ih"), getattr(self, f"l{i}_bias_ih"))
        gh = _dense(h, getattr(self, f"l{i}_weight_hh"), getattr(self, f"l{i}_bias_hh"))
        i_r, i_z, i_n = gi.chunk(3, dim=-1)
        h_r, h_z, h_n = gh.chunk(3, dim=-1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return (1 - z) * n + z * h


class Policy(torch.nn.Module):
    """One deterministic policy (a population of one) with unbatched-member shapes:
    ``forward(obs [N, obs_dim], state [N, hidden]) -> (action [N, act_dim], state)``.

    Also accepts a single observation (obs_dim,) with state (hidden,).
    """

    def __init__(self, population: PolicyPopulation):
        super().__init__()
        if population.members != 1:
            raise ValueError(f"a Policy wraps a population of one member, got {population.members}")
        self.population = population

    @classmethod
    def build(cls, kind: str, obs_dim: int, act_dim: int, action_limit: float, **kwargs) -> "Policy":
        """A single policy of ``kind`` (see :meth:`PolicyPopulation.build`)."""
        return cls(PolicyPopulation.build(kind, obs_dim, act_dim, action_limit, members=1, **kwargs))

    @property
    def hidden_dim(self) -> int:
        """Size of the recurrent state (0 for stateless policies)."""
        return self.population.hidden_dim

    def initial_state(self, batch: int | None = None) -> torch.Tensor:
        """Zero state [batch, hidden] (or [hidden] when ``batch`` is None)."""
        state = self.population.initial_state(1 if batch is None else batch)[0]
        return state[0] if batch is None else state

    def forward(self, obs: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Action and next state for obs [N, obs_dim] (or one obs [obs_dim])."""
        single = obs.dim() == 1
        if single:
            obs, state = obs.unsqueeze(0), state.unsqueeze(0)
        action, new = self.population(obs.unsqueeze(0), state.unsqueeze(0))
        action, new = action[0], new[0]
        return (action[0], new[0]) if single else (action, new)

    def numpy_forward(self, obs: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`forward` in numpy at the parameters' dtype, for obs (..., obs_dim) and state (..., hidden).

        The Drake block ``RecurrentTorchPolicy`` calls it at every policy period on one state, where
        torch's per-call overhead was most of the cost. The same formulas (dense layers, the GRU
        cell); it agrees with :meth:`forward` to rounding (numpy and torch sum the products in
        their own orders). The numpy copies are refreshed when a parameter changed in place.
        """
        layers, mean, std = self._numpy_copies()
        x = (np.asarray(obs, dtype=mean.dtype) - mean) / std
        state = np.asarray(state, dtype=mean.dtype)
        new_states, offset = [], 0
        for layer, weights in zip(self.population.layers, layers):
            if layer.kind == "dense":
                x = x @ weights[0] + weights[1]
                if layer.activation == "relu":
                    x = np.maximum(x, 0)
                elif layer.activation == "tanh":
                    x = np.tanh(x)
            else:
                h = state[..., offset:offset + layer.n_out]
                offset += layer.n_out
                w_ih, w_hh, b_ih, b_hh = weights
                i_r, i_z, i_n = np.split(x @ w_ih + b_ih, 3, axis=-1)
                h_r, h_z, h_n = np.split(h @ w_hh + b_hh, 3, axis=-1)
                r = 1 / (1 + np.exp(-(i_r + h_r)))
                z = 1 / (1 + np.exp(-(i_z + h_z)))
                n = np.tanh(i_n + r * h_n)
                x = (1 - z) * n + z * h
                new_states.append(x)
        new_state = np.concatenate(new_states, axis=-1) if new_states else state
        return self.population.action_limit * x, new_state

    def _numpy_copies(self):
        """Per layer the transposed weights and biases of member 0, and obs_mean, obs_std, as numpy."""
        pop = self.population
        tensors = self.__dict__.get("_numpy_tensors")
        if tensors is None or [t._version for t in tensors] != self._numpy_key:
            tensors = [*pop.parameters(), *pop.buffers()]
            layers = []
            for i, layer in enumerate(pop.layers):
                get = lambda name: getattr(pop, f"l{i}_{name}")[0].detach().cpu().numpy()  # noqa: E731
                if layer.kind == "dense":
                    layers.append((get("weight").T.copy(), get("bias").copy()))
                else:
                    layers.append((get("weight_ih").T.copy(), get("weight_hh").T.copy(), get("bias_ih").copy(),
                                   get("bias_hh").copy()))
            self._numpy = (layers, pop.obs_mean.detach().cpu().numpy().copy(), pop.obs_std.detach().cpu().numpy().copy())
            self._numpy_tensors, self._numpy_key = tensors, [t._version for t in tensors]
        return self._numpy

    def to_flat(self) -> torch.Tensor:
        """The parameters as one vector [P]."""
        return self.population.to_flat()[0]

    def from_flat(self, flat: torch.Tensor) -> "Policy":
        """Write a [P] vector into the parameters."""
        self.population.from_flat(torch.as_tensor(flat, device=self.population.device).reshape(1, -1))
        return self
