"""One RBPF step piece by piece: the SMP's weight and fallback, the weight recursion, the reset
when every weight is zero, the resampling trigger, and the step inputs at the end of a log."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from rooms import ROOM_EXTENT, SENSOR, build_room_map, paged_field, paged_maps, room_path, scan_at

from jaxslam import rbpf, slip_search
from jaxslam.config import SlamConfig, default_params
from jaxslam.geometry import between, compose
from jaxslam.laser import within_usable_range
from jaxslam.laserlog import LaserLog, select_updates
from jaxslam.proposals import odometry, scan_match
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.maps import FIELD_AXES, fields
from jaxslam import window_posterior

N = 6
CONFIG = SlamConfig(num_particles=N, proposal="smp", map_extent=ROOM_EXTENT, max_insert_range=10.0, beam_stride=1)
# Jitted once here (op by op, a scan-matching step takes tens of seconds).
smp_propose = jax.jit(scan_match.propose, static_argnames="config")
op_propose = jax.jit(odometry.propose, static_argnames="config")
posterior_fn = jax.jit(window_posterior.window_posterior, static_argnames="config")
step = jax.jit(rbpf.step, static_argnames="config")


@pytest.fixture(scope="module")
def room_map():
    return build_room_map(3)


@pytest.fixture(scope="module")
def room_field(room_map):
    return paged_field(room_map, CONFIG)


def _inputs():
    path = room_path(6)
    return StepInputs(motion=jnp.asarray(between(path[1], path[2])), ranges=scan_at(path[2]),
                      future_motions=jnp.zeros((0, 3)), future_ranges=jnp.zeros((0, 61)),
                      future_valid=jnp.zeros((0,), bool)), jnp.asarray(path[1])


def _state(room_map, pose, log_weights):
    maps = paged_maps(room_map, CONFIG, N)
    return rbpf.SlamState(jnp.broadcast_to(pose, (N, 3)), jnp.asarray(log_weights, jnp.float32), maps, jnp.int32(0))


def test_smp_weight_is_the_window_posteriors_and_its_draw_comes_from_a_mode(room_field):
    """The SMP's increment is the window posterior's log_eta, and its draw is the mixture's draw
    with the same key (a mode by its mass, then that mode's Gaussian)."""
    inputs, pose = _inputs()
    params = default_params()
    key = jax.random.key(4)
    out = smp_propose(key, pose, room_field, inputs, SENSOR, params, CONFIG)
    post = posterior_fn(pose, room_field, inputs.motion, inputs.ranges, SENSOR, params, config=CONFIG, fit_gain=1.0)
    assert not bool(out.fallback) and bool(post.matched)
    np.testing.assert_allclose(float(out.log_weight_increment), float(post.log_eta), rtol=1e-6)
    key_sample, _ = jax.random.split(key)
    draw = window_posterior.sample(key_sample, post, window_posterior.mixture_log_weights(post))
    np.testing.assert_allclose(np.asarray(out.pose), np.asarray(draw), atol=1e-5)


def test_smp_falls_back_to_the_odometry_proposal_when_the_match_fails(room_field):
    """A match score under scan_match.min_score (here impossible: 1.01) uses the OP's draw and
    weight, with the OP's own key (the second half of the SMP's split)."""
    inputs, pose = _inputs()
    params = default_params(**{"scan_match.min_score": 1.01})
    key = jax.random.key(4)
    out = smp_propose(key, pose, room_field, inputs, SENSOR, params, CONFIG)
    _, key_fallback = jax.random.split(key)
    op = op_propose(key_fallback, pose, room_field, inputs, SENSOR, params, CONFIG)
    assert bool(out.fallback)
    np.testing.assert_array_equal(np.asarray(out.pose), np.asarray(op.pose))
    assert float(out.log_weight_increment) == float(op.log_weight_increment)


def test_step_weight_recursion_matches_the_proposals_increments(room_map):
    """w_t ∝ w_{t-1} exp(increment): the step's normalised log-weights (no resampling at threshold
    0) and its log-evidence log sum_i w_{t-1,i} exp(increment_i), against NumPy in float64 on the
    increments the proposal returns for the step's own keys."""
    inputs, pose = _inputs()
    params = default_params(**{"resample_threshold": 0.0})
    rng = np.random.default_rng(0)
    prior = np.log(rng.dirichlet(np.ones(N)))
    state = _state(room_map, pose, prior)
    key = jax.random.key(7)
    new_state, info = step(key, state, inputs, SENSOR, params, CONFIG)
    key_prop, _ = jax.random.split(key)
    out = jax.vmap(smp_propose, in_axes=(0, 0, FIELD_AXES, None, None, None, None))(
        jax.random.split(key_prop, N), state.poses, fields(state.maps), inputs, SENSOR, params, CONFIG)
    unnormalised = np.asarray(state.log_weights, np.float64) + np.asarray(out.log_weight_increment, np.float64)
    log_evidence = np.logaddexp.reduce(unnormalised)
    np.testing.assert_allclose(np.asarray(new_state.log_weights), unnormalised - log_evidence, atol=1e-5)
    # The evidence, not the weights, carries the normalising constant per counted beam: a Gaussian
    # over cells of the map's width at 0, 1, 2, ... cells from the wall.
    ranges = np.asarray(inputs.ranges, np.float64)
    counted = np.sum((ranges >= SENSOR.range_min) & (ranges < SENSOR.range_max))
    lik = params.likelihood
    cells = CONFIG.resolution * np.arange(10_000)
    log_z = np.log(CONFIG.resolution * np.sum(np.exp(-0.5 * (cells / float(lik.sigma)) ** 2)))
    normalizer = -float(lik.gain) * counted * log_z
    np.testing.assert_allclose(float(info.log_evidence), log_evidence + normalizer, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(new_state.poses), np.asarray(out.pose), atol=1e-6)
    assert not bool(info.resampled) and not bool(info.degenerate)
    np.testing.assert_array_equal(np.asarray(info.ancestors), np.arange(N))
    assert int(info.best_particle) == int(np.argmax(unnormalised))


def test_every_weight_zero_resets_to_uniform_and_reports_it(room_map, monkeypatch):
    """A proposal that gives every particle weight zero (or NaN) leaves finite poses and uniform
    weights; the step says ``degenerate`` and its log-evidence is -inf."""
    inputs, pose = _inputs()

    def hopeless(key, pose, grid_map, inputs, sensor, params, config, step_motion=None):
        inc = jnp.where(jax.random.uniform(key) < 0.5, -jnp.inf, jnp.nan)
        return ProposalOutput(pose, inc, jnp.bool_(True))

    from jaxslam.proposals import PROPOSALS, Proposal

    monkeypatch.setitem(PROPOSALS, "op", Proposal(hopeless, "test"))
    state = _state(room_map, pose, np.full(N, -math.log(N)))
    # A config no other test traces (jit caches traces per function and static config).
    config = dataclasses.replace(CONFIG, proposal="op", match_iterations=1)
    new_state, info = step(jax.random.key(0), state, inputs, SENSOR, default_params(), config)
    assert bool(info.degenerate) and np.isneginf(float(info.log_evidence))
    np.testing.assert_allclose(np.asarray(new_state.log_weights), np.full(N, -math.log(N)), rtol=1e-6)
    assert np.all(np.isfinite(np.asarray(new_state.poses)))
    assert int(info.num_fallbacks) == N


@pytest.mark.parametrize("threshold, resampled", [(0.0, False), (1.01, True)])
def test_resampling_is_triggered_by_the_ess_threshold(room_map, threshold, resampled):
    """ESS < threshold * N resamples: 0 never does, above 1 always does (then weights are uniform
    and every particle's map is its ancestor's)."""
    inputs, pose = _inputs()
    params = default_params(**{"resample_threshold": threshold})
    state = _state(room_map, pose, np.full(N, -math.log(N)))
    new_state, info = step(jax.random.key(3), state, inputs, SENSOR, params, CONFIG)
    assert bool(info.resampled) == resampled
    if resampled:
        np.testing.assert_allclose(np.asarray(new_state.log_weights), np.full(N, -math.log(N)), rtol=1e-6)
        anc = np.asarray(info.ancestors)
        np.testing.assert_array_equal(np.asarray(new_state.poses), np.asarray(info.proposed_poses)[anc])
    assert float(info.ess) <= N + 1e-3


def test_build_inputs_at_the_end_of_the_log():
    """Step s carries scans s+1..s+K; past the last processed scan they are marked invalid, their
    motions are zero and their ranges repeat the last scan (never read: the horizon shrinks)."""
    num_scans, num_beams, horizon = 7, 5, 3
    odometry = np.stack([np.arange(num_scans) * 1.0, np.zeros(num_scans), np.zeros(num_scans)], axis=1)
    ranges = np.arange(num_scans * num_beams, dtype=np.float32).reshape(num_scans, num_beams) / 10.0 + 0.5
    sensor = SENSOR._replace(beam_angles=SENSOR.beam_angles[:num_beams])
    log = LaserLog(np.arange(num_scans, dtype=np.float64), odometry, ranges, sensor, None, "line")
    selection = select_updates(log, 0.0, 0.0)  # every scan
    inputs = rbpf.build_inputs(log, selection, horizon)
    steps = num_scans - 1
    assert inputs.ranges.shape == (steps, num_beams)
    assert inputs.future_ranges.shape == (steps, horizon, num_beams)
    np.testing.assert_array_equal(inputs.ranges, ranges[1:])
    for s in range(steps):  # step s processes scan s + 1
        for k in range(horizon):
            scan = s + 2 + k
            assert bool(inputs.future_valid[s, k]) == (scan < num_scans)
            if scan < num_scans:
                np.testing.assert_array_equal(inputs.future_ranges[s, k], ranges[scan])
                np.testing.assert_allclose(inputs.future_motions[s, k], [1.0, 0.0, 0.0], atol=1e-6)
            else:
                np.testing.assert_array_equal(inputs.future_motions[s, k], 0.0)
                np.testing.assert_array_equal(inputs.future_ranges[s, k], ranges[-1])
    assert not inputs.future_valid[-1].any()
    assert rbpf.build_inputs(log, selection, 0).future_ranges.shape == (steps, 0, num_beams)


def test_beams_beyond_the_usable_range_do_not_dilute_the_match_score(room_map):
    """A match's score counts only beams shorter than ``max_insert_range`` (GMapping's usable
    range): the map registers no endpoint farther from a pose. Here 60 % of the beams read 6 m
    (> 5 m, < the laser's 8 m): counted, they pull the score under ``min_score = 0.4``; the SMP
    leaves them out and every particle of a step matches."""
    from jaxslam.likelihood_field import endpoint_match_score as match_score

    config = dataclasses.replace(CONFIG, max_insert_range=5.0)
    inputs, pose = _inputs()
    params = default_params(**{"scan_match.min_score": 0.4, "resample_threshold": 0.0})
    ranges = np.asarray(inputs.ranges).copy()
    long = np.arange(ranges.size) % 5 < 3
    assert np.mean(ranges[~long] < 5.0) > 0.8  # the others are mostly usable
    ranges[long] = 6.0
    field = paged_field(room_map, config)
    true_pose = compose(pose, inputs.motion)
    sigma = params.likelihood.sigma
    diluted = float(match_score(config.grid, field, true_pose, jnp.asarray(ranges), SENSOR, sigma))
    usable = float(match_score(config.grid, field, true_pose, within_usable_range(jnp.asarray(ranges), 5.0), SENSOR,
                               sigma))
    assert diluted < 0.4 < usable
    _, info = step(jax.random.key(3), _state(room_map, pose, np.full(N, -math.log(N))),
                   inputs._replace(ranges=jnp.asarray(ranges)), SENSOR, params, config)
    assert int(info.num_fallbacks) == 0
    np.testing.assert_array_equal(np.asarray(within_usable_range(jnp.asarray(ranges), 5.0)),
                                  np.where(ranges < 5.0, ranges, -1.0))


def test_a_step_in_blocks_of_particles_is_the_same_bit_for_bit(room_map):
    """``particle_block`` (proposals and insertion a block at a time) changes no bit of the step:
    6 particles in blocks of 4 (a remainder block of 2; an insertion padded to 8) and of 1."""
    inputs, pose = _inputs()
    params = default_params()
    state = _state(room_map, pose, np.full(N, -math.log(N)))
    whole = step(jax.random.key(3), state, inputs, SENSOR, params, CONFIG)
    for block in (4, 1):
        blocked = step(jax.random.key(3), state, inputs, SENSOR, params, dataclasses.replace(CONFIG,
                                                                                              particle_block=block))
        for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(blocked)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("slip_odds, slips", [(10.0, True), (-10.0, False)])
def test_the_slip_search_proposes_again_under_the_slip_component_when_it_triggers(room_map, monkeypatch, slip_odds,
                                                                                   slips):
    """``with_slip_search(propose_fn)``: slip odds of the heaviest particle (here fixed) whose
    probability is over ``scan_match.slip_trigger`` run ``propose_fn`` a second time, under the
    slip component with the key ``fold_in(key, _TAG_SLIP)``, and the particles draw from the
    mixture (here every one keeps its slip draw); under it, the proposal is ``propose_fn``'s
    alone and no particle slipped."""
    inputs, pose = _inputs()
    monkeypatch.setattr(slip_search, "slip_log_odds", lambda *args: jnp.float32(slip_odds))

    def propose_fn(key, state, inputs, sensor, params, config, step_motion=None):
        slipped = step_motion is not None
        # The slip component's draws explain the scan far better than the usual ones.
        return ProposalOutput(jax.random.uniform(key, (N, 3)) + (10.0 if slipped else 0.0),
                              jnp.full((N,), 0.0 if slipped else -1e3), jnp.zeros((N,), bool))

    key = jax.random.key(5)
    state = _state(room_map, pose, np.full(N, -math.log(N)))
    out, num_slipped = slip_search.with_slip_search(propose_fn)(key, state, inputs, SENSOR, default_params(), CONFIG)
    if slips:
        expected = jax.random.uniform(jax.random.fold_in(key, slip_search._TAG_SLIP), (N, 3)) + 10.0
        assert int(num_slipped) == N
    else:
        expected = jax.random.uniform(key, (N, 3))
        assert int(num_slipped) == 0
        np.testing.assert_array_equal(np.asarray(out.log_weight_increment), -1e3)
    np.testing.assert_array_equal(np.asarray(out.pose), np.asarray(expected))
    _, none = slip_search.without_slip_search(propose_fn)(key, state, inputs, SENSOR, default_params(), CONFIG)
    assert int(none) == 0
