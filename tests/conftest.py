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
    "test_xdist_groups.py",     # an inner pytest session on 2 processes (1 to 20 s on the shared machine)
    "test_fit.py",              # a module fixture runs hybridctl fit's stages (about 14 s)
    "test_learned_gate_basin.py",   # warm-started gates measured on the furuta (about 15 s)
})
"""Files whose tests are all heavy; so is every test of the xdist group "ray" (it starts Ray)."""


HEAVY_TESTS = frozenset({
    # single tests over about 5 s on 2 busy cores (pytest --durations=0), each a whole workflow
    "test_multibody.py::test_the_command_line_trains_fine_tunes_and_simulates_a_multibody_system_by_name",
    "test_cli.py::test_demo_balances_the_acrobot_and_the_cartpole",
    "test_cli.py::test_debug_flag_shows_the_traceback",
    "test_cli.py::test_output_into_a_closed_pipe_is_not_an_error",
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
    # about 1 s of CPU or more each (all parametrisations together for the many-case ones), so that
    # `make test-fast` stays near a minute; each file keeps its quicker tests there
    "test_apg.py::test_benchmark_reports_ratios_and_batched_equals_loop",                 # a subprocess
    "test_apg.py::test_ce_apg_improves_a_short_pendulum_swing_up",
    "test_apg_study.py::test_run_one_writes_a_record_and_resumes_by_skipping",
    "test_architecture.py::test_light_rooms_do_not_load_heavy_dependencies",             # subprocesses
    "test_architecture.py::test_learners_and_their_plots_do_not_need_drake",             # subprocesses
    "test_bad_checkpoints.py::test_every_key_set_to_a_hostile_value_loads_or_raises_the_documented_error",  # 185
    "test_bad_input.py::test_cli_rejects_bad_input_in_one_line",                          # 57 command lines
    "test_balance_engines.py::test_both_engines_agree_on_a_grid",
    "test_cli.py::test_mesh_compass_gait_coarse",
    "test_cli.py::test_train_spec_overrides_are_recorded_and_checked_on_resume",
    "test_cli.py::test_train_sac_set_flags_resume_in_process",
    "test_cli.py::test_train_reward_flag_goes_with_spec_overrides",
    "test_cli.py::test_version_and_help_examples_parse_as_printed",
    "test_device_ssac.py::test_ssac_warm_starts_trains_and_refits_with_every_tensor_on_its_device",
    "test_drake_sections.py::test_compass_gait_parameters_are_set_and_checked",
    "test_drake_sections.py::test_compass_gait_hip_pd_changes_the_gait",
    "test_finetune.py::test_apg_source_fine_tunes_saves_and_drives_drake",
    "test_finetune.py::test_a_system_checkpoint_is_tuned_on_the_reward_and_starts_it_was_trained_on",
    "test_finetune.py::test_ssac_source_fine_tunes_the_swing_up_inside_the_switched_controller",
    "test_finetune.py::test_a_fine_tuned_checkpoint_loads_from_any_working_folder",
    "test_finetune_agents.py::test_one_agent_files_record_and_resume",
    "test_finetune_sb3.py::test_cli_fine_tunes_a_zip_and_sb3_loads_the_result",
    "test_hostile_files.py::test_a_spoiled_sb3_zip_gives_one_line",                        # 26 zips
    "test_hostile_files.py::test_twenty_thousand_welded_links_are_refused_before_drake_parses_them",
    "test_markov.py::test_near_singular_chain_fails_fast_with_a_message",
    "test_matrix.py::test_a_second_driver_writing_the_matrix_is_refused_at_once",
    "test_mesh_report_backends.py::test_monte_carlo_and_sizes_use_the_backend_and_give_the_same_numbers",  # 10 pools
    "test_multibody.py::test_the_acrobot_urdf_swings_up_like_the_chain_acrobot_on_both_engines",
    "test_multibody.py::test_a_tampered_cache_entry_is_derived_anew_with_one_warning",
    "test_reachable.py::test_mfpt_vs_roughness_sweep_writes_record_and_skips_unaffordable_monte_carlo",
    "test_reachable.py::test_refinement_stops_at_its_cap_and_calls_a_never_failing_chain_infinite",
    "test_sac.py::test_resume_continues_steps_weights_and_replay",
    "test_sac.py::test_callback_objects_get_every_hook_with_the_agent",
    "test_sac.py::test_tiny_run_writes_progress_checkpoint_and_curves",
    "test_sac.py::test_same_seed_same_weights_different_seed_different",
    "test_safe_runs.py::test_a_folder_the_command_made_is_written_again",
    "test_safe_runs.py::test_mesh_refuses_a_folder_that_holds_a_run",
    "test_safe_runs.py::test_cli_resume_without_gate_data_refuses_before_training_and_force_continues",
    "test_sb3.py::test_module_imports_and_reads_zips_without_sb3",                        # a subprocess
    "test_shipped_models.py::test_shipped_ssac_cartpole_reproduces_its_evaluation_and_balances_from_hanging_down_in_drake",
    "test_ssac.py::test_save_load_keeps_policy_gate_and_resume_restores_gate_data",
    "test_ssac.py::test_same_seed_repeats",
    "test_ssac.py::test_nan_loss_stops_and_keeps_the_last_checkpoint",
    "test_ssac.py::test_a_failed_overlapped_refit_raises_in_training",
    "test_trajopt.py::test_cache_round_trips_and_refuses_corrupt_or_pickled_files",
    "test_trajopt.py::test_a_cache_entry_claiming_huge_gains_is_recomputed_without_allocating_them",
    "test_viz.py::test_acrobot_replay_renders_in_chromium",                               # headless Chromium
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


GROUPED_FILES = {
    "test_fit.py": "fit",       # two module fixtures run hybridctl fit's stages (about 100 s on 2 busy cores)
}
"""Files whose tests all go to one xdist process (``xdist_group``), so that their module-scoped fixtures run once
in ``make test``, not once on each of the two processes that the tests would otherwise be spread over."""


@pytest.hookimpl(tryfirst=True)     # before pytest-xdist's own hook reads the xdist_group markers
def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`HEAVY_FILES`, :data:`HEAVY_TESTS` and the Ray ones ``heavy`` (``make test-fast``
    leaves them out), those of :data:`SLOW_TESTS` ``slow`` and those of :data:`GROUPED_FILES` with their
    ``xdist_group``; a name in HEAVY_TESTS or SLOW_TESTS that no longer exists is an error, so the lists cannot
    rot."""
    collected = set()
    for item in items:
        name = f"{item.path.name}::{item.originalname}"
        collected.add(name)
        if item.path.name in GROUPED_FILES and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(GROUPED_FILES[item.path.name]))
        if item.path.name in HEAVY_FILES or name in HEAVY_TESTS or _may_use_local_ray(item):
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
