"""Localising every scan in a fixed map (jaxslam.refine)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.config import SlamConfig, default_params
from jaxslam.grid import GridSpec
from jaxslam.occupancy import empty_map, insert_scan
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
    config = SlamConfig(beam_stride=1)
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
                                SlamConfig())
    assert not refined.matched.any()
    np.testing.assert_array_equal(refined.poses, poses)


def test_mismatched_shapes_are_named(mapped_office):
    scenario, grid_map, params = mapped_office
    with pytest.raises(ValueError, match="do not match"):
        refine_trajectory(SPEC, grid_map.hit_dist2, np.zeros((4, 3)), scenario.log.ranges[:5],
                          scenario.log.sensor, params, SlamConfig())


# --- fusing the matches with the odometry --------------------------------------------------

from jaxslam.refine import _solve_block_tridiagonal, smooth_with_odometry  # noqa: E402


def _motion(translation_std=1e-3, rotation_std=1e-3):
    """Motion params with only the floors: the odometry steps are (nearly) exact."""
    return default_params(**{"motion.srr": 0.0, "motion.srt": 0.0, "motion.str": 0.0, "motion.stt": 0.0,
                             "motion.min_translation_std": translation_std,
                             "motion.min_rotation_std": rotation_std}).motion


def _arc(num=60):
    t = np.linspace(0.0, 3.0, num)
    return np.column_stack([4.0 * np.cos(t), 4.0 * np.sin(t), t + np.pi / 2])


@pytest.mark.parametrize("shift", [4.0, -1.5])
def test_block_tridiagonal_solve_matches_a_dense_solve(shift):
    # shift 4: positive definite (the banded Cholesky); -1.5: symmetric but indefinite, which
    # the Cholesky refuses and the banded LU solves.
    rng = np.random.default_rng(1)
    num, n = 7, 3
    dense = np.zeros((num * n, num * n))
    for t in range(num):
        a = rng.normal(size=(n, n))
        dense[t * n:(t + 1) * n, t * n:(t + 1) * n] = a @ a.T + shift * np.eye(n)
    upper = rng.normal(size=(num - 1, n, n))
    for t in range(num - 1):
        dense[t * n:(t + 1) * n, (t + 1) * n:(t + 2) * n] = upper[t]
        dense[(t + 1) * n:(t + 2) * n, t * n:(t + 1) * n] = upper[t].T
    assert (np.linalg.eigvalsh(dense).min() > 0) == (shift > 0)
    rhs = rng.normal(size=(num, n))
    diag = np.stack([dense[t * n:(t + 1) * n, t * n:(t + 1) * n] for t in range(num)])
    got = _solve_block_tridiagonal(diag, upper, rhs)
    np.testing.assert_allclose(got.reshape(-1), np.linalg.solve(dense, rhs.reshape(-1)), rtol=1e-10, atol=1e-12)
    single = _solve_block_tridiagonal(diag[:1], upper[:0], rhs[:1])
    np.testing.assert_allclose(single[0], np.linalg.solve(diag[0], rhs[0]), rtol=1e-10, atol=1e-12)


def test_exact_odometry_averages_the_measurement_noise():
    truth = _arc()
    rng = np.random.default_rng(2)
    sigma = np.array([0.05, 0.05, 0.02])
    measured = truth + rng.normal(0.0, sigma, truth.shape)
    cov = np.broadcast_to(np.diag(sigma**2), (truth.shape[0], 3, 3))
    # The odometry frame is arbitrary: a rigid motion of the truth.
    c, s = np.cos(1.0), np.sin(1.0)
    odometry = np.column_stack([c * truth[:, 0] - s * truth[:, 1] + 7.0, s * truth[:, 0] + c * truth[:, 1] - 2.0,
                                truth[:, 2] + 1.0])
    start = measured.copy()
    smoothed = smooth_with_odometry(start, measured, cov, np.ones(truth.shape[0], bool), odometry, _motion())
    before = np.hypot(*(measured[:, :2] - truth[:, :2]).T)
    after = np.hypot(*(smoothed[:, :2] - truth[:, :2]).T)
    # With exact odometry the chain is rigid and 60 measurements pin it: the error shrinks
    # by about sqrt(60) in translation (less near the ends, where the heading error acts).
    assert np.median(after) < 0.25 * np.median(before)
    assert np.max(np.abs(np.angle(np.exp(1j * (smoothed[:, 2] - truth[:, 2]))))) < 0.01


def test_a_wrong_match_barely_moves_the_chain():
    truth = _arc()
    measured = truth.copy()
    measured[30, :2] += 2.0  # a match caught in a wrong optimum, 2 m off
    cov = np.broadcast_to(np.diag([0.02**2, 0.02**2, 0.01**2]), (truth.shape[0], 3, 3))
    ok = np.ones(truth.shape[0], bool)
    smoothed = smooth_with_odometry(truth, measured, cov, ok, truth, _motion(0.01, 0.005))
    assert np.max(np.hypot(*(smoothed[:, :2] - truth[:, :2]).T)) < 0.05
    # Without the Huber weights the same outlier drags its neighbourhood much further.
    plain = smooth_with_odometry(truth, measured, cov, ok, truth, _motion(0.01, 0.005), huber=np.inf)
    assert np.max(np.hypot(*(plain[:, :2] - truth[:, :2]).T)) > 0.1


def test_weak_match_directions_follow_the_odometry():
    """A corridor: the matches pin y and theta, not x; the odometry carries x."""
    num = 40
    truth = np.column_stack([np.linspace(0.0, 4.0, num), np.zeros(num), np.zeros(num)])
    rng = np.random.default_rng(3)
    measured = truth + np.column_stack([rng.normal(0.0, 0.3, num), rng.normal(0.0, 0.01, num), np.zeros(num)])
    cov = np.broadcast_to(np.diag([1.0, 0.01**2, 0.005**2]), (num, 3, 3))
    smoothed = smooth_with_odometry(truth + [0.5, 0.0, 0.0], measured, cov, np.ones(num, bool), truth,
                                    _motion(0.002, 0.001))
    steps = np.diff(smoothed[:, 0])
    np.testing.assert_allclose(steps, np.diff(truth[:, 0]), atol=0.01)  # the odometry's spacing, not the jitter
    assert np.max(np.abs(smoothed[:, 1])) < 0.01


def test_no_usable_match_returns_the_input():
    truth = _arc(10)
    out = smooth_with_odometry(truth + 0.1, truth, np.broadcast_to(np.eye(3), (10, 3, 3)), np.zeros(10, bool),
                               truth, _motion())
    np.testing.assert_array_equal(out, truth + 0.1)


def test_refinement_with_odometry_stays_on_the_truth(mapped_office):
    """The fused trajectory is as close to the truth as the matches (the simulated odometry
    is no better than a match here: its gain shows on real logs, see docs/tuning.md)."""
    scenario, grid_map, params = mapped_office
    truth = np.asarray(scenario.true_poses, np.float64)
    rng = np.random.default_rng(0)
    noisy = truth + rng.normal(0.0, [0.04, 0.04, 0.02], truth.shape)
    config = SlamConfig(beam_stride=1)
    params = params._replace(motion=scenario.metadata["motion_params"])  # the odometry's true noise
    refined = refine_trajectory(SPEC, grid_map.hit_dist2, noisy, scenario.log.ranges, scenario.log.sensor,
                                params, config, odometry=scenario.log.odometry, chunk_size=16)
    fused = np.hypot(*(refined.poses[:, :2] - truth[:, :2]).T)
    assert np.median(fused) < 0.02 < np.median(np.hypot(*(noisy[:, :2] - truth[:, :2]).T))
    cov = refined.match_covariances
    assert cov.shape == (NUM_SCANS, 3, 3)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-9)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    with pytest.raises(ValueError, match="odometry"):
        refine_trajectory(SPEC, grid_map.hit_dist2, noisy, scenario.log.ranges, scenario.log.sensor, params, config,
                          odometry=scenario.log.odometry[:-1])


def test_bilinear_matcher_lands_closer_than_a_cell(mapped_office):
    """With ``match_lookup="bilinear"`` the matcher settles between cells: on the same scans it
    lands closer to the truth than with the nearest-cell lookup (medians measured 0.017 and
    0.009 m)."""
    scenario, grid_map, params = mapped_office
    truth = np.asarray(scenario.true_poses, np.float64)
    noisy = truth + np.random.default_rng(0).normal(0.0, [0.04, 0.04, 0.02], truth.shape)
    errors = {}
    for lookup in ("nearest", "bilinear"):
        config = SlamConfig(beam_stride=1, match_lookup=lookup)
        refined = refine_trajectory(SPEC, grid_map.hit_dist2, noisy, scenario.log.ranges, scenario.log.sensor,
                                    params, config)
        errors[lookup] = np.median(np.hypot(*(refined.matched_poses[:, :2] - truth[:, :2]).T))
    assert errors["bilinear"] < 0.8 * errors["nearest"], errors


# --- rounds: the map drawn again at the refined poses ---------------------------------------

from jaxslam.config import ConfigError  # noqa: E402
from jaxslam.geometry import between_np  # noqa: E402
from jaxslam.occupancy import map_from_scans  # noqa: E402
from jaxslam.refine import refine_in_rounds  # noqa: E402


def _relative_error(poses, truth, lag=10):
    """Mean translation error of the relative poses ``lag`` scans apart (as the logs' relations)."""
    error = between_np(poses[:-lag], poses[lag:]) - between_np(truth[:-lag], truth[lag:])
    return float(np.mean(np.hypot(error[:, 0], error[:, 1])))


@pytest.fixture(scope="module")
def drifted_office():
    """120 scans of the simulated office and a trajectory that drifts from the truth (a random walk
    of 5 mm and 2.5 mrad a scan plus 1 cm of jitter), as a filter's or a pose graph's does."""
    scenario = office_scenario(jax.random.key(0), num_scans=120)
    truth = np.asarray(scenario.true_poses, np.float64)
    return scenario, truth, default_params(), SlamConfig(beam_stride=1, max_insert_range=10.0)


def _drifted(truth, seed):
    rng = np.random.default_rng(seed)
    return (truth + np.cumsum(rng.normal(0.0, [0.005, 0.005, 0.0025], truth.shape), axis=0)
            + rng.normal(0.0, [0.01, 0.01, 0.005], truth.shape))


def test_map_from_scans_is_the_scans_inserted_one_by_one(drifted_office):
    scenario, truth, params, _ = drifted_office
    scans = np.arange(0, 30, 3)
    grid_map, spec = map_from_scans(truth[scans], scenario.log.ranges[scans], scenario.log.sensor, params.insertion,
                                    0.05, 10.0, 4)
    # The grid covers every pose with the insertion range and a metre to spare.
    assert spec.origin[0] <= truth[scans, 0].min() - 11.0 and spec.origin[1] <= truth[scans, 1].min() - 11.0
    reference = empty_map(spec)
    for pose, ranges in zip(truth[scans], scenario.log.ranges[scans]):
        reference, _ = insert_scan(spec, reference, jnp.asarray(pose, jnp.float32), jnp.asarray(ranges),
                                   scenario.log.sensor, params.insertion, 10.0, 4)
    np.testing.assert_array_equal(np.asarray(grid_map.hit_dist2), np.asarray(reference.hit_dist2))
    np.testing.assert_array_equal(np.asarray(grid_map.logodds), np.asarray(reference.logodds))
    with pytest.raises(ValueError, match="map_from_scans: poses"):
        map_from_scans(truth[scans], scenario.log.ranges[:3], scenario.log.sensor, params.insertion, 0.05, 10.0, 4)


def test_the_map_drawn_again_sharpens_a_drifted_trajectory(drifted_office):
    """The first round localises every scan in a map drawn at drifted poses; the second in the map
    drawn again at the first round's poses. Measured (relative error 10 scans apart, seeds 0-3):
    0.065, 0.138, 0.037, 0.032 m after one round, 0.063, 0.134, 0.032, 0.029 after two; the
    drifted input 0.11, 0.19, 0.058, 0.049."""
    scenario, truth, params, config = drifted_office
    scans = np.arange(0, truth.shape[0], 3)
    errors = []
    for seed in range(4):
        drifted = _drifted(truth, seed)
        grid_map, spec = map_from_scans(drifted[scans], scenario.log.ranges[scans], scenario.log.sensor,
                                        params.insertion, config.resolution, config.max_insert_range,
                                        config.field_radius)
        errors.append([_relative_error(refine_in_rounds(
            spec, grid_map.hit_dist2, drifted, scenario.log.ranges, scenario.log.sensor, params,
            dataclasses.replace(config, refine_rounds=rounds), scans, odometry=np.asarray(scenario.log.odometry),
            chunk_size=64).poses, truth) for rounds in (1, 2)] + [_relative_error(drifted, truth)])
    errors = np.array(errors)
    assert np.all(errors[:, 0] < errors[:, 2]), errors  # one round already gains on the drift
    assert np.all(errors[:, 1] < errors[:, 0]), errors  # and the map drawn again gains in every seed
    assert np.mean(errors[:, 1] / errors[:, 0]) < 0.97, errors


def test_rounds_compose_the_single_refinement(drifted_office):
    scenario, truth, params, config = drifted_office
    drifted = _drifted(truth, 0)
    scans = np.arange(0, truth.shape[0], 3)
    ranges, sensor = scenario.log.ranges, scenario.log.sensor
    grid_map, spec = map_from_scans(drifted[scans], ranges[scans], sensor, params.insertion, 0.05, 10.0, 4)
    once = refine_trajectory(spec, grid_map.hit_dist2, drifted, ranges, sensor, params, config, chunk_size=64)
    one_round = refine_in_rounds(spec, grid_map.hit_dist2, drifted, ranges, sensor, params,
                                 dataclasses.replace(config, refine_rounds=1), scans, chunk_size=64)
    np.testing.assert_array_equal(one_round.poses, once.poses)
    redrawn, redrawn_spec = map_from_scans(once.poses[scans], ranges[scans], sensor, params.insertion, 0.05, 10.0, 4)
    twice = refine_trajectory(redrawn_spec, redrawn.hit_dist2, once.poses, ranges, sensor, params, config,
                              chunk_size=64)
    two_rounds = refine_in_rounds(spec, grid_map.hit_dist2, drifted, ranges, sensor, params, config, scans,
                                  chunk_size=64)
    assert config.refine_rounds == 2  # the default
    np.testing.assert_array_equal(two_rounds.poses, twice.poses)
    np.testing.assert_array_equal(two_rounds.scores, twice.scores)


@pytest.mark.parametrize("map_scans", [np.array([], int), np.array([0.0, 3.0]), np.array([0, 120]),
                                       np.array([-1, 3]), np.zeros((2, 2), int)])
def test_bad_map_scans_are_named_before_any_work(drifted_office, map_scans):
    scenario, truth, params, config = drifted_office
    with pytest.raises(ValueError, match="refine_in_rounds: map_scans"):
        refine_in_rounds(SPEC, jnp.zeros(SPEC.shape, jnp.uint8), truth, scenario.log.ranges, scenario.log.sensor,
                         params, config, map_scans)


def test_refine_rounds_below_one_is_refused():
    with pytest.raises(ConfigError, match="refine_rounds must be >= 1"):
        SlamConfig(refine_rounds=0)


# --------------------------------------------------------------------------- the odometry's noise

from jaxslam.geometry import chain_np  # noqa: E402
from jaxslam.motion import noise_std  # noqa: E402
from jaxslam.refine import odometry_noise_scale  # noqa: E402


@pytest.mark.parametrize("fraction", [(0.3, 0.2, 0.1), (0.6, 0.5, 0.4)])
def test_odometry_noise_scale_recovers_how_loose_the_motion_model_is(fraction):
    """Steps drawn at a known fraction of the motion model's std around the odometry's: the robust
    spread gives the fraction back, within its Monte Carlo error (about 1.1 / sqrt(n) for a
    median absolute deviation), and never above 1."""
    rng = np.random.default_rng(5)
    num = 4001
    motion = default_params().motion
    steps = np.column_stack([rng.uniform(0.05, 0.3, num - 1), rng.normal(0.0, 0.01, num - 1),
                             rng.normal(0.0, 0.05, num - 1)])
    odometry = chain_np(np.array([1.0, 2.0, 0.3]), steps)
    std = np.asarray(noise_std(jnp.asarray(steps, jnp.float32), motion), np.float64)
    poses = chain_np(np.array([-4.0, 0.5, 1.0]), steps + rng.normal(0.0, 1.0, steps.shape) * std * np.array(fraction))
    got = odometry_noise_scale(poses, odometry, np.ones(num, bool), motion)
    tolerance = 4 * 1.1 / np.sqrt(num - 1) * np.array(fraction)
    assert np.all(np.abs(np.array(got) - fraction) < tolerance + 0.01 * np.array(fraction)), got
    # Looser than the model: capped at 1. Unmatched scans are left out; too few steps give 1.
    wild = chain_np(odometry[0], steps + rng.normal(0.0, 1.0, steps.shape) * std * 3.0)
    assert odometry_noise_scale(wild, odometry, np.ones(num, bool), motion) == (1.0, 1.0, 1.0)
    matched = np.zeros(num, bool)
    matched[:8] = True
    assert odometry_noise_scale(poses, odometry, matched, motion) == (1.0, 1.0, 1.0)


def test_a_trusted_odometry_holds_the_chain_to_its_steps():
    """smooth_with_odometry's noise_scale: at (1, 1, 1) the default bit for bit; at a tenth, the
    exact odometry's steps hold the chain against noisy matches far better."""
    truth = _arc()
    rng = np.random.default_rng(6)
    sigma = np.array([0.05, 0.05, 0.02])
    measured = truth + rng.normal(0.0, sigma, truth.shape)
    cov = np.broadcast_to(np.diag(sigma**2), (truth.shape[0], 3, 3))
    ok = np.ones(truth.shape[0], bool)
    loose = _motion(0.05, 0.02)
    default = smooth_with_odometry(measured, measured, cov, ok, truth, loose)
    np.testing.assert_array_equal(smooth_with_odometry(measured, measured, cov, ok, truth, loose,
                                                       noise_scale=(1.0, 1.0, 1.0)), default)
    trusted = smooth_with_odometry(measured, measured, cov, ok, truth, loose, noise_scale=(0.1, 0.1, 0.1))
    assert _relative_error(trusted, truth, lag=5) < 0.3 * _relative_error(default, truth, lag=5)


def test_refine_in_rounds_trusts_the_odometry_only_when_told(drifted_office):
    scenario, truth, params, config = drifted_office
    drifted = _drifted(truth, 1)
    scans = np.arange(0, truth.shape[0], 3)
    ranges, sensor, odometry = scenario.log.ranges, scenario.log.sensor, np.asarray(scenario.log.odometry)
    grid_map, spec = map_from_scans(drifted[scans], ranges[scans], sensor, params.insertion, 0.05, 10.0, 4)
    plain = refine_in_rounds(spec, grid_map.hit_dist2, drifted, ranges, sensor, params, config, scans,
                             odometry=odometry, chunk_size=64)
    trusted = refine_in_rounds(spec, grid_map.hit_dist2, drifted, ranges, sensor, params, config, scans,
                               odometry=odometry, chunk_size=64, trust_odometry=True)
    assert plain.odometry_noise_scale == (1.0, 1.0, 1.0)
    assert all(0 < v <= 1 for v in trusted.odometry_noise_scale) and min(trusted.odometry_noise_scale) < 1
    assert not np.array_equal(plain.poses, trusted.poses)
    # Measured: scales (0.37, 0.33, 0.41), relative error 0.134 m plain and 0.124 trusted (the
    # odometry alone 0.49). A bound that a scale gone wrong (a chain held to a drifting odometry)
    # would break, not the measured gain.
    assert _relative_error(trusted.poses, truth) < 1.2 * _relative_error(plain.poses, truth)


def test_trusts_odometry_where_the_loops_take_its_heading():
    from types import SimpleNamespace

    from jaxslam.refine import trusts_odometry

    assert trusts_odometry(SimpleNamespace(num_loops=3, odometry_share=0.9))
    assert not trusts_odometry(SimpleNamespace(num_loops=3, odometry_share=0.06))  # MIT CSAIL's
    assert not trusts_odometry(SimpleNamespace(num_loops=0, odometry_share=1.0))  # nothing measured it
    assert not trusts_odometry(None)
