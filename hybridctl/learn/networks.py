"""The networks of SAC and SSAC (thesis Ch. 3 appendix): observation features, MLPs, the
squashed-Gaussian actor, the Q network and the frozen deterministic policy for Drake blocks."""

from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import nn

OBS_TRANSFORMS = ("none", "angle_sincos")


class ObsTransform(nn.Module):
    """Observation features fed to every network (part of the deterministic policy module).

    ``"none"``: the raw state (thesis). ``"angle_sincos"``: each angle (``angle_indices``)
    replaced by its sine and cosine, so unwrapped angles (the envs do not wrap) map to
    the same features as their wrapped values. Stateless: no statistics to fit.
    """

    def __init__(self, kind: str, n_states: int, angle_indices: list[int] = ()):
        super().__init__()
        if kind not in OBS_TRANSFORMS:
            raise ValueError(f"obs transform must be one of {OBS_TRANSFORMS}, got {kind!r}")
        self.kind, self.n_states = kind, int(n_states)
        self.angle_indices = [int(i) for i in angle_indices] if kind == "angle_sincos" else []
        other = [i for i in range(self.n_states) if i not in self.angle_indices]
        self.register_buffer("angle_idx", torch.tensor(self.angle_indices, dtype=torch.long), persistent=False)
        self.register_buffer("other_idx", torch.tensor(other, dtype=torch.long), persistent=False)
        self.out_dim = self.n_states + len(self.angle_indices)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Features (..., out_dim) of states (..., n_states)."""
        if self.kind == "none":
            return obs
        angles = obs.index_select(-1, self.angle_idx)
        return torch.cat([angles.sin(), angles.cos(), obs.index_select(-1, self.other_idx)], dim=-1)

    def describe(self) -> dict:
        """What normalization.json holds."""
        if self.kind == "none":
            return {"type": "none"}
        return {"type": "angle_sincos", "n_states": self.n_states, "angle_indices": self.angle_indices,
                "features": "[sin(angles), cos(angles), other states]"}


def mlp(in_dim: int, out_dim: int, hidden_layers: int, hidden_size: int) -> nn.Sequential:
    """in -> hidden_layers x (Linear(hidden_size) + ReLU) -> Linear(out) (author's seagul MLP)."""
    layers: list[nn.Module] = []
    width = in_dim
    for _ in range(hidden_layers):
        layers += [nn.Linear(width, hidden_size), nn.ReLU()]
        width = hidden_size
    layers.append(nn.Linear(width, out_dim))
    return nn.Sequential(*layers)


_LOG_2PI = math.log(2 * math.pi)


class Actor(nn.Module):
    """Squashed Gaussian policy: ``a = action_scale * tanh(mu + sigma eps)`` (thesis eq. 2.16).

    One MLP outputs (mu, log sigma) (author code); log sigma is clamped to
    [log_std_min, log_std_max].
    """

    def __init__(self, transform: ObsTransform, action_dim: int, action_scale: torch.Tensor,
                 hidden_layers: int, hidden_size: int, log_std_min: float, log_std_max: float):
        super().__init__()
        self.transform, self.action_dim = transform, int(action_dim)
        self.net = mlp(transform.out_dim, 2 * action_dim, hidden_layers, hidden_size)
        self.register_buffer("action_scale", action_scale.clone().float())
        self.log_std_min, self.log_std_max = float(log_std_min), float(log_std_max)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mu, log sigma), each (B, m)."""
        mu, log_std = self.net(self.transform(obs)).split(self.action_dim, dim=-1)
        return mu, log_std.clamp(self.log_std_min, self.log_std_max)

    def sample(self, obs: torch.Tensor, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised action (B, m) and its log density (B,) for standard-normal ``eps``.

        log pi(a|s) = log N(u; mu, sigma) - sum log(action_scale (1 - tanh(u)^2)), with
        log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)) (numerically stable). The
        log action_scale term (as in CleanRL) only shifts the entropy by a constant.
        """
        mu, log_std = self(obs)
        return squashed_sample(mu, log_std, eps, self.action_scale)

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        """``action_scale * tanh(mu)`` (thesis Sec. 3.4.2: eps set to zero)."""
        return self.action_scale * torch.tanh(self(obs)[0])


def squashed_sample(mu: torch.Tensor, log_std: torch.Tensor, eps: torch.Tensor,
                    action_scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``action_scale * tanh(mu + sigma eps)`` and its log density (B,): :meth:`Actor.sample`'s formula,
    on the actor's outputs (also for a functional call of the actor with other weights)."""
    u = mu + log_std.exp() * eps
    logp = (-0.5 * eps.pow(2) - log_std - 0.5 * _LOG_2PI).sum(-1)
    logp = logp - (action_scale.log() + 2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)
    return action_scale * torch.tanh(u), logp


class QNetwork(nn.Module):
    """Q(s, a): MLP on [features(s), a / action_scale] (actions scaled to [-1, 1])."""

    def __init__(self, transform: ObsTransform, action_dim: int, action_scale: torch.Tensor,
                 hidden_layers: int, hidden_size: int):
        super().__init__()
        self.transform = transform
        self.net = mlp(transform.out_dim + action_dim, 1, hidden_layers, hidden_size)
        self.register_buffer("action_scale", action_scale.clone().float())

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Q values (B,) of states (B, n) and actions (B, m)."""
        return self.net(torch.cat([self.transform(obs), action / self.action_scale], dim=-1)).squeeze(-1)


def twin_q_values(q1: QNetwork, q2: QNetwork, params1: dict, params2: dict, obs: torch.Tensor,
                  action: torch.Tensor) -> torch.Tensor:
    """Q values (2, B) of two same-shaped :class:`QNetwork` s with the weights ``params1`` / ``params2``
    (name -> tensor, as ``named_parameters``): :meth:`QNetwork.forward`'s formula, both networks in one
    batched matrix product per layer (SAC's twin critics in the compiled gradient step)."""
    x = torch.cat([q1.transform(obs), action / q1.action_scale], dim=-1).expand(2, -1, -1)
    for index, layer in enumerate(q1.net):
        if isinstance(layer, nn.Linear):
            weight = torch.stack([params1[f"net.{index}.weight"], params2[f"net.{index}.weight"]])
            bias = torch.stack([params1[f"net.{index}.bias"], params2[f"net.{index}.bias"]])
            x = torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))
        else:
            x = layer(x)
    return x.squeeze(-1)


class DeterministicPolicy(nn.Module):
    """A frozen copy of the actor: states (B, n) -> ``action_scale * tanh(mu)`` (B, m).

    Includes the observation transform, so it is all a Drake ``TorchPolicy`` block
    needs. Accepts any floating dtype (computes in float32, returns the input's dtype);
    a 1-D state (n,) gives (m,).
    """

    def __init__(self, actor: Actor):
        super().__init__()
        self.actor = copy.deepcopy(actor).eval()
        for p in self.actor.parameters():
            p.requires_grad_(False)
        self.eval()

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        """Deterministic actions for states (B, n) or (n,), in the input's floating dtype."""
        param = next(self.actor.parameters())
        states = torch.as_tensor(states, device=None if isinstance(states, torch.Tensor) else param.device)
        dtype = states.dtype if states.is_floating_point() else torch.float32
        return self.actor.deterministic(states.to(device=param.device, dtype=param.dtype)).to(dtype)

