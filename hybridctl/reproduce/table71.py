"""Thesis Tables 7.1 / 7.2 in direction (hybridctl.experiments.apg_study): run, resume, collect.

    python -m hybridctl.reproduce.table71 run cartpole --seeds 0 1 2 3      # one process per call
    python -m hybridctl.reproduce.table71 collect                           # -> results/ch7/table71.json

Runs go to runs/ch7/table71/SYSTEM/METHOD-sSEED/record.json; a finished run is skipped, so an
interrupted study continues. ``--budget thesis`` runs the thesis' own budget (StudySettings.thesis:
K 24, N 4, T 500, 100 x 200 APG iterations, 9.6e8 interactions, ~1 h a run here) into the committed
tree, results/ch7/table71_thesis/SYSTEM/METHOD-sSEED/ (checkpoints every 5 epochs, so a run killed
at a session's end resumes from the same command), collected into results/ch7/table71_thesis.json with every run's training curves (finished or not) in
results/ch7/table71_thesis_curves.png.
``collect`` merges every record into results/ch7/table71.json (keeping the runs already recorded
there) with the per-(system, method) summary. ``--methods sb3-ppo sb3-sac`` trains Stable-Baselines3's
PPO and SAC (defaults; the ``sb3`` extra) through the gymnasium wrapper on the same tasks (PPO ~3 min
a run here, SB3 SAC ~45 min: one gradient step per env step). Not yet run: the
double cart-pole except CE-APG seed 0 (``run double_cartpole``; ~25 min a run on this machine).
``run`` takes ``--backend``/``--workers``/``--address`` for the APG family's population (each epoch's
APG phase as chunks of members, one per worker; default serial): ``APGConfig.backend``.
"""

import argparse
from pathlib import Path

from hybridctl import io
from hybridctl.experiments.apg_study import STUDY_METHODS, StudySettings, run_study, summarize, zero_policy_baseline
from hybridctl.reproduce.common import RESULTS, add_backend_flags, backend_options, check_backend_flags, command_line

OUT = Path("runs/ch7/table71")
RECORD = RESULTS / "ch7" / "table71.json"
BUDGETS = {"reduced": (OUT, RECORD, StudySettings), "thesis": (RESULTS / "ch7" / "table71_thesis",
                                                             RESULTS / "ch7" / "table71_thesis.json",
                                                             StudySettings.thesis)}
"""Per --budget: (run folder, record, settings)."""


def write_curves(out: Path, path: Path) -> Path:
    """The training curves of every run under ``out/SYSTEM/METHOD-sSEED/run/progress.csv`` (finished or
    not) side by side, labelled METHOD-sSEED: :func:`hybridctl.viz.plot_return_curves`."""
    from hybridctl import viz

    runs = {folder.parent.name: viz.read_progress_rows(folder / "progress.csv")
            for folder in sorted(out.glob("*/*/run")) if (folder / "progress.csv").exists()}
    return viz.plot_return_curves(runs, path, title="Table 7.1 at the thesis' budget: training curves")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="cmd", required=True)
    run = sub.add_parser("run")
    run.add_argument("systems", nargs="+")
    run.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    run.add_argument("--methods", nargs="+", default=list(STUDY_METHODS))
    add_backend_flags(run, "serial", "the APG family's population")
    co = sub.add_parser("collect")
    co.add_argument("--record", type=Path, default=None, help=f"the record to update (default {RECORD}; "
                                                             f"thesis: {BUDGETS['thesis'][1]})")
    for p in (run, co):
        p.add_argument("--budget", choices=tuple(BUDGETS), default="reduced",
                       help="reduced: StudySettings (default); thesis: the thesis' own budget")
    args = parser.parse_args(argv)
    out, record, make_settings = BUDGETS[args.budget]
    if args.cmd == "run":
        check_backend_flags(args, run)
        command = command_line("hybridctl.reproduce.table71", argv)
        # APGConfig fields of every APG-family run (the runs do not depend on them; SAC runs in this process)
        settings = make_settings()
        settings.extra.update(backend_options(args))
        run_study(out, systems=args.systems, methods=args.methods, seeds=args.seeds, settings=settings,
                  command=command)
    else:
        # the committed record's runs, replaced by any run folder here (runs/ is not committed: a fresh
        # clone keeps the recorded runs and adds what it ran)
        key = lambda r: (r["system"], r["method"], r["seed"])   # noqa: E731
        record = args.record or record
        merged = {key(r): r for r in (io.read_json(record)["runs"] if record.exists() else [])}
        merged.update({key(r): r for r in (io.read_json(p) for p in sorted(out.glob("*/*/record.json")))})
        records = list(merged.values())
        systems = sorted({r["system"] for r in records})
        io.write_json(record, {"settings": make_settings().__dict__, "summary": summarize(records),
                               "zero_policy": {name: zero_policy_baseline(name, make_settings()) for name in systems},
                               "runs": records})
        print(f"wrote {record}: {len(records)} runs")
        if args.budget == "thesis":
            print(f"wrote {write_curves(out, record.with_name(record.stem + '_curves.png'))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
