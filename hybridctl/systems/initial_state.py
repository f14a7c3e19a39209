"""The ``[initial_state]`` section: its type and the check that its ``low`` / ``high`` are offsets.

Starts are ``nominal + U(low, high)`` elementwise: ``low`` and ``high`` are offsets from ``nominal``
(their lengths, finiteness and low <= high are refused in one line by ``spec.validate_shapes``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

__all__ = ["InitialStateSection", "warn_absolute_offsets"]


@dataclass(frozen=True)
class InitialStateSection:
    """``[initial_state]``: x0 = nominal + U(low, high), elementwise: ``low`` / ``high`` are offsets from
    ``nominal`` (low <= high, finite, one per state), not absolute values (a range that holds the nominal
    but not 0 is warned about: ``warn_absolute_offsets``)."""

    nominal: np.ndarray
    low: np.ndarray
    high: np.ndarray

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n initial states (n, len(nominal)) drawn with ``rng``."""
        return self.nominal + rng.uniform(self.low, self.high, size=(n, len(self.nominal)))


def warn_absolute_offsets(spec) -> None:
    """Warn (one line) where ``initial_state.low`` / ``high`` look like absolute values rather than the
    offsets from ``nominal`` they are (x0 = nominal + U(low, high)): a coordinate whose [low, high] holds
    its nonzero nominal but not 0, as ``nominal = 3.0, low = 2.9, high = 3.1`` written to mean 2.9..3.1
    (drawn: 5.9..6.1). A range that holds 0 or a nominal of 0 is never ambiguous and stays quiet."""
    nominal, low, high = (np.asarray(spec.get(f"initial_state.{k}"), dtype=float) for k in ("nominal", "low", "high"))
    odd = [i for i in range(nominal.size)
           if nominal[i] != 0 and low[i] <= nominal[i] <= high[i] and not low[i] <= 0 <= high[i]]
    if odd:
        names = spec.get("state.names")
        shown = ", ".join(f"{names[i]}: nominal {nominal[i]:.6g}, [low, high] = [{low[i]:.6g}, {high[i]:.6g}] -> "
                          f"starts in [{nominal[i] + low[i]:.6g}, {nominal[i] + high[i]:.6g}]" for i in odd)
        where = spec.path.name if "initial_state.low" not in spec.overridden else spec.overridden["initial_state.low"]
        warnings.warn(f"{spec.name} ({where}): initial_state.low/high are offsets from initial_state.nominal "
                      f"(x0 = nominal + U(low, high)), but these hold the nominal and not 0, as absolute values "
                      f"would: {shown}; write them as offsets", UserWarning, stacklevel=2)
