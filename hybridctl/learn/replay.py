"""Replay for SAC and SSAC: a torch ring buffer, the needle-buffer mixture of thesis Sec. 3.3,
and the per-env staging area that holds the running episodes until they succeed or fail."""

from __future__ import annotations

from typing import Any

import torch

REPLAY_FIELDS = ("obs", "actions", "rewards", "next_obs", "dones")


class ReplayBuffer:
    """Preallocated torch ring buffer of transitions (float32, on one device).

    Fields: obs (C, n), actions (C, m), rewards (C,), next_obs (C, n), dones (C,)
    (1.0 = terminated: no bootstrap). :meth:`add` takes a batch (k rows, oldest first);
    when full, the oldest rows are overwritten.
    """

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, device: str | torch.device = "cpu"):
        self.capacity, self.device = int(capacity), torch.device(device)
        shapes = {"obs": (obs_dim,), "actions": (action_dim,), "rewards": (), "next_obs": (obs_dim,), "dones": ()}
        self.data = {k: torch.zeros((self.capacity, *s), dtype=torch.float32, device=self.device)
                     for k, s in shapes.items()}
        self.ptr = 0   # next row to write
        self.size = 0  # rows filled

    def __len__(self) -> int:
        return self.size

    def add(self, obs, actions, rewards, next_obs, dones) -> None:
        """Append k transitions (each argument has k rows)."""
        batch = dict(zip(REPLAY_FIELDS, (obs, actions, rewards, next_obs, dones)))
        k = int(batch["rewards"].shape[0])
        if k == 0:
            return
        if k > self.capacity:  # only the newest rows fit
            batch = {f: v[-self.capacity:] for f, v in batch.items()}
            k = self.capacity
        idx = (self.ptr + torch.arange(k, device=self.device)) % self.capacity
        for f, v in batch.items():
            self.data[f].index_copy_(0, idx, v.to(device=self.device, dtype=torch.float32))
        self.ptr = (self.ptr + k) % self.capacity
        self.size = min(self.size + k, self.capacity)

    def get(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """Rows ``idx`` of every field (``index_select``: the same rows as ``v[idx]``, 2.5x faster here)."""
        return {f: v.index_select(0, idx) for f, v in self.data.items()}

    def state_dict(self) -> dict[str, Any]:
        """The filled rows, oldest first (what replay.pt stores)."""
        order = torch.arange(self.size, device=self.device)
        if self.size == self.capacity:
            order = (order + self.ptr) % self.capacity
        return {"size": self.size, **{f: v[order].cpu() for f, v in self.data.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the content with ``state`` (oldest first); keeps the newest rows that fit."""
        self.ptr = self.size = 0
        self.add(*(state[f] for f in REPLAY_FIELDS))


def sample_mixed(main: ReplayBuffer, needle: ReplayBuffer, batch_size: int, needle_prob: float,
                 generator: torch.Generator | None = None) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Draw ``batch_size`` rows with replacement; each row from ``needle`` with prob ``needle_prob``.

    Thesis Sec. 3.3: "with probability p_d we sample from D_n". Rows come from the main
    buffer only while the needle buffer is empty (or ``needle_prob`` is 0). Returns the
    batch and the (B,) bool mask of rows taken from the needle buffer.
    """
    if main.size == 0:
        raise RuntimeError("cannot sample from an empty replay buffer")
    dev = main.device
    idx = torch.randint(main.size, (batch_size,), generator=generator, device=dev)
    if needle_prob <= 0 or needle.size == 0:
        return main.get(idx), torch.zeros(batch_size, dtype=torch.bool, device=dev)
    from_needle = torch.rand(batch_size, generator=generator, device=dev) < needle_prob
    k = int(from_needle.sum())
    if not k:
        return main.get(idx), from_needle
    nidx = torch.randint(needle.size, (k,), generator=generator, device=dev)
    # the same draws as gathering all rows from main and overwriting the needle rows, without
    # gathering the rows that would be overwritten (random reads from 1e6-row buffers dominate)
    needle_pos = from_needle.nonzero().squeeze(1)
    main_pos = (~from_needle).nonzero().squeeze(1)
    from_main = main.get(idx.index_select(0, main_pos))
    from_needle_rows = needle.get(nidx)
    batch = {}
    for f, v in from_main.items():
        out = v.new_empty((batch_size, *v.shape[1:]))
        out.index_copy_(0, main_pos, v)
        out.index_copy_(0, needle_pos, from_needle_rows[f])
        batch[f] = out
    return batch, from_needle


class EpisodeStaging:
    """Each env's current-episode transitions, so successful episodes can go to the needle buffer.

    Tensors (num_envs, horizon, ...): transition t of env i lives at [i, t]. Rows longer
    than ``horizon`` are marked overflowed and never copied.
    """

    def __init__(self, num_envs: int, horizon: int, obs_dim: int, action_dim: int, device):
        self.horizon = int(horizon)
        shapes = {"obs": (obs_dim,), "actions": (action_dim,), "rewards": (), "next_obs": (obs_dim,), "dones": ()}
        self.data = {k: torch.zeros((num_envs, self.horizon, *s), dtype=torch.float32, device=device)
                     for k, s in shapes.items()}
        self.length = torch.zeros(num_envs, dtype=torch.long, device=device)
        self.overflow = torch.zeros(num_envs, dtype=torch.bool, device=device)
        self._rows = torch.arange(num_envs, device=device)

    def add(self, obs, actions, rewards, next_obs, dones) -> None:
        """One transition per env (each argument has num_envs rows)."""
        t = self.length.clamp(max=self.horizon - 1)
        self.overflow |= self.length >= self.horizon
        for f, v in zip(REPLAY_FIELDS, (obs, actions, rewards, next_obs, dones)):
            self.data[f][self._rows, t] = v.to(dtype=torch.float32, device=self.length.device)
        self.length += 1

    def take(self, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """Transitions of the envs in the bool mask ``rows`` (overflowed ones skipped), in order."""
        rows = rows & ~self.overflow
        steps = torch.arange(self.horizon, device=self.length.device)
        keep = steps[None, :] < self.length[rows][:, None]
        return {f: v[rows][keep] for f, v in self.data.items()}

    def clear(self, rows: torch.Tensor | None = None) -> None:
        """Start new episodes in the bool mask ``rows`` (all if None)."""
        if rows is None:
            self.length.zero_()
            self.overflow.zero_()
        else:
            self.length[rows] = 0
            self.overflow[rows] = False

