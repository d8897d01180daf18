"""The window posterior (jaxslam.window_posterior): the search against a brute-force evaluation of
the whole window, its masses against a float64 recomputation, and a window with two modes."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from rooms import ROOM_EXTENT, SENSOR, build_room_map, paged_field, room_path, scan_at

from jaxslam import motion
from jaxslam import window_posterior as W
from jaxslam.config import SlamConfig, default_params
from jaxslam.geometry import between, compose
from jaxslam.likelihood_field import endpoint_log_likelihoods
from jaxslam.occupancy import empty_map, insert_scan

CONFIG = SlamConfig(num_particles=4, proposal="smp", map_extent=ROOM_EXTENT, max_insert_range=10.0)
PARAMS = default_params()
posterior_fn = jax.jit(W.window_posterior, static_argnames=("config",))


@pytest.fixture(scope="module")
def room_field():
    return paged_field(build_room_map(3), CONFIG)


def _step(error=(0.0, 0.0, 0.0)):
    """x_{t-1}, the odometry u_t (the true motion plus ``error``) and z_t along the room's path."""
    path = room_path(6)
    motion_step = jnp.asarray(between(path[1], path[2])) + jnp.asarray(error, jnp.float32)
    return jnp.asarray(path[1]), motion_step, scan_at(path[2]), path[2]


def _log_pi(field, pose, motion_step, ranges, offsets, lookup):
    """log pi at x_{t-1} (+) (u + offsets), computed directly (no search)."""
    poses = compose(pose, motion_step + offsets)
    log_lik = endpoint_log_likelihoods(CONFIG.grid, field, poses, ranges, SENSOR, PARAMS.likelihood._replace(gain=1.0),
                                       lookup)
    return PARAMS.likelihood.gain * log_lik + motion.log_density(poses, pose, motion_step, PARAMS.motion)


def test_half_widths_are_sigmas_times_the_motion_stds_with_floors():
    u = jnp.asarray([0.8, 0.0, 0.2])
    std = np.asarray(motion.noise_std(u, PARAMS.motion))
    half = np.asarray(W.half_widths(u, PARAMS))
    np.testing.assert_allclose(half, np.maximum(3.0 * std, [0.1, 0.1, 0.1]), rtol=1e-6)
    still = np.asarray(W.half_widths(jnp.zeros(3), PARAMS))  # no motion: the floors
    np.testing.assert_allclose(still, [0.1, 0.1, 0.1], rtol=1e-6)


@pytest.mark.parametrize("error", [(0.0, 0.0, 0.0), (0.1, -0.05, 0.08), (-0.12, 0.08, -0.1)])
def test_search_finds_the_best_pose_of_a_brute_force_window(room_field, error):
    """Every pose of the window on the last level's lattice (80^3 poses) scored directly: the
    search's heaviest peak is within 1.5 nats of that lattice's best log pi (15 nats of the
    untempered scan) and within 1.5 cells and 0.03 rad of its pose, and the heaviest mode's mean
    within 1.5 cells and 0.03 rad of the pose the scan was cast from. A cell is what the search
    resolves: the last level reads the field by the nearest cell (``likelihood_lookup``), on which
    the posterior is flat across a cell."""
    pose, motion_step, ranges, truth = _step(error)
    post = posterior_fn(pose, room_field, motion_step, ranges, SENSOR, PARAMS, config=CONFIG, fit_gain=1.0)
    half = W.half_widths(motion_step, PARAMS)
    lattice = W.coarse_offsets(half, CONFIG.window_cells * 2**CONFIG.window_levels)
    values = np.concatenate([np.asarray(_log_pi(room_field, pose, motion_step, ranges, chunk, CONFIG.likelihood_lookup))
                             for chunk in jnp.split(lattice, 16)])
    best = int(np.argmax(values))
    heaviest = int(np.argmax(np.asarray(post.log_masses)))
    peak_offset = between(compose(pose, motion_step), post.peaks[heaviest])
    found = float(_log_pi(room_field, pose, motion_step, ranges, peak_offset[None], CONFIG.likelihood_lookup)[0])
    assert found >= values[best] - 1.5
    cell = CONFIG.resolution
    for reference, estimate in ((np.asarray(compose(pose, motion_step + lattice[best])), post.peaks[heaviest]),
                                (truth, post.means[heaviest])):
        gap = np.asarray(estimate) - reference
        assert np.hypot(gap[0], gap[1]) < 1.5 * cell and abs(gap[2]) < 0.03, gap


def test_masses_are_the_stencil_riemann_sums_and_log_eta_their_sum(room_field):
    """Each kept mode's log-mass is log sum_j p(z | x_j)^gain p(x_j | x_{t-1}, u) + log(cell volume)
    over the 27 stencil poses round its peak, recomputed in float64; log_eta is the log of their
    sum; each Gaussian is the untempered likelihood's softmax moments plus the floor, times the
    motion prior's world-frame Gaussian (the product in float64)."""
    pose, motion_step, ranges, _ = _step((0.1, -0.05, 0.08))
    post = posterior_fn(pose, room_field, motion_step, ranges, SENSOR, PARAMS, config=CONFIG, fit_gain=1.0)
    sm = PARAMS.scan_match
    spacing = np.array([float(sm.linear_step), float(sm.linear_step), float(sm.angular_step)])
    offsets = np.array(list(itertools.product((-1, 0, 1), repeat=3)), np.float64) * spacing
    gain = float(PARAMS.likelihood.gain)
    masses = np.asarray(post.log_masses, np.float64)
    kept = np.isfinite(masses)
    assert kept.sum() >= 1
    for m in np.flatnonzero(kept):
        candidates = np.asarray(post.peaks[m], np.float64) + offsets
        raw = np.asarray(endpoint_log_likelihoods(CONFIG.grid, room_field, jnp.asarray(candidates, jnp.float32), ranges,
                                                  SENSOR, PARAMS.likelihood._replace(gain=1.0)), np.float64)
        log_prior = np.asarray(motion.log_density(jnp.asarray(candidates, jnp.float32), pose, motion_step,
                                                  PARAMS.motion), np.float64)
        terms = gain * raw + log_prior
        want = terms.max() + math.log(np.exp(terms - terms.max()).sum()) + np.log(spacing).sum()
        assert masses[m] == pytest.approx(want, rel=1e-4)
        mean, cov = _product_reference(np.asarray(post.peaks[m], np.float64), offsets, raw, spacing, pose, motion_step)
        chol = np.asarray(post.chols[m], np.float64)
        np.testing.assert_allclose(chol @ chol.T, cov, rtol=1e-3, atol=1e-9)
        np.testing.assert_allclose(np.asarray(post.means[m], np.float64), mean, rtol=0, atol=1e-5)
    top = masses[kept].max()
    assert float(post.log_eta) == pytest.approx(top + math.log(np.exp(masses[kept] - top).sum()), rel=1e-5)


def _product_reference(peak, offsets, raw, spacing, pose, motion_step):
    """A mode's Gaussian in float64: the likelihood's stencil moments (gain 1) plus the floor,
    multiplied by the prior N(x_{t-1} (+) u, R diag(std^2) R^T) through the precisions."""
    w = np.exp(raw - raw.max())
    w /= w.sum()
    centred = offsets - w @ offsets
    cov_lik = (centred * w[:, None]).T @ centred + np.diag((float(PARAMS.scan_match.min_std_fraction) * spacing) ** 2)
    lik_mean = peak + w @ offsets
    std = np.asarray(motion.noise_std(motion_step, PARAMS.motion), np.float64)
    heading = float(pose[2])
    rot = np.array([[math.cos(heading), -math.sin(heading), 0.0], [math.sin(heading), math.cos(heading), 0.0],
                    [0.0, 0.0, 1.0]])
    cov_prior = rot @ np.diag(std**2) @ rot.T
    prior_mean = np.asarray(compose(pose, motion_step), np.float64)
    residual = prior_mean - lik_mean
    residual[2] = (residual[2] + math.pi) % (2 * math.pi) - math.pi
    cov = np.linalg.inv(np.linalg.inv(cov_lik) + np.linalg.inv(cov_prior))
    mean = lik_mean + cov @ np.linalg.inv(cov_prior) @ residual
    return mean, cov


def test_where_the_scan_says_nothing_the_modes_gaussian_is_the_motion_priors():
    """No beam returns (every range at range_max): the likelihood is flat, and with a motion noise
    as small as the box world's (stds about 0.01 m, 0.01 rad, a fifth of the stencil's 5 cm) the
    mode's Gaussian is the prior's (within 15 % in every std; the flat stencil's own moments
    pull it in by 5-10 %), centred on the prediction. With the prior inside the stencil's
    weights, as before, the fit kept the centre alone: stds at the floor, 0.005 m."""
    pose, motion_step, _, _ = _step()
    ranges = jnp.full_like(scan_at(room_path(6)[2]), SENSOR.range_max)
    params = PARAMS._replace(motion=motion.motion_params(0.01, 0.01, 0.01, 0.01, 0.005, 0.005))
    field = paged_field(build_room_map(3), CONFIG)
    post = posterior_fn(pose, field, motion_step, ranges, SENSOR, params, config=CONFIG, fit_gain=1.0)
    heaviest = int(np.argmax(np.asarray(post.log_masses)))
    chol = np.asarray(post.chols[heaviest], np.float64)
    prior_mean, prior_cov = (np.asarray(v, np.float64) for v in motion.world_gaussian(pose, motion_step, params.motion))
    np.testing.assert_allclose(np.sqrt(np.diag(chol @ chol.T)), np.sqrt(np.diag(prior_cov)), rtol=0.15)
    gap = np.asarray(post.means[heaviest], np.float64) - prior_mean
    assert np.hypot(gap[0], gap[1]) < 0.005 and abs(gap[2]) < 0.005, gap


def _twin_field(shift):
    """A room map with its walls twice, the second copy moved by ``shift`` (m) in x: a scan from
    a pose p fits at p and at p + shift equally."""
    from rooms import SPEC
    params = default_params()
    grid_map = empty_map(SPEC)
    insert = jax.jit(insert_scan, static_argnums=(0, 6, 7))
    for pose in room_path(6)[:3]:
        for dx in (0.0, shift):
            grid_map, _ = insert(SPEC, grid_map, jnp.asarray(pose) + jnp.asarray([dx, 0.0, 0.0]), scan_at(pose), SENSOR,
                                 params.insertion, 10.0, 4)
    return paged_field(grid_map, CONFIG)


def test_two_modes_are_both_kept_and_drawn_in_proportion_to_their_mass():
    """The scan fits at p and at p + 0.3 m; the odometry predicts the midpoint, so the prior
    weighs both alike. The search keeps a mode at each (within a cell), and 4,000 draws of the SMP's
    mixture fall near each in the share of its mass (within 4 standard errors)."""
    shift = 0.3
    field = _twin_field(shift)
    path = room_path(6)
    true_pose = path[2]
    predicted = np.asarray(true_pose) + np.array([shift / 2, 0.0, 0.0], np.float32)
    pose = jnp.asarray(path[1])
    motion_step = jnp.asarray(between(pose, jnp.asarray(predicted)))
    post = posterior_fn(pose, field, motion_step, scan_at(true_pose), SENSOR, PARAMS, config=CONFIG, fit_gain=1.0)
    assert bool(post.matched)
    kept = np.flatnonzero(np.isfinite(np.asarray(post.log_masses)))
    peaks = np.asarray(post.peaks)[kept]
    for centre in (true_pose, np.asarray(true_pose) + np.array([shift, 0.0, 0.0])):
        assert np.min(np.hypot(peaks[:, 0] - centre[0], peaks[:, 1] - centre[1])) < CONFIG.resolution
    log_mix = W.mixture_log_weights(post)
    draws = np.asarray(W.sample(jax.random.PRNGKey(0), post, log_mix, (4000,)))
    near_first = np.hypot(draws[:, 0] - true_pose[0], draws[:, 1] - true_pose[1]) < 0.1
    near_second = np.hypot(draws[:, 0] - true_pose[0] - shift, draws[:, 1] - true_pose[1]) < 0.1
    assert (near_first | near_second).mean() > 0.98
    weights = np.exp(np.asarray(log_mix, np.float64))
    means = np.asarray(post.means)
    share_first = weights[np.hypot(means[:, 0] - true_pose[0], means[:, 1] - true_pose[1]) < 0.1].sum()
    assert 0.1 < share_first < 0.9  # the prior and the scan leave both modes real mass
    se = math.sqrt(share_first * (1 - share_first) / 4000)
    assert abs(near_first.mean() - share_first) < 4 * se


def test_mixture_log_density_matches_numpy_and_uniform_share(room_field):
    """log_density is the float64 log of sum_m w_m N(x; mean_m, L_m L_m^T) (angle wrapped), and the
    uniform share gives every kept mode at least that share over the kept count."""
    pose, motion_step, ranges, _ = _step((0.2, 0.1, -0.15))
    post = posterior_fn(pose, room_field, motion_step, ranges, SENSOR, PARAMS, config=CONFIG, fit_gain=1.0)
    log_mix = W.mixture_log_weights(post, 0.5)
    weights = np.exp(np.asarray(log_mix, np.float64))
    kept = np.isfinite(np.asarray(post.log_masses))
    assert weights.sum() == pytest.approx(1.0, abs=1e-5)
    assert np.all(weights[kept] >= 0.5 / kept.sum() - 1e-6) and np.all(weights[~kept] == 0)
    xs = np.asarray(W.sample(jax.random.PRNGKey(1), post, log_mix, (5,)), np.float64)
    got = np.asarray(W.log_density(jnp.asarray(xs, jnp.float32), post, log_mix))
    for x, value in zip(xs, got):
        total = 0.0
        for m in np.flatnonzero(weights > 0):
            chol = np.asarray(post.chols[m], np.float64)
            r = x - np.asarray(post.means[m], np.float64)
            r[2] = (r[2] + math.pi) % (2 * math.pi) - math.pi
            z = np.linalg.solve(chol, r)
            total += weights[m] * math.exp(-0.5 * z @ z) / ((2 * math.pi) ** 1.5 * np.prod(np.diag(chol)))
        assert value == pytest.approx(math.log(total), rel=1e-4, abs=1e-4)
