"""What the drivers share: the machine record, the command line as recorded, paths as recorded, and
the parallel-work flags (``--backend``/``--workers``/``--address``) of the drivers that run parallel work.

Records hold paths relative to the working directory the driver ran in (the repository root, for
the commands the docs give), never the absolute path of the machine that made them:
:func:`recorded_path` turns a path into that form and :func:`command_line` writes the command as
``python -m hybridctl.reproduce.NAME ARGS`` with its path arguments relative as well.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import shlex
import sys
from pathlib import Path

import numpy as np
import torch

from hybridctl.io import atomic_write_text
from hybridctl.parallel import add_backend_arguments, check_backend_arguments
from hybridctl.systems.spec import DATA_DIR

__all__ = ["RESULTS", "machine_info", "package_version", "emit", "shipped_policy", "recorded_path", "command_line",
           "add_backend_flags", "check_backend_flags", "backend_options", "backend_cli_args"]

# The records tree, one folder per chapter, relative to the working directory (the repository root).
RESULTS = Path("results")


def package_version(dist: str) -> str | None:
    """The installed version of the distribution ``dist`` (None when it is not installed)."""
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def machine_info() -> dict:
    """Where the numbers come from: platform, cores, load, library versions, torch threads."""
    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "cpus_available": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "numpy": np.__version__,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "drake": package_version("drake"),
        "gymnasium": package_version("gymnasium"),
    }


def emit(report: dict, out: Path | None) -> None:
    """Print ``report`` as one JSON document; also write it to ``out`` if given."""
    text = json.dumps(report, indent=2, allow_nan=False)
    print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out, text + "\n")


def shipped_policy(name: str) -> Path:
    """The folder of a pretrained checkpoint that ships in the package (``models/policies/NAME``)."""
    return DATA_DIR / "models" / "policies" / name


def recorded_path(path: str | os.PathLike, base: str | os.PathLike | None = None) -> str:
    """``path`` as a record holds it: a file shipped in the package as ``models/...`` or ``systems/...``
    (the repository's links to ``hybridctl/data``), else relative to ``base`` (default: the working
    directory) when it lies below it, else as given with the home folder written ``~``.

    >>> recorded_path(Path.cwd() / "results" / "ch5")
    'results/ch5'
    """
    text = os.fspath(path)
    if not os.path.isabs(text):
        return Path(text).as_posix()
    resolved = Path(text).resolve()
    for root in (DATA_DIR.resolve(), (Path(base) if base is not None else Path.cwd()).resolve()):
        if resolved.is_relative_to(root):
            return resolved.relative_to(root).as_posix() or "."
    home = str(Path.home())
    return "~" + text[len(home):] if text.startswith(home + os.sep) else text


def command_line(module: str, argv: list[str] | None = None) -> str:
    """The command as recorded: ``python -m MODULE ARGS`` (``argv``: default ``sys.argv[1:]``), each
    argument that is an absolute path below the working directory written relative to it."""
    args = sys.argv[1:] if argv is None else list(argv)
    args = [recorded_path(a) if os.path.isabs(str(a)) else str(a) for a in args]
    return shlex.join(["python", "-m", module, *args])


# ---------------------------------------------------------------- parallel work: --backend/--workers/--address
#
# The flags of hybridctl's commands (hybridctl.cli._common.add_backend_flags / check_backend_flags), with
# the same names, choices, types and meaning. They are written here rather than imported: reproduce and
# cli are rooms on one line of ARCHITECTURE.md, which never import each other (tests/test_architecture.py);
# tests/test_reproduce_backends.py checks that the two stay alike.


def add_backend_flags(parser: argparse.ArgumentParser, default: str | None, what: str,
                      workers: int | None = None) -> None:
    """``--backend``, ``--workers`` and ``--address`` as on every hybridctl command that runs parallel work
    (:func:`hybridctl.parallel.add_backend_arguments`), and ``--force``; :func:`backend_options` passes
    them to the workload. ``default``: the driver's backend, ``workers``: its worker count (None: all
    cores, or the Ray cluster's CPUs), so that a driver run without the flags runs as before."""
    add_backend_arguments(parser, default, what, workers)
    parser.add_argument("--force", action="store_true",
                        help="allow local --workers above the cores this process may use")


def check_backend_flags(args: argparse.Namespace, parser: argparse.ArgumentParser | None = None) -> None:
    """Refuse ``--address`` without ``--backend ray`` and local ``--workers`` above the cores unless
    ``--force`` (a driver's own default count is taken as it is). ValueError, or with ``parser`` its
    usage error (one line, exit status 2)."""
    given = args.workers is not None and (parser is None or args.workers != parser.get_default("workers"))
    try:
        check_backend_arguments(args.backend, args.workers if given else None, args.address, args.force)
    except ValueError as exc:
        if parser is None:
            raise
        parser.error(str(exc))


def backend_options(args: argparse.Namespace, default: str | None = None) -> dict:
    """``backend``, ``workers`` and ``address`` of :func:`add_backend_flags`' flags, as keyword
    arguments of a workload (balance maps, meshes, Monte Carlo, failure rates, fine-tuning, APG).
    ``default``: the backend where ``--backend`` was not given and the driver's default is None
    (one driver, several workloads with their own defaults)."""
    return {"backend": args.backend or default, "workers": args.workers, "address": args.address}


def backend_cli_args(args: argparse.Namespace, default: str = "serial") -> list[str]:
    """The same flags for a ``hybridctl`` command the driver starts (``hybridctl train ars``):
    ``--backend`` always (``default`` where not given), ``--workers`` for a parallel backend,
    ``--address`` when given."""
    backend = args.backend or default
    out = ["--backend", backend]
    if args.workers is not None and backend != "serial":
        out += ["--workers", str(args.workers)]
    if args.address is not None:
        out += ["--address", args.address]
    return out
