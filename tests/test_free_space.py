"""The free-space evidence (likelihood_field.see_through_log_likelihood) against a NumPy reference,
and in the RBPF's weights."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from rooms import ROOM_EXTENT, SENSOR as ROOM_SENSOR, build_room_map, paged_maps, room_path, scan_at

from jaxslam import likelihood_field as S
from jaxslam import rbpf
from jaxslam.config import ConfigError, SlamConfig, default_params, params_from_dict
from jaxslam.geometry import between
from jaxslam.grid import GridSpec
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.maps import fields
from jaxslam.occupancy import FAR, free_lengths
from jaxslam.proposals.base import StepInputs

SPEC = GridSpec((40, 50), 0.1, (-2.0, -1.5))  # x in [-2, 3], y in [-1.5, 2.5]
SENSOR = make_sensor(uniform_beams(31, math.pi), range_min=0.1, range_max=3.0, laser_pose=(0.05, 0.0, 0.1))
INSERTION = default_params().insertion
NUM_SAMPLES = 40
see_through = jax.jit(S.see_through_log_likelihood, static_argnums=(0, 6))


def params(see=0.05, margin=0.15, gain=0.7):
    return S.LikelihoodParams(*(jnp.float32(v) for v in (0.1, 0.9, 0.05, gain, see, margin)))


def np_crossings(spec, hit, pose, free_len, sensor, margin, num_samples):
    """Beam by beam, ray by ray and sample by sample in float64: how many beams cross a registered
    cell and come out into clear space (two cells from any registered one) again before their
    checked length ends, along all three of their rays (the beam's and one two cells to either side)."""
    lp = np.asarray(sensor.laser_pose, np.float64)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    origin = np.array([pose[0] + c * lp[0] - s * lp[1], pose[1] + s * lp[0] + c * lp[1]])
    count = 0
    for angle, length in zip(np.asarray(sensor.beam_angles, np.float64), np.asarray(free_len, np.float64)):
        a = pose[2] + lp[2] + angle
        direction = np.array([math.cos(a), math.sin(a)])
        normal = np.array([-direction[1], direction[0]])
        rays_crossing = 0
        for side in S.SEE_THROUGH_RAYS:
            registered_at = None
            for k in range(1, num_samples + 1):
                d = k * spec.resolution
                if d > length - margin:
                    break
                x, y = origin + d * direction + side * spec.resolution * normal
                row = math.floor((y - spec.origin[1]) / spec.resolution)
                col = math.floor((x - spec.origin[0]) / spec.resolution)
                inside = 0 <= row < spec.shape[0] and 0 <= col < spec.shape[1]
                d2 = int(hit[row, col]) if inside else FAR
                if d2 == 0 and registered_at is None:
                    registered_at = k
                if d2 >= 4 and registered_at is not None:  # clear again after a registered cell
                    rays_crossing += 1
                    break
        count += rays_crossing == 3
    return count


def test_counts_the_beams_crossing_registered_cells_as_the_numpy_reference():
    rng = np.random.default_rng(3)
    for trial in range(6):
        hit = np.where(rng.random(SPEC.shape) < 0.25, 0, FAR).astype(np.uint8)
        near = rng.random(SPEC.shape) < 0.15
        hit[near] = rng.choice(np.array([1, 2, 4, 9], np.uint8), size=int(near.sum()))  # 1, 2: not clear yet
        ranges = rng.uniform(0.05, 3.5, 31).astype(np.float32)  # below range_min, returns, no return
        pose = np.array([rng.uniform(-0.5, 1.0), rng.uniform(0.0, 1.0), rng.uniform(-3, 3)], np.float32)
        free = free_lengths(jnp.asarray(ranges), SENSOR, INSERTION, 15.0)
        got = float(see_through(SPEC, jnp.asarray(hit), jnp.asarray(pose), free, SENSOR, params(), NUM_SAMPLES))
        n = np_crossings(SPEC, hit, pose.astype(np.float64), np.asarray(free), SENSOR, 0.15, NUM_SAMPLES)
        assert got == pytest.approx(0.7 * math.log(0.05) * n, rel=1e-5, abs=1e-6), trial
        assert n > 0 or trial > 0  # the first trial's map does cross something


def test_a_beam_through_a_wall_costs_once_and_the_margin_and_its_end_bound_the_check():
    hit = np.full(SPEC.shape, FAR, np.uint8)
    hit[13:18, 30:33] = 0  # cells x in [1.0, 1.3), y in [-0.2, 0.3): straight ahead of the pose below
    clipped = np.full(SPEC.shape, FAR, np.uint8)
    clipped[16:18, 30:33] = 0  # the two rows up only: the beam's left ray alone crosses them
    sensor = make_sensor(jnp.zeros(1), range_min=0.1, range_max=3.0)
    pose = jnp.array([0.03, 0.05, 0.0])  # samples at x = 0.13, 0.23, ... (off the cells' edges)

    def cost(r, margin=0.15, samples=NUM_SAMPLES):
        free = free_lengths(jnp.array([r]), sensor, INSERTION, 15.0)
        return float(see_through(SPEC, jnp.asarray(hit), pose, free, sensor, params(margin=margin), samples))

    one = 0.7 * math.log(0.05)
    assert cost(2.0) == pytest.approx(one)  # through fifteen registered cells: one beam, counted once
    assert cost(0.95) == 0.0  # ends before them
    assert cost(1.1) == 0.0  # ends in them: the margin (0.15 m) skips its last cells
    assert cost(1.1, margin=0.0) == 0.0  # checked to its end, but never clear again after them: its own wall
    assert cost(1.4) == 0.0  # ends just behind them: the margin leaves no clear cell after them
    assert cost(1.4, margin=0.0) == pytest.approx(one)
    assert cost(2.0, samples=9) == 0.0  # the samples reach 0.9 m only
    assert cost(3.5) == pytest.approx(one)  # no return: its free length (no_return_free_range) crosses
    free = free_lengths(jnp.array([2.0]), sensor, INSERTION, 15.0)
    assert float(see_through(SPEC, jnp.asarray(clipped), pose, free, sensor, params(), NUM_SAMPLES)) == 0.0


def test_see_through_one_adds_nothing_and_the_settings_are_checked():
    hit = np.full(SPEC.shape, FAR, np.uint8)
    hit[:, 29:31] = 0  # a wall across the map at x in [0.9, 1.1): the beams ahead pass it
    free = jnp.full((31,), 2.0)
    pose = jnp.array([0.5, 0.53, 0.0])
    assert float(see_through(SPEC, jnp.asarray(hit), pose, free, SENSOR, params(see=1.0), NUM_SAMPLES)) == 0.0
    n = np_crossings(SPEC, hit, np.asarray(pose, np.float64), np.asarray(free), SENSOR, 0.15, NUM_SAMPLES)
    assert n > 5
    assert float(see_through(SPEC, jnp.asarray(hit), pose, free, SENSOR, params(), NUM_SAMPLES)) == pytest.approx(
        0.7 * math.log(0.05) * n)
    with pytest.raises(ConfigError, match="free_space_samples"):
        SlamConfig(free_space_samples=-1)
    for name, bad in (("likelihood.see_through", 0.0), ("likelihood.see_through", 1.5),
                      ("likelihood.free_margin", -0.1)):
        with pytest.raises(ConfigError, match=name):
            params_from_dict({name: bad})


def test_the_step_adds_the_evidence_at_each_drawn_pose_in_its_own_map():
    """With ``free_space_samples`` the step's weights are the proposal's increments plus the
    free-space evidence at each particle's drawn pose in its map; at ``see_through`` 1 the step is
    the one without, bit for bit."""
    n = 4
    config = SlamConfig(num_particles=n, proposal="op", map_extent=ROOM_EXTENT, max_insert_range=10.0, beam_stride=1,
                        free_space_samples=200)
    room_map = build_room_map(3)
    path = room_path(6)
    # The robot's scan from a pose the map does not expect (0.4 m aside): its beams pass the walls
    # the map holds, so the evidence is not zero.
    seen = path[2] + np.array([0.0, 0.4, 0.0], np.float32)
    inputs = StepInputs(motion=jnp.asarray(between(path[1], path[2])), ranges=scan_at(seen),
                        future_motions=jnp.zeros((0, 3)), future_ranges=jnp.zeros((0, 61)),
                        future_valid=jnp.zeros((0,), bool))
    state = rbpf.SlamState(jnp.broadcast_to(jnp.asarray(path[1]), (n, 3)), jnp.full((n,), -math.log(n)),
                           paged_maps(room_map, config, n), jnp.int32(0))
    step = jax.jit(rbpf.step, static_argnames="config")
    key = jax.random.key(2)
    on_params = default_params(resample_threshold=0.0)
    off_params = default_params(resample_threshold=0.0, **{"likelihood.see_through": 1.0})
    plain = dataclasses.replace(config, free_space_samples=0)
    on, on_info = step(key, state, inputs, ROOM_SENSOR, on_params, config)
    off, off_info = step(key, state, inputs, ROOM_SENSOR, off_params, config)
    without, without_info = step(key, state, inputs, ROOM_SENSOR, on_params, plain)
    np.testing.assert_array_equal(np.asarray(off.log_weights), np.asarray(without.log_weights))
    np.testing.assert_array_equal(np.asarray(off.poses), np.asarray(without.poses))
    np.testing.assert_array_equal(np.asarray(on.poses), np.asarray(without.poses))
    free = free_lengths(inputs.ranges, ROOM_SENSOR, on_params.insertion, config.max_insert_range)
    evidence = np.array([float(S.see_through_log_likelihood(config.grid, field, pose, free, ROOM_SENSOR,
                                                            on_params.likelihood, config.free_space_samples))
                         for field, pose in zip(particle_fields(state.maps, n), np.asarray(without.poses))])
    assert np.all(evidence < 0)
    expected = np.asarray(without.log_weights, np.float64) + evidence
    expected -= np.logaddexp.reduce(expected)
    np.testing.assert_allclose(np.asarray(on.log_weights), expected, atol=1e-5)



def particle_fields(maps, n):
    """Each particle's paged field (its directory into the shared pools)."""
    field = fields(maps)
    return [field._replace(directory=field.directory[i]) for i in range(n)]
