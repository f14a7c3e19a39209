"""Scripts just work: the process backend names a missing ``if __name__ == "__main__":`` guard in one line."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

UNGUARDED = """\
from hybridctl.parallel import ProcessBackend

with ProcessBackend(workers=1) as backend:
    print(backend.map(abs, [-1, -2]))
"""

GUARDED = """\
from hybridctl.parallel import ProcessBackend


def main():
    with ProcessBackend(workers=1) as backend:
        print(backend.map(abs, [-1, -2]))


if __name__ == "__main__":
    main()
"""

UNGUARDED_BALANCE_MAP = """\
from hybridctl.experiments import balance_map

balance_map("pendulum", "energy", grid=2, duration=0.2, workers=2, progress=False)
"""


def run_script(tmp_path, source):
    script = tmp_path / "script.py"
    script.write_text(source)
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)


@pytest.mark.parametrize("source, line", [(UNGUARDED, 4), (UNGUARDED_BALANCE_MAP, 3)])
def test_an_unguarded_script_gets_one_line_naming_the_guard(tmp_path, source, line):
    out = run_script(tmp_path, source)
    assert out.returncode != 0
    message = [l for l in out.stderr.splitlines() if l.startswith("RuntimeError")]
    assert len(message) == 1, out.stderr
    assert f"script.py:{line} starts worker processes outside 'if __name__ == \"__main__\":'" in message[0]
    assert "workers died" not in out.stderr  # the cause, not the symptom


def test_a_guarded_script_runs_its_workers(tmp_path):
    out = run_script(tmp_path, GUARDED)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[1, 2]"


def test_no_check_outside_scripts():
    from hybridctl.parallel import unguarded_script_line

    assert unguarded_script_line() is None  # under pytest, whose entry point is guarded
    code = textwrap.dedent("""
        from hybridctl.parallel import unguarded_script_line
        print(unguarded_script_line())
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "None"  # python -c: no script file to re-import


def test_a_script_read_from_standard_input_is_refused_before_workers_start():
    """``python -`` names its main script '<stdin>': spawned workers cannot re-import it and would die at
    start-up (a multiprocessing Pool then starts new ones forever)."""
    code = textwrap.dedent("""
        from hybridctl.parallel import ProcessBackend
        try:
            ProcessBackend(workers=2).map(abs, [-1, -2])
        except RuntimeError as exc:
            print(exc)
    """)
    out = subprocess.run([sys.executable, "-"], input=code, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "'<stdin>', which spawned worker processes cannot re-import" in out.stdout


# --------------------------------------------------------------------------- workers die with their parent
POOL_PARENT = """\
import sys, time
from hybridctl.parallel import ProcessBackend

if __name__ == "__main__":
    backend = ProcessBackend(workers=2)
    backend.map(abs, [-1, -2, -3, -4])
    print(*backend._pool._processes, flush=True)   # the worker pids
    time.sleep(600)                                # blocked, as a run killed mid-way
"""

WATCHED_PARENT = """\
import multiprocessing as mp, os, sys, time
from hybridctl.parallel import die_with_parent

def child(parent, pdeathsig):
    die_with_parent(parent, pdeathsig)
    time.sleep(600)

if __name__ == "__main__":
    worker = mp.get_context("spawn").Process(target=child, args=(os.getpid(), sys.argv[1] == "1"))
    worker.start()
    time.sleep(1.0)                                # the initializer has run
    print(worker.pid, flush=True)
    time.sleep(600)
"""


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie left for a reaper that never comes counts as dead)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _kill_parent_and_watch(tmp_path, source: str, *args: str, within: float = 5.0) -> list[int]:
    """Run ``source`` as a parent script, read its workers' pids, kill -9 it; return the pids still alive
    ``within`` seconds later."""
    import os
    import signal
    import time

    script = tmp_path / "parent.py"
    script.write_text(source)
    parent = subprocess.Popen([sys.executable, str(script), *args], stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert pids and all(_alive(p) for p in pids), pids
    finally:
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
    deadline = time.monotonic() + within
    while time.monotonic() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.05)
    alive = [p for p in pids if _alive(p)]
    for p in alive:  # do not leave them behind when the test fails
        os.kill(p, signal.SIGKILL)
    return alive


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.timeout(60)
def test_process_workers_die_with_a_killed_parent(tmp_path):
    """kill -9 of a run with --backend processes left a ~470 MB worker behind, blocked for ever."""
    assert _kill_parent_and_watch(tmp_path, POOL_PARENT) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.timeout(60)
@pytest.mark.parametrize("pdeathsig", ["1", "0"], ids=["prctl", "watcher-thread"])
def test_each_way_of_dying_with_the_parent_works_alone(tmp_path, pdeathsig):
    """The kernel's parent-death signal, and the portable fallback (a thread polling getppid)."""
    assert _kill_parent_and_watch(tmp_path, WATCHED_PARENT, pdeathsig) == []



# 127.0.0.1, ::ffff:127.0.0.1 and ::1 as /proc/net writes them
LOOPBACK = {"0100007F", "0000000000000000FFFF00000100007F", "00000000000000000000000001000000"}


def _square(x):
    """A task for the Ray workers (a module function: Ray cannot wrap a builtin)."""
    return x * x


def _listening_sockets() -> dict[int, tuple[str, int]]:
    """Socket inode -> (address, port) of every listening TCP socket on this machine, from /proc/net."""
    found = {}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = open(table).read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            if fields[3] == "0A":                                   # LISTEN
                address, port = fields[1].split(":")
                found[int(fields[9])] = (address, int(port, 16))
    return found


def _sockets_of_processes(marker: str) -> set[int]:
    """Socket inodes held open by the processes whose command line contains ``marker``."""
    import os

    inodes = set()
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            if marker not in open(f"/proc/{pid}/cmdline", "rb").read().decode(errors="replace"):
                continue
            for fd in os.listdir(f"/proc/{pid}/fd"):
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
                if target.startswith("socket:["):
                    inodes.add(int(target[8:-1]))
        except OSError:        # the process ended or is not ours
            continue
    return inodes


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.xdist_group("ray")
def test_the_local_ray_instance_listens_on_loopback_only_and_the_backend_joins_it(local_ray):
    """The Ray instance the tests start binds to 127.0.0.1 only (no Ray process listens on another address),
    and the ray backend joins an instance that is already running without passing num_cpus (which Ray
    refuses) and leaves it running."""
    from hybridctl.parallel import make_backend

    with make_backend("ray", workers=2) as backend:
        assert backend.map(_square, [-1, 2, -3]) == [1, 4, 9]
    assert local_ray.is_initialized() and local_ray.cluster_resources().get("CPU") == 2
    assert local_ray.get_runtime_context().gcs_address.startswith("127.0.0.1:")
    listening = _listening_sockets()
    ray_listening = {listening[inode] for inode in _sockets_of_processes("ray") if inode in listening}
    assert ray_listening, "found no listening socket of a Ray process"
    public = {(address, port) for address, port in ray_listening if address not in LOOPBACK}
    assert not public, public


def _worker_facts(name: str) -> dict:
    """What a pool worker sees: its parent, one environment variable, whether Drake came preloaded."""
    import os
    return {"ppid": os.getppid(), "env": os.environ.get(name), "drake_preloaded": "pydrake.all" in sys.modules,
            "pid": os.getpid()}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fork server is Linux's start method here")
@pytest.mark.timeout(120)
def test_pool_workers_fork_from_a_preloaded_server_and_see_the_environment_as_the_pool_starts(monkeypatch):
    """Each spawned worker spent 2-3 s importing torch and Drake; workers now fork from one server that imported
    them once. A server started earlier must not hand a later pool its old environment."""
    import os

    from hybridctl.parallel import ProcessBackend
    monkeypatch.delenv("HYBRIDCTL_TEST_POOL_VALUE", raising=False)
    with ProcessBackend(workers=1) as backend:
        first = backend.map(_worker_facts, ["HYBRIDCTL_TEST_POOL_VALUE"])[0]
    monkeypatch.setenv("HYBRIDCTL_TEST_POOL_VALUE", "set after the server started")
    with ProcessBackend(workers=1) as backend:
        second = backend.map(_worker_facts, ["HYBRIDCTL_TEST_POOL_VALUE"])[0]
    assert first["env"] is None and second["env"] == "set after the server started"
    assert first["ppid"] == second["ppid"] != os.getpid() and first["pid"] != second["pid"]
    assert "forkserver" in open(f"/proc/{first['ppid']}/cmdline", "rb").read().decode(errors="replace")
    assert first["drake_preloaded"] and second["drake_preloaded"]
