"""The refinement's hill-climbing scan matcher and its score, against NumPy references in the
small room of tests/rooms.py."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from rooms import ROOM_EXTENT, SENSOR, SPEC, build_room_map, paged_field, room_path, scan_at

from jaxslam.config import SlamConfig, default_params
from jaxslam.likelihood_field import endpoint_cell_distances, endpoint_log_likelihood
from jaxslam.occupancy import FAR
from jaxslam.likelihood_field import endpoint_match_score as match_score
from jaxslam.scan_matching import match

PARAMS = default_params()
CONFIG = SlamConfig(num_particles=4, proposal="smp", map_extent=ROOM_EXTENT, max_insert_range=10.0)


@pytest.fixture(scope="module")
def room_map():
    return build_room_map(3)


def _match(room_map, start, ranges, iterations=24, lookup="nearest", spec=SPEC):
    sm = PARAMS.scan_match
    field = room_map.hit_dist2 if spec is SPEC else paged_field(room_map, CONFIG)
    return jax.jit(match, static_argnums=(0, 8, 9))(spec, field, jnp.asarray(start, jnp.float32),
                                                    ranges, SENSOR, PARAMS.likelihood, sm.linear_step,
                                                    sm.angular_step, iterations, lookup)


@pytest.mark.parametrize("lookup", ["nearest", "bilinear"])
@pytest.mark.parametrize("offset", [(0.08, -0.06, 0.04), (-0.1, 0.05, -0.05), (0.0, 0.0, 0.0)])
def test_match_climbs_back_to_the_true_pose(room_map, offset, lookup):
    """From up to 0.1 m and 0.05 rad off, the matcher ends within a cell and 0.02 rad of the pose
    the scan was cast from, never below the start's log-likelihood. With the bilinear lookup (the
    likelihood is continuous in the pose, so float32 rounding cannot move an endpoint to another
    cell) its log-likelihood is the endpoint model's at the returned pose."""
    truth = room_path(6)[2]
    ranges = scan_at(truth)
    start = truth + np.asarray(offset, np.float32)
    result = _match(room_map, start, ranges, lookup=lookup)
    error = np.asarray(result.pose) - truth
    assert math.hypot(error[0], error[1]) <= SPEC.resolution and abs(error[2]) < 0.02, error
    lik = jax.jit(endpoint_log_likelihood, static_argnums=(0, 6))
    at_start = lik(SPEC, room_map.hit_dist2, jnp.asarray(start), ranges, SENSOR, PARAMS.likelihood, lookup)
    assert float(result.log_likelihood) >= float(at_start) - 1e-5
    if lookup == "bilinear":
        direct = lik(SPEC, room_map.hit_dist2, result.pose, ranges, SENSOR, PARAMS.likelihood, lookup)
        np.testing.assert_allclose(float(result.log_likelihood), float(direct), rtol=1e-5, atol=1e-4)


def test_match_with_no_iterations_returns_the_start(room_map):
    truth = room_path(6)[2]
    start = truth + np.float32([0.1, 0.0, 0.0])
    result = _match(room_map, start, scan_at(truth), iterations=0)
    np.testing.assert_array_equal(np.asarray(result.pose), start)


def test_match_score_is_the_mean_fit_of_the_returned_beams(room_map):
    """NumPy reference: exp(-d^2 / 2 sigma^2) per beam from the stored squared cell distance,
    0 beyond the field, averaged over the beams with a return; 0 when no beam returns."""
    pose = jnp.asarray(room_path(6)[2] + np.float32([0.03, -0.02, 0.01]))
    ranges = scan_at(room_path(6)[2])
    sigma = PARAMS.likelihood.sigma
    d2, valid = endpoint_cell_distances(SPEC, room_map.hit_dist2, pose[None], ranges, SENSOR)
    d2 = np.asarray(d2[0], np.float64)
    fit = np.where(d2 == FAR, 0.0, np.exp(-0.5 * d2 * SPEC.resolution**2 / float(sigma) ** 2))
    expected = fit[np.asarray(valid)].mean()
    got = float(match_score(SPEC, room_map.hit_dist2, pose, ranges, SENSOR, sigma))
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    no_return = jnp.full_like(ranges, SENSOR.range_max)
    assert float(match_score(SPEC, room_map.hit_dist2, pose, no_return, SENSOR, sigma)) == 0.0
