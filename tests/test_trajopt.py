"""The collocation swing-up tracked by TVLQR (hybridctl.drake.trajopt) and the ``trajopt`` controller.

Every test caches into its own tmp folder (``cache_dir`` or ``$HYBRIDCTL_CACHE``), so none reads a cache
another test or run wrote. The acrobot and the pendulum solve in well under a second each.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hybridctl import systems
from hybridctl.drake import trajopt
from hybridctl.drake.trajopt import TrajectoryTracker, TrajoptSettings, swingup_trajectory, tracking_gains


@pytest.fixture(scope="module")
def acrobot():
    return systems.load("acrobot")


@pytest.fixture(scope="module")
def pendulum():
    return systems.load("pendulum")


@pytest.fixture(scope="module")
def acrobot_swingup(acrobot, tmp_path_factory):
    folder = tmp_path_factory.mktemp("trajopt-cache")
    return swingup_trajectory(acrobot, cache_dir=folder), folder


def test_trajectory_satisfies_drakes_collocation_constraints_and_goes_from_hanging_down_to_the_goal(
        acrobot, acrobot_swingup):
    from pydrake.planning import DirectCollocationConstraint

    traj, _ = acrobot_swingup
    assert traj.solver == "SNOPT" and traj.attempts[-1]["solved"]
    # the acrobot's Drake plant measures th1 from hanging down: the spec's nominal and goal, converted
    np.testing.assert_allclose(traj.states[0], acrobot.to_drake_state(acrobot.initial_state.nominal), atol=1e-9)
    np.testing.assert_allclose(traj.states[-1], acrobot.to_drake_state(acrobot.goal), atol=1e-9)
    assert np.abs(traj.inputs).max() <= traj.settings.input_margin * acrobot.action_limit + 1e-6
    # Drake's own collocation constraint on every interval: variables (h, x_k, x_k+1, u_k, u_k+1)
    diagram, context = trajopt._plant_diagram(acrobot)
    constraint = DirectCollocationConstraint(diagram, context, input_port_index=diagram.get_input_port(0).get_index())

    def defects(states):
        return np.array([constraint.Eval(np.concatenate([[t1 - t0], x0, x1, u0, u1]))
                         for t0, t1, x0, x1, u0, u1 in zip(traj.times[:-1], traj.times[1:], states[:-1], states[1:],
                                                           traj.inputs[:-1], traj.inputs[1:])])

    assert np.abs(defects(traj.states)).max() < 1e-5
    moved = traj.states.copy()
    moved[len(moved) // 2, 1] += 0.01        # the check can fail: one knot off the dynamics
    assert np.abs(defects(moved)).max() > 1e-3


def test_cache_round_trips_and_refuses_corrupt_or_pickled_files(acrobot, acrobot_swingup, tmp_path):
    traj, folder = acrobot_swingup
    again = swingup_trajectory(acrobot, cache_dir=folder)
    assert again.cached and not traj.cached and again.path == traj.path
    for name in ("times", "states", "derivatives", "inputs"):
        np.testing.assert_array_equal(getattr(again, name), getattr(traj, name))
    assert again.solve_time == traj.solve_time and again.attempts == traj.attempts
    gains = tracking_gains(acrobot, traj, cache_dir=folder)
    gains_again = tracking_gains(acrobot, again, cache_dir=folder)
    assert gains_again.cached and not gains.cached
    np.testing.assert_array_equal(gains_again.K, gains.K)
    np.testing.assert_array_equal(gains_again.x0, gains.x0)

    # another folder: a truncated file is refused (a warning), solved again and rewritten
    copy = tmp_path / traj.path.name
    copy.write_bytes(traj.path.read_bytes()[:200])
    with pytest.warns(UserWarning, match="cannot be used"):
        fresh = swingup_trajectory(acrobot, cache_dir=tmp_path)
    assert not fresh.cached and fresh.path == copy
    np.testing.assert_allclose(fresh.states, traj.states, atol=1e-6)
    assert swingup_trajectory(acrobot, cache_dir=tmp_path).cached

    # a file holding a pickled object under the right names is refused without unpickling it
    marker = tmp_path / "unpickled"
    arrays = dict(np.load(traj.path, allow_pickle=False))
    arrays["states"] = np.array([_Unpickle(str(marker))], dtype=object)
    with open(copy, "wb") as f:
        np.savez(f, **arrays)
    with pytest.warns(UserWarning, match="cannot be used"):
        assert not swingup_trajectory(acrobot, cache_dir=tmp_path).cached
    assert not marker.exists()

    # a file under the right name whose key or shapes do not match is refused too
    arrays = dict(np.load(traj.path, allow_pickle=False))
    with open(copy, "wb") as f:
        np.savez(f, **{**arrays, "inputs": arrays["inputs"][:-1]})
    with pytest.warns(UserWarning, match="shape"):
        assert not swingup_trajectory(acrobot, cache_dir=tmp_path).cached


class _Unpickle:
    """An object whose unpickling leaves a file behind: proof that a cache read unpickled."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_cache_key_follows_the_spec_and_the_settings(acrobot):
    base = trajopt.cache_key(acrobot, {"knots": 41})
    assert trajopt.cache_key(acrobot, {"knots": 31}) != base
    assert trajopt.cache_key(systems.load("acrobot", action__limit=20.0), {"knots": 41}) != base
    assert trajopt.cache_key(systems.load("acrobot"), {"knots": 41}) == base


def test_tracker_reads_the_time_from_its_context(acrobot, acrobot_swingup):
    traj, folder = acrobot_swingup
    gains = tracking_gains(acrobot, traj, cache_dir=folder)
    block = TrajectoryTracker(acrobot, traj, gains)
    assert block.get_input_port(0).get_name() == "state" and block.get_output_port(0).get_name() == "command"
    assert len(gains.x0) == round(traj.duration / acrobot.control_period) + 1
    k = len(gains.x0) // 2
    context = block.CreateDefaultContext()
    x = gains.x0[k] + np.array([0.01, -0.02, 0.0, 0.05])
    block.get_input_port(0).FixValue(context, x)
    context.SetTime(k * block.period)
    state = block.EvalUniquePeriodicDiscreteUpdate(context)
    expected = np.clip(gains.u0[k] - gains.K[k] @ (x - gains.x0[k]) - gains.k0[k], -25, 25)
    np.testing.assert_allclose(state.get_vector(0).CopyToVector(), expected, atol=1e-12)
    assert not np.allclose(block.command(0.0, x), expected)       # another time, another row
    # after the trajectory: the last row, the goal with the LQR's gain (TVLQR's final cost is the LQR's S)
    np.testing.assert_allclose(gains.x0[-1], acrobot.goal, atol=1e-9)
    np.testing.assert_allclose(gains.K[-1], acrobot.lqr()[0], rtol=1e-6, atol=1e-6)


def test_the_trajopt_controller_swings_the_pendulum_up_and_balances_it_in_drake(pendulum, tmp_path, monkeypatch):
    from hybridctl.drake import simulate
    from hybridctl.experiments.controllers import CONTROLLERS, build_named_diagram

    monkeypatch.setenv("HYBRIDCTL_CACHE", str(tmp_path))
    assert "trajopt" in CONTROLLERS
    diagram = build_named_diagram(pendulum, "trajopt")
    assert isinstance(diagram.swingup, TrajectoryTracker)
    assert list((tmp_path / "trajopt").glob("pendulum-trajectory-*.npz"))
    traj = simulate(diagram, pendulum.initial_state.nominal)       # exactly hanging down, at rest
    assert traj.balanced and not traj.diverged
    on = np.flatnonzero(traj.gate > 0.5)
    assert len(on) and traj.gate[-1] == 1          # handed over to the LQR, and stayed there
    assert np.abs(traj.x[: on[0], 0]).max() > 2.5   # swung up by the tracker, not started at the top
    # the zero-order hold of the swing-up block keeps the command within the pendulum's 2 N m
    assert np.abs(traj.u).max() <= pendulum.action_limit + 1e-12


def test_the_torch_engine_refuses_trajopt_by_name(pendulum):
    from hybridctl.experiments.balance_map import torch_rollouts

    with pytest.raises(ValueError, match="trajopt"):
        torch_rollouts(pendulum, "trajopt", pendulum.initial_state.nominal[None])


@pytest.mark.parametrize("call, name", [
    (lambda s: swingup_trajectory(s, knots=2), "knots"),
    (lambda s: swingup_trajectory(s, durations=(2.0, -1.0)), "durations"),
    (lambda s: swingup_trajectory(s, input_margin=0.0), "input_margin"),
    (lambda s: swingup_trajectory(s, knot=41), "knot"),
    (lambda s: swingup_trajectory(s, settings={"knots": 41}), "settings"),
    (lambda s: swingup_trajectory("pendulum"), "system"),
    (lambda s: TrajoptSettings(Q=[[1.0, 2.0]]), "Q"),
])
def test_bad_arguments_are_value_errors_naming_them(pendulum, call, name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=name):
            call(pendulum)


def test_a_bad_period_or_a_foreign_trajectory_is_refused(acrobot, pendulum, acrobot_swingup):
    traj, folder = acrobot_swingup
    with pytest.raises(ValueError, match="period"):
        tracking_gains(acrobot, traj, period=-0.01, cache_dir=folder)
    with pytest.raises(ValueError, match="trajectory"):
        tracking_gains(pendulum, traj, cache_dir=folder)


# ------------------------------------------------------------------ failures are one line (issue 47)
STEP_TOO_SMALL = ("Error control wants to select step smaller than minimum allowed (1e-14)")


def test_one_riccati_solve_serves_every_period_with_a_fresh_solves_numbers(acrobot, acrobot_swingup, monkeypatch):
    """The fit screens several decision periods of one swing-up; the TVLQR was solved again for each (about 1 s
    apiece on the acrobot). Now one solve is sampled at each period, and each table equals a fresh solve's."""
    from pydrake.systems import controllers

    solves = []
    drakes = controllers.FiniteHorizonLinearQuadraticRegulator

    def counted(*args, **kwargs):
        solves.append(1)
        return drakes(*args, **kwargs)
    monkeypatch.setattr(controllers, "FiniteHorizonLinearQuadraticRegulator", counted)
    monkeypatch.setattr(trajopt, "_TVLQR_SOLUTIONS", {})
    traj, _ = acrobot_swingup
    tables = {period: tracking_gains(acrobot, traj, period, cache=False) for period in (0.02, 0.05, 0.1)}
    assert len(solves) == 1
    monkeypatch.setattr(trajopt, "_TVLQR_SOLUTIONS", {})
    fresh = tracking_gains(acrobot, traj, 0.05, cache=False)
    assert len(solves) == 2 and len(tables[0.05].K) == len(fresh.K) < len(tables[0.02].K)
    for name in ("x0", "u0", "K", "k0"):
        np.testing.assert_array_equal(getattr(tables[0.05], name), getattr(fresh, name))


def test_a_tvlqr_step_below_drakes_minimum_is_one_line_with_what_to_try(acrobot, acrobot_swingup, monkeypatch):
    """The public pendubot's TVLQR ended in Drake's integrator RuntimeError (a traceback); the same message,
    raised by the Riccati integration, is now a ValueError naming the system, the stage and what to try."""
    from pydrake.systems import controllers

    def fails(*args, **kwargs):
        raise RuntimeError(STEP_TOO_SMALL + "\nmore lines of Drake's text")
    monkeypatch.setattr(controllers, "FiniteHorizonLinearQuadraticRegulator", fails)
    monkeypatch.setattr(trajopt, "_TVLQR_SOLUTIONS", {})     # no solution kept from an earlier test
    traj, _ = acrobot_swingup
    with pytest.raises(ValueError) as failed:
        tracking_gains(acrobot, traj, cache=False)
    message = str(failed.value)
    assert "\n" not in message and "acrobot" in message and "TVLQR" in message, message
    assert "step smaller than minimum allowed" in message and "durations" in message, message


@pytest.mark.parametrize("status", ["IterationLimit", "error: SNOPT threw"])
def test_a_collocation_that_does_not_solve_is_one_line_with_what_to_try(pendulum, monkeypatch, tmp_path, status):
    """The multibody cart's SNOPT iteration limit ended in a RuntimeError traceback; now a ValueError."""
    def unsolved(system, settings, duration, *args):
        if status.startswith("error"):
            raise RuntimeError("SNOPT threw\nsecond line")
        return None, "SNOPT", status
    monkeypatch.setattr(trajopt, "_solve_fixed_duration", unsolved)
    with pytest.raises(ValueError) as failed:
        swingup_trajectory(pendulum, cache_dir=tmp_path, durations=(2.0, 3.0))
    message = str(failed.value)
    assert "\n" not in message and "pendulum" in message and "collocation" in message, message
    assert "SNOPT" in message and "T = 3 s" in message and "durations" in message, message


def test_the_cli_prints_a_trajopt_failure_in_one_line(cli_error, monkeypatch, tmp_path):
    monkeypatch.setenv("HYBRIDCTL_CACHE", str(tmp_path))
    monkeypatch.setattr(trajopt, "_solve_fixed_duration", lambda *a: (None, "SNOPT", "IterationLimit"))
    err = cli_error(["simulate", "pendulum", "--controller", "trajopt", "--duration", "0.1", "--no-html",
                     "--out", tmp_path / "out"])
    assert "collocation" in err and "pendulum" in err


def _forged_npz(path, real: dict, name: str, shape: tuple) -> None:
    """``real``'s arrays, but ``name`` as an .npy whose header claims ``shape`` over a few bytes of data."""
    import zipfile
    with zipfile.ZipFile(path, "w") as z:
        for key, value in real.items():
            buffer = __import__("io").BytesIO()
            if key == name:
                np.lib.format.write_array_header_2_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": shape})
                buffer.write(b"\0" * 64)
            else:
                np.lib.format.write_array(buffer, np.asarray(value), allow_pickle=False)
            z.writestr(f"{key}.npy", buffer.getvalue())


@pytest.mark.timeout(60)
def test_a_cache_entry_claiming_huge_gains_is_recomputed_without_allocating_them(acrobot, acrobot_swingup, tmp_path):
    """A tracking entry whose ``K`` header claims 4e9 elements (29.8 GB) made np.load allocate them; every
    size is now read from the headers and checked (limits.MAX_TRAJOPT_ROWS) first: one warning, recomputed."""
    import tracemalloc
    traj, folder = acrobot_swingup
    gains = tracking_gains(acrobot, traj, cache_dir=folder)
    real = dict(np.load(gains.path, allow_pickle=False))
    forged = tmp_path / gains.path.name
    _forged_npz(forged, real, "K", (1_000_000_000, 1, 4))
    tracemalloc.start()
    try:
        with pytest.warns(UserWarning, match="cannot be used"):
            again = tracking_gains(acrobot, traj, cache_dir=tmp_path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert not again.cached and peak < 100e6
    np.testing.assert_allclose(again.K, gains.K, rtol=1e-9, atol=1e-9)
    assert tracking_gains(acrobot, traj, cache_dir=tmp_path).cached      # rewritten


def test_a_tracking_table_above_its_row_limit_is_refused_before_allocating(acrobot, acrobot_swingup):
    traj, folder = acrobot_swingup
    with pytest.raises(ValueError, match="MAX_TRAJOPT_ROWS|limit"):
        tracking_gains(acrobot, traj, period=1e-12, cache=False)


def test_knots_above_their_limit_are_refused():
    with pytest.raises(ValueError, match="knots"):
        TrajoptSettings(knots=10**9)


def test_a_multibody_carts_rail_is_its_prismatic_limits_else_cart_bound(tmp_path):
    """A multibody cart (fit_robots' made-up long-pole cart) with a rail of +-1 m: the collocation keeps the cart
    on it (on a 100 m rail this swing-up runs the cart out to 1.89 m, at 3 s and 41 knots); without limits in the
    file the rail is +-cart_bound, as for a chain's cart."""
    from hybridctl.reproduce.fit_robots import MADE_UP

    rail = MADE_UP["cart_long_pole"].replace('<limit effort="10.0"', '<limit lower="-1.0" upper="1.0" effort="10.0"')
    assert rail != MADE_UP["cart_long_pole"]
    paths = {}
    for name, text in (("rail", rail), ("free", MADE_UP["cart_long_pole"])):
        paths[name] = tmp_path / f"{name}.urdf"
        paths[name].write_text(text)
    goal, weights = [0.0, np.pi, 0.0, 0.0], dict(Q=np.diag([1.0, 10.0, 1.0, 1.0]), R=[[0.1]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")        # the joint-limit warning: the collocation is what reads them here
        cart = systems.from_drake(str(paths["rail"]), goal=goal, **weights)
    free = systems.from_drake(str(paths["free"]), goal=goal, **weights)
    assert trajopt.rail_bounds(cart, trajopt._plant_diagram(cart)[0], 2.0) == [(0, -1.0, 1.0)]
    assert trajopt.rail_bounds(free, trajopt._plant_diagram(free)[0], 0.7) == [(0, -0.7, 0.7)]
    found = swingup_trajectory(cart, cache=False)
    assert np.abs(found.states[:, 0]).max() <= 1.0 + 1e-6
