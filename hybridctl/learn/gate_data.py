"""SSAC's gate data: the labelled set D_g (:class:`GateDataset`) and the states waiting for labels
(:class:`RelabelPool`), as :class:`hybridctl.learn.ssac.SSAC` keeps them (thesis Alg. 4 line 8)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["GateDataset", "RelabelPool"]


class GateDataset:
    """D_g: gate states (float32) and labels (bool), warm-start rows first, capped FIFO after them.

    Kept on the host (CPU tensors) whatever the learner's device: rows arrive once per ended
    episode and per refit, and a refit copies the whole set to the gate's device once
    (:func:`~hybridctl.learn.gate.fit_gate`), so a GPU holds no second, growing copy."""

    def __init__(self, n_states: int, capacity: int):
        self.n_states, self.capacity = int(n_states), int(capacity)
        self.states = torch.zeros((0, self.n_states), dtype=torch.float32, device="cpu")
        self.labels = torch.zeros(0, dtype=torch.bool, device="cpu")
        self.n_warm = 0

    def __len__(self) -> int:
        return int(self.labels.numel())

    def add(self, states, labels, warm: bool = False) -> None:
        """Append rows (numpy, or torch on any device: copied to the host); episode rows beyond
        ``capacity`` push out the oldest episode rows."""
        states = _host_tensor(states, torch.float32).reshape(-1, self.n_states)
        labels = _host_tensor(labels, torch.bool).reshape(-1)
        self.states = torch.cat([self.states, states])
        self.labels = torch.cat([self.labels, labels])
        if warm:
            self.n_warm += len(labels)
        excess = len(self) - max(self.capacity, self.n_warm)
        if excess > 0:  # keep the warm-start rows, drop the oldest episode rows
            keep = torch.ones(len(self), dtype=torch.bool, device="cpu")
            keep[self.n_warm:self.n_warm + excess] = False
            self.states, self.labels = self.states[keep], self.labels[keep]

    def state_dict(self) -> dict[str, Any]:
        """The rows and the number of warm-start rows (gate_data.pt)."""
        return {"states": self.states, "labels": self.labels, "n_warm": self.n_warm}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take the rows of :meth:`state_dict` (loaded on any device) back to the host."""
        self.states = state["states"].to(torch.float32).cpu()
        self.labels = state["labels"].to(torch.bool).cpu()
        self.n_warm = int(state["n_warm"])


def _host_tensor(values, dtype: torch.dtype) -> torch.Tensor:
    """``values`` (numpy, a sequence, or a tensor on any device) as a ``dtype`` CPU tensor."""
    if isinstance(values, torch.Tensor):
        return values.detach().to(device="cpu", dtype=dtype)
    return torch.as_tensor(np.asarray(values), dtype=dtype, device="cpu")


class RelabelPool:
    """The newest ``capacity`` states waiting for LQR-rollout labels, in a ring buffer on ``device``.

    SSAC queues the swing-up decision states near the goal at every env step: :meth:`add` takes
    the rows under a mask with no read-back to the host (no sync per step on a GPU). A refit reads
    :meth:`states` (oldest first) once, as the earlier list of rows trimmed to its newest
    ``capacity`` held them.
    """

    def __init__(self, n_states: int, capacity: int, device: str | torch.device):
        self.n_states, self.capacity = int(n_states), int(capacity)
        # one row more than the capacity: masked-out rows are written there and never read
        self._rows = torch.zeros((self.capacity + 1, self.n_states), dtype=torch.float32, device=device)
        self._added = torch.zeros((), dtype=torch.int64, device=device)  # rows ever added, on the device

    def add(self, states: torch.Tensor, keep: torch.Tensor | None = None) -> None:
        """Queue the rows of ``states`` (B, n) where ``keep`` (B,) bool is set (None: all of them)."""
        states = states.detach().to(device=self._rows.device, dtype=torch.float32).reshape(-1, self.n_states)
        if states.shape[0] == 0:
            return
        if keep is None:
            keep = torch.ones(states.shape[0], dtype=torch.bool, device=states.device)
        rank = torch.cumsum(keep, 0)  # 1, 2, ... over the kept rows
        n_kept = rank[-1]
        keep = keep & (rank > n_kept - self.capacity)  # of more kept rows than fit, the newest
        slot = torch.where(keep, (self._added + rank - 1) % self.capacity, self.capacity)
        self._rows.index_copy_(0, slot, states)
        self._added += n_kept

    def __len__(self) -> int:
        return min(int(self._added), self.capacity)

    def states(self) -> torch.Tensor:
        """The queued states (len, n), oldest first (one read-back of the count)."""
        added = int(self._added)
        if added <= self.capacity:
            return self._rows[:added]
        start = added % self.capacity
        return torch.cat([self._rows[start:self.capacity], self._rows[:start]])

    def clear(self) -> None:
        """Empty the pool."""
        self._added.zero_()

    def replace(self, states: torch.Tensor) -> None:
        """Hold exactly ``states`` (the newest ``capacity`` of them), e.g. from a checkpoint."""
        self.clear()
        self.add(states)
