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
    with pytest.raises(ValueError, match=r"task_resources\['num_cpus'\] must be a finite number >= 0"):
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
