"""The learner x system matrix: every shipped swing-up of every chain, each with its gate and
Drake's LQR, on an 11 x 11 Drake balance map of starts near hanging down, with the interactions and
wall time its training took. One record, ``results/matrix/matrix.json``, its maps
(``results/matrix/maps/SYSTEM-ROW/balance_map.{json,png}``) and one figure of them
(``results/matrix/matrix.png``); the README's matrix table is :func:`markdown_table` of the record.

    python -m hybridctl.reproduce.matrix run               # every cell with a controller (~8 min, serial)
    python -m hybridctl.reproduce.matrix run --cells acrobot:trajopt cartpole:ssac
    python -m hybridctl.reproduce.matrix attempt acrobot:apg-family runs/ch7/papg-gru-acrobot-near-s0
                                                           # a training run tried for a cell: its map,
                                                           # into results/matrix/attempts.json
    python -m hybridctl.reproduce.matrix table             # the README table, from the record
                                                           # (also table.md, short.md: the docs page's)

Maps: the acrobot's two angles within +-0.3 rad of hanging down (its default map spans every angle:
more than a swing-up from hanging down); the cart-poles' default maps, which are their start spreads
near hanging down (cart +-0.5 m x first pole +-0.3 rad). Each start runs the spec's 10 s episode and
passes the thesis' success test. A cell without a shipped controller is kept with what was tried.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridctl import io
from hybridctl.experiments.balance_map import balance_map, near_hanging_down
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_options, check_backend_flags, machine_info,
                                       recorded_path)
from hybridctl.systems import load
from hybridctl.systems.spec import MODELS_DIR

OUT = RESULTS / "matrix"
GRID = 11
NEAR = 0.3
"""Half-width (rad) of the acrobot's map around hanging down: the cart-poles' own pole spread."""
SYSTEMS = ("acrobot", "cartpole", "double_cartpole")
ROWS = ("SSAC", "APG family", "SSAC fine-tuned", "APG fine-tuned", "trajopt", "energy")
FINETUNED = RESULTS / "matrix" / "finetune"
"""Fine-tuning runs of the shipped swing-ups (thesis Alg. 8 inside the switched controller), committed
with their final/ checkpoints: ``hybridctl finetune SYSTEM --policy ssac:models/policies/ssac-SYSTEM
--updates 100 --seed 0 --backend serial --out results/matrix/finetune/ssac-SYSTEM``; the APG family's
``hybridctl finetune SYSTEM --policy KIND:models/policies/NAME --updates 100 --seed 0 --backend serial
--step-size 0.002 0.0002 --noise 0.0025 0.00025 --out results/matrix/finetune/NAME`` (NAME-thesis-settings:
the same at the thesis' step size and noise)."""
APG_SMALL_STEPS = ("step size 0.002 -> 0.0002 and noise 0.0025 -> 0.00025, a tenth of the thesis' (SSAC's), one "
                   "setting for both, chosen on the fine-tuning's own evaluation (100 torch episodes from the "
                   "training's starts), not on the map. At the thesis' 0.02 / 0.025 the acrobot's swing-up got "
                   "worse (map 113/121, torch success 92 % -> 88 %) and the cart-pole's balanced 121/121 (torch "
                   "return -34.9 against -34.6 here): results/matrix/finetune/*-thesis-settings")
GOALS = {"acrobot": {"APG family": 0.9}, "double_cartpole": {"SSAC": 0.8, "APG family": 0.8}}
"""The aims the project set (fraction of the map); the other cells have none."""


def cell_key(system: str, row: str) -> str:
    """``system:row`` as the record and the command line name a cell (row lower-case, spaces as dashes)."""
    return f"{system}:{row.lower().replace(' ', '-')}"


@dataclass(frozen=True)
class Cell:
    """One controller of the matrix: ``controller`` is a ``--controller`` string (None: nothing
    shipped), ``policy`` the shipped checkpoint whose progress.json holds the training's
    interactions and wall time, ``note`` what the cell is or what was tried."""

    system: str
    row: str
    controller: str | None
    policy: str | None = None
    note: str = ""
    finetune: str | None = None     # a fine-tuning run folder (report.json): its env steps and wall time

    @property
    def key(self) -> str:
        """``system:row`` as on the command line (row lower-case, spaces as dashes)."""
        return cell_key(self.system, self.row)


def _shipped(name: str) -> str:
    """A shipped checkpoint as the record names it (relative to the repository root)."""
    return f"models/policies/{name}"


SSAC_NOTE = "Switched SAC, thesis Ch. 3 (learned gate)"
FINETUNE_NOTE = "the shipped SSAC swing-up, 100 updates of Alg. 8 inside the switched controller"
APG_FINETUNE_NOTE = ("the shipped APG-family GRU swing-up, 100 updates of Alg. 8 inside the switched controller "
                     "(cost-to-go gate + LQR; the GRU's state carried; its training's reward and starts), "
                     + APG_SMALL_STEPS)
TRAJOPT_NOTE = "direct collocation + Drake's time-varying LQR"
ENERGY_NOTE = "energy-shaping swing-up (hand-tuned gains)"


def _learned(system: str, row: str, kind: str, name: str, note: str) -> Cell:
    """A cell of a shipped checkpoint ``models/policies/NAME`` run as ``KIND:PATH``."""
    return Cell(system, row, f"{kind}:{_shipped(name)}", _shipped(name), note)


def _finetuned(system: str, row: str, run: str, note: str) -> Cell:
    """A fine-tuned row's cell: the fine-tuning run ``run`` of a shipped swing-up (under :data:`FINETUNED`)."""
    folder = f"{FINETUNED.as_posix()}/{run}"
    return Cell(system, row, f"finetune:{folder}/final", None, note, finetune=folder)


def _finetuned_ssac(system: str) -> Cell:
    """The fine-tuned row's cell of a system's shipped SSAC swing-up (:data:`FINETUNED`)."""
    return _finetuned(system, "SSAC fine-tuned", f"ssac-{system}", FINETUNE_NOTE)


def _empty(system: str, row: str, note: str) -> Cell:
    """A cell without a shipped controller, and why."""
    return Cell(system, row, None, None, note)


def _shipped_row(system: str, ssac: str, apg: Cell) -> tuple[Cell, ...]:
    """A system's cells where SSAC and the APG family have shipped checkpoints (``ssac``: the SSAC
    checkpoint's name; ``apg``: the APG-family cell), with the fine-tuned rows and both baselines."""
    apg_name = Path(apg.policy).name
    return (_learned(system, "SSAC", "ssac", ssac, SSAC_NOTE), apg, _finetuned_ssac(system),
            _finetuned(system, "APG fine-tuned", apg_name, APG_FINETUNE_NOTE),
            Cell(system, "trajopt", "trajopt", None, TRAJOPT_NOTE), Cell(system, "energy", "energy", None, ENERGY_NOTE))


CELLS = (
    *_shipped_row("acrobot", "ssac-acrobot", _learned(
        "acrobot", "APG family", "ce-apg", "ceapg-gru-acrobot",
        "CE-APG, GRU, through the LQR takeover (spec's cost-to-go gate), starts near hanging down")),
    *_shipped_row("cartpole", "ssac-cartpole", _learned(
        "cartpole", "APG family", "papg", "papg-gru-cartpole",
        "PAPG, GRU, through the LQR takeover (spec's cost-to-go gate)")),
    _learned("double_cartpole", "SSAC", "ssac", "ssac-double-cartpole",
             "Switched SAC from the spec's starts near hanging down, 3e6 steps (earlier, from starts on the whole "
             "circle at 2e6 steps: 64 % success, 58.5 % of a 21 x 21 map, results/ch3/double_cartpole)"),
    _learned("double_cartpole", "APG family", "shapg", "shapg-gru-double-cartpole",
             "short-horizon APG (20-step unrolls), GRU, through the LQR takeover: 40 epochs with the angle reward "
             "(it swings up and holds both poles by itself but its cart drifts past the gate: 39-41/121), then 20 "
             "more from that policy (--init) with the gate's cost-to-go as a reward term, k log(1 + e' S e / s) "
             "(the same term from the start, 40 epochs: 120/121 on seeds 0 and 1; seed 1 without it: 14/121). "
             "Tried before, none shipped: CE-APG-GRU with the angle or the tip-distance reward (0/121), "
             "short-horizon APG's seed 1 (14/121), 6 s episodes (33/121), 80 epochs (15/121), cart weights 0.3 and "
             "1 (12 and 2/121), a cart-speed penalty of 0.1 or 0.02 from scratch (5 and 0/121)"),
    _finetuned_ssac("double_cartpole"),
    _finetuned("double_cartpole", "APG fine-tuned", "shapg-gru-double-cartpole", APG_FINETUNE_NOTE),
    Cell("double_cartpole", "trajopt", "trajopt", None, TRAJOPT_NOTE),
    _empty("double_cartpole", "energy", "no energy swing-up for two poles"),
)


def cell_by_key(key: str) -> Cell:
    """The cell named ``system:row`` (e.g. ``acrobot:apg-family``); a clear error otherwise."""
    for cell in CELLS:
        if cell.key == key:
            return cell
    raise ValueError(f"--cells: unknown cell {key!r}; known: {', '.join(c.key for c in CELLS)}")


def map_ranges(system_name: str):
    """``(axes, ranges)`` of a system's matrix map (None, None: its default map)."""
    if system_name == "acrobot":
        return near_hanging_down(load(system_name), NEAR)
    return None, None


def training_record(policy: str | None) -> dict:
    """The interactions (environment steps; APG family: K x N x T x iterations) and wall time of a
    shipped checkpoint's training, from its progress.json; empty without a checkpoint."""
    if policy is None:
        return {}
    progress = io.read_json(MODELS_DIR / "policies" / Path(policy).name / "progress.json")
    return {"interactions": int(progress["env_steps"]), "train_wall_time_s": float(progress["wall_time"])}


def finetune_record(folder: str | None) -> dict:
    """The fine-tuning's own interactions and wall time (its report.json; the source's training not
    included) and the return and success before and after; empty without a run folder."""
    if folder is None:
        return {}
    report = io.read_json(Path(folder) / "report.json")
    keep = ("mean_return", "std_return", "success_rate", "episodes")
    return {"interactions": int(report["env_steps"]), "train_wall_time_s": float(report["train_wall_time_s"]),
            "finetune_command": report.get("command"),
            "before": {k: report["before"].get(k) for k in keep}, "after": {k: report["after"].get(k) for k in keep}}


def measure(cell: Cell, **backend) -> dict:
    """The cell's balance map (saved under ``results/matrix/maps``) and its record."""
    record = {"system": cell.system, "row": cell.row, "controller": cell.controller, "policy": cell.policy,
              "note": cell.note, "goal": GOALS.get(cell.system, {}).get(cell.row)}
    if cell.controller is None:
        return record
    axes, ranges = map_ranges(cell.system)
    start = time.perf_counter()
    result = balance_map(load(cell.system), cell.controller, grid=GRID, axes=axes, ranges=ranges, progress=False,
                         **backend)
    folder = OUT / "maps" / cell.key.replace(":", "-")
    summary = result.save(folder)
    record.update(training_record(cell.policy))
    record.update(finetune_record(cell.finetune))
    record.update({"balanced_fraction": summary["balanced_fraction"], "balanced_count": summary["balanced_count"],
                   "grid": GRID, "axes": summary["axes"],
                   "ranges": [[float(v[0]), float(v[-1])] for v in (summary["values1"], summary["values2"])],
                   "map_wall_time_s": time.perf_counter() - start, "map": f"{folder.as_posix()}/balance_map.json"})
    return record


def run(keys: list[str] | None, **backend) -> dict:
    """Measure the named cells (default: all), merged into the record; returns the record. The
    folder is locked meanwhile: a second driver writing it is refused at once."""
    cells = [cell_by_key(k) for k in keys] if keys else list(CELLS)
    with io.locked_folder(OUT, "results/matrix"):
        return _run(cells, **backend)


def _run(cells: list[Cell], **backend) -> dict:
    path = OUT / "matrix.json"
    record = io.read_json(path) if path.exists() else {"cells": {}}
    for cell in cells:
        entry = measure(cell, **backend)
        entry["machine"] = machine_info()
        record["cells"][cell.key] = entry
        shown = f"{entry['balanced_count']}/{GRID * GRID}" if "balanced_count" in entry else "no controller"
        print(f"{cell.key}: {shown}", flush=True)
        io.write_json(path, record)           # after every cell: an interrupted run keeps what it measured
    record["cells"] = {c.key: record["cells"][c.key] for c in CELLS if c.key in record["cells"]}
    io.write_json(path, record)
    plot(record, OUT / "matrix.png")
    write_pages(record)
    return record


ATTEMPT_PREFIX = {"SSAC": "ssac", "APG family": None}
"""The ``--controller`` prefix of a cell's training runs (None: the run's own method, from its config)."""


def attempt(key: str, run_folder: str | Path, **backend) -> dict:
    """Map a training run tried for a cell (its ``final/`` checkpoint) on the cell's map and add it to
    ``results/matrix/attempts.json``: the command, interactions, wall time, eval.json and the map."""
    cell = cell_by_key(key)
    with io.locked_folder(OUT, "results/matrix"):
        return _attempt(cell, Path(run_folder), **backend)


def _attempt(cell: Cell, run_folder: Path, **backend) -> dict:
    final = run_folder / "final"
    if not (final / "config.json").exists():
        raise ValueError(f"{run_folder}: no final/config.json (a finished hybridctl train run folder)")
    config = io.read_json(final / "config.json")
    prefix = ATTEMPT_PREFIX.get(cell.row) or config.get("method") or config.get("algorithm")
    evaluation = io.read_json(run_folder / "eval.json")
    axes, ranges = map_ranges(cell.system)
    result = balance_map(load(cell.system), f"{prefix}:{final}", grid=GRID, axes=axes, ranges=ranges, progress=False,
                         **backend)
    entry = {"cell": cell.key, "run": recorded_path(run_folder), "controller": f"{prefix}:{recorded_path(final)}",
             "command": evaluation.get("command"), "interactions": evaluation.get("env_steps"),
             "train_wall_time_s": evaluation.get("train_wall_time_s"),
             "eval": {k: v for k, v in evaluation.items() if isinstance(v, (int, float, str)) and k != "command"},
             "balanced_fraction": result.fraction, "balanced_count": int(result.balanced.sum()), "grid": GRID,
             "machine": machine_info()}
    path = OUT / "attempts.json"
    record = io.read_json(path) if path.exists() else {"attempts": []}
    record["attempts"] = [a for a in record["attempts"] if a["run"] != entry["run"]] + [entry]
    io.write_json(path, record)
    print(f"{cell.key} <- {entry['run']}: {entry['balanced_count']}/{GRID * GRID}", flush=True)
    return entry


def _cell_text(entry: dict | None) -> str:
    if entry is None or "balanced_fraction" not in entry:
        return "-"
    text = f"{entry['balanced_fraction']:.0%}"
    if "balanced_count" in entry:
        text = f"{entry['balanced_count']}/{entry['grid'] ** 2} ({text})"
    if "interactions" in entry:
        text += f" ({entry['interactions']:.1e} steps, {entry['train_wall_time_s'] / 60:.0f} min)"
    goal = entry.get("goal")
    return text + (f" (aim {goal:.0%})" if goal is not None and entry["balanced_fraction"] < goal else "")


def markdown_table(record: dict) -> str:
    """The matrix as a Markdown table: one row per learner, one column per system; each cell the
    balanced fraction of its map, training interactions and wall time ('-': nothing shipped)."""
    names = {"acrobot": "acrobot", "cartpole": "cart-pole", "double_cartpole": "double cart-pole"}
    lines = ["| learner | " + " | ".join(names[s] for s in SYSTEMS) + " |", "|---" * (len(SYSTEMS) + 1) + "|"]
    for row in ROWS:
        entries = [record["cells"].get(cell_key(s, row)) for s in SYSTEMS]
        lines.append(f"| {row} | " + " | ".join(_cell_text(e) for e in entries) + " |")
    return "\n".join(lines)


def short_of_aim(record: dict, attempts: list[dict] = ()) -> str:
    """A Markdown list of the cells that have an aim (:data:`GOALS`) and miss it, each with its note
    and the training runs tried for it (``attempts``: entries of ``attempts.json``)."""
    lines = []
    for cell in CELLS:
        goal = GOALS.get(cell.system, {}).get(cell.row)
        entry = record["cells"].get(cell.key, {})
        fraction = entry.get("balanced_fraction")
        if goal is None or (fraction is not None and fraction >= goal):
            continue
        reached = f"{fraction:.0%} of the map" if fraction is not None else "nothing shipped"
        lines.append(f"- **{cell.system}, {cell.row}** (aim {goal:.0%}): {reached}. {cell.note}")
        for tried in (a for a in attempts if a["cell"] == cell.key):
            lines.append(f"    - {tried['balanced_count']}/{tried['grid'] ** 2} of the map: `{tried['command']}` "
                         f"({tried['interactions']:.2g} interactions, {tried['train_wall_time_s'] / 60:.0f} min)")
    return "\n".join(lines) if lines else "Every cell with an aim reaches it."


README_MARKER = "<!-- matrix table: results/matrix/table.md, written by `python -m hybridctl.reproduce.matrix table` -->"


README = Path("README.md")
"""The README whose table :func:`write_pages` rewrites (the repository root's, as the driver runs there)."""


def update_readme(table: str, readme: Path | None = None) -> bool:
    """Replace the table after :data:`README_MARKER` in ``readme`` (up to the next blank line) with
    ``table``; False where there is no such README (a driver run outside the repository)."""
    readme = README if readme is None else readme
    if not readme.exists() or README_MARKER not in (text := readme.read_text()):
        return False
    start = text.index(README_MARKER) + len(README_MARKER) + 1
    end = text.find("\n\n", start)
    io.atomic_write_text(readme, text[:start] + table + (text[end:] if end >= 0 else "\n"))
    return True


def write_pages(record: dict) -> None:
    """``table.md`` and ``short.md`` beside the record (the docs page includes both) and the README's table."""
    io.atomic_write_text(OUT / "table.md", markdown_table(record) + "\n")
    update_readme(markdown_table(record))
    attempts = OUT / "attempts.json"
    tried = io.read_json(attempts)["attempts"] if attempts.exists() else []
    io.atomic_write_text(OUT / "short.md", short_of_aim(record, tried) + "\n")


def plot(record: dict, path: Path) -> None:
    """Every measured map of the record in one figure: rows are learners, columns systems."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, grid = plt.subplots(len(ROWS), len(SYSTEMS), figsize=(3.2 * len(SYSTEMS), 2.9 * len(ROWS)), squeeze=False)
    for i, row in enumerate(ROWS):
        for j, system in enumerate(SYSTEMS):
            ax = grid[i][j]
            entry = record["cells"].get(cell_key(system, row))
            if entry is None or "map" not in entry:
                ax.axis("off")
                ax.set_title(f"{system}, {row}: none", fontsize=8)
                continue
            data = io.read_json(entry["map"])
            (lo1, hi1), (lo2, hi2) = entry["ranges"]
            ax.imshow(np.asarray(data["balanced"], dtype=float).T, origin="lower", cmap="RdYlGn", vmin=0, vmax=1,
                      extent=(lo1, hi1, lo2, hi2), aspect="auto")
            ax.set_title(f"{system}, {row}: {entry['balanced_fraction']:.0%}", fontsize=8)
            ax.set_xlabel(entry["axes"][0], fontsize=7)
            ax.set_ylabel(entry["axes"][1], fontsize=7)
            ax.tick_params(labelsize=6)
    fig.suptitle("11 x 11 Drake balance maps near hanging down (green: balanced)", fontsize=10)
    fig.tight_layout()
    io.atomic_write(path, lambda f: fig.savefig(f, dpi=110, format="png"))
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """``run`` (measure cells) or ``table`` (print the README table from the record)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    run_parser = sub.add_parser("run", help="measure cells into results/matrix/matrix.json")
    run_parser.add_argument("--cells", nargs="+", metavar="SYSTEM:ROW",
                            help=f"cells to measure (default all): {', '.join(c.key for c in CELLS)}")
    add_backend_flags(run_parser, "serial", "each map's Drake runs")
    attempt_parser = sub.add_parser("attempt", help="map a training run tried for a cell into attempts.json")
    attempt_parser.add_argument("cell", metavar="SYSTEM:ROW", help="the cell the run was trained for")
    attempt_parser.add_argument("runs", nargs="+", type=Path, help="hybridctl train run folders (final/, eval.json)")
    add_backend_flags(attempt_parser, "serial", "each map's Drake runs")
    sub.add_parser("table", help="print the README's matrix table from the record (and rewrite table.md, "
                                 "short.md, matrix.png)")
    args = parser.parse_args(argv)
    if args.command == "table":
        record = io.read_json(OUT / "matrix.json")
        write_pages(record)
        plot(record, OUT / "matrix.png")
        print(markdown_table(record))
        return 0
    if args.command == "attempt":
        check_backend_flags(args, attempt_parser)
        try:
            for folder in args.runs:
                attempt(args.cell, folder, **backend_options(args))
        except (ValueError, io.RunFolderError) as error:
            attempt_parser.error(str(error))
        write_pages(io.read_json(OUT / "matrix.json"))
        return 0
    check_backend_flags(args, run_parser)
    try:
        keys = [cell_by_key(k).key for k in args.cells or []]
    except ValueError as error:
        run_parser.error(str(error))
    try:
        run(keys, **backend_options(args))
    except io.RunFolderError as error:
        run_parser.error(str(error))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
