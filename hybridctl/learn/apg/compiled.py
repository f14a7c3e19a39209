"""How the APG family compiles its rollouts: when (``APGConfig.compile = "auto"``: long runs only), how many
policy steps one compiled call holds (``APGConfig.compile_steps = None``), and one shared compiled function per
rollout function (:func:`~hybridctl.learn.apg.core.compiled_policy_steps` and ``compiled_policy_step``)."""

from __future__ import annotations

from typing import Callable

from ...systems.compiled import LazyCompiled

__all__ = ["APG_AUTO_COMPILE_MIN_STEPS", "COMPILED_INTEGRATOR_STEPS", "LazyCompiled", "compiled",
           "policy_steps_per_call"]

APG_AUTO_COMPILE_MIN_STEPS = 5_000_000
"""``APGConfig.compile = "auto"`` compiles runs of at least this many policy steps (members x batch x horizon x
APG iterations x epochs, in this process). Measured on the acrobot, 24 x 4 x 500, 4 sub-steps, float32, one
thread: the chunked graphs take 141 s to compile with cold inductor caches (9 s warm) and save about 1 s of
the 1.2 s eager iteration (48,000 policy steps), so they pay back after about 7e6 steps cold; with 20
sub-steps (the acrobot spec's 0.2 s period) after about 1e6."""

COMPILED_INTEGRATOR_STEPS = 40
"""Integrator steps per compiled call that ``APGConfig.compile_steps = None`` aims at. The graph's size (and its
compile time) grows with policy steps x sub-steps, its speed does not: acrobot, 24 x 4 x 500, cold caches,
one thread: 4 sub-steps x 10 policy steps compiled in 141 s, 0.14-0.19 s an iteration; 20 sub-steps (the
spec's 0.2 s period) x 10 in about 580 s, x 2 in 117 s, both 0.65-0.69 s an iteration."""


def policy_steps_per_call(substeps: int) -> int:
    """Policy steps per compiled call for ``substeps`` integrator steps a policy step: about
    :data:`COMPILED_INTEGRATOR_STEPS` integrator steps, at least 1 (10 at 4 sub-steps, 2 at 20)."""
    return max(1, round(COMPILED_INTEGRATOR_STEPS / max(1, int(substeps))))


_COMPILED: dict = {}


def compiled(fn: Callable, strict: bool) -> LazyCompiled:
    """``fn`` through ``torch.compile``, one shared instance per function and ``strict`` (so that every
    problem built in a process reuses the graphs). ``strict`` False: a failure to compile warns and runs
    ``fn`` eagerly (``APGConfig.compile = "auto"``). Inductor's default Python wrapper, not the C++ one
    the switched env and SAC use: on the acrobot's 24 x 4 x 500 iteration the C++ wrapper compiled in
    275 s against 141 s (cold caches) and ran 0.214 against 0.186 s an iteration."""
    key = (fn.__name__, bool(strict))
    if key not in _COMPILED:
        _COMPILED[key] = LazyCompiled(fn, True, strict=strict, name=f"the APG family's {fn.__name__}", options={})
    return _COMPILED[key]
