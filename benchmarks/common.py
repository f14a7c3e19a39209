"""What every benchmark script shares: the machine record and how the JSON report is emitted.

Both are the reproduction drivers' (``hybridctl.reproduce.common``), so a benchmark and a thesis
record describe their machine the same way.
"""

from __future__ import annotations

from hybridctl.reproduce.common import emit, machine_info

__all__ = ["emit", "machine_info"]
