"""Reachable-state meshes (thesis Alg. 7), Poincare maps and Monte Carlo validation (Ch. 5)."""

import math

import numpy as np
import pytest

from hybridctl.analysis.poincare import FiniteDisturbances, FunctionMap, GaussianDisturbance, RimlessWheel
from hybridctl.analysis.reachable import build_mesh, mesh_sizes, monte_carlo_mfpt
from mesh_maps import contracting_plane_map as lambda_free_map, exploding_map, walk_map

WHEEL = RimlessWheel()
SLOPES = GaussianDisturbance(mean=0.15, std=0.06, count=25)


def test_rimless_wheel_fixed_point_and_failure():
    w = WHEEL.fixed_point(0.15)
    assert WHEEL.step([w], 0.15)[0] == pytest.approx(w)
    assert WHEEL.step([0.3], -0.2) is None                     # too slow for an uphill step: rolls back
    steeper = WHEEL.step([w], 0.25)[0]
    assert steeper > w                                          # a steeper step adds energy


def test_gaussian_quantiles():
    finite = GaussianDisturbance(0.0, 1.0, 4, rule="quantiles").finite_set()
    np.testing.assert_allclose(finite.values, [-1.1503, -0.3186, 0.3186, 1.1503], atol=1e-4)
    assert finite.weights.sum() == pytest.approx(1.0)


def test_walk_mesh_is_the_known_chain():
    mesh = build_mesh(FunctionMap(walk_map), seeds=[[3.0]], disturbances=[-1.0, 1.0], box_size=0.5, progress=False)
    assert mesh.size == 5 and mesh.complete
    T = mesh.transition_matrix()
    assert np.allclose(T.sum(axis=1), 1.0) and T[0, 0] == 1.0
    by_value = {float(s[0]): i + 1 for i, s in enumerate(mesh.states)}
    assert T[by_value[1.0], 0] == 0.5 and T[by_value[5.0], by_value[5.0]] == 0.5
    # gambler's ruin with a sticky top at 5 (t_5 = 2 + t_4): t_x - t_(x-1) = 2 (6 - x), so t_1 = 10, t_5 = 30
    result = mesh.mfpt()
    for x in range(1, 6):
        assert result.mfpt[by_value[float(x)]] == pytest.approx(sum(2 * (6 - k) for k in range(1, x + 1)))


def test_wheel_mesh_matches_monte_carlo_on_the_same_disturbances():
    w = WHEEL.fixed_point(0.15)
    mesh = build_mesh(WHEEL, [[w]], SLOPES, box_size=1e-3, progress=False)
    mesh_mfpt = mesh.mfpt().mean(mesh.seed_distribution())
    mc = monte_carlo_mfpt(WHEEL, [[w]], SLOPES.finite_set(), episodes=4000, seed=3)
    lo, hi = mc.interval95
    assert mc.censored == 0 and lo <= mesh_mfpt <= hi, (mesh_mfpt, mc.interval95)


def test_more_disturbances_approach_the_continuous_distribution():
    w = WHEEL.fixed_point(0.15)
    continuous = monte_carlo_mfpt(WHEEL, [[w]], SLOPES, episodes=3000, seed=4)
    coarse = build_mesh(WHEEL, [[w]], GaussianDisturbance(0.15, 0.06, 25, rule="quantiles"), 2e-3, progress=False)
    fine = build_mesh(WHEEL, [[w]], GaussianDisturbance(0.15, 0.06, 200, rule="quantiles"), 2e-3, progress=False)
    err = [abs(m.mfpt().mean(m.seed_distribution()) - continuous.mean) for m in (coarse, fine)]
    assert err[1] < err[0] / 3            # 25 quantiles miss the tails that cause failures


def test_weighted_grid_keeps_the_tails_and_any_scipy_distribution_works():
    """Issue 50: 25 quantiles reach +-2.05 std; the grid reaches +-6 std with each cell's probability."""
    import scipy.stats as stats
    from hybridctl.analysis import ScipyDisturbance
    quantiles = GaussianDisturbance(0.0, 1.0, 25, rule="quantiles").finite_set()
    grid = GaussianDisturbance(0.0, 1.0, 25).finite_set()
    assert max(quantiles.values) == pytest.approx(2.054, abs=1e-3)
    assert min(grid.values) == pytest.approx(-6.0) and max(grid.values) == pytest.approx(6.0)
    assert grid.weights.sum() == pytest.approx(1.0) and grid.weights[0] == pytest.approx(stats.norm.cdf(-5.75))
    same = ScipyDisturbance(stats.norm(0.0, 1.0), 25).finite_set()
    np.testing.assert_allclose(same.values, grid.values, atol=1e-12)
    np.testing.assert_allclose(same.weights, grid.weights, atol=1e-15)
    heavy = ScipyDisturbance(stats.t(3, loc=0.15, scale=0.05), 49)
    finite = heavy.finite_set()
    assert finite.weights.sum() == pytest.approx(1.0) and np.isclose(np.dot(finite.values, finite.weights), 0.15)
    assert heavy.sample(np.random.default_rng(0), 5).shape == (5,)
    with pytest.raises(ValueError, match="rule must be one of"):
        GaussianDisturbance(0.0, 1.0, rule="midpoints")


def test_refined_gaussian_slopes_match_monte_carlo_where_25_quantiles_do_not():
    """Issue 50: at the command's defaults (mean 0.15 rad, sigma 0.06) the 25-quantile mesh gives 177 steps
    where Monte Carlo with continuous slopes gives about 110; the refined weighted grid lies inside the
    Monte Carlo interval, and its record says how it settled."""
    from hybridctl.analysis import refined_mesh
    w = WHEEL.fixed_point(0.15)
    continuous = monte_carlo_mfpt(WHEEL, [[w]], GaussianDisturbance(0.15, 0.06), episodes=3000, seed=5)
    lo, hi = continuous.interval95
    mesh, result, record = refined_mesh(WHEEL, [[w]], GaussianDisturbance(0.15, 0.06), 2e-3, progress=False)
    refined = result.mean(mesh.seed_distribution())
    assert lo <= refined <= hi, (refined, continuous.interval95)
    assert record["converged"] and record["relative_change"] <= record["rtol"] == 0.01
    assert record["counts"][:3] == [25, 49, 97] and record["mfpt_from_seed"][-1] == refined
    assert mesh.weights.size == record["count"] == record["counts"][-1]
    q_mesh, q_result, q_record = refined_mesh(WHEEL, [[w]], GaussianDisturbance(0.15, 0.06, rule="quantiles"), 2e-3,
                                              progress=False)
    quantiles = q_result.mean(q_mesh.seed_distribution())
    assert q_record["counts"] == [25] and q_record["converged"] is None
    assert not lo <= quantiles <= hi and quantiles > 1.4 * continuous.mean, (quantiles, continuous.interval95)


def test_refinement_stops_at_its_cap_and_calls_a_never_failing_chain_infinite():
    from hybridctl.analysis import refined_mesh
    w = WHEEL.fixed_point(0.15)
    lines = []
    _, _, capped = refined_mesh(WHEEL, [[w]], GaussianDisturbance(0.15, 0.06, 5), 1e-2, rtol=1e-9, max_count=20,
                                progress=False, report=lines.append)
    assert capped["counts"] == [5, 9, 17] and capped["converged"] is False and "max_count 20" in capped["stopped"]
    # one line per grid, as it is meshed: a long refinement (the compass gait's: 20 min a grid) says where it stands
    assert [line.split(" points")[0] for line in lines] == [f"disturbance grid of {n}" for n in (5, 9, 17)]
    assert f"{capped['states'][2]} states" in lines[2] and f"{capped['mfpt_from_seed'][2]:.6g} steps" in lines[2]
    assert "from the grid before" not in lines[0] and "from the grid before" in lines[1]
    mesh, result, calm = refined_mesh(WHEEL, [[w]], GaussianDisturbance(0.15, math.radians(1), 9), 1e-2,
                                      progress=False)
    # two equal grids settle only once the points are at most 0.5 std apart: 9 (1.5 std) and 17 (0.75) do not
    assert result is None and calm["mfpt_from_seed"] == [math.inf] * 3 and calm["converged"]
    assert calm["counts"] == [9, 17, 33] and calm["spacing_std"] == pytest.approx([1.5, 0.75, 0.375])
    assert "almost never fails" in calm["never_fails_note"]


def test_box_size_controls_the_mesh_size():
    rows = mesh_sizes(WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, [0.1, 0.01, 0.001])
    sizes = [r["states"] for r in rows]
    assert sizes[0] < sizes[1] < sizes[2] and all(r["complete"] for r in rows)


def test_processes_backend_builds_the_same_mesh():
    args = (WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, 1e-2)
    serial = build_mesh(*args, progress=False)
    parallel = build_mesh(*args, backend="processes", workers=2, batch_size=16, progress=False, in_process_below=0)
    assert parallel.rounds["backend"] > 1 and parallel.rounds["in_process"] == 0
    np.testing.assert_array_equal(serial.successors, parallel.successors)
    np.testing.assert_array_equal(serial.states, parallel.states)


def test_a_cheap_map_stays_in_process_and_starts_no_workers(monkeypatch):
    """The analytic wheel's rounds cost well under PARALLEL_MIN_ROUND_SECONDS: on a processes backend the whole
    mesh runs here, no pool is made, and the mesh equals the serial one; a round that costs more goes out."""
    from hybridctl.analysis import reachable
    made = []
    monkeypatch.setattr(reachable, "_backend", lambda *args: made.append(args))
    args = (WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, 1e-2)
    serial = build_mesh(*args, progress=False)
    cheap = build_mesh(*args, backend="processes", workers=2, batch_size=16, progress=False)
    assert made == [] and cheap.rounds == {"in_process": cheap.rounds["in_process"], "backend": 0}
    np.testing.assert_array_equal(serial.successors, cheap.successors)
    with pytest.raises(ValueError, match="^in_process_below must be"):
        build_mesh(*args, in_process_below=-1.0, progress=False)
    from hybridctl.parallel import SizedRounds
    rounds = SizedRounds(lambda: "pool", min_seconds=0.05)
    assert rounds.run(10, lambda: "here", lambda pool: pool) == "here"    # the first round is measured here
    rounds.unit_seconds = 0.01                                            # 10 units: 0.1 s > 0.05 s
    assert rounds.run(10, lambda: "here", lambda pool: pool) == "pool" and rounds.run(4, lambda: "here", str) == "here"


def test_cap_marks_the_mesh_incomplete_and_resume_finishes_it(tmp_path):
    ck = tmp_path / "mesh.npz"
    args = (WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, 3e-3)
    partial = build_mesh(*args, max_states=50, checkpoint=ck, batch_size=8, progress=False)
    assert not partial.complete and partial.size == 50 and ck.is_file()
    with pytest.raises(ValueError, match="incomplete"):
        partial.transition_matrix()
    resumed = build_mesh(*args, checkpoint=ck, resume=True, batch_size=8, progress=False)
    fresh = build_mesh(*args, batch_size=8, progress=False)
    assert resumed.complete and resumed.size == fresh.size
    np.testing.assert_array_equal(resumed.successors, fresh.successors)
    assert resumed.wall_time >= float(np.load(ck)["wall_time"]) >= partial.wall_time > 0   # the parts add up
    with pytest.raises(ValueError, match="box_size"):
        build_mesh(WHEEL, [[1.29]], SLOPES, 1e-2, checkpoint=ck, resume=True, progress=False)


def test_section_map_that_raises_is_named():
    with pytest.raises(RuntimeError, match=r"raised at state \[3.0\]"):
        build_mesh(FunctionMap(exploding_map), [[1.0]], [-1.0, 1.0], 0.5, progress=False)


@pytest.mark.parametrize("kwargs, message", [
    ({"seeds": [[np.nan]]}, "finite"),
    ({"box_size": 0.0}, "box_size"),
    ({"disturbances": []}, "empty"),
])
def test_bad_mesh_input(kwargs, message):
    args = {"section_map": WHEEL, "seeds": [[1.29]], "disturbances": SLOPES, "box_size": 1e-2, **kwargs}
    with pytest.raises(ValueError, match=message):
        build_mesh(**args, progress=False)


def test_monte_carlo_reports_censoring():
    mc = monte_carlo_mfpt(WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, episodes=50, max_steps=5, seed=0)
    assert mc.censored > 0 and "lower bound" in mc.summary()["note"] and mc.steps.max() == 5
    assert math.isfinite(mc.interval95[0])


def test_cumulative_mass_and_failure_states():
    from hybridctl.analysis import cumulative_transition_mass, failure_states
    T = np.array([[1.0, 0, 0, 0], [0.0, 0.5, 0.5, 0], [0.0, 0.5, 0.5, 0], [0.2, 0.8, 0, 0]])
    x, y = cumulative_transition_mass(T)
    np.testing.assert_allclose(x, [1 / 3, 2 / 3, 1.0])
    np.testing.assert_allclose(y, [1.8 / 2.8, 2.8 / 2.8, 1.0])
    quantiles = GaussianDisturbance(0.15, 0.06, 25, rule="quantiles")   # no failure weights of 1e-9 (grid tails)
    mesh = build_mesh(WHEEL, [[WHEEL.fixed_point(0.15)]], quantiles, 1e-2, progress=False)
    red = failure_states(mesh, share=1.0)
    assert set(red) == set(np.flatnonzero(mesh.failure_probability() > 0))
    assert len(failure_states(mesh, share=0.5)) < len(red)


def test_reachable_dimension_of_the_wheel_is_one():
    from hybridctl.analysis import reachable_dimension
    rows = mesh_sizes(WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, [0.1, 0.03, 0.01, 0.003, 0.001])
    assert reachable_dimension(rows) == pytest.approx(1.0, abs=0.05)
    with pytest.raises(ValueError, match="at least 2"):
        reachable_dimension(rows[:1])


def test_mesh_views_write_pngs(tmp_path):
    from hybridctl import viz
    mesh = build_mesh(WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, 1e-2, progress=False)
    T = mesh.transition_matrix()
    rows = mesh_sizes(WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, [0.1, 0.01])
    for name, call in {"sparsity": lambda p: viz.plot_transition_sparsity(T, path=p),
                       "mass": lambda p: viz.plot_cumulative_mass(T, path=p),
                       "states": lambda p: viz.plot_mesh_states(mesh, path=p),
                       "sizes": lambda p: viz.plot_mesh_sizes(rows, path=p)}.items():
        call(tmp_path / f"{name}.png")
        assert (tmp_path / f"{name}.png").stat().st_size > 5000, name
    # a 2-D map uses principal components
    two_d = build_mesh(FunctionMap(lambda_free_map), [[0.5, 0.5]], [-0.1, 0.0, 0.1], 0.05, progress=False)
    viz.plot_mesh_states(two_d, path=tmp_path / "pca.png")
    assert (tmp_path / "pca.png").stat().st_size > 5000


def test_mesh_save_and_load_round_trip(tmp_path):
    from hybridctl.analysis import ReachableMesh
    mesh = build_mesh(WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, 1e-2, progress=False)
    again = ReachableMesh.load(mesh.save(tmp_path / "mesh.npz"))
    np.testing.assert_array_equal(again.successors, mesh.successors)
    assert (again.transition_matrix() != mesh.transition_matrix()).nnz == 0
    assert again.settings["state_names"] == ["w"] and again.complete
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="not a mesh file"):
        ReachableMesh.load(tmp_path / "other.npz")


def test_monte_carlo_chunks_give_the_same_result_on_every_backend():
    w = WHEEL.fixed_point(0.15)
    serial = monte_carlo_mfpt(WHEEL, [[w]], SLOPES, episodes=400, seed=5, chunks=4)
    parallel = monte_carlo_mfpt(WHEEL, [[w]], SLOPES, episodes=400, seed=5, chunks=4, backend="processes", workers=2)
    np.testing.assert_array_equal(serial.steps, parallel.steps)
    one = monte_carlo_mfpt(WHEEL, [[w]], SLOPES, episodes=400, seed=5)
    assert one.steps.size == serial.steps.size == 400
    # different streams, same distribution: the two means agree within their intervals
    assert serial.interval95[0] < one.mean < serial.interval95[1] or one.interval95[0] < serial.mean < one.interval95[1]
    with pytest.raises(ValueError, match="chunks"):
        monte_carlo_mfpt(WHEEL, [[w]], SLOPES, episodes=10, chunks=11)


@pytest.mark.xdist_group("ray")
def test_ray_backend_builds_the_same_mesh_and_monte_carlo(local_ray):
    """build_mesh and monte_carlo_mfpt on a local 2-CPU Ray instance equal the serial backend."""
    assert local_ray.cluster_resources().get("CPU") == 2
    args = (WHEEL, [[WHEEL.fixed_point(0.15)]], SLOPES, 1e-2)
    serial = build_mesh(*args, batch_size=16, progress=False)
    on_ray = build_mesh(*args, backend="ray", workers=2, batch_size=16, progress=False, in_process_below=0)
    assert on_ray.size == serial.size > 16 and on_ray.complete and on_ray.rounds["backend"] > 1   # batches went out
    np.testing.assert_array_equal(serial.successors, on_ray.successors)
    np.testing.assert_array_equal(serial.states, on_ray.states)
    assert local_ray.is_initialized()          # the backend did not shut down an instance it did not start
    w = WHEEL.fixed_point(0.15)
    serial_mc = monte_carlo_mfpt(WHEEL, [[w]], SLOPES, episodes=400, seed=5, chunks=4)
    ray_mc = monte_carlo_mfpt(WHEEL, [[w]], SLOPES, episodes=400, seed=5, chunks=4, backend="ray", workers=2)
    np.testing.assert_array_equal(serial_mc.steps, ray_mc.steps)
    assert ray_mc.censored == serial_mc.censored


PLANE_PUSHES = list(np.linspace(-0.5, 0.5, 9))


def test_samples_per_box_rows_are_the_mean_of_their_samples_rows():
    mesh = build_mesh(FunctionMap(lambda_free_map), [[0.0, 0.0]], PLANE_PUSHES, 0.2, samples_per_box=4,
                      progress=False)
    owners = mesh.owners
    assert mesh.complete and owners is not None and mesh.states.shape[0] == owners.size == mesh.successors.shape[0]
    counts = np.bincount(owners)[1:]
    assert counts.min() >= 1 and counts.max() == 4 and counts.size == mesh.size   # ids 1..size, <= 4 samples each
    T = mesh.transition_matrix().toarray()
    by_hand = np.zeros_like(T)
    by_hand[0, 0] = 1.0
    for owner, row in zip(owners, mesh.successors):
        for j in row:
            by_hand[owner, j] += 1.0 / (len(row) * counts[owner - 1])
    np.testing.assert_allclose(T, by_hand, atol=1e-15)
    np.testing.assert_allclose(mesh.failure_probability(), T[1:, 0], atol=1e-15)
    first = [int(np.flatnonzero(owners == b)[0]) for b in range(1, mesh.size + 1)]
    np.testing.assert_array_equal(mesh.representatives, mesh.states[first])
    assert mesh.summary()["samples"] == owners.size


def test_more_samples_per_box_bring_a_coarse_mesh_towards_monte_carlo():
    # one representative per box follows one state's path; a shearing map sends the box's other
    # states elsewhere, so coarse meshes fail too early. Averaging arrivals narrows the error.
    plane = FunctionMap(lambda_free_map)
    mc = monte_carlo_mfpt(plane, [[0.0, 0.0]], FiniteDisturbances(PLANE_PUSHES), episodes=4000, seed=3)
    for box in (0.2, 0.4):
        meshes = [build_mesh(plane, [[0.0, 0.0]], PLANE_PUSHES, box, samples_per_box=k, progress=False)
                  for k in (1, 4, 32)]
        errors = [abs(m.mfpt().mean(m.seed_distribution()) - mc.mean) for m in meshes]
        assert errors[2] < errors[1] < errors[0], (box, errors, mc.mean)
    assert errors[0] > 0.4 * mc.mean and errors[2] < 0.15 * mc.mean       # box 0.4: 45 % off -> 10 %


def test_samples_per_box_resume_and_round_trip(tmp_path):
    from hybridctl.analysis import ReachableMesh
    ck = tmp_path / "mesh.npz"
    args = (FunctionMap(lambda_free_map), [[0.0, 0.0]], PLANE_PUSHES, 0.1)
    partial = build_mesh(*args, samples_per_box=3, max_states=40, checkpoint=ck, batch_size=8, progress=False)
    assert not partial.complete and partial.size <= 40
    resumed = build_mesh(*args, samples_per_box=3, checkpoint=ck, resume=True, batch_size=8, progress=False)
    fresh = build_mesh(*args, samples_per_box=3, batch_size=8, progress=False)
    assert resumed.complete and resumed.size == fresh.size
    np.testing.assert_array_equal(resumed.successors, fresh.successors)
    np.testing.assert_array_equal(resumed.owners, fresh.owners)
    again = ReachableMesh.load(fresh.save(tmp_path / "saved.npz"))
    np.testing.assert_array_equal(again.owners, fresh.owners)
    assert (again.transition_matrix() != fresh.transition_matrix()).nnz == 0
    with pytest.raises(ValueError, match="samples_per_box 3, not 2"):
        build_mesh(*args, samples_per_box=2, checkpoint=ck, resume=True, progress=False)
    with pytest.raises(ValueError, match="samples_per_box must be an integer >= 1"):
        build_mesh(*args, samples_per_box=0, progress=False)


def test_mfpt_vs_roughness_sweep_writes_record_and_skips_unaffordable_monte_carlo(tmp_path):
    """Issue 50 item 3: the mesh inside the Monte Carlo interval where Monte Carlo is cheap; a sigma whose
    Monte Carlo would pass the budget is skipped with the reason (not run); a never-failing chain too."""
    from hybridctl.experiments.mfpt_sweep import mfpt_vs_roughness
    from hybridctl.io import read_json

    stds = [0.06, 0.08, math.radians(2), math.radians(1)]
    record = mfpt_vs_roughness("rimless-wheel", tmp_path / "sweep", stds, box_size=1e-2, monte_carlo=300,
                               monte_carlo_budget=1e5)
    assert (tmp_path / "sweep" / "mfpt_vs_roughness.png").stat().st_size > 10_000
    saved = read_json(tmp_path / "sweep" / "mfpt_vs_roughness.json")
    rows = {round(row["slope_std"], 6): row for row in saved["rows"]}
    for std in (0.06, 0.08):
        row = rows[std]
        lo, hi = row["monte_carlo"]["interval95"]
        assert row["monte_carlo"]["status"] == "run" and row["monte_carlo"]["censored"] == 0
        assert lo <= row["mesh_mfpt"] <= hi, (std, row["mesh_mfpt"], lo, hi)
        assert row["refinement"]["converged"] and len(row["refinement"]["counts"]) >= 2
    two = rows[round(math.radians(2), 6)]
    assert two["mesh_mfpt"] > 1e4 and two["monte_carlo"]["status"] == "skipped"
    assert "budget" in two["monte_carlo"]["reason"] and "episodes" not in two["monte_carlo"]
    one = rows[round(math.radians(1), 6)]
    assert one["never_fails"] and one["mesh_mfpt"] is None and "never fails" in one["monte_carlo"]["reason"]
    assert record["regimes"] == {"monte_carlo": [0.06, 0.08], "mesh_only": [math.radians(2)],
                                 "never_fails": [math.radians(1)]}


def test_a_sweep_writes_each_row_as_it_comes_and_resume_keeps_them(tmp_path, monkeypatch):
    """A sweep writes its record after every sigma (finished: false until the end); --resume on the same settings
    keeps the rows it holds and measures only the new sigmas; on other settings it is refused, naming the setting."""
    from hybridctl.experiments import mfpt_sweep
    from hybridctl.io import read_json

    out = tmp_path / "sweep"
    first = mfpt_sweep.mfpt_vs_roughness("rimless-wheel", out, [0.08], box_size=1e-2)
    assert first["finished"] and read_json(out / "mfpt_vs_roughness.json")["rows"] == first["rows"]
    measured, real = [], mfpt_sweep.refined_mesh

    def counting(section_map, seeds, slopes, *args, **kwargs):
        measured.append(slopes.std)
        return real(section_map, seeds, slopes, *args, **kwargs)
    monkeypatch.setattr(mfpt_sweep, "refined_mesh", counting)
    again = mfpt_sweep.mfpt_vs_roughness("rimless-wheel", out, [0.06, 0.08], box_size=1e-2, resume=True)
    assert measured == [0.06]
    assert again["rows"][1] == first["rows"][0] and [r["slope_std"] for r in again["rows"]] == [0.06, 0.08]
    with pytest.raises(ValueError, match="box_size"):
        mfpt_sweep.mfpt_vs_roughness("rimless-wheel", out, [0.06, 0.08], box_size=2e-2, resume=True)
    # a sweep killed after its first sigma leaves that row on disk, unfinished
    def killed(section_map, seeds, slopes, *args, **kwargs):
        if slopes.std > 0.07:
            raise KeyboardInterrupt
        return real(section_map, seeds, slopes, *args, **kwargs)
    monkeypatch.setattr(mfpt_sweep, "refined_mesh", killed)
    with pytest.raises(KeyboardInterrupt):
        mfpt_sweep.mfpt_vs_roughness("rimless-wheel", tmp_path / "killed", [0.06, 0.08], box_size=1e-2)
    left = read_json(tmp_path / "killed" / "mfpt_vs_roughness.json")
    assert not left["finished"] and [r["slope_std"] for r in left["rows"]] == [0.06]


def test_grid_spacing_is_measured_in_the_central_std():
    """The settling rule's spacing unit: a Gaussian's std, and half the central 68.3 % of any scipy distribution
    (finite where heavy tails have no std: Student t with 2 degrees of freedom)."""
    import scipy.stats as stats
    from hybridctl.analysis import ScipyDisturbance
    from hybridctl.analysis.refine import _spacing_std
    assert ScipyDisturbance(stats.norm(0.1, 0.05)).central_std == pytest.approx(0.05)
    assert _spacing_std(ScipyDisturbance(stats.norm(0.1, 0.05), 25)) == pytest.approx(0.5)
    assert _spacing_std(GaussianDisturbance(0.1, 0.05, 9)) == pytest.approx(1.5)
    heavy = ScipyDisturbance(stats.t(2, scale=0.05))
    assert math.isinf(heavy.distribution.std()) and 0.05 < heavy.central_std < 0.07
