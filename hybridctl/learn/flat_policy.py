"""Policies as flat parameter vectors (plain, picklable): :class:`PolicySpec` rebuilds ARS's linear map, a
torch module (``vector_to_parameters``) or a fixed function from a vector theta, :class:`FrozenPolicy` is one
such policy behind a frozen affine observation normalisation."""

from __future__ import annotations

import copy
from typing import Callable

import numpy as np
import torch


class PolicySpec:
    """What a worker needs to rebuild a policy from a flat parameter vector (pickles)."""

    def __init__(self, obs_dim: int, act_dim: int, low: np.ndarray, high: np.ndarray,
                 module: torch.nn.Module | None = None, function: Callable | None = None):
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.low, self.high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        self.module = module      # None: linear
        self.function = function  # a fixed policy obs -> action (no parameters), e.g. for robustness tests

    @property
    def n_params(self) -> int:
        """Length of theta."""
        if self.function is not None:
            return 0
        if self.module is None:
            return self.obs_dim * self.act_dim
        return sum(p.numel() for p in self.module.parameters())

    def initial_theta(self) -> np.ndarray:
        """Zero for the linear policy (Mania et al.); the module's own initialisation otherwise."""
        if self.module is None:
            return np.zeros(self.n_params)
        return torch.nn.utils.parameters_to_vector(self.module.parameters()).detach().double().numpy().copy()

    def actor(self, theta: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        """action(normalised obs) for these parameters, clipped to the action bounds."""
        if self.function is not None:
            return lambda z: np.clip(np.asarray(self.function(z), dtype=np.float64), self.low, self.high)
        if self.module is None:
            matrix = theta.reshape(self.act_dim, self.obs_dim)
            return lambda z: np.clip(matrix @ z, self.low, self.high)
        torch.nn.utils.vector_to_parameters(torch.as_tensor(theta, dtype=torch.float64), self.module.parameters())
        mid, half = (self.high + self.low) / 2, (self.high - self.low) / 2

        def act(z):
            with torch.no_grad():
                y = self.module(torch.as_tensor(z, dtype=torch.float64)).numpy()
            return mid + half * y
        return act


class FrozenPolicy:
    """A fixed ARS policy with frozen observation normalisation: ``policy(obs) -> action`` (pickles)."""

    def __init__(self, spec: PolicySpec, theta: np.ndarray, obs_mean: np.ndarray, obs_std: np.ndarray):
        # a torch policy gets its own module: the trainer's module is overwritten by every rollout
        self.spec = copy.deepcopy(spec) if spec.module is not None else spec
        self.theta = np.asarray(theta, dtype=np.float64)
        self.obs_mean, self.obs_std = np.asarray(obs_mean, dtype=np.float64), np.asarray(obs_std, dtype=np.float64)
        self._actor = None

    def __getstate__(self):
        return {**self.__dict__, "_actor": None}   # closures do not pickle: rebuilt on first call

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The action for one observation (clipped to the action bounds)."""
        if self._actor is None:
            self._actor = self.spec.actor(self.theta)
        return self._actor((np.asarray(obs, dtype=np.float64) - self.obs_mean) / self.obs_std)

    def many(self, obs: np.ndarray) -> np.ndarray:
        """Actions (n, act_dim) for observations (n, obs_dim), equal bit for bit to calling the
        policy on each row (the normalisation and the clip are elementwise and run batched; the
        linear map runs row by row, the same matrix-vector product as one call)."""
        z = (np.asarray(obs, dtype=np.float64) - self.obs_mean) / self.obs_std
        if z.ndim != 2 or z.shape[1] != self.spec.obs_dim:
            raise ValueError(f"obs must have shape (n, {self.spec.obs_dim}), got {np.shape(obs)}")
        if self.spec.module is not None or self.spec.function is not None:
            return np.array([self(o) for o in obs], dtype=np.float64).reshape(len(z), self.spec.act_dim)
        matrix = self.theta.reshape(self.spec.act_dim, self.spec.obs_dim)
        z = np.ascontiguousarray(z)
        out = np.empty((z.shape[0], self.spec.act_dim))
        for i in range(z.shape[0]):
            out[i] = matrix @ z[i]
        return np.clip(out, self.spec.low, self.spec.high)
