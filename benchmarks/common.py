"""What every benchmark script shares: the machine record and how the JSON report is emitted.

Both are the reproduction drivers' (``hybridctl.reproduce.common``), so a benchmark and a thesis
record describe their machine the same way.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from hybridctl.reproduce.common import emit, machine_info

__all__ = ["command_line", "emit", "machine_info"]

ROOT = Path(__file__).resolve().parents[1]


def command_line() -> list[str]:
    """This process's command as a record keeps it: the interpreter relative to the repository root when it
    lies inside it (``.venv/bin/python``), so no record holds this machine's absolute paths."""
    interpreter = Path(sys.executable)
    try:
        shown = str(interpreter.relative_to(ROOT))
    except ValueError:
        shown = os.path.basename(sys.executable)
    return [shown, *sys.argv]
