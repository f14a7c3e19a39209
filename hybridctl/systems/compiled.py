"""``torch.compile`` for the hot loops of training (the switched env's decision, SAC's losses).

Tiny tensors (batch 32 states, 32-unit layers) make eager torch pay a few microseconds of
dispatch per operation; one decision of the switched acrobot env is ~300 of them. Compiled
by inductor into a few C++ kernels, the same decision ran 13x faster here (0.8 ms against
11 ms, batch 32, one thread) and agreed with eager to 2e-15. Compiling takes 15-70 s once
per process (inductor caches kernels on disk for the next one), so short runs stay eager.

``COMPILE_MODES``: ``"off"`` (eager), ``"on"`` (compile; a failure to compile raises) and
``"auto"`` (compile runs of at least :data:`AUTO_COMPILE_MIN_STEPS` env steps; a failure to
compile falls back to eager with a warning, e.g. on a machine without a C++ compiler).
"""

from __future__ import annotations

import gc
import sys
import warnings
from typing import Callable

import torch

COMPILE_MODES = ("auto", "on", "off")

AUTO_COMPILE_MIN_STEPS = 200_000
"""``"auto"`` compiles runs of at least this many env steps: compiling (~15-70 s on 2 cores) pays
back after ~2e5 steps of the switched acrobot (each vector decision of 32 steps saves ~10 ms)."""


def check_compile_mode(mode: str, name: str = "compile") -> str:
    """``mode`` if it is one of :data:`COMPILE_MODES`, else ValueError naming ``name``."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"{name} must be one of {COMPILE_MODES}, got {mode!r}")
    return mode


def wants_compile(mode: str, total_steps: int | None = None, min_steps: int = AUTO_COMPILE_MIN_STEPS) -> bool:
    """Whether ``mode`` compiles a run of ``total_steps`` steps (``"auto"``: runs of at least ``min_steps``,
    default :data:`AUTO_COMPILE_MIN_STEPS` env steps; a learner whose compile takes longer passes its own)."""
    check_compile_mode(mode)
    if mode == "auto":
        return total_steps is not None and total_steps >= min_steps
    return mode == "on"


INDUCTOR_OPTIONS = {"cpp_wrapper": True}
"""Options handed to ``torch.compile``. The C++ wrapper launches a graph's kernels from C++: a SAC
gradient step (two graphs of ~50 small kernels each) took 1.18 ms against 1.67 ms with inductor's
default Python wrapper here (2-core AMD EPYC, one thread, torch 2.13). Measured alternatives:
``mode="max-autotune-no-cudagraphs"`` gave 1.70 ms (1.32 ms with the C++ wrapper)."""


class LazyCompiled:
    """``fn`` compiled with ``torch.compile`` on its first call, or ``fn`` itself when disabled.

    Args:
        fn: a function of tensors (and modules / plain values that do not change between calls).
        enabled: compile (True) or call ``fn`` eagerly (False).
        strict: when compiling fails, raise (True) or warn and run ``fn`` eagerly from then on
            (False). A call whose eager run raises too is a real error and is raised as such.
        name: what the warning calls it.
        options: inductor's options (default :data:`INDUCTOR_OPTIONS`).

    The compiled function has fixed shapes (``dynamic=False``): a new batch size compiles again.
    Inductor's C++ wrapper (:data:`INDUCTOR_OPTIONS`) calls the graph's ~50 kernels from C++
    instead of Python.
    """

    def __init__(self, fn: Callable, enabled: bool, strict: bool = False, name: str | None = None,
                 options: dict | None = None):
        self.fn, self.enabled, self.strict = fn, bool(enabled), bool(strict)
        self.name = name or getattr(fn, "__qualname__", repr(fn))
        self.options = dict(INDUCTOR_OPTIONS if options is None else options)
        self._compiled: Callable | None = None

    def __call__(self, *args, **kwargs):
        if not self.enabled:
            return self.fn(*args, **kwargs)
        if self._compiled is None:
            self._compiled = torch.compile(self.fn, dynamic=False, options=dict(self.options) or None)
        try:
            return self._compiled(*args, **kwargs)
        except Exception as error:  # noqa: BLE001 - compile failures come in many types
            if self.strict:
                raise RuntimeError(f"torch.compile of {self.name} failed ({type(error).__name__}: "
                                   f"{str(error).splitlines()[0] if str(error) else ''}); use compile='off' "
                                   f"(or 'auto', which falls back to eager)") from error
            result = self.fn(*args, **kwargs)  # raises if the function itself is at fault
            warnings.warn(f"torch.compile of {self.name} failed ({type(error).__name__}); running it eagerly",
                          RuntimeWarning, stacklevel=2)
            self.enabled = False
            return result



def compiled_graph_count() -> int:
    """Graphs ``torch.compile`` has built in this process so far (0 before its first use; reading it imports
    nothing)."""
    if "torch._dynamo" not in sys.modules:
        return 0
    from torch._dynamo.utils import counters
    return int(counters["stats"]["unique_graphs"])


class CompileGarbage:
    """Keeps the objects a ``torch.compile`` leaves behind out of the garbage collector's full passes.

    A compile leaves about half a million long-lived Python objects (graphs, guards, symbolic shapes). Python's
    full collection walks all of them: measured on CE-APG (acrobot, 24 x 4 x 500, compiled), a 0.35-0.45 s pause
    every ~9 APG iterations of 0.15-0.28 s. ``settle()`` after each update: when a graph was built since the last
    call, collect once and ``gc.freeze()`` what is alive (later full passes skip it); ``release()`` at the run's
    end unfreezes, so objects of the run that were frozen are collected normally again.
    """

    def __init__(self):
        self.graphs = compiled_graph_count()
        self.froze = False

    def settle(self) -> None:
        """Freeze the survivors once a graph was built since the last call (else nothing: one dict lookup)."""
        graphs = compiled_graph_count()
        if graphs != self.graphs:
            self.graphs = graphs
            gc.collect()
            gc.freeze()
            self.froze = True

    def release(self) -> None:
        """Undo :meth:`settle`'s freezes (``gc.unfreeze``)."""
        if self.froze:
            gc.unfreeze()
            self.froze = False
