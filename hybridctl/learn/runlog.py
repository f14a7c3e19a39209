"""``progress.csv`` of a training run (and TensorBoard scalars when ``torch.utils.tensorboard`` imports)."""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from io import StringIO
from pathlib import Path

import numpy as np

__all__ = ["RunLog", "PROGRESS_CSV"]

PROGRESS_CSV = "progress.csv"


class RunLog:
    """``progress.csv`` in a log folder (and TensorBoard scalars in ``tb/`` when available).

    Opening it keeps the rows of the existing file whose ``key`` column is at most
    ``upto`` (the learner's counter: the rows a resumed checkpoint had seen) and drops
    the rest; ``upto == 0`` starts a fresh file. A file without the key column is not a
    log of this learner: ValueError. The header is the learner's ``columns``.
    """

    def __init__(self, log_dir: str | Path, columns: tuple[str, ...], key: str, upto: int,
                 int_columns: tuple[str, ...] = (), float_format: str | None = ".6g", tensorboard: bool = False,
                 fallback_rows: Iterable[dict] = ()):
        self.dir = Path(log_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.columns, self.key, self.int_columns = tuple(columns), key, set(int_columns) | {key}
        self.float_format = float_format
        self.path = self.dir / PROGRESS_CSV
        self.rows = self._kept_rows(upto, fallback_rows)
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=self.columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(self._cells(r) for r in self.rows)
        tmp.replace(self.path)
        self._fh = open(self.path, "a", newline="")
        self._csv = csv.DictWriter(self._fh, fieldnames=self.columns, extrasaction="ignore")
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
                self.tb = SummaryWriter(str(self.dir / "tb"))
            except Exception:  # noqa: BLE001 - tensorboard is optional
                self.tb = None

    def _kept_rows(self, upto: int, fallback_rows: Iterable[dict]) -> list[dict]:
        if upto == 0:
            return []
        if not self.path.is_file():  # a new folder for a learner that trained before: its rows so far
            return [dict(r) for r in fallback_rows if r.get(self.key, math.inf) <= upto]
        text = self.path.read_text()
        if text and not text.endswith("\n"):  # a row cut short by a kill: dropped (its key may be cut too)
            text = text[:text.rfind("\n") + 1]
        with StringIO(text, newline="") as fh:
            reader = csv.DictReader(fh)
            if self.key not in (reader.fieldnames or []):
                raise ValueError(f"{self.path} has no {self.key!r} column: not a progress log of this learner; "
                                 f"move it or pick another log_dir")
            rows = []
            for r in reader:
                try:
                    if int(float(r[self.key])) <= upto:
                        rows.append({k: float(v) if v not in ("", None) else math.nan for k, v in r.items()})
                except (TypeError, ValueError):
                    continue
        return rows

    def _cells(self, row: dict) -> dict:
        out = {}
        for k in self.columns:
            v = row.get(k, math.nan)
            if k in self.int_columns and isinstance(v, (int, float, np.number)) and math.isfinite(v):
                out[k] = int(v)
            else:
                out[k] = format(v, self.float_format) if isinstance(v, float) and self.float_format else v
        return out

    def write(self, row: dict) -> None:
        """Append one row (missing columns empty) and flush; TensorBoard gets every finite number."""
        self._csv.writerow(self._cells(row))
        self._fh.flush()
        if self.tb is not None:
            for k, v in row.items():
                if k != self.key and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(f"train/{k}", v, row[self.key])

    def close(self) -> None:
        """Close the CSV file and the TensorBoard writer."""
        self._fh.close()
        if self.tb is not None:
            self.tb.close()
