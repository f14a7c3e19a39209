"""What every benchmark script shares: the machine record and how the JSON report is emitted.

Both are the reproduction drivers' (``hybridctl.reproduce.common``), so a benchmark and a thesis
record describe their machine the same way.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from hybridctl.reproduce.common import emit, machine_info, recorded_path

__all__ = ["command_line", "emit", "machine_info"]

ROOT = Path(__file__).resolve().parents[1]


def command_line() -> list[str]:
    """This process's command as a record keeps it: the interpreter as ``.venv/bin/python`` (its environment's
    folder through :func:`~hybridctl.reproduce.common.recorded_path`, relative to the repository root), so no
    record holds this machine's absolute paths. Not the interpreter's own path: a venv's ``python`` is a link
    that resolves outside the repository."""
    return [f"{recorded_path(sys.prefix, ROOT)}/bin/{os.path.basename(sys.executable)}", *sys.argv]
