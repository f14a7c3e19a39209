"""Pointing at a Ray cluster, as a cluster user would (issue: a running head made `--workers` fail with
"num_cpus ... must not be provided", and a run without an address silently joined that head)."""

import json
import os
import shutil
import socket
import subprocess
import sys
import signal
import textwrap
import time

import pytest

pytest.importorskip("ray")
RAY = shutil.which("ray", path=os.path.dirname(sys.executable))

PROBE = textwrap.dedent("""
    import json, sys, ray
    from hybridctl.parallel import make_backend
    address, workers = sys.argv[1] or None, int(sys.argv[2]) if sys.argv[2] else None

    def square(x):
        return x * x

    with make_backend("ray", workers=workers, address=address) as backend:
        out = {"workers": backend.workers, "cpus": ray.cluster_resources().get("CPU"),
               "gcs": ray.get_runtime_context().gcs_address, "squares": backend.map(square, [1, 2, 3])}
    print(json.dumps(out))
""")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_head():
    """A Ray head of 1 CPU on 127.0.0.1, started as a user starts one (`ray start --head`, Ray's default
    temp dir, so that a plain ``ray.init()`` on this machine would find and join it), and stopped
    with its processes (``--block``: they end with it) without touching any other Ray instance."""
    port = _free_port()
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    env.pop("RAY_ADDRESS", None)
    head = subprocess.Popen([RAY, "start", "--head", "--block", f"--port={port}", "--num-cpus=1",
                             "--include-dashboard=false", "--node-ip-address=127.0.0.1", "--disable-usage-stats"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:      # up when its GCS port answers
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.5)
    time.sleep(3)
    yield f"127.0.0.1:{port}", env
    head.send_signal(signal.SIGTERM)
    try:
        head.wait(timeout=60)
    except subprocess.TimeoutExpired:
        head.kill()


def _probe(address: str, workers: str, env: dict) -> dict:
    run = subprocess.run([sys.executable, "-c", PROBE, address, workers], capture_output=True, text=True,
                         env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.xdist_group("ray")
def test_workers_with_a_running_head_join_it_only_when_pointed_at_it(ray_head):
    address, env = ray_head
    joined = _probe(address, "2", env)                       # used to fail: num_cpus passed to a running cluster
    port = address.rsplit(":", 1)[1]
    assert joined["cpus"] == 1 and joined["gcs"].endswith(f":{port}") and joined["squares"] == [1, 4, 9]
    assert joined["workers"] == 2
    from_env = _probe("", "", {**env, "RAY_ADDRESS": address})   # RAY_ADDRESS, as `ray job submit` sets it
    assert from_env["gcs"].endswith(f":{port}") and from_env["workers"] == 1
    local = _probe("", "2", {k: v for k, v in env.items() if k != "RAY_ADDRESS"})
    assert not local["gcs"].endswith(f":{port}") and local["cpus"] == 2    # a new local instance, not the running head


def test_ray_only_settings_with_a_local_backend_are_refused():
    from hybridctl.parallel import make_backend
    with pytest.raises(ValueError, match=r"task_resources \{'num_gpus': 1\} \(--task-resources\) applies to "
                                         r"backend 'ray' only, not 'processes'"):
        make_backend("processes", task_resources={"num_gpus": 1})


def _task_view(_):
    """What a Ray task sees: its assigned resources and one env var (module level: Ray ships it by name)."""
    import ray
    return ray.get_runtime_context().get_assigned_resources(), os.environ.get("HYBRIDCTL_PROBE")


@pytest.mark.xdist_group("ray")
def test_ray_options_reach_every_task_of_a_backend_made_inside(local_ray):
    """``ray_options`` (the CLI's --task-cpus/--task-gpus/--task-memory/--runtime-env) sets what each task
    of a Ray backend made inside asks for and its env, also when Ray was started before (per task)."""
    from hybridctl.parallel import make_backend, ray_options
    with ray_options(task_resources={"num_cpus": 2}, runtime_env={"env_vars": {"HYBRIDCTL_PROBE": "yes"}}):
        backend = make_backend("ray")
    resources, probe = backend.map(_task_view, [0])[0]
    assert resources.get("CPU") == 2 and probe == "yes"
    plain = make_backend("ray")                      # outside the block: Ray's defaults
    resources, probe = plain.map(_task_view, [0])[0]
    assert resources.get("CPU") == 1 and probe is None


def test_ray_options_are_checked_first():
    from hybridctl.parallel import ray_options
    with pytest.raises(ValueError, match="task_resources key 'gpus'"):
        with ray_options(task_resources={"gpus": 1}):
            pass
    with pytest.raises(ValueError, match=r"task_resources\['num_cpus'\] \(--task-cpus\) must be a finite number >= 0"):
        with ray_options(task_resources={"num_cpus": -1}):
            pass
    with pytest.raises(ValueError, match="runtime_env key 'pip_packages'"):
        with ray_options(runtime_env={"pip_packages": ["x"]}):
            pass


def test_cli_ray_task_flags(tmp_path):
    """The shared flags: refused without --backend ray, values checked, a file read within its limit."""
    import argparse
    from hybridctl.cli._common import add_backend_flags, check_backend_flags, ray_task_options
    parser = argparse.ArgumentParser()
    add_backend_flags(parser, "serial", "work")
    parser.add_argument("--force", action="store_true")
    args = parser.parse_args(["--task-gpus", "0.5"])
    with pytest.raises(ValueError, match="--task-gpus applies to --backend ray only, not 'serial'"):
        check_backend_flags(args)
    env_file = tmp_path / "env.json"
    env_file.write_text('{"working_dir": "."}')
    args = parser.parse_args(["--backend", "ray", "--task-cpus", "2", "--task-memory", "0.5",
                              "--runtime-env", str(env_file)])
    check_backend_flags(args)
    assert ray_task_options(args) == {"task_resources": {"num_cpus": 2.0, "memory": 2**29},
                                      "runtime_env": {"working_dir": "."}}
    env_file.write_text(" " * (64 * 1024 + 1))
    with pytest.raises(ValueError, match="at most 65,536 bytes"):
        check_backend_flags(parser.parse_args(["--backend", "ray", "--runtime-env", str(env_file)]))
    with pytest.raises(ValueError, match="not valid JSON"):
        check_backend_flags(parser.parse_args(["--backend", "ray", "--runtime-env", "{nope"]))


def test_train_cli_gives_ray_task_flags_to_the_learners_backends(monkeypatch, tmp_path):
    """``hybridctl train ars ... --backend ray --task-cpus 2 --runtime-env JSON``: the learner's backends
    are made inside ray_options with those values (seen from a stand-in for the training driver)."""
    from hybridctl import parallel
    from hybridctl.cli import main, train as train_cli
    seen = {}

    def fake_train(*args, **kwargs):
        seen.update(parallel._RAY_OPTIONS.get())
        raise ValueError("stop here")
    monkeypatch.setattr(train_cli, "train_and_evaluate", fake_train)
    with pytest.raises(SystemExit, match="stop here"):
        main(["train", "ars", "Pendulum-v1", "--backend", "ray", "--task-cpus", "2", "--task-gpus", "0.25",
              "--runtime-env", '{"env_vars": {"A": "1"}}', "--out", str(tmp_path / "run")])
    assert seen == {"task_resources": {"num_cpus": 2.0, "num_gpus": 0.25}, "runtime_env": {"env_vars": {"A": "1"}}}
    with pytest.raises(SystemExit, match="--task-gpus applies to --backend ray only, not 'processes'"):
        main(["train", "ars", "Pendulum-v1", "--task-gpus", "1", "--out", str(tmp_path / "r2")])


def test_finetune_cli_takes_the_shared_backend_flags_and_a_device(monkeypatch, tmp_path):
    """``hybridctl finetune`` has the same --backend/--workers/--address/--task-* flags as the other commands
    and --device; the config and the Ray options reach the driver (seen from a stand-in)."""
    from hybridctl import parallel
    from hybridctl.cli import finetune as finetune_cli, main
    seen = {}

    def fake(env, policy, out, config, **kwargs):
        seen.update(options=parallel._RAY_OPTIONS.get(), config=config)
        raise ValueError("stop here")
    monkeypatch.setattr(finetune_cli, "finetune_and_report", fake)
    with pytest.raises(SystemExit, match="stop here"):
        main(["finetune", "pendulum", "--policy", "ssac:x", "--backend", "ray", "--address", "auto",
              "--task-gpus", "0.5", "--device", "cpu", "--out", str(tmp_path / "f")])
    assert seen["options"] == {"task_resources": {"num_gpus": 0.5}}
    assert seen["config"].device == "cpu" and seen["config"].address == "auto" and seen["config"].chunk_size is None
    with pytest.raises(SystemExit, match="--address auto applies to --backend ray only"):
        main(["finetune", "pendulum", "--policy", "ssac:x", "--address", "auto", "--out", str(tmp_path / "g")])


# ------------------------------------------------------------------ every wait has a stated limit (issue 47)
UNREACHABLE = textwrap.dedent("""
    import contextlib, io, json, socket, sys, threading, time
    case = sys.argv[1]

    def closed_port():
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    def listener(reply):
        server = socket.socket()
        server.bind(("127.0.0.1", 0))
        server.listen()
        def serve():
            kept = []
            while True:
                conn, _ = server.accept()
                if reply == "close":
                    conn.close()
                else:
                    kept.append(conn)          # accepts and says nothing
        threading.Thread(target=serve, daemon=True).start()
        return server.getsockname()[1]

    import hybridctl.parallel as parallel
    address = {"closed": lambda: f"127.0.0.1:{closed_port()}", "unknown": lambda: "nohost.invalid:6379",
               "client": lambda: f"ray://127.0.0.1:{closed_port()}", "env": lambda: None,
               "not-ray": lambda: f"127.0.0.1:{listener('close')}", "silent": lambda: f"127.0.0.1:{listener('wait')}",
               "cli": lambda: None}[case]()
    parallel.RAY_CONNECT_TIMEOUT_S = 1.0       # the silent listener: refused after the (shortened) limit
    import ray                                 # imports are not the wait measured
    if case == "cli":
        import hybridctl.cli
    start = time.monotonic()
    try:
        if case == "cli":
            from hybridctl.cli import main
            err = io.StringIO()
            with contextlib.redirect_stderr(err):
                main(["balance-map", "pendulum", "--grid", "2", "--duration", "0.1", "--backend", "ray",
                      "--address", "nohost.invalid:6379", "--out", sys.argv[2]])
            out = {"error": None}
        else:
            parallel.make_backend("ray", address=address).close()
            out = {"error": None}
    except SystemExit as exc:
        out = {"error": "SystemExit", "code": exc.code, "message": err.getvalue()}
    except Exception as exc:
        out = {"error": type(exc).__name__, "message": str(exc), "value_or_os": isinstance(exc, (ValueError, OSError))}
    out["seconds"] = time.monotonic() - start
    print(json.dumps(out))
""")
UNREACHABLE_CASES = ("closed", "unknown", "client", "env", "not-ray", "silent", "cli")


@pytest.fixture(scope="module")
def unreachable(tmp_path_factory):
    """Each case's outcome (probe subprocesses run side by side: a regression waits, it does not hang the
    session: each is stopped after 60 s and reported as such)."""
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_ADDRESS": ""}
    runs = {}
    for case in UNREACHABLE_CASES:
        case_env = {**env, "RAY_ADDRESS": "nohost.invalid:6379"} if case == "env" else env
        runs[case] = subprocess.Popen([sys.executable, "-c", UNREACHABLE, case, str(tmp_path_factory.mktemp(case))],
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=case_env)
    outcomes = {}
    for case, run in runs.items():
        try:
            out, err = run.communicate(timeout=60)
            outcomes[case] = json.loads(out.strip().splitlines()[-1]) if out.strip() else {"error": "crash", "stderr": err[-2000:]}
        except subprocess.TimeoutExpired:
            run.kill()
            run.communicate()
            outcomes[case] = {"error": "still waiting after 60 s"}
    return outcomes


# one xdist worker runs the tests of the probes, so the module fixture starts its 7 interpreters once, not per worker
@pytest.mark.timeout(120)
@pytest.mark.xdist_group("unreachable")
@pytest.mark.parametrize("case, words", [
    ("closed", ["127.0.0.1:", "refused"]), ("unknown", ["nohost.invalid", "unknown host"]),
    ("client", ["ray://127.0.0.1:", "refused"]), ("env", ["RAY_ADDRESS", "nohost.invalid"]),
    ("not-ray", ["not as a Ray cluster"]), ("silent", ["not as a Ray cluster", "1 s"]),
])
def test_an_unreachable_cluster_is_refused_in_one_line_within_the_stated_limit(unreachable, case, words):
    """A closed port, an unknown host (the reserved .invalid TLD), a bogus RAY_ADDRESS, a port that is not a
    Ray head: refused before ray.init, in one line naming the address (Ray itself waited 70 s or more)."""
    out = unreachable[case]
    assert out["error"] == "ConnectionError" and out["value_or_os"], out
    assert "\n" not in out["message"] and all(w in out["message"] for w in words), out
    assert out["seconds"] < 5, out


@pytest.mark.timeout(120)
@pytest.mark.xdist_group("unreachable")
def test_the_cli_refuses_an_unreachable_cluster_in_one_line(unreachable):
    out = unreachable["cli"]
    assert out["error"] == "SystemExit" and out["code"] == 2, out
    assert out["message"].count("\n") == 1 and "nohost.invalid" in out["message"] and "Traceback" not in out["message"]
    assert out["seconds"] < 10, out


@pytest.mark.timeout(60)
@pytest.mark.xdist_group("ray")
@pytest.mark.parametrize("resources, words", [
    ({"num_cpus": 1000}, ["--task-cpus", "1000", "2 CPUs"]),
    ({"num_gpus": 1}, ["--task-gpus", "1", "0 GPUs"]),
    ({"memory": 1 << 45}, ["--task-memory", "32768 GiB"]),
])
def test_task_resources_above_the_clusters_are_refused_before_any_task_waits(local_ray, resources, words):
    """Ray queues a task that no node can hold forever; the backend refuses it when made (the session's
    instance has 2 CPUs, no GPU)."""
    from hybridctl.parallel import make_backend, ray_options
    start = time.monotonic()
    with pytest.raises(ValueError) as refused:
        with ray_options(task_resources=resources):
            make_backend("ray")
    message = str(refused.value)
    assert "\n" not in message and all(w in message for w in words), message
    assert time.monotonic() - start < 5


@pytest.mark.parametrize("resources, words", [
    ({"memory": 1e300}, ["task_resources['memory']", "--task-memory", "above its limit"]),
    ({"memory": 10**30}, ["--task-memory", "above its limit"]),
    ({"num_cpus": 1e6}, ["--task-cpus", "above its limit"]),
    ({"num_gpus": 0.00001}, ["--task-gpus", "0.0001"]),
    ({"num_cpus": True}, ["--task-cpus", "number"]),
])
def test_task_resources_are_checked_fully_before_ray_sees_them(resources, words):
    from hybridctl.parallel import check_task_resources
    with pytest.raises(ValueError) as refused:
        check_task_resources(resources)
    assert all(w in str(refused.value) for w in words), str(refused.value)


@pytest.mark.parametrize("env, words", [
    ({"env_vars": {"A": 1}}, ["runtime_env['env_vars']", "strings"]),
    ({"env_vars": ["A=1"]}, ["runtime_env['env_vars']", "strings"]),
    ({"pip": ["numpy"]}, ["'pip'", "pre-install"]),
    ({"uv": ["numpy"]}, ["'uv'", "pre-install"]),
    ({"conda": {"dependencies": ["numpy"]}}, ["'conda'", "pre-install"]),
    ({"container": {"image": "x"}}, ["'container'", "pre-install"]),
    ({"working_dir": 3}, ["runtime_env['working_dir']"]),
    ({"working_dir": "/nonexistent/hybridctl-folder"}, ["runtime_env['working_dir']", "/nonexistent"]),
    ({"py_modules": "mod"}, ["runtime_env['py_modules']", "list"]),
    ({"excludes": [1]}, ["runtime_env['excludes']", "list"]),
    ({"config": {"setup_timeout_seconds": "x"}}, ["setup_timeout_seconds"]),
    ({"config": {"retries": 1}}, ["runtime_env['config']", "retries"]),
])
def test_runtime_env_values_are_checked_before_ray_sees_them(env, words):
    from hybridctl.parallel import check_runtime_env
    with pytest.raises(ValueError) as refused:
        check_runtime_env(env)
    message = str(refused.value)
    assert "\n" not in message and all(w in message for w in words), message


def test_runtime_env_well_formed_values_pass(tmp_path):
    from hybridctl.parallel import check_runtime_env
    env = {"working_dir": str(tmp_path), "py_modules": [str(tmp_path)], "env_vars": {"A": "1"}, "excludes": ["*.npz"],
           "config": {"setup_timeout_seconds": 60, "eager_install": True}}
    assert check_runtime_env(env) == env


def test_cli_task_memory_overflow_is_one_line(cli_error):
    """--task-memory 1e300 (GiB) used to overflow converting to bytes (OverflowError, a traceback)."""
    err = cli_error(["balance-map", "pendulum", "--backend", "ray", "--task-memory", "1e300"])
    assert "--task-memory" in err and "limit" in err
