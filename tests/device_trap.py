"""Catch tensors, generators and host copies that ignore a learner's device, on a CPU-only machine.

Without a GPU a learner set to ``device="cpu"`` cannot show that it would keep its work on a
GPU: every tensor is on the CPU either way. :func:`device_trap` makes the difference visible:

- every tensor made without naming a device lands on torch's ``meta`` device (no data), so
  the first time such a tensor meets a real one, or is read (``.item()``, ``.numpy()``), the
  run fails with "Tensor on device meta is not on the expected device cpu" or similar;
- a ``torch.Generator()`` made without naming its device raises (on a GPU it would be a CPU
  generator, and a draw on the GPU from it fails there);
- :class:`HostSyncs` counts copies to the host (``.numpy()``, ``.item()``, ``.tolist()``,
  ``.cpu()``, ``bool``/``float``/``int`` of a tensor) so a test can check a hot loop makes
  O(1) of them rather than one per step.

The default device is per thread: work a learner hands to another thread (SSAC's overlapped
gate refit) escapes the trap, so tests turn such overlap off.

Code passes the trap by naming the device (``torch.zeros(n, device=self.device)``), by
following an input's (``device=x.device``), or by building modules inside
``with torch.device(device):``.
"""

from __future__ import annotations

import contextlib

import torch
from torch.overrides import TorchFunctionMode

_REAL_GENERATOR = torch.Generator


class _GeneratorNamingItsDevice(_REAL_GENERATOR):
    """``torch.Generator`` that refuses to be made without a device (a CPU default on a GPU run)."""

    def __new__(cls, device=None):
        if device is None:
            raise RuntimeError("device_trap: torch.Generator() made without a device (it would be a CPU "
                               "generator on a GPU run); pass device=")
        return _REAL_GENERATOR.__new__(cls, device)


@contextlib.contextmanager
def device_trap():
    """Inside: tensors made without a device are ``meta`` tensors; ``torch.Generator()`` needs a device."""
    previous = torch.get_default_device()
    torch.set_default_device("meta")
    torch.Generator = _GeneratorNamingItsDevice
    try:
        yield
    finally:
        torch.Generator = _REAL_GENERATOR
        torch.set_default_device(previous)


_HOST_SYNCS = {"numpy", "item", "tolist", "cpu", "__bool__", "__float__", "__int__", "__index__"}


class HostSyncs(TorchFunctionMode):
    """Counts tensor-to-host copies made inside ``with HostSyncs() as syncs:`` (``syncs.count``)."""

    def __init__(self):
        super().__init__()
        self.count = 0
        self.by_name: dict[str, int] = {}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in _HOST_SYNCS:
            self.count += 1
            self.by_name[name] = self.by_name.get(name, 0) + 1
        return func(*args, **(kwargs or {}))
