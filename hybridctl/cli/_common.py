"""What every command shares: the parser class, argument types and the error handler.

``cli_errors`` turns the errors a user can cause (an unknown system, a bad value, a missing
or unreadable checkpoint or file) into one ``error: ...`` line on stderr and exit code 2
(as argparse does for a bad flag: ``SystemExit(2)``); a diverged training run
(FloatingPointError) returns exit code 3. ``hybridctl --debug ...`` re-raises instead, to
show the traceback.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from pathlib import Path
from typing import Callable

import gymnasium

from .. import limits
from ..io import FileFormatError
from ..learn.checkpoint import CheckpointError
from ..systems.spec import SpecError

USAGE_ERROR = 2
"""Exit code of a command stopped by a bad argument, file or checkpoint (argparse uses it too)."""
DIVERGED = 3
"""Exit code of a training run stopped by a non-finite loss."""

EXPECTED_ERRORS = (SpecError, FileFormatError, CheckpointError, OSError, KeyError, ValueError, ImportError,
                   gymnasium.error.Error)
"""Errors that mean "the input was wrong" (a bad value, name, file or folder, an optional extra that is
not installed, an unknown gymnasium env), reported as one line instead of a traceback."""


def error_message(exc: BaseException) -> str:
    """The one-line text of an expected error (a KeyError without its quotes)."""
    if isinstance(exc, KeyError) and exc.args:
        return str(exc.args[0])
    return str(exc) or type(exc).__name__


class CommandError(SystemExit):
    """How ``cli_errors`` stops a command after printing its error: exit code 2, ``str()`` the message.

    A SystemExit, as argparse's usage errors, so that ``main([...])`` called in-process stops
    the same way for a bad flag and for a bad value, and the message can be matched.
    """

    def __init__(self, message: str):
        super().__init__(message)
        self.code = USAGE_ERROR


def cli_errors(command: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """Decorate a command ``f(args) -> exit code``: an expected error prints ``error: ...`` on
    stderr and raises :class:`CommandError` (exit code 2, no traceback).

    FloatingPointError (training diverged) prints ``error: ...`` and returns 3. With
    ``args.debug`` every error propagates with its traceback.
    """
    @functools.wraps(command)
    def run(args: argparse.Namespace) -> int:
        try:
            return command(args)
        except FloatingPointError as exc:
            if getattr(args, "debug", False):
                raise
            print(f"error: {error_message(exc)}", file=sys.stderr)
            return DIVERGED
        except EXPECTED_ERRORS as exc:
            if getattr(args, "debug", False) or isinstance(exc, BrokenPipeError):
                raise  # a closed pipe is handled by main: the reader left
            message = f"error: {error_message(exc)}"
            print(message, file=sys.stderr)
            raise CommandError(message) from None
    return run


def systems_help() -> str:
    """Help of a SYSTEM argument: the known systems (shipped and from $HYBRIDCTL_SYSTEMS)."""
    from ..systems import known_systems  # reads $HYBRIDCTL_SYSTEMS when the parser is built

    try:
        names = ", ".join(known_systems())
    except SpecError as exc:  # a bad $HYBRIDCTL_SYSTEMS is reported when the command runs
        names = f"(unreadable: {exc})"
    return f"system name: {names}; or a path to a spec file NAME.toml"


def add_system_argument(parser: argparse.ArgumentParser, help: str | None = None) -> None:
    """The positional SYSTEM argument, its help listing the known systems."""
    parser.add_argument("system", metavar="SYSTEM", help=help or systems_help())


class DefaultsHelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps descriptions as written and appends "(default: X)" to every option whose help
    does not already name its default (flags, None and suppressed defaults excepted)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if ("default" in text or default is None or default is False or default is argparse.SUPPRESS
                or not action.option_strings or action.nargs == 0):
            return text
        return f"{text} (default: {default})"


class CommandParser(argparse.ArgumentParser):
    """An ArgumentParser that rejects unknown arguments itself, with its own usage line.

    argparse hands a sub-command's unknown arguments up to the top-level parser, which
    reports them under the top-level usage; this parser reports them at once, under the
    sub-command's usage, followed by ``unknown_flag_hint(flag)`` for each unknown flag
    (e.g. "--epochs applies to ars only"). It never accepts an abbreviated flag
    (``allow_abbrev=False``, on every sub-parser too).
    """

    unknown_flag_hint: Callable[[str], str | None] | None = None

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", DefaultsHelpFormatter)
        # no abbreviations: `--init 0.5` must not set --init-std, nor `--over` act as --overwrite;
        # sub-parsers are made by their parent's class, so every parser of the command gets it
        kwargs["allow_abbrev"] = False
        super().__init__(*args, **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        """Parse like ArgumentParser, but exit with a usage error on any unknown argument."""
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            message = "unrecognized arguments: " + " ".join(extras)
            if self.unknown_flag_hint is not None:
                hints = [self.unknown_flag_hint(item.split("=", 1)[0]) for item in extras if item.startswith("--")]
                hints = [h for h in hints if h]
                if hints:
                    message += " (" + "; ".join(hints) + ")"
            self.error(message)
        return namespace, extras


def positive(kind: type) -> Callable[[str], float | int]:
    """An argparse type: ``kind(text)``, rejected unless finite and > 0 ("must be a finite number > 0, got ...")."""
    return _bounded(kind, lambda v: v > 0, "> 0")


def non_negative(kind: type) -> Callable[[str], float | int]:
    """An argparse type: ``kind(text)``, rejected unless finite and >= 0."""
    return _bounded(kind, lambda v: v >= 0, ">= 0")


def _bounded(kind: type, accept: Callable, rule: str) -> Callable[[str], float | int]:
    def parse(text: str):
        value = kind(text)
        # an int is always finite (and math.isfinite overflows on one of 400 digits)
        if not (isinstance(value, int) or math.isfinite(value)) or not accept(value):
            raise argparse.ArgumentTypeError(f"must be a finite number{' ' + rule if rule else ''}, got {text}")
        return value
    parse.__name__ = kind.__name__  # argparse names the type in "invalid int value"
    return parse


def finite(kind: type) -> Callable[[str], float | int]:
    """An argparse type: ``kind(text)``, rejected unless finite ("must be a finite number, got inf")."""
    return _bounded(kind, lambda v: True, "")


def _limit_lines() -> dict[str, str]:
    """One line per flag that has a limit, its numbers read from :mod:`hybridctl.limits`."""
    return {
        "duration": f"--duration: at most {limits.MAX_SIMULATION_STEPS:,} time steps of the spec's dt per run",
        "grid": f"--grid: at most {limits.MAX_GRID:,} points per axis, and at most {limits.MAX_TOTAL_STEPS:,} "
                "time steps of all runs together (grid x grid x duration / dt)",
        "workers": f"--workers: local processes at most the cores this process may use ({limits.cpu_count()}), "
                   "and never more than there are tasks",
        "disturbances": f"--disturbances: at most {limits.MAX_DISTURBANCES:,}",
        "monte-carlo": f"--monte-carlo: at most {limits.MAX_MONTE_CARLO:,} episodes",
    }


def limits_epilog(*flags: str) -> str:
    """The ``--help`` epilog listing the limits on ``flags`` (keys of the limit lines: "duration", "grid", ...)
    and the memory limit that ``--force`` does not lift."""
    lines = _limit_lines()
    budget = limits.memory_budget() / 2**30
    return "\n".join(["limits, checked before any work (--force lifts them, except memory):",
                      *(f"  {lines[f]}" for f in flags),
                      f"  memory: what a run records or batches must fit in {limits.MEMORY_FRACTION:.0%} of this "
                      f"machine's memory ({budget:.1f} GiB); nothing lifts it"])


def add_force_flag(parser: argparse.ArgumentParser, also: str = "") -> None:
    """``--force``: lift the stated caps (the epilog lists them); the memory limit stays. ``also``: what else
    it does on this command (``simulate``: load a checkpoint trained on other spec values)."""
    parser.add_argument("--force", action="store_true",
                        help="lift the stated limits on sizes, counts and durations (listed below); "
                             "never the memory limit" + (f"; {also}" if also else ""))


def add_debug_flag(parser: argparse.ArgumentParser, top_level: bool = False) -> None:
    """``--debug``: show the traceback of an error instead of a one-line message.

    On a sub-command its default is suppressed, so that ``hybridctl --debug CMD`` and
    ``hybridctl CMD --debug`` both work.
    """
    parser.add_argument("--debug", action="store_true", default=False if top_level else argparse.SUPPRESS,
                        help="show the full traceback of an error instead of a one-line message")


def add_quiet_flag(parser: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress bar."""
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def command_line(argv: list[str]) -> str:
    """The command as typed, recorded in outputs (``"hybridctl simulate acrobot ..."``)."""
    return "hybridctl " + " ".join(argv)


def add_backend_flags(parser: argparse.ArgumentParser, default: str, what: str) -> None:
    """``--backend``, ``--workers`` and ``--address`` (:func:`hybridctl.parallel.add_backend_arguments`,
    shared with the ``reproduce`` drivers) and the Ray task flags (:func:`add_ray_task_flags`)."""
    from ..parallel import add_backend_arguments

    add_backend_arguments(parser, default, what)
    add_ray_task_flags(parser)


def add_ray_task_flags(parser: argparse.ArgumentParser) -> None:
    """``--task-cpus``, ``--task-gpus``, ``--task-memory`` and ``--runtime-env``: what one Ray task asks
    for and the environment Ray builds for the tasks (with ``--backend ray`` only)."""
    group = parser.add_argument_group("Ray tasks (with --backend ray)")
    group.add_argument("--task-cpus", type=positive(float), metavar="N",
                       help="CPUs one Ray task asks for (Ray's num_cpus; default 1)")
    group.add_argument("--task-gpus", type=non_negative(float), metavar="N",
                       help="GPUs one Ray task asks for (Ray's num_gpus, fractions share a GPU; default 0)")
    group.add_argument("--task-memory", type=positive(float), metavar="GIB",
                       help="memory one Ray task reserves, in GiB (Ray's memory; default none reserved)")
    group.add_argument("--runtime-env", metavar="JSON|FILE.json",
                       help="Ray runtime environment of the tasks, a JSON object or a .json file of one (at most "
                            "64 KiB), e.g. '{\"working_dir\": \".\"}' to ship this folder's specs and models to "
                            "a cluster; keys: working_dir, py_modules, env_vars, excludes, image_uri, config "
                            "(pip, uv, conda, container are refused: pre-install packages on the cluster)")


def ray_task_options(args: argparse.Namespace) -> dict:
    """``task_resources`` and ``runtime_env`` (each None when not given) from :func:`add_ray_task_flags`'
    flags, for :func:`hybridctl.parallel.ray_options`; ValueError naming the flag for a bad value."""
    from ..parallel import MAX_RUNTIME_ENV_BYTES, check_runtime_env, check_task_resources, task_memory_bytes

    resources = {key: value for key, value in (
        ("num_cpus", getattr(args, "task_cpus", None)), ("num_gpus", getattr(args, "task_gpus", None)),
        ("memory", None if getattr(args, "task_memory", None) is None else task_memory_bytes(args.task_memory)))
        if value is not None}
    check_task_resources(resources)         # the limits, before Ray sees them
    text, runtime_env = getattr(args, "runtime_env", None), None
    if text is not None:
        if not text.lstrip().startswith("{"):       # a file name
            path = Path(text)
            if not path.is_file():
                raise ValueError(f"--runtime-env {text}: neither a JSON object nor an existing .json file")
            size = path.stat().st_size
            if size > MAX_RUNTIME_ENV_BYTES:
                raise ValueError(f"--runtime-env {text}: at most {MAX_RUNTIME_ENV_BYTES:,} bytes, this file has {size:,}")
            text = path.read_text(encoding="utf-8", errors="replace")
        try:
            runtime_env = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--runtime-env is not valid JSON: {exc}") from None
        try:
            check_runtime_env(runtime_env)
        except ValueError as exc:
            raise ValueError(f"--runtime-env: {exc}") from None
    return {"task_resources": resources or None, "runtime_env": runtime_env}


def ray_options_for(args: argparse.Namespace):
    """The context (:func:`hybridctl.parallel.ray_options`) in which a command's workloads make their
    Ray backends with the ``--task-*`` and ``--runtime-env`` flags' values."""
    from ..parallel import ray_options

    return ray_options(**ray_task_options(args))


def check_backend_flags(args: argparse.Namespace) -> None:
    """Refuse ``--address`` without ``--backend ray``, Ray task flags without it, and local ``--workers``
    above the cores (``--force``): :func:`hybridctl.parallel.check_backend_arguments`."""
    from ..parallel import check_backend_arguments

    check_backend_arguments(args.backend, args.workers, args.address, args.force)
    check_ray_task_flags(args, args.backend)


def check_ray_task_flags(args: argparse.Namespace, backend: str) -> None:
    """Refuse ``--task-cpus``/``--task-gpus``/``--task-memory``/``--runtime-env`` unless ``backend`` is
    "ray" (they would be ignored), and check their values (:func:`ray_task_options`)."""
    for flag in ("task_cpus", "task_gpus", "task_memory", "runtime_env"):
        if getattr(args, flag, None) is not None and backend != "ray":
            raise ValueError(f"--{flag.replace('_', '-')} applies to --backend ray only, not {backend!r}")
    ray_task_options(args)
