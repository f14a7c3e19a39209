"""Shared test setup: deterministic torch and a small thread count (CI has 2 cores)."""

import os
import tempfile

import numpy as np
import pytest
import torch

os.environ.setdefault("MPLBACKEND", "Agg")
# SB3's default logger makes an empty SB3-<date> folder per learn call where SB3_LOGDIR does not name one
os.environ.setdefault("SB3_LOGDIR", os.path.join(tempfile.gettempdir(), "hybridctl-tests-sb3-log"))
torch.set_num_threads(1)


@pytest.fixture
def rng():
    """A seeded numpy generator."""
    return np.random.default_rng(12345)


@pytest.fixture
def one_torch_thread():
    """One torch thread for the test (as the learners' records were made), restored afterwards."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def cli_error(capsys):
    """Run ``hybridctl ARGV`` in-process and return its stderr, asserting the bad-input contract:
    exit code 2 and no traceback. Use: ``assert "--duration" in cli_error([...])``."""
    from hybridctl.cli import main

    def run(argv):
        with pytest.raises(SystemExit) as stop:
            main([str(a) for a in argv])
        err = capsys.readouterr().err
        assert stop.value.code == 2, err
        assert "Traceback" not in err, err
        return err
    return run


# `make test` sets HYBRIDCTL_REQUIRE_EXTRAS to the extras it installed: a missing one is then an error at the
# start of the session, so the tests of its paths cannot quietly skip in CI (a skipped test proves nothing).
EXTRA_MODULES = {
    "test": ("pytest_timeout", "xdist", "nbclient", "nbformat", "ipykernel"),
    "sb3": ("stable_baselines3", "sb3_contrib"),
    "mujoco": ("mujoco", "mujoco.batch"),
    "ray": ("ray",),
    "docs": ("mkdocs", "mkdocstrings", "mkdocs_jupyter", "material"),
}


def pytest_sessionstart(session):
    """Refuse to run when an extra that ``make test`` installed cannot be imported."""
    import importlib

    required = [name for name in os.environ.get("HYBRIDCTL_REQUIRE_EXTRAS", "").split(",") if name]
    unknown = sorted(set(required) - set(EXTRA_MODULES))
    if unknown:
        raise pytest.UsageError(f"HYBRIDCTL_REQUIRE_EXTRAS names unknown extras {unknown}; known: {sorted(EXTRA_MODULES)}")
    missing = []
    for extra in required:
        for module in EXTRA_MODULES[extra]:
            try:
                importlib.import_module(module)
            except ImportError as exc:
                missing.append(f"{module} (extra '{extra}': {exc})")
    if missing:
        raise pytest.UsageError("HYBRIDCTL_REQUIRE_EXTRAS: not importable, so their tests would skip: "
                                + "; ".join(missing))


@pytest.fixture
def local_ray():
    """One real local Ray instance (2 CPUs, bound to 127.0.0.1, no dashboard), started by the first test that
    asks for it and shared by the next ones; stopped after the last test that may use it
    (:func:`pytest_runtest_teardown`) or at the end of the session.

    Tests that use it carry ``@pytest.mark.xdist_group("ray")`` so that ``make test`` (``--dist loadgroup``)
    runs them on one process, which starts the instance once. hybridctl's Ray backend joins a running
    instance (it passes no ``num_cpus``) and leaves it running. Skipped when Ray is not installed, which
    ``make test`` turns into an error (HYBRIDCTL_REQUIRE_EXTRAS)."""
    ray = pytest.importorskip("ray")
    import sys

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")     # nothing leaves the machine
    if not ray.is_initialized():
        # the workers import hybridctl and these test modules as this process does
        env = {"env_vars": {"PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}}
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
                 _node_ip_address="127.0.0.1", runtime_env=env)   # a new instance, never a head running here
        _LOCAL_RAY["started"] = True
    return ray


_LOCAL_RAY = {"started": False}
"""Whether :func:`local_ray` started the instance that is running now (it stops only that one)."""


def _stop_local_ray() -> None:
    if _LOCAL_RAY["started"]:
        import ray

        ray.shutdown()
        _LOCAL_RAY["started"] = False


def _may_use_local_ray(item) -> bool:
    return "local_ray" in getattr(item, "fixturenames", ()) or any(
        marker.args[:1] == ("ray",) for marker in item.iter_markers("xdist_group"))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
    """Stop the local Ray instance after the last test that may use it, not at the end of the session: its
    idle processes (raylet, GCS, workers) would take CPU from every later test. "Last" in collection order,
    which the process that runs the xdist group "ray" follows too; a later request would start it again."""
    yield
    if _LOCAL_RAY["started"] and _may_use_local_ray(item):
        items = item.session.items
        if not any(_may_use_local_ray(later) for later in items[items.index(item) + 1:]):
            _stop_local_ray()


def pytest_sessionfinish(session):
    """The local Ray instance, if a test started it and it still runs."""
    _stop_local_ray()


# The edit-test loop's tier (`make test-fast`): every test except the whole-workflow ones below, which
# `make test` (and CI) still runs. A file is heavy when its tests start kernels, subprocess commands, Ray
# or a wheel install, or train end to end; a single heavy test elsewhere carries @pytest.mark.heavy.
HEAVY_FILES = frozenset({
    "test_notebooks.py",        # a Jupyter kernel per chapter notebook
    "test_doc_blocks.py",       # every Python block of the README and the chapter pages
    "test_install.py",          # builds and installs the wheel
    "test_ray_cluster.py",      # a local Ray instance and ray start
    "test_apg_parallel.py",     # process pools and Ray
    "test_sb3_baselines.py",    # Stable-Baselines3 training runs
    "test_run_folders.py",      # concurrent training processes
    "test_device_balance_map.py", "test_device_apg.py", "test_device_finetune.py",   # every backend
})


HEAVY_TESTS = frozenset({
    # single tests over about 5 s on 2 busy cores (pytest --durations=0), each a whole workflow
    "test_multibody.py::test_the_command_line_trains_fine_tunes_and_simulates_a_multibody_system_by_name",
    "test_cli.py::test_demo_balances_the_acrobot_and_the_cartpole",
    "test_cli.py::test_mesh_writes_matrix_report_and_figures",
    "test_cli.py::test_debug_flag_shows_the_traceback",
    "test_cli.py::test_output_into_a_closed_pipe_is_not_an_error",
    "test_cli.py::test_balance_map_writes_png_and_json",
    "test_ssac.py::test_gate_is_refit_on_schedule_and_env_uses_it",
    "test_ssac.py::test_overlapped_gate_refit_gives_the_one_thread_numbers",
    "test_ssac.py::test_cli_train_resume_simulate_and_balance_map",
    "test_finetune.py::test_apg_source_rolls_out_what_apg_trains_recurrent_through_its_takeover",
    "test_finetune.py::test_same_seed_same_result_on_serial_and_processes_and_another_seed_differs",
    "test_finetune.py::test_cli_finetune_reports_before_and_after_and_resumes",
    "test_safe_runs.py::test_resume_applies_run_settings_and_refuses_changed_math_settings",
    "test_safe_runs.py::test_kill_9_ars_then_resume_continues_from_the_checkpoint",
    "test_ars.py::test_processes_and_serial_backends_agree",
    "test_hopper_section.py::test_mesh_on_worker_processes_matches_serial",
    "test_apg_study.py::test_sb3_learners_train_through_the_gym_wrapper_and_are_scored_by_the_same_code",
    "test_parallel.py::test_an_unguarded_script_gets_one_line_naming_the_guard",
    "test_compiled.py::test_compiled_sac_gradients_equal_eager",
    "test_drake_hybrid.py::test_balance_map_workers_keep_the_systems_overrides",
})
"""Single heavy tests outside :data:`HEAVY_FILES`, by ``file::name`` (every parametrisation of it)."""


SLOW_TESTS = frozenset({
    # moved out of `make test` to keep it under 5 minutes from a clean clone on 2 cores; `make test-all`
    # runs them. Each is a second check of a path other default tests cover (seconds: clean clone, idle).
    "test_compiled.py::test_compiled_sac_gradients_equal_eager",          # 14.7 s, cold torch.compile
    "test_compiled.py::test_compiled_switched_env_equals_eager",          # 8.9 s
    "test_compiled.py::test_compiled_gate_fit_follows_the_eager_fit",     # 6.5 s
    "test_multibody.py::test_the_command_line_trains_fine_tunes_and_simulates_a_multibody_system_by_name",  # 16.3 s
    "test_sb3_baselines.py::test_two_chunks_then_resume_trains_only_the_difference",   # 13 s setup
    "test_safe_runs.py::test_kill_9_ars_then_resume_continues_from_the_checkpoint",    # 6.7 s
    "test_run_folders.py::test_two_training_runs_started_together_one_refused_one_consistent_run",  # 7.4 s
    "test_drake_hybrid.py::test_balance_map_workers_keep_the_systems_overrides",       # 6.4 s
    # the CLI's SSAC train/resume/simulate/balance-map round trip: test_safe_runs' CLI SSAC resume,
    # test_cli's train/resume and its ssac:PATH simulate and balance-map runs cover each step
    "test_ssac.py::test_cli_train_resume_simulate_and_balance_map",                    # 6.0 s CPU (shared machine)
    # the finetune command: test_finetune_sb3's CLI run (report, before/after) and test_finetune's API resume
    "test_finetune.py::test_cli_finetune_reports_before_and_after_and_resumes",        # 8.6 s CPU (shared machine)
})
"""Tests marked slow here rather than in their files, by ``file::name``."""


def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`HEAVY_FILES` and :data:`HEAVY_TESTS` ``heavy`` (``make test-fast`` leaves
    them out); a name in HEAVY_TESTS that no longer exists is an error, so the list cannot rot."""
    collected = set()
    for item in items:
        name = f"{item.path.name}::{item.originalname}"
        collected.add(name)
        if item.path.name in HEAVY_FILES or name in HEAVY_TESTS:
            item.add_marker(pytest.mark.heavy)
        if name in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
    # a name is stale when its file's module lacks it (not when a node id or -k selected other tests only)
    modules = {item.path.name: item.module for item in items if getattr(item, "module", None) is not None}
    stale = sorted(t for t in HEAVY_TESTS | SLOW_TESTS
                   if t.split("::")[0] in modules and t not in collected
                   and not hasattr(modules[t.split("::")[0]], t.split("::")[1]))
    if stale:
        raise pytest.UsageError(f"tests/conftest.py HEAVY_TESTS / SLOW_TESTS name tests that do not exist: {stale}")
