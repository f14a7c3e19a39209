"""Local worker processes: how they start, and that they never outlive the process that asked for them.

A process pool's workers are forked from a *fork server* (Linux) that imported torch, Drake and the
package's task modules once: a new pool's workers start in about 0.05 s instead of the 2-3 s each a
spawned worker spends importing them (``multiprocessing``'s ``forkserver`` start method with a preload;
elsewhere plain ``spawn``). The fork server is one quiet, single-threaded process per parent; it
starts with the first pool and ends with its parent. A worker gets the parent's environment as it is
when the pool starts (:func:`worker_initializer`), as a spawned one would, and re-imports the main
script as a spawned one does, so scripts still need ``if __name__ == "__main__":``
(:func:`require_main_guard` says so in one line before any worker starts).
"""

from __future__ import annotations

import ast
import ctypes
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from typing import Callable

PR_SET_PDEATHSIG = 1
"""Linux prctl(2) option: the signal a process gets when the thread that created it ends."""
PARENT_POLL_S = 0.5
"""How often a worker's watcher thread checks that its parent still lives (the portable fallback)."""
PRELOAD = ("numpy", "scipy.sparse", "torch", "pydrake.all", "hybridctl.experiments", "hybridctl.learn",
           "hybridctl.analysis")
"""What the fork server imports once, so its workers start with it (a module that fails to import is skipped by
``multiprocessing``; a worker then imports it itself)."""


def process_context() -> mp.context.BaseContext:
    """The ``multiprocessing`` context of local worker pools: a fork server preloading :data:`PRELOAD` on Linux,
    ``spawn`` elsewhere (forking a process that loaded Apple's frameworks is unsafe)."""
    if not sys.platform.startswith("linux"):
        return mp.get_context("spawn")
    context = mp.get_context("forkserver")
    context.set_forkserver_preload(list(PRELOAD))   # read when the server starts: with this process's first pool
    return context


def _pid_runs(pid: int) -> bool:
    """Whether ``pid`` runs (on Linux a zombie, dead and not yet reaped, counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # pragma: no cover - another user's process: it runs
        return True
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return True


def die_with_parent(parent: int, pdeathsig: bool = True, environ: dict | None = None,
                    via_server: bool = False) -> None:
    """Worker initializer: end this process when ``parent`` (the pid that asked for the pool) dies, even by kill -9.

    A worker outliving its parent blocks forever on its task queue, holding memory and the
    caller's stdout. On Linux the kernel kills it (``prctl(PR_SET_PDEATHSIG, SIGKILL)``) when the
    process that forked it ends: the parent itself, or with ``via_server`` the fork server, which
    ends when the parent does. The kernel ties the signal to the creating *thread*: pass
    ``pdeathsig=False`` where a spawning pool may be grown from a thread that ends early (a fork
    server forks from its one thread). Everywhere, a daemon thread also polls ``os.getppid()``
    (and with ``via_server`` the parent's pid) and exits the process once either is gone.
    ``environ``: the parent's environment, applied here (a fork server's children would otherwise
    see the server's, from when it started).
    """
    if pdeathsig and sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - a libc without prctl
            pass
    if environ is not None:
        os.environ.clear()
        os.environ.update(environ)
    forked_by = os.getppid()
    if forked_by == 1 or (forked_by != parent and not via_server) or not _pid_runs(parent):
        os._exit(1)  # the parent (or the server) died before the signal was armed
    threading.Thread(target=_exit_when_orphaned, args=(parent, forked_by), name="hybridctl-parent-watch",
                     daemon=True).start()


def _exit_when_orphaned(parent: int, forked_by: int) -> None:
    """Poll the parent pids; exit this process at once (no cleanup: the parent is gone) when one is gone."""
    while os.getppid() == forked_by and (forked_by == parent or _pid_runs(parent)):
        time.sleep(PARENT_POLL_S)
    os._exit(1)


def worker_initializer(context: mp.context.BaseContext | None = None) -> tuple[Callable[..., None], tuple]:
    """(initializer, initargs) for a pool of worker processes created by this thread in ``context`` (default:
    :func:`process_context`): :func:`die_with_parent` with this process's pid and environment."""
    via_server = (context or process_context()).get_start_method() == "forkserver"
    pdeathsig = via_server or threading.current_thread() is threading.main_thread()
    return die_with_parent, (os.getpid(), pdeathsig, dict(os.environ), via_server)


def _is_main_guard(node: ast.stmt) -> bool:
    """``if __name__ == "__main__":`` (either operand order)."""
    if not isinstance(node, ast.If) or not isinstance(node.test, ast.Compare) or len(node.test.ops) != 1:
        return False
    sides = [node.test.left, *node.test.comparators]
    names = [s for s in sides if isinstance(s, ast.Name) and s.id == "__name__"]
    consts = [s for s in sides if isinstance(s, ast.Constant) and s.value == "__main__"]
    return isinstance(node.test.ops[0], ast.Eq) and len(names) == 1 and len(consts) == 1


def unguarded_script_line() -> tuple[str, int] | None:
    """Where a script starts worker processes from module-level code outside ``if __name__ == "__main__":``.

    Spawned workers import the main script again; without the guard each of them would run
    the script's work too, and the pool dies with an error that only the workers' stderr
    shows. Returns (file, line) of the unguarded module-level statement, or None (guarded,
    interactive, a notebook, or no readable source).
    """
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if main is None or not path:
        return None
    spec = getattr(main, "__spec__", None)
    if spec is not None and (spec.name == "__main__" or spec.name.endswith(".__main__")):
        return None  # `python -m pkg`: multiprocessing does not re-run a package's __main__ in workers
    frame = sys._getframe(1)
    while frame is not None and not (frame.f_globals is vars(main) and frame.f_code.co_name == "<module>"):
        frame = frame.f_back
    if frame is None:
        return None
    try:
        tree = ast.parse(open(path, encoding="utf-8").read())
    except (OSError, SyntaxError, UnicodeDecodeError):
        return None
    line = frame.f_lineno
    for node in tree.body:
        if _is_main_guard(node) and node.lineno <= line <= (node.end_lineno or node.lineno):
            return None
    return path, line


def unreadable_main_script() -> str | None:
    """The main script's name when spawned workers could not re-import it (code read from
    standard input, ``python -``: ``__file__`` is ``'<stdin>'``), else None. Such workers die at
    start-up, and a ``multiprocessing.Pool`` would start new ones forever."""
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    return path if path and not os.path.isfile(path) else None


def require_main_guard() -> None:
    """Raise RuntimeError in one line when :func:`unguarded_script_line` finds unguarded script code,
    or when the main script cannot be re-imported by spawned workers (:func:`unreadable_main_script`)."""
    unreadable = unreadable_main_script()
    if unreadable is not None:
        raise RuntimeError(f"the main script is {unreadable!r}, which spawned worker processes cannot re-import: "
                           "save the code to a file and run that (or use one worker / backend='serial')")
    found = unguarded_script_line()
    if found is not None:
        path, line = found
        raise RuntimeError(f"{path}:{line} starts worker processes outside 'if __name__ == \"__main__\":'; "
                           "spawned workers re-import the script, so put its code under that guard "
                           "(or use backend='serial')")
