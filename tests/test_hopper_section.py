"""Hopper-v5 apex-to-apex section map (thesis Ch. 5), on the shipped ARS hopper; needs the `mujoco` extra."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from hybridctl.analysis import build_mesh  # noqa: E402
from hybridctl.envs.sections import HopperApexMap, random_pushes, x_pushes  # noqa: E402
from hybridctl.learn.ars import ARS  # noqa: E402

CHECKPOINT = Path(__file__).resolve().parents[1] / "models" / "policies" / "ars-hopper"
VZ = 6   # the torso's vertical velocity in the 11-number section state


@pytest.fixture(scope="module")
def section():
    return HopperApexMap(ARS.load(CHECKPOINT, backend="serial").frozen_policy())


def test_apex_states_are_height_peaks(section):
    apexes = section.apex_states(steps=600)
    assert apexes.shape[1] == 11 and len(apexes) >= 3
    # the first step after the torso stopped rising: vz <= 0, and at most one step of gravity below 0
    assert np.all(apexes[:, VZ] <= 0) and np.all(apexes[:, VZ] > -0.25), apexes[:, VZ]
    assert np.all(apexes[:, 0] > 0.7)                      # healthy torso height


def test_unpushed_step_continues_the_run(section):
    apexes = section.apex_states(steps=600, skip=1)
    for a, b in zip(apexes[:3], apexes[1:4]):
        np.testing.assert_allclose(section.step(a, [0.0, 0.0]), b, rtol=0, atol=1e-6)


def test_pushes_move_the_next_apex_and_a_hard_one_fails(section):
    start = section.apex_states(steps=600)[0]
    left, right = section.step(start, [-15.0, 0.0]), section.step(start, [15.0, 0.0])
    assert left is not None and right is not None and not np.allclose(left, right)
    assert section.step(start, [0.0, -30_000.0]) is None   # slammed into the floor
    assert HopperApexMap(section.policy, timeout_steps=2).step(start, [0.0, 0.0]) is None   # no apex in time


def test_mesh_on_worker_processes_matches_serial(section):
    seeds = section.apex_states(steps=400)
    pushes = x_pushes(15.0, 3)
    meshes = [build_mesh(section, seeds, pushes, box_size=2.0, max_states=12, backend=b, workers=2, batch_size=4,
                         progress=False, in_process_below=0) for b in ("serial", "processes")]
    assert meshes[1].rounds["backend"] >= 1                     # rounds went to the workers
    np.testing.assert_array_equal(meshes[0].states, meshes[1].states)
    np.testing.assert_array_equal(meshes[0].successors, meshes[1].successors)


def test_disturbance_sets_and_bad_input():
    assert len(x_pushes(15.0, 25).values) == 25 and x_pushes(15.0, 25).values[0][0] == -15.0
    sizes = np.linalg.norm(random_pushes(100, 5.0, 15.0).values, axis=1)
    assert sizes.min() >= 5.0 and sizes.max() <= 15.0
    with pytest.raises(ValueError, match="magnitude"):
        x_pushes(-1.0)
    with pytest.raises(ValueError, match="policy"):
        HopperApexMap(policy=3)
    with pytest.raises(ValueError, match="timeout_steps"):
        HopperApexMap(policy=lambda o: o, timeout_steps=1)


def test_a_step_does_not_depend_on_the_previous_one(section):
    """The same state and push give the same next apex whatever the worker stepped before
    (what makes build_mesh give one mesh on every backend and worker count)."""
    apexes = section.apex_states(steps=600)
    first = section.step(apexes[0], [-10.0, 0.0])
    section.step(apexes[2], [15.0, 0.0])
    np.testing.assert_array_equal(section.step(apexes[0], [-10.0, 0.0]), first)

def test_batched_engine_is_bit_identical_to_gymnasium(section):
    """engine="batch" (all states at once on MuJoCo threads) gives the gymnasium path's bits, failures included."""
    pytest.importorskip("mujoco.batch")
    starts = section.apex_states(steps=600, skip=1)[:3]
    pushes = [[-15.0, 0.0], [0.0, 0.0], [15.0, 0.0], [0.0, -30_000.0], [40.0, 10.0], [-60.0, 0.0]]
    states = np.repeat(starts, len(pushes), axis=0)
    disturbances = pushes * len(starts)
    gym_map = HopperApexMap(section.policy, engine="gym")
    expected = gym_map.step_many(states, disturbances)
    assert np.isnan(expected).any(axis=1).sum() >= len(starts)      # the slam fails from every start
    for nthread in (1, 2):
        batched = HopperApexMap(section.policy, engine="batch", nthread=nthread)
        np.testing.assert_array_equal(batched.step_many(states, disturbances), expected)
    # a state's successor does not depend on what the process stepped before
    np.testing.assert_array_equal(gym_map.step_many(states[::-1], disturbances[::-1]), expected[::-1])
    with pytest.raises(ValueError, match="engine"):
        HopperApexMap(section.policy, engine="rollout")
