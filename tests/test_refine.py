"""Localising every scan in a fixed map (jaxslam.refine)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.config import SlamConfig, default_params
from jaxslam.grid import GridSpec, empty_map, insert_scan
from jaxslam.refine import refine_trajectory
from jaxslam.sim import office_scenario

SPEC = GridSpec.from_bounds(-3.0, -3.0, 25.0, 13.0, 0.05)
NUM_SCANS = 60


@pytest.fixture(scope="module")
def mapped_office():
    """The first scans of the simulated office and a map built from them at their true poses."""
    scenario = office_scenario(jax.random.key(0), num_scans=NUM_SCANS)
    log = scenario.log
    params = default_params()
    insert = jax.jit(insert_scan, static_argnums=(0, 6, 7))
    grid_map = empty_map(SPEC)
    for pose, ranges in zip(scenario.true_poses[::3], log.ranges[::3]):
        grid_map, _ = insert(SPEC, grid_map, jnp.asarray(pose, jnp.float32), jnp.asarray(ranges), log.sensor,
                             params.insertion, 10.0, 4)
    return scenario, grid_map, params


def test_refinement_pulls_perturbed_poses_back_to_the_truth(mapped_office):
    scenario, grid_map, params = mapped_office
    truth = np.asarray(scenario.true_poses, np.float64)
    rng = np.random.default_rng(0)
    noisy = truth + rng.normal(0.0, [0.04, 0.04, 0.02], truth.shape)
    config = SlamConfig(grid=SPEC, beam_stride=1)
    refined = refine_trajectory(SPEC, grid_map.hit_dist2, noisy, scenario.log.ranges, scenario.log.sensor,
                                params, config, chunk_size=16)  # several chunks, the last one padded
    assert refined.poses.shape == truth.shape and refined.matched.mean() > 0.9
    before = np.hypot(*(noisy[:, :2] - truth[:, :2]).T)
    after = np.hypot(*(refined.poses[:, :2] - truth[:, :2]).T)
    # About 5 cm of error before; a match against a map built at the true poses lands within
    # about a cell (5 cm resolution, 2 cm range noise).
    assert np.median(after) < 0.02 < np.median(before)
    heading = np.abs(np.angle(np.exp(1j * (refined.poses[:, 2] - truth[:, 2]))))
    assert np.median(heading) < 0.01


def test_failed_matches_keep_the_input_pose(mapped_office):
    scenario, grid_map, params = mapped_office
    poses = np.asarray(scenario.true_poses[:5], np.float64) + np.array([0.03, -0.02, 0.01])
    no_returns = np.full((5, scenario.log.num_beams), scenario.log.sensor.range_max, np.float32)
    refined = refine_trajectory(SPEC, grid_map.hit_dist2, poses, no_returns, scenario.log.sensor, params,
                                SlamConfig(grid=SPEC))
    assert not refined.matched.any()
    np.testing.assert_array_equal(refined.poses, poses)


def test_mismatched_shapes_are_named(mapped_office):
    scenario, grid_map, params = mapped_office
    with pytest.raises(ValueError, match="do not match"):
        refine_trajectory(SPEC, grid_map.hit_dist2, np.zeros((4, 3)), scenario.log.ranges[:5],
                          scenario.log.sensor, params, SlamConfig(grid=SPEC))
