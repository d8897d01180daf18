"""Tests of the simulator: ray casting, scans, odometry, paths, worlds and scenarios."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxslam.geometry import between
from jaxslam.motion import motion_params, noise_std
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.sim import (
    box_segments,
    box_world_scenario,
    circle_path,
    concat_paths,
    concat_worlds,
    hall_scenario,
    make_world,
    noisy_odometry,
    office_scenario,
    passage_indices,
    path_crossings,
    point_segment_distance,
    polyline_segments,
    raycast,
    simulate_log,
    simulate_scan,
    simulate_scans,
    wall_segments,
    waypoint_path,
)

# ------------------------------------------------------------------ reference ray caster


def wrap(theta):
    """Angles wrapped to (-pi, pi], in float64 (geometry.wrap_angle computes in float32)."""
    return np.pi - np.mod(np.pi - np.asarray(theta, np.float64), 2.0 * np.pi)


# Jitted once per shape: eager dispatch would compile each primitive separately.
jit_raycast = jax.jit(raycast)

_NEAR = 1e-4  # float32 casts differ from float64 near these edges; such rays are not compared


def reference_raycast(segments, origin, angle, max_range):
    """Textbook ray/segment intersection in float64, one segment at a time.

    Returns ``(range, hit, ambiguous)``: ``ambiguous`` flags rays whose answer float32
    rounding may change (grazing an endpoint, near-parallel, two hits at nearly the same
    distance, a hit at nearly max_range or at the origin).
    """
    d = np.array([np.cos(angle), np.sin(angle)])
    hits, ambiguous = [], False
    for m, (x1, y1, x2, y2) in enumerate(np.asarray(segments, np.float64)):
        e = np.array([x2 - x1, y2 - y1])
        ap = np.array([x1 - origin[0], y1 - origin[1]])
        denom = d[0] * e[1] - d[1] * e[0]
        if abs(denom) <= _NEAR * np.hypot(*e):
            # (Near-)parallel: a miss, unless the ray runs along the segment's line.
            ambiguous |= abs(ap[0] * d[1] - ap[1] * d[0]) < 1e-3
            continue
        t = (ap[0] * e[1] - ap[1] * e[0]) / denom
        s = (ap[0] * d[1] - ap[1] * d[0]) / denom
        if -_NEAR < t < max_range + _NEAR and -_NEAR < s < 1 + _NEAR:
            ambiguous |= s < _NEAR or s > 1 - _NEAR or t < _NEAR or abs(t - max_range) < _NEAR
        if t > 0 and 0 <= s <= 1:
            hits.append((t, m))
    hits.sort()
    if len(hits) > 1 and hits[1][0] - hits[0][0] < _NEAR:
        ambiguous = True
    if hits and hits[0][0] < max_range:
        return hits[0][0], hits[0][1], ambiguous
    return max_range, -1, ambiguous


def compare_with_reference(segments, origins, angles, max_range):
    """Number of compared rays; asserts every unambiguous ray matches the reference."""
    ranges, hit = jit_raycast(jnp.asarray(segments, jnp.float32), jnp.asarray(origins, jnp.float32),
                          jnp.asarray(angles, jnp.float32), max_range)
    ranges, hit = np.asarray(ranges), np.asarray(hit)
    # Compare against the float32 inputs the caster saw.
    segments32 = np.asarray(segments, np.float32).astype(np.float64)
    origins32 = np.asarray(origins, np.float32).astype(np.float64)
    angles32 = np.asarray(angles, np.float32).astype(np.float64)
    compared = 0
    for i in range(len(angles32)):
        ref_range, ref_hit, ambiguous = reference_raycast(segments32, origins32[i], angles32[i], max_range)
        if ambiguous:
            continue
        compared += 1
        assert hit[i] == ref_hit, (i, hit[i], ref_hit, ranges[i], ref_range)
        assert abs(ranges[i] - ref_range) <= 1e-4 * (1 + ref_range), (i, ranges[i], ref_range)
    return compared


def random_rays(rng, num_segments=20, num_rays=64, extent=10.0):
    segments = rng.uniform(-extent, extent, (num_segments, 4))
    origins = rng.uniform(-extent, extent, (num_rays, 2))
    angles = rng.uniform(-np.pi, np.pi, num_rays)
    return segments, origins, angles


@pytest.mark.parametrize("seed", range(4))
def test_raycast_matches_reference_random(seed):
    rng = np.random.default_rng(seed)
    segments, origins, angles = random_rays(rng)
    compared = compare_with_reference(segments, origins, angles, max_range=12.0)
    assert compared >= 60  # nearly every random ray is unambiguous


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.5, 30.0))
def test_raycast_matches_reference_hypothesis(seed, max_range):
    rng = np.random.default_rng(seed)
    segments, origins, angles = random_rays(rng)
    compare_with_reference(segments, origins, angles, max_range=max_range)


def test_raycast_axis_aligned_and_grid_angles():
    # Beams at exactly 0, +-90 and 180 degrees against walls of a room: the common case in
    # an office, where sin/cos in float32 are not exactly 0.
    room = box_segments(0.0, 0.0, 8.0, 6.0)
    angles = np.linspace(-np.pi, np.pi, 73)
    origins = np.tile([[0.7, -0.4]], (angles.size, 1))
    assert compare_with_reference(room, origins, angles, max_range=20.0) >= 70
    ranges, _ = jit_raycast(room, jnp.array([0.7, -0.4]), jnp.array([0.0, np.pi / 2, np.pi, -np.pi / 2]), 20.0)
    np.testing.assert_allclose(ranges, [3.3, 3.4, 4.7, 2.6], atol=1e-5)


def test_raycast_parallel_rays_miss():
    rng = np.random.default_rng(7)
    segments = rng.uniform(-5, 5, (50, 4))
    e = segments[:, 2:] - segments[:, :2]
    direction = np.arctan2(e[:, 1], e[:, 0])
    normal = np.stack([-np.sin(direction), np.cos(direction)], axis=-1)
    # Rays parallel to their segment, offset sideways by 0.05 to 1 m, starting before it.
    offset = rng.uniform(0.05, 1.0, 50)[:, None] * np.where(rng.random(50) < 0.5, -1, 1)[:, None]
    origins = segments[:, :2] + offset * normal - 0.5 * e
    for m in range(50):
        for angle in (direction[m], direction[m] + np.pi):
            r, hit = jit_raycast(segments[m:m + 1], origins[m], angle, 50.0)
            assert int(hit) == -1 and float(r) == 50.0
    # Exactly axis-aligned: the cross product is exactly zero.
    r, hit = jit_raycast(np.array([[1.0, 1.0, 5.0, 1.0]]), np.array([0.0, 0.5]), 0.0, 50.0)
    assert int(hit) == -1


def test_raycast_ray_starting_on_segment_ignores_it():
    rng = np.random.default_rng(3)
    segments = rng.uniform(-10, 10, (200, 4)).astype(np.float32)
    fraction = rng.uniform(0.05, 0.95, (200, 1))
    origins = segments[:, :2] + fraction * (segments[:, 2:] - segments[:, :2])
    angles = rng.uniform(-np.pi, np.pi, 200)
    for m in range(200):
        _, hit = jit_raycast(segments[m:m + 1], origins[m], angles[m], 30.0)
        assert int(hit) == -1, m


def test_raycast_collinear_ray_misses_or_hits_near_end():
    rng = np.random.default_rng(4)
    segments = rng.uniform(-10, 10, (200, 4)).astype(np.float32)
    e = segments[:, 2:] - segments[:, :2]
    length = np.hypot(e[:, 0], e[:, 1])
    gap = rng.uniform(0.1, 3.0, 200)
    origins = segments[:, :2] - (gap / length)[:, None] * e
    angles = np.arctan2(e[:, 1], e[:, 0])
    for m in range(200):
        r, hit = jit_raycast(segments[m:m + 1], origins[m], angles[m], 30.0)
        assert int(hit) == -1 or abs(float(r) - gap[m]) < 1e-3, (m, float(r), gap[m])


def test_raycast_active_mask_and_hit_index():
    segments = np.array([[2.0, -1.0, 2.0, 1.0], [4.0, -1.0, 4.0, 1.0]])
    r, hit = jit_raycast(segments, jnp.zeros(2), 0.0, 10.0)
    assert int(hit) == 0 and abs(float(r) - 2.0) < 1e-6
    r, hit = jit_raycast(segments, jnp.zeros(2), 0.0, 10.0, active=jnp.array([False, True]))
    assert int(hit) == 1 and abs(float(r) - 4.0) < 1e-6
    r, hit = jit_raycast(segments, jnp.zeros(2), 0.0, 3.0, active=jnp.array([False, True]))
    assert int(hit) == -1 and float(r) == 3.0


# ------------------------------------------------------------------------------- worlds


def test_world_builders():
    box = box_segments(1.0, 2.0, 2.0, 1.0, angle=np.pi / 2)
    assert box.shape == (4, 4) and box.dtype == np.float32
    np.testing.assert_allclose(np.sort(box[:, 0::2].ravel()), [0.5] * 4 + [1.5] * 4, atol=1e-6)
    np.testing.assert_allclose(np.sort(box[:, 1::2].ravel()), [1.0] * 4 + [3.0] * 4, atol=1e-6)
    assert polyline_segments([[0, 0], [1, 0], [1, 1]]).shape == (2, 4)
    assert polyline_segments([[0, 0], [1, 0], [1, 1]], closed=True).shape == (3, 4)
    wall = wall_segments([0, 0], [10, 0], [(3.0, 1.0), (7.0, 2.0)])
    np.testing.assert_allclose(wall, [[0, 0, 2.5, 0], [3.5, 0, 6, 0], [8, 0, 10, 0]])
    a = make_world(box, groups={"box": range(4)})
    b = make_world(wall, groups={"wall": range(3), "box": []})
    both = concat_worlds(a, b)
    assert both.num_segments == 7
    np.testing.assert_array_equal(both.groups["wall"], [4, 5, 6])
    np.testing.assert_array_equal(both.groups["box"], [0, 1, 2, 3])
    assert both.bounds[0] <= -1.0 and both.bounds[2] >= 11.0
    with pytest.raises(ValueError):
        make_world(box, bounds=(0, 0, 1, 1))  # a segment outside the bounds


def test_path_crossings_and_clearance():
    wall = np.array([[1.0, -1.0, 1.0, 1.0]])
    through = np.array([[0.0, 0.0], [0.9, 0.0], [1.1, 0.0], [2.0, 0.0]])
    np.testing.assert_array_equal(path_crossings(through, wall)[:, 0], [False, True, False])
    grazing = np.array([[0.0, 1.0], [2.0, 1.0]])  # touches the wall's end
    assert path_crossings(grazing, wall).all()
    along = np.array([[1.0, -3.0], [1.0, -0.5]])  # collinear, overlapping
    assert path_crossings(along, wall).all()
    spin = np.array([[1.0, 0.0], [1.0, 0.0]])
    assert not path_crossings(spin, wall).any()
    np.testing.assert_allclose(point_segment_distance([[0.0, 0.0], [1.0, 3.0]], wall)[:, 0], [1.0, 2.0])


# ------------------------------------------------------------------------------- scans


def _room_world():
    # A 10 m x 8 m room; from its centre every beam hits a wall 4 to 6.4 m away.
    return make_world(box_segments(0.0, 0.0, 10.0, 8.0))


def test_simulate_scan_noise_statistics():
    world = _room_world()
    sensor = make_sensor(uniform_beams(180), range_max=10.0)
    sigma = 0.05
    num_scans = 400
    poses = np.tile([0.3, -0.2, 0.4], (num_scans, 1))
    ranges = np.asarray(simulate_scans(jax.random.key(0), world, poses, sensor, sigma), np.float64)
    exact, hit = jit_raycast(world.segments, jnp.array([0.3, -0.2]), 0.4 + sensor.beam_angles, 10.0)
    assert (np.asarray(hit) >= 0).all()
    errors = ranges - np.asarray(exact, np.float64)
    n = errors.size
    # Monte Carlo tolerances: 5 standard errors of the mean and of the sample std.
    assert abs(errors.mean()) < 5 * sigma / np.sqrt(n)
    assert abs(errors.std() - sigma) < 5 * sigma / np.sqrt(2 * n)
    # The same key reproduces the scans bit for bit, another key does not.
    again = np.asarray(simulate_scans(jax.random.key(0), world, poses, sensor, sigma), np.float64)
    np.testing.assert_array_equal(ranges, again)
    other = np.asarray(simulate_scans(jax.random.key(1), world, poses, sensor, sigma), np.float64)
    assert not np.array_equal(ranges, other)


def test_simulate_scan_no_return_clipping_and_consistency():
    # Only one wall, 2 m ahead: beams that miss it read exactly range_max.
    world = make_world(np.array([[2.0, -1.0, 2.0, 1.0]]))
    sensor = make_sensor(uniform_beams(181), range_max=5.0)
    key = jax.random.key(3)
    ranges = np.asarray(simulate_scan(key, world, jnp.zeros(3), sensor, 0.01))
    exact, hit = jit_raycast(world.segments, jnp.zeros(2), sensor.beam_angles, 5.0)
    hit = np.asarray(hit)
    assert 0 < (hit >= 0).sum() < hit.size
    np.testing.assert_array_equal(ranges[hit < 0], np.float32(5.0))
    assert (np.abs(ranges[hit >= 0] - np.asarray(exact)[hit >= 0]) < 0.06).all()
    # max_range below range_max: the wall is out of reach, every beam reads range_max.
    far = np.asarray(simulate_scan(key, world, jnp.zeros(3), sensor, 0.01, max_range=1.5))
    np.testing.assert_array_equal(far, np.float32(5.0))
    # Huge noise: clipped to [0, range_max].
    wild = np.asarray(simulate_scan(key, world, jnp.zeros(3), sensor, 10.0))
    assert wild.min() >= 0.0 and wild.max() <= 5.0 and (wild == 0.0).any()
    # An inactive segment is transparent.
    none = np.asarray(simulate_scan(key, world, jnp.zeros(3), sensor, 0.01, active=jnp.array([False])))
    np.testing.assert_array_equal(none, np.float32(5.0))
    # Row i of a batch is the single scan with the key folded with i.
    poses = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, 0.3], [-1.0, 0.0, -0.2]])
    batch = np.asarray(simulate_scans(key, world, poses, sensor, 0.01))
    for i in range(3):
        single = simulate_scan(jax.random.fold_in(key, i), world, poses[i], sensor, 0.01)
        np.testing.assert_allclose(batch[i], single, atol=1e-6)


def test_simulate_scan_uses_laser_pose():
    world = _room_world()
    sensor = make_sensor(uniform_beams(90), range_max=10.0, laser_pose=(0.2, 0.1, 0.3))
    pose = jnp.array([1.0, -0.5, 0.7])
    ranges = simulate_scan(jax.random.key(0), world, pose, sensor, 0.0)
    c, s = np.cos(0.7), np.sin(0.7)
    origin = np.array([1.0 + c * 0.2 - s * 0.1, -0.5 + s * 0.2 + c * 0.1])
    exact, _ = jit_raycast(world.segments, origin, 1.0 + sensor.beam_angles, 10.0)
    np.testing.assert_allclose(ranges, exact, atol=1e-5)


# ---------------------------------------------------------------------------- odometry


def _wiggly_path():
    return waypoint_path([[0, 0], [6, 0], [6, 4], [1, 4], [3, 4], [3, -2]], 0.1, 0.15, start_heading=2.0)


def test_noisy_odometry_without_noise_is_the_truth():
    truth = _wiggly_path()
    zero = motion_params(0, 0, 0, 0, 0, 0)
    odometry = noisy_odometry(jax.random.key(0), truth, zero)
    assert odometry.shape == truth.shape and odometry.dtype == np.float64
    np.testing.assert_allclose(odometry[:, :2], truth[:, :2], atol=1e-4)
    np.testing.assert_allclose((wrap(odometry[:, 2] - truth[:, 2])), 0.0, atol=1e-5)


def test_noisy_odometry_relative_motion_statistics():
    truth = _wiggly_path()
    params = motion_params(0.05, 0.02, 0.05, 0.1, 0.001, 0.002)
    true_motion = np.asarray(between(truth[:-1], truth[1:]), np.float64)
    std = np.asarray(noise_std(jnp.asarray(true_motion, jnp.float32), params), np.float64)
    residuals = []
    for seed in range(8):
        odometry = noisy_odometry(jax.random.key(seed), truth, params)
        np.testing.assert_array_equal(odometry[0], truth[0])
        motion = np.asarray(between(odometry[:-1], odometry[1:]), np.float64)
        residual = motion - true_motion
        residual[:, 2] = (wrap(residual[:, 2]))
        residuals.append(residual / std)
    z = np.concatenate(residuals)
    n = z.shape[0]
    # Standardised noise: mean 0 and std 1 per component, within 5 standard errors.
    assert np.all(np.abs(z.mean(axis=0)) < 5 / np.sqrt(n))
    assert np.all(np.abs(z.std(axis=0) - 1) < 5 / np.sqrt(2 * n))
    # Reproducible bit for bit.
    np.testing.assert_array_equal(noisy_odometry(jax.random.key(0), truth, params),
                                  noisy_odometry(jax.random.key(0), truth, params))


def test_simulate_log_fields():
    world = _room_world()
    truth = waypoint_path([[-3, -2], [3, -2], [3, 2]], 0.1, 0.2)
    sensor = make_sensor(uniform_beams(36), range_max=8.0)
    params = motion_params(0.05, 0.02, 0.05, 0.1, 0.001, 0.002)
    log = simulate_log(jax.random.key(0), world, truth, sensor, params, 0.02, dt=0.25)
    assert log.num_scans == truth.shape[0] and log.num_beams == 36
    np.testing.assert_array_equal(log.ground_truth, truth)
    np.testing.assert_allclose(log.timestamps, 0.25 * np.arange(truth.shape[0]))
    assert not np.allclose(log.odometry, truth)
    again = simulate_log(jax.random.key(0), world, truth, sensor, params, 0.02, dt=0.25)
    np.testing.assert_array_equal(log.ranges, again.ranges)
    np.testing.assert_array_equal(log.odometry, again.odometry)


# ------------------------------------------------------------------------------- paths


def _check_steps(path, step, max_turn, radius, rel=1e-9, joins=0):
    """Translating steps are one step of arc (within ``rel``), except the one arriving at a
    stop (a turn on the spot, or the end) and at most ``joins`` steps that arrive at the
    start of a circle; headings change by at most max_turn and follow the motion."""
    xy = path[:, :2]
    chords = np.hypot(*np.diff(xy, axis=0).T)
    turns = np.abs((wrap(np.diff(path[:, 2]))))
    assert turns.max() <= max_turn + 1e-9
    moving = chords > 1e-12
    # A step is "arriving" when the next step does not move (a spin) or it is the last one.
    arriving = moving & ~np.append(moving[1:], False)
    shortest_chord = step * (1 - step**2 / (24 * radius**2)) - 1e-9  # chord of an arc of length `step`
    full = moving & ~arriving
    ok = (chords >= shortest_chord * (1 - rel)) & (chords <= step * (1 + rel) + 1e-9)
    assert (full & ~ok).sum() <= joins
    assert np.all(chords[moving] <= step * (1 + rel) + 1e-9)
    # Heading follows the direction of travel (the chord's direction is the mean heading).
    # Exact on lines and arcs; a step from a line onto an arc is off by less than half its turn.
    direction = np.arctan2(*np.diff(xy, axis=0)[moving].T[::-1])
    step_turn = np.diff(np.unwrap(path[:, 2]))[moving]
    mean_heading = path[:-1, 2][moving] + 0.5 * step_turn
    off = np.abs(np.angle(np.exp(1j * (direction - mean_heading))))
    assert np.all(off <= 0.5 * np.abs(step_turn) + 1e-6)
    return moving, arriving


def test_waypoint_path_constant_steps():
    waypoints = [[0, 0], [5, 0], [5, 5], [0, 5], [3, 5], [3.2, 1.0]]
    path = waypoint_path(waypoints, 0.1, 0.1, start_heading=np.pi / 2)
    moving, arriving = _check_steps(path, 0.1, 0.1, 1.0)
    np.testing.assert_allclose(path[-1, :2], waypoints[-1], atol=1e-9)
    np.testing.assert_allclose(path[0], [0, 0, np.pi / 2])
    # The start heading and the U-turn at (0, 5) are turned on the spot; the rest are arcs.
    assert arriving.sum() == 2  # before the U-turn, and the end
    assert (~moving).sum() == 16 + 32  # 90 degrees and 180 degrees in 0.1 rad steps


def test_circle_path():
    path = circle_path([1.0, -2.0], 1.75, 2.5, 0.1, start_angle=0.3)
    chords = np.hypot(*np.diff(path[:, :2], axis=0).T)
    assert np.ptp(chords) < 1e-9 and abs(chords[0] - 0.1) < 0.01
    np.testing.assert_allclose(np.hypot(path[:, 0] - 1.0, path[:, 1] + 2.0), 1.75)
    polar = np.arctan2(path[:, 1] + 2.0, path[:, 0] - 1.0)
    np.testing.assert_allclose((wrap(path[:, 2] - polar - np.pi / 2)), 0.0, atol=1e-9)
    np.testing.assert_allclose(polar[-1], (wrap(0.3 + 5 * np.pi)), atol=1e-9)
    cw = circle_path([0.0, 0.0], 2.0, 1.0, 0.1, start_angle=0.0, clockwise=True)
    assert cw[1, 1] < 0 and abs(cw[0, 2] + np.pi / 2) < 1e-12


def test_concat_paths_and_passages():
    a = waypoint_path([[0, 0], [2, 0]], 0.1, 0.1)
    b = waypoint_path([[2, 0], [4, 0]], 0.1, 0.1)
    joined = concat_paths(a, b)
    assert joined.shape[0] == a.shape[0] + b.shape[0] - 1
    with pytest.raises(ValueError):
        concat_paths(a, b + [0.5, 0, 0])
    back = waypoint_path([[0, 0], [3, 0], [0, 0]], 0.1, 0.2)
    np.testing.assert_array_equal(passage_indices(back, [1.0, 0.0], 0.12), [10, back.shape[0] - 11])


# --------------------------------------------------------------------------- scenarios


@pytest.fixture(scope="module")
def office():
    return office_scenario(jax.random.key(0))


@pytest.fixture(scope="module")
def box():
    return box_world_scenario(jax.random.key(0))


def test_office_scenario(office):
    log, world = office.log, office.world
    assert log.num_scans == 500 and log.num_beams == 180
    assert float(log.sensor.range_max) == 10.0
    np.testing.assert_array_equal(log.ground_truth, office.true_poses)
    xmin, ymin, xmax, ymax = world.bounds
    assert 18 <= xmax - xmin <= 24 and 13 <= ymax - ymin <= 19
    step = office.metadata["step_length"]
    _check_steps(office.true_poses, step, step / office.metadata["turn_radius"], office.metadata["turn_radius"])
    # The tour ends where it began: a loop.
    assert np.hypot(*(office.true_poses[-1, :2] - office.true_poses[0, :2])) < 0.05
    # Odometry drifts, but not absurdly.
    drift = np.hypot(*(log.odometry[:, :2] - office.true_poses[:, :2]).T)
    assert 0.05 < drift.max() < 15.0
    # Deterministic given the key.
    again = office_scenario(jax.random.key(0))
    np.testing.assert_array_equal(again.log.ranges, log.ranges)
    np.testing.assert_array_equal(again.log.odometry, log.odometry)


def test_office_path_never_crosses_a_wall(office):
    xy = office.true_poses[:, :2]
    assert not path_crossings(xy, office.world.segments).any()
    # And keeps a robot's radius (0.25 m) plus a margin off every wall and piece of furniture.
    assert point_segment_distance(xy, office.world.segments).min() > 0.4
    # The path visits rooms on both sides of the corridor (not just the corridor).
    assert xy[:, 1].max() > 12.0 and xy[:, 1].min() < 2.0



def test_hall_scenario_is_a_second_world_beside_the_office():
    hall = hall_scenario(jax.random.key(0))
    log, xy = hall.log, hall.true_poses[:, :2]
    assert log.num_scans == 500 and log.num_beams == 180
    step = hall.metadata["step_length"]
    _check_steps(hall.true_poses, step, step / hall.metadata["turn_radius"], hall.metadata["turn_radius"])
    assert np.hypot(*(xy[-1] - xy[0])) < 0.05  # a loop
    assert not path_crossings(xy, hall.world.segments).any()
    assert point_segment_distance(xy, hall.world.segments).min() > 0.4
    # Other odometry terms than the office's, so a fit there is a second case, not a repeat.
    office_terms = np.array(office_scenario(jax.random.key(0)).metadata["motion_params"][:4], np.float64)
    hall_terms = np.array(hall.metadata["motion_params"][:4], np.float64)
    assert np.all(np.abs(np.log(hall_terms / office_terms)) > 0.3)
    # An open hall: most beams end beyond the office's 2 m corridor, and some reach no wall.
    ranges = log.ranges
    assert np.median(ranges[ranges < 10.0]) > 4.0 and np.mean(ranges >= 10.0) > 0.1
    again = hall_scenario(jax.random.key(0))
    np.testing.assert_array_equal(again.log.ranges, log.ranges)


def _hit_groups(scenario):
    """(T, B) segment index hit by each beam of each scan, without noise (exact casts)."""
    sensor = scenario.log.sensor
    poses = jnp.asarray(scenario.true_poses, jnp.float32)
    angles = poses[:, 2:3] + sensor.beam_angles[None, :]
    _, hit = jit_raycast(scenario.world.segments, poses[:, None, :2], angles, sensor.range_max)
    return np.asarray(hit)


def test_box_world_no_scan_sees_both_boxes(box):
    world = box.world
    hit = _hit_groups(box)
    sees = {name: np.isin(hit, world.groups[name]).any(axis=1) for name in ("box1", "box2", "hedge")}
    assert not (sees["box1"] & sees["box2"]).any()
    assert sees["box1"].any() and sees["box2"].any() and sees["hedge"].any()
    # The hedge and box 1 are out of view while the robot circles box 2.
    near_box2 = np.hypot(*(box.true_poses[:, :2] - box.metadata["box2_center"]).T) < 2.1
    assert near_box2.sum() > 1500
    assert not (sees["hedge"] | sees["box1"])[near_box2].any()
    # Box 2 is in view all the way round the circle.
    radius = np.hypot(*(box.true_poses[:, :2] - box.metadata["box2_center"]).T)
    on_circle = np.abs(radius - box.metadata["circle_radius"]) < 1e-6
    assert on_circle.sum() > 1500 and sees["box2"][on_circle].all()
    # The boxes are further apart than twice the laser range, with a margin.
    box1, box2 = world.segments[world.groups["box1"]], world.segments[world.groups["box2"]]
    corners1 = box1[:, :2]
    assert point_segment_distance(corners1, box2).min() > 2 * 4.0 + 0.5
    assert float(box.log.sensor.range_max) == 4.0


def test_box_world_passages_over_x(box):
    meta = box.metadata
    passages = meta["x_passages"]
    laps = meta["lap_end_indices"]
    assert len(laps) == 15 and len(passages) >= 4
    x = meta["checkpoint_x"]
    dist = np.hypot(*(box.true_poses[passages, :2] - x).T)
    assert (dist <= meta["x_tolerance"]).all()
    # At the start, after laps 5 and 10, and at the end.
    assert passages[0] < 5 and passages[-1] > laps[-1]
    for lap in (5, 10):
        assert ((passages > laps[lap - 1]) & (passages < laps[lap])).any()
    # The robot's surroundings at X are seen at the start: the hedge is in view early on.
    hit = _hit_groups(box)
    assert np.isin(hit[:30], box.world.groups["hedge"]).any()
    # Circling at 1.5 to 2 m, 1,500 to 3,000 scans, 0.1 to 0.2 m steps.
    assert 1.5 <= meta["circle_radius"] <= 2.0
    assert 1500 <= box.log.num_scans <= 3000 and 0.1 <= meta["step_length"] <= 0.2
    step = meta["step_length"]
    # Circles adjust the step by < 0.1 % to close exactly; the 3 lines that join the circle
    # end with a short step.
    _check_steps(box.true_poses, step, 0.1, meta["turn_radius"], rel=1e-3, joins=3)


def test_box_world_odometry_drifts(box):
    # Odometry alone ends up clearly away from X at the last passage.
    last = box.metadata["x_passages"][-1]
    drift = np.hypot(*(box.log.odometry[last, :2] - box.true_poses[last, :2]))
    assert drift > 0.3
    again = box_world_scenario(jax.random.key(0))
    np.testing.assert_array_equal(again.log.ranges, box.log.ranges)


def test_box_world_field_of_view():
    """A wider laser sees behind the robot: at the start (at X, facing the hedge) box 2, 3.5 m
    behind, is out of a 180-degree laser's view and in a 360-degree one's."""
    narrow = box_world_scenario(jax.random.key(0), laps=1, laps_per_visit=1)
    wide = box_world_scenario(jax.random.key(0), laps=1, laps_per_visit=1, num_beams=361,
                              field_of_view=2 * np.pi)
    np.testing.assert_allclose(float(wide.log.sensor.beam_angles[0]), -np.pi, atol=1e-6)
    assert narrow.log.sensor.beam_angles.shape == (180,) and wide.log.sensor.beam_angles.shape == (361,)
    range_max = float(narrow.log.sensor.range_max)
    behind = np.abs(np.abs(np.asarray(wide.log.sensor.beam_angles)) - np.pi) < 0.1
    assert np.any(wide.log.ranges[0][behind] < range_max)
    assert np.max(np.abs(np.asarray(narrow.log.sensor.beam_angles))) <= np.pi / 2 + 1e-6


def test_markov_door_states_follow_their_chain():
    from jaxslam.sim.door_worlds import markov_door_states

    p_open_closed, p_closed_open = 0.05, 0.02
    states = markov_door_states(jax.random.key(0), 20_000, 3, p_open_closed, p_closed_open)
    before, after = states[:-1], states[1:]
    closed, opened = (~before).sum(), before.sum()
    # Binomial counts: the estimates lie within 4 standard errors of the chain's probabilities.
    for got, p, n in (((~before & after).sum() / closed, p_open_closed, closed),
                      ((before & ~after).sum() / opened, p_closed_open, opened)):
        assert abs(got - p) < 4 * np.sqrt(p * (1 - p) / n), (got, p)
    with pytest.raises(ValueError, match="transition probabilities"):
        markov_door_states(jax.random.key(0), 10, 3, 0.0, 0.5)


def test_patrol_scenario_doors_change_and_are_seen():
    from jaxslam.sim.door_worlds import patrol_doors_scenario

    scenario = patrol_doors_scenario(jax.random.key(1), num_round_trips=2)
    assert scenario.true_door_open.shape == (scenario.num_scans, 6)
    assert (scenario.true_door_open[1:] != scenario.true_door_open[:-1]).sum() > 0
    assert scenario.observed_doors.any(axis=0).all()  # every door is seen on a pass
    with pytest.raises(ValueError, match="num_round_trips"):
        patrol_doors_scenario(jax.random.key(1), num_round_trips=0)
