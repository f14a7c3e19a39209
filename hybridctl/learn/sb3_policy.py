"""The deterministic action path of an SB3 ``MlpPolicy`` rebuilt from its state dict (:class:`SB3Policy`).

A plain ``torch.nn.Module`` whose parameter names are the SB3 keys, built from what
:mod:`hybridctl.learn.sb3_zip` read; the random search of fine-tuning perturbs its parameters.
"""

from __future__ import annotations

import re

import numpy as np
import torch
from torch import nn

from .checkpoint import CheckpointError
from .sb3_zip import ACTIVATIONS, DEFAULT_ACTIVATION, FAMILY, POLICY_ENTRY, SB3_ALGORITHMS

SELECTIONS = ("action", "all", "last")
"""The parameter selections of :meth:`SB3Policy.parameter_names`."""


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
