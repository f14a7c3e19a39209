"""``fitted:DIR``: the controller ``hybridctl fit`` kept in its folder, read from the folder's report.json.

Apart from :mod:`hybridctl.experiments.fit` so that the named controllers (:mod:`~hybridctl.experiments.controllers`)
read it without importing the stages that train and verify it.
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["GATES", "CHECKPOINT", "CLONE", "CHECKPOINTS", "MAX_REPORT_BYTES", "fitted_controller"]

GATES = {"learned": "ssac", "cost-to-go": "ssac-costgate"}
"""The gate kinds fit keeps, and the checkpoint controller kind of each."""
CHECKPOINT = "learner/final"
"""Where in the fit's folder the learner's checkpoint lies."""
CLONE = "clone"
"""Where in the fit's folder the cloned swing-up's checkpoint lies (SSAC's starting point)."""
CHECKPOINTS = (CHECKPOINT, CLONE)
"""The checkpoints the verification may keep; report.json names one of them."""
MAX_REPORT_BYTES = 16 * 2 ** 20
"""A report.json larger than this is not read."""


def fitted_controller(folder) -> tuple[Path, str]:
    """``(checkpoint folder, controller kind)`` of the controller ``hybridctl fit`` kept in ``folder`` (its
    report.json's ``controller``: the gate and which of :data:`CHECKPOINTS`): what ``fitted:DIR`` loads. One-line ValueError for a folder without one."""
    folder = Path(folder).expanduser()
    report_file = folder / "report.json"
    if not report_file.is_file():
        raise ValueError(f"fitted:{folder}: no report.json there (a folder `hybridctl fit` wrote)")
    if report_file.stat().st_size > MAX_REPORT_BYTES:
        raise ValueError(f"fitted:{folder}: report.json is over {MAX_REPORT_BYTES} bytes")
    try:
        entry = json.loads(report_file.read_text()).get("controller")
    except (ValueError, AttributeError, UnicodeDecodeError):
        raise ValueError(f"fitted:{folder}: report.json is not a fit report") from None
    if not isinstance(entry, dict) or entry.get("gate") not in GATES:
        raise ValueError(f"fitted:{folder}: the fit has no verified controller yet (run `hybridctl fit ... --resume`)")
    checkpoint = entry.get("checkpoint", CHECKPOINT)
    if checkpoint not in CHECKPOINTS:
        raise ValueError(f"fitted:{folder}: report.json names checkpoint {checkpoint!r}, not one of {CHECKPOINTS}")
    # the checkpoint is one of fit's own, inside the folder: a path read from the file is never followed
    return folder / CHECKPOINTS[CHECKPOINTS.index(checkpoint)], GATES[entry["gate"]]
