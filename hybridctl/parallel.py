"""Parallel work (rollouts, mesh expansion): one worker interface, three backends (serial, local processes, Ray).

A backend maps a module-level function over a list of tasks and returns the results
in task order, so the same seed gives the same result on every backend::

    with make_backend("processes", workers=2) as backend:      # the default
        results = backend.map(run_episode, tasks)

* ``serial``: in this process (debugging, tests, tiny jobs).
* ``processes``: a ``concurrent.futures`` pool of local processes (forked from a server that
  imported torch and Drake once: :mod:`hybridctl.workers`). A worker
  that dies (killed, out of memory, a segfault in a simulator) breaks only the
  current map: the pool is rebuilt and the unfinished tasks are run again, up to
  ``retries`` times, so a long job loses nothing that had finished. Workers die with
  their parent, even after a kill -9 of it (:func:`die_with_parent`): no orphan is left
  blocked on its queue.
* ``ray``: Ray tasks, on a local Ray instance (``address=None``) or a cluster
  (``address="ray://host:10001"`` or ``"auto"``). Needs the optional ``ray`` extra.
  A local instance is started on 127.0.0.1 without its dashboard, and its workers get
  this process's ``sys.path``; on a cluster, pass ``runtime_env`` to ship code.
  What one task asks for (CPUs, GPUs, memory) and the runtime environment can also be set
  for every Ray backend made inside a block, ``with ray_options(task_resources=...,
  runtime_env=...):``, which is how the command line's ``--task-cpus``, ``--task-gpus``,
  ``--task-memory`` and ``--runtime-env`` reach workloads that make their own backend.

Simulator objects (Drake systems, MuJoCo models) do not pickle: tasks carry plain
parameters, and workers build their simulators themselves (see :func:`cached_env`).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import contextlib
import contextvars
import json
import os
import reprlib
import socket
import sys
import threading
import time
from typing import Any, Callable, Iterator, Sequence

from .limits import (MAX_TASK_CPUS, MAX_TASK_GPUS, MAX_TASK_MEMORY_BYTES, RAY_CONNECT_TIMEOUT_S, check_at_most,
                     cpu_count)
# how local workers start and die with their parent (re-exported: scripts and tests import them from here)
from .workers import (die_with_parent, process_context, require_main_guard, unguarded_script_line,  # noqa: F401
                      unreadable_main_script, worker_initializer)

BACKENDS = ("serial", "processes", "ray")

TASK_RESOURCE_KEYS = ("num_cpus", "num_gpus", "memory")
"""What one Ray task may ask for (Ray's own names; ``memory`` in bytes)."""
TASK_RESOURCE_FLAGS = {"num_cpus": "--task-cpus", "num_gpus": "--task-gpus", "memory": "--task-memory"}
"""The command-line flag of each task resource, named in every refusal."""
RUNTIME_ENV_KEYS = ("working_dir", "py_modules", "env_vars", "excludes", "image_uri", "config")
"""The Ray runtime-environment fields accepted (Ray's own names); anything else is refused as a typo."""
INSTALLING_RUNTIME_ENV_KEYS = ("pip", "uv", "conda", "container")
"""Runtime-environment fields that install code on every node at run time: refused (see :func:`check_runtime_env`)."""
MAX_RUNTIME_ENV_BYTES = 64 * 1024
"""A runtime environment is a few paths and package names; its JSON above this is refused."""

_ENV_CACHE: dict[Any, Any] = {}


def cached_env(key: Any, make: Callable[[], Any]) -> Any:
    """The object ``make()`` built in this process under ``key`` (built once per worker)."""
    if key not in _ENV_CACHE:
        _ENV_CACHE[key] = make()
    return _ENV_CACHE[key]


class SerialBackend:
    """Run tasks one after another in this process."""

    name = "serial"
    workers = 1

    def put(self, value: Any) -> Any:
        """A large read-only input shared by every task (Ray: stored once; here: the value itself)."""
        return value

    def map(self, fn: Callable, tasks: Sequence) -> list:
        """``[fn(t) for t in tasks]``."""
        return [fn(t) for t in tasks]

    def imap_unordered(self, fn: Callable, tasks: Sequence) -> Iterator:
        """``fn`` over ``tasks``, each result as soon as it is done (here: in task order), for progress bars."""
        for task in tasks:
            yield fn(task)

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class ProcessBackend(SerialBackend):
    """A pool of local worker processes (:func:`~hybridctl.workers.process_context`); rebuilt and retried when a
    worker dies."""

    name = "processes"

    def __init__(self, workers: int | None = None, retries: int = 2):
        if workers is not None and (not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
        self.workers = workers or max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                                      else os.cpu_count() or 1)
        self.retries = retries
        self._pool: cf.ProcessPoolExecutor | None = None

    def _executor(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            require_main_guard()
            context = process_context()                    # forked from a preloaded server: no 2-3 s imports
            initializer, initargs = worker_initializer(context)   # no orphan survives a kill -9 of this process
            self._pool = cf.ProcessPoolExecutor(self.workers, mp_context=context,
                                                initializer=initializer, initargs=initargs)
        return self._pool

    def map(self, fn: Callable, tasks: Sequence) -> list:
        """Results of ``fn`` over ``tasks``, in task order."""
        results = dict(self._completed(fn, tasks))
        return [results[i] for i in range(len(tasks))]

    def imap_unordered(self, fn: Callable, tasks: Sequence) -> Iterator:
        """``fn`` over ``tasks``, each result as soon as its task is done (completion order)."""
        for _, result in self._completed(fn, tasks):
            yield result

    def _completed(self, fn: Callable, tasks: Sequence) -> Iterator[tuple[int, Any]]:
        """(task index, result) as tasks finish. A worker that dies breaks the pool: what finished is
        kept, the pool is rebuilt and the unfinished tasks run again, up to ``retries`` times."""
        pending = set(range(len(tasks)))
        for attempt in range(self.retries + 1):
            pool = self._executor()
            futures = {}
            try:
                # inside the try: a pool whose worker died since the last map breaks already at submit
                for i in sorted(pending):
                    futures[pool.submit(fn, tasks[i])] = i
                for future in cf.as_completed(futures):
                    result = future.result()
                    pending.discard(futures[future])
                    yield futures[future], result
                return
            except cf.process.BrokenProcessPool:
                # a worker died: keep what finished, rebuild the pool, rerun the rest
                for future, i in futures.items():
                    if i in pending and future.done() and not future.cancelled() and future.exception() is None:
                        pending.discard(i)
                        yield i, future.result()
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
                if attempt == self.retries:
                    raise RuntimeError(f"rollout workers died {self.retries + 1} times; "
                                       f"{len(pending)} of {len(tasks)} tasks unfinished") from None

    def close(self) -> None:
        """Shut the pool down."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


PARALLEL_MIN_ROUND_SECONDS = 0.05
"""A round of work estimated below this many seconds runs in this process (:class:`SizedRounds`): a local
worker round trip costs about a millisecond and a Ray task several: the analytic rimless wheel's mesh took
0.08 s on one Ray worker and 0.40 s on two (``benchmarks/ray_scaling.py``, 2026-12-05)."""


class SizedRounds:
    """Rounds of independent work units, each round run in this process or on a backend by its measured size.

    ``make_backend()`` is called on the first round worth sending out (never, for work that stays small).
    A round's cost is estimated from the seconds per unit of the rounds run here; while no round has run here
    (the first), or the estimate is below ``min_seconds``, the round runs here (0: every round goes out).
    The results must not depend on where a task runs (pure functions), so the choice only moves time.
    ``rounds`` counts both kinds."""

    def __init__(self, make_backend: Callable[[], Any], min_seconds: float = PARALLEL_MIN_ROUND_SECONDS):
        self._make, self.backend, self.min_seconds = make_backend, None, float(min_seconds)
        self.unit_seconds: float | None = None
        self.rounds = {"in_process": 0, "backend": 0}

    def here(self, units: float) -> bool:
        """Whether a round of ``units`` work units runs in this process."""
        return self.min_seconds > 0 and (self.unit_seconds is None or self.unit_seconds * units < self.min_seconds)

    def run(self, units: float, in_process: Callable[[], Any], on_backend: Callable[[Any], Any]) -> Any:
        """``in_process()`` (timed, to size later rounds) or ``on_backend(backend)``, by :meth:`here`."""
        if self.here(units):
            start = time.perf_counter()
            result = in_process()
            if units > 0:
                self.unit_seconds = (time.perf_counter() - start) / units
            self.rounds["in_process"] += 1
            return result
        self.rounds["backend"] += 1
        return on_backend(self.made())

    def made(self) -> Any:
        """The backend, made now if it was not yet."""
        if self.backend is None:
            self.backend = self._make()
        return self.backend


_RAY_OPTIONS: contextvars.ContextVar[dict] = contextvars.ContextVar("hybridctl_ray_options", default={})


def check_task_resources(task_resources: dict | None) -> dict | None:
    """``task_resources`` if it is None or a dict of :data:`TASK_RESOURCE_KEYS` to finite numbers >= 0 within
    ``limits.MAX_TASK_CPUS`` / ``MAX_TASK_GPUS`` (fractions in Ray's steps of 0.0001) / ``MAX_TASK_MEMORY_BYTES``
    (whole bytes); else ValueError naming the key and flag. The cluster's nodes are checked on joining it."""
    if task_resources is None:
        return None
    if not isinstance(task_resources, dict):
        raise ValueError(f"task_resources must be a dict with keys from {TASK_RESOURCE_KEYS}, got {task_resources!r}")
    checked = {}
    for key, value in task_resources.items():
        if key not in TASK_RESOURCE_KEYS:
            raise ValueError(f"task_resources key {key!r} is not one of {TASK_RESOURCE_KEYS}")
        name = f"task_resources[{key!r}] ({TASK_RESOURCE_FLAGS[key]})"
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0 or value == float("inf"):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        limit = {"num_cpus": MAX_TASK_CPUS, "num_gpus": MAX_TASK_GPUS, "memory": MAX_TASK_MEMORY_BYTES}[key]
        check_at_most(name, value, limit, why="what one task may ask for", force_flag=None)
        if key == "memory":
            if int(value) != value:
                raise ValueError(f"{name} is in bytes and must be whole, got {value!r}")
            value = int(value)
        elif 0 < value < 1e-4:
            raise ValueError(f"{name} is {value!r}: Ray counts resources in steps of 0.0001")
        checked[key] = value
    return checked


def task_memory_bytes(gib: float) -> int:
    """``--task-memory`` (GiB, a finite number > 0) as whole bytes; ValueError above ``MAX_TASK_MEMORY_BYTES``."""
    check_at_most("--task-memory", gib, MAX_TASK_MEMORY_BYTES / 2**30, force_flag=None, why="GiB one task may reserve")
    return int(gib * 2**30)


def _strings(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) and v for v in value)


_RUNTIME_ENV_VALUES = {
    "working_dir": (lambda v: isinstance(v, str) and v, "a non-empty string"),
    "image_uri": (lambda v: isinstance(v, str) and v, "a non-empty string"),
    "py_modules": (_strings, "a list of non-empty strings"), "excludes": (_strings, "a list of non-empty strings"),
    "env_vars": (lambda v: isinstance(v, dict) and all(isinstance(k, str) and k and isinstance(x, str)
                                                       for k, x in v.items()),
                 'an object of strings to strings (write "1", not 1)'),
    "config": (lambda v: isinstance(v, dict) and set(v) <= {"setup_timeout_seconds", "eager_install"}
               and isinstance(v.get("eager_install", True), bool)
               and (lambda t: type(t) is int and (t > 0 or t == -1))(v.get("setup_timeout_seconds", 1)),
               "an object of setup_timeout_seconds (an integer > 0, or -1) and eager_install (a bool)")}
"""Each accepted runtime-env field: (accepts its value, what it must be)."""


def check_runtime_env(runtime_env: dict | None) -> dict | None:
    """``runtime_env`` if it is None or a dict of :data:`RUNTIME_ENV_KEYS` whose JSON is at most
    :data:`MAX_RUNTIME_ENV_BYTES`, each value as :data:`_RUNTIME_ENV_VALUES` says (a local ``working_dir`` or
    ``py_modules`` must exist); else ValueError naming the key. :data:`INSTALLING_RUNTIME_ENV_KEYS` (``pip``,
    ``uv``, ``conda``, ``container``) are refused, saying to pre-install the packages on the cluster: they
    install at run time on every node, which needs network access a node may lack and runs unpinned code."""
    if runtime_env is None:
        return None
    if not isinstance(runtime_env, dict):
        raise ValueError(f"runtime_env must be a dict (a JSON object) with keys from {RUNTIME_ENV_KEYS}, "
                         f"got {type(runtime_env).__name__}")
    for key in runtime_env:
        if key in INSTALLING_RUNTIME_ENV_KEYS:
            raise ValueError(f"runtime_env key {key!r} is refused: it installs packages on every node at run time "
                             "(network access, unpinned code); pre-install them on the cluster's nodes (or in its "
                             "image) and leave it out")
        if key not in RUNTIME_ENV_KEYS:
            raise ValueError(f"runtime_env key {key!r} is not one of {RUNTIME_ENV_KEYS}")
    size = len(json.dumps(runtime_env, default=str))
    if size > MAX_RUNTIME_ENV_BYTES:
        raise ValueError(f"runtime_env is {size:,} bytes of JSON; at most {MAX_RUNTIME_ENV_BYTES:,} are accepted")
    for key, value in runtime_env.items():
        accepts, what = _RUNTIME_ENV_VALUES[key]
        if not accepts(value):
            raise ValueError(f"runtime_env[{key!r}] must be {what}, got {reprlib.repr(value)}")
        for path in {"working_dir": [value], "py_modules": value}.get(key, []):
            if "://" not in path and not os.path.exists(path):   # local: Ray packs it here; a URI: the cluster's
                raise ValueError(f"runtime_env[{key!r}]: {path!r} does not exist here (a folder, .zip, .whl or URI)")
    return dict(runtime_env)


@contextlib.contextmanager
def ray_options(task_resources: dict | None = None, runtime_env: dict | None = None) -> Iterator[None]:
    """Inside the block, every :class:`RayBackend` made without its own ``task_resources`` or
    ``runtime_env`` uses these: the way to give resources to workloads that make their own
    backend (meshes, balance maps, learners). Both are checked first (:func:`check_task_resources`,
    :func:`check_runtime_env`); no effect on the serial and process backends."""
    options = {"task_resources": check_task_resources(task_resources), "runtime_env": check_runtime_env(runtime_env)}
    token = _RAY_OPTIONS.set({k: v for k, v in options.items() if v is not None})
    try:
        yield
    finally:
        _RAY_OPTIONS.reset(token)


def ray_address(address: str | None = None) -> str | None:
    """The Ray cluster to join: ``address`` (``--address``), else the ``RAY_ADDRESS`` environment
    variable (as ``ray job submit`` and Ray's own tools set it), else None: a new local instance."""
    return address or os.environ.get("RAY_ADDRESS") or None


# a gRPC (HTTP/2) client's preface and empty SETTINGS frame; a Ray head (GCS or Ray Client) answers with SETTINGS
_HTTP2_HELLO = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


def check_ray_address(address: str, timeout: float | None = None, shown: str | None = None) -> None:
    """Refuse in one line naming ``address`` (or ``shown``; ConnectionError, ValueError if malformed) a Ray cluster
    that does not answer within ``timeout`` s (default ``limits.RAY_CONNECT_TIMEOUT_S``; ``ray.init`` waited 70 s
    or more): DNS lookup (on a thread: ``getaddrinfo`` has no timeout), TCP connect, a Ray head's gRPC greeting
    (not under ``RAY_USE_TLS``). ``"auto"`` is resolved as Ray does; ``"local"`` and ``name://`` go to Ray."""
    timeout = RAY_CONNECT_TIMEOUT_S if timeout is None else timeout
    deadline, shown = time.monotonic() + timeout, shown or address
    if address == "auto":   # as Ray resolves it (ConnectionError when no cluster runs here)
        from ray._private.services import canonicalize_bootstrap_address
        address = canonicalize_bootstrap_address("auto") or "local"
    text = address[len("ray://"):] if address.startswith("ray://") else address
    if address == "local" or "://" in text:
        return
    host, colon, port = text.rpartition(":") if text.count(":") == 1 or text.startswith("[") else ("", "", "")
    host = host.strip("[]")
    if not (host and colon and port.isdigit() and 0 < int(port) < 65536):
        raise ValueError(f"Ray address {shown!r} is not host:port, ray://host:port or auto")
    where, limit = f"the Ray cluster at {shown}", f"within {timeout:g} s (limits.RAY_CONNECT_TIMEOUT_S)"
    found: dict = {}

    def lookup():
        try:
            found["infos"] = socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
        except OSError as exc:
            found["error"] = exc
    (thread := threading.Thread(target=lookup, name="hybridctl-ray-dns", daemon=True)).start()
    thread.join(timeout)
    if "infos" not in found:
        raise ConnectionError(f"{where}: unknown host {host!r}" + (
            f" ({found['error'].strerror or found['error']})" if "error" in found else f": no DNS answer {limit}"))
    reason = "no address"
    for family, kind, proto, _, sockaddr in found["infos"]:
        with socket.socket(family, kind, proto) as sock:
            try:
                sock.settimeout(max(1e-3, deadline - time.monotonic()))
                sock.connect(sockaddr)
            except OSError as exc:
                reason = exc.strerror or str(exc) or type(exc).__name__
                continue
            if os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true"):
                return                                   # TLS: no plain greeting to check
            try:
                sock.sendall(_HTTP2_HELLO)
                sock.settimeout(max(1e-3, deadline - time.monotonic()))
                hello = sock.recv(9)
            except OSError:
                hello = b""
            if len(hello) >= 4 and hello[3] == 4:        # an HTTP/2 SETTINGS frame: a gRPC server
                return
            raise ConnectionError(f"{where} answers, but not as a Ray cluster: no gRPC greeting {limit}")
    raise ConnectionError(f"{where} does not answer: {reason} (waited at most {timeout:g} s, limits.RAY_CONNECT_TIMEOUT_S)")


def check_fits_cluster(ray: Any, task_resources: dict) -> None:
    """ValueError naming the flag when one task asks for more CPUs (default 1), GPUs or memory than the cluster's
    largest live node has (Ray would queue it forever; an autoscaler's future nodes do not count)."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive", True)] or [ray.cluster_resources()]
    for key, resource, unit, scale in (("num_cpus", "CPU", "CPUs", 1), ("num_gpus", "GPU", "GPUs", 1),
                                       ("memory", "memory", "GiB", 2**30)):
        asked = task_resources.get(key, 1 if key == "num_cpus" else 0)
        most = max(node.get(resource, 0) for node in nodes)
        if asked > most:
            given = "" if key in task_resources else " (the default)"
            raise ValueError(f"{TASK_RESOURCE_FLAGS[key]} {asked / scale:g}{given}: one task asks for {asked / scale:g} "
                             f"{unit}, the Ray cluster's largest node has {most / scale:g} {unit} (it would wait forever)")


class RayBackend(SerialBackend):
    """Ray tasks on a local instance or a cluster (optional ``ray`` extra).

    Args:
        workers: tasks in flight at once (chunk counts are chosen from it); a new local instance
            gets this many CPUs. Default: the cluster's CPUs.
        address: the cluster to join (``"host:6379"``, ``"ray://host:10001"``, ``"auto"``; default
            :func:`ray_address`). Joining never passes ``num_cpus`` (the cluster has its own). Without
            one, a NEW local instance is started on 127.0.0.1 (``address="local"``), even when a Ray
            head runs on this machine: a local run never joins a cluster it was not pointed at.
        runtime_env: Ray's runtime environment for the tasks (e.g. ``{"working_dir": "."}`` to ship a
            user's specs and models to a cluster); a local instance's workers get this process's
            ``sys.path`` by default.
        task_resources: what one task asks for (``{"num_cpus": 1, "num_gpus": 0.5, "memory": 2**30}``).

    ``runtime_env`` and ``task_resources`` left None take the enclosing :func:`ray_options`' values.
    """

    name = "ray"

    def __init__(self, workers: int | None = None, address: str | None = None, runtime_env: dict | None = None,
                 task_resources: dict | None = None):
        try:
            import ray
        except ImportError as exc:
            raise ImportError("backend 'ray' needs Ray: pip install 'hybridctl[ray]' (in a checkout: "
                              "pip install -c constraints.txt -e '.[ray]')") from exc
        if workers is not None and (not isinstance(workers, int) or isinstance(workers, bool) or workers < 1):
            raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
        defaults = _RAY_OPTIONS.get()
        runtime_env = check_runtime_env(runtime_env if runtime_env is not None else defaults.get("runtime_env"))
        task_resources = check_task_resources(task_resources if task_resources is not None
                                              else defaults.get("task_resources"))
        self._ray = ray
        self._started_here = not ray.is_initialized()
        given, address = address, ray_address(address)
        if self._started_here:
            if address is None:
                # a new local instance on loopback only; workers import what this process imports
                # (a user's runtime_env is kept, with this PYTHONPATH added unless it sets its own)
                env = dict(runtime_env or {})
                env["env_vars"] = {"PYTHONPATH": os.pathsep.join(p for p in sys.path if p), **env.get("env_vars", {})}
                ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False,
                         _node_ip_address="127.0.0.1", runtime_env=env)
            else:              # an address that does not answer is refused before ray.init waits on it
                check_ray_address(address, shown=address if given else f"RAY_ADDRESS={address}")
                ray.init(address=address, log_to_driver=False, runtime_env=runtime_env)
        try:
            check_fits_cluster(ray, task_resources or {})
        except ValueError:
            self.close()
            raise
        cluster_cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.workers = workers or cluster_cpus
        self.task_resources = dict(task_resources or {})
        if runtime_env is not None and not self._started_here:
            # Ray was started before (a notebook's ray.init): the env goes with each task instead
            self.task_resources["runtime_env"] = runtime_env
        self._remote: dict[Callable, Any] = {}

    def put(self, value: Any) -> Any:
        """``value`` in Ray's object store once (``ray.put``): tasks given the reference receive the value,
        without a copy per task."""
        return self._ray.put(value)

    def _submit(self, fn: Callable, tasks: Sequence) -> list:
        """``fn`` over ``tasks`` as Ray tasks (each asking for ``task_resources``; a task whose worker
        died is retried by Ray, ``max_retries``); their object references, in task order."""
        if fn not in self._remote:
            self._remote[fn] = self._ray.remote(max_retries=3, **self.task_resources)(fn)
        return [self._remote[fn].remote(t) for t in tasks]

    def map(self, fn: Callable, tasks: Sequence) -> list:
        """Results of ``fn`` over ``tasks`` as Ray tasks, in task order."""
        return self._ray.get(self._submit(fn, tasks))

    def imap_unordered(self, fn: Callable, tasks: Sequence) -> Iterator:
        """``fn`` over ``tasks`` as Ray tasks, each result as soon as its task is done (``ray.wait``)."""
        waiting = self._submit(fn, tasks)
        while waiting:
            done, waiting = self._ray.wait(waiting, num_returns=1)
            yield self._ray.get(done[0])

    def close(self) -> None:
        """Shut Ray down if this backend started it."""
        if self._started_here and self._ray.is_initialized():
            self._ray.shutdown()


def make_backend(name: str = "processes", workers: int | None = None, address: str | None = None,
                 task_resources: dict | None = None, runtime_env: dict | None = None):
    """A rollout backend by name: "serial", "processes" (default) or "ray" (``address`` for a cluster,
    default ``RAY_ADDRESS``; ``task_resources`` and ``runtime_env``: see :class:`RayBackend`).

    An ``address``, task resources or a runtime env with a local backend is refused (ValueError): it
    would be silently ignored.
    """
    for flag, value in (("address", address), ("task_resources", task_resources), ("runtime_env", runtime_env)):
        if value is not None and name in ("serial", "processes"):
            raise ValueError(f"{flag} {value!r} (--{flag.replace('_', '-')}) applies to backend 'ray' only, "
                             f"not {name!r}")
    if name == "serial":
        return SerialBackend()
    if name == "processes":
        return ProcessBackend(workers)
    if name == "ray":
        return RayBackend(workers, address, runtime_env, task_resources)
    raise ValueError(f"backend must be one of {BACKENDS}, got {name!r}")


def _worker_count(text: str) -> int:
    """argparse type of ``--workers``: an integer > 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


_worker_count.__name__ = "int"   # argparse names the type in "invalid int value"


def add_backend_arguments(parser: argparse.ArgumentParser, default: str | None, what: str,
                          workers: int | None = None) -> None:
    """``--backend``, ``--workers`` and ``--address``: where ``what`` runs, the same three flags on every
    ``hybridctl`` command and ``hybridctl.reproduce`` driver that runs parallel work (each adds its own
    ``--force``, which :func:`check_backend_arguments` reads). ``default``: the backend without the flag;
    ``workers``: the worker count without the flag (None: all cores, or the Ray cluster's CPUs).
    ``--address`` defaults to ``RAY_ADDRESS``; with ``--backend ray`` and no address a new local Ray
    instance on 127.0.0.1 is started, never a running one joined."""
    parser.add_argument("--backend", choices=BACKENDS, default=default,
                        help=f"where {what} runs: this process, local worker processes or Ray (default {default})")
    shown = workers if workers is not None else "all cores, or the cluster's CPUs"
    parser.add_argument("--workers", type=_worker_count, default=workers,
                        help=f"worker processes, or Ray tasks in flight (default: {shown}; local workers above "
                             f"the cores are refused without --force)")
    parser.add_argument("--address", default=None,
                        help="Ray cluster to join with --backend ray (host:6379, ray://host:10001, auto; "
                             "default: $RAY_ADDRESS, else a new local instance)")


def check_backend_arguments(backend: str | None, workers: int | None, address: str | None, force: bool) -> None:
    """Refuse (ValueError, naming the flag) ``--address`` without ``--backend ray`` and, unless ``force``,
    local ``--workers`` above the cores this process may use (Ray workers are not bound by local cores).
    ``workers``: the count the user gave, None where they gave none."""
    if address is not None and backend != "ray":
        raise ValueError(f"--address {address} applies to --backend ray only, not "
                         f"{backend or 'the default backend'!r}")
    if workers is not None and backend != "ray":
        check_at_most("--workers", workers, cpu_count(), force, why="cores this process may use")
