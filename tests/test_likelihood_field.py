"""The endpoint (likelihood-field) model (jaxslam.likelihood_field) against a NumPy reference."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import likelihood_field as S
from jaxslam.geometry import compose
from jaxslam.grid import GridSpec
from jaxslam.laser import make_sensor, subsample_beams, uniform_beams
from jaxslam.occupancy import FAR

SPEC = GridSpec((10, 12), 0.2, (-0.5, -0.3))  # x in [-0.5, 1.9], y in [-0.3, 1.7]
PARAMS = S.LikelihoodParams(*(jnp.float32(v) for v in (0.25, 0.8, 0.05, 0.7)))
POSE = np.array([0.7, 0.6, 0.4], np.float32)
LASER_POSE = np.array([0.05, 0.02, -0.3], np.float32)
RANGE_MIN, RANGE_MAX = 0.15, 1.2

loglik = jax.jit(S.endpoint_log_likelihood, static_argnums=0)


def np_compose(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


def cell_centre(r, c, spec=SPEC):
    return np.array([spec.origin[0] + (c + 0.5) * spec.resolution, spec.origin[1] + (r + 0.5) * spec.resolution])


def np_loglik(spec, hit, pose, ranges, angles, range_min, range_max, laser_pose, params, margin=1e-3):
    """Beam by beam, in float64."""
    sigma, z_hit, z_rand, gain = (float(v) for v in params[:4])
    o = np_compose(pose, laser_pose)
    h, w = spec.shape
    total = 0.0
    for r, a in zip(np.asarray(ranges, np.float64), np.asarray(angles, np.float64)):
        if not (range_min <= r < range_max):
            continue  # no return, or below the minimum range: skipped
        end = o[:2] + r * np.array([math.cos(o[2] + a), math.sin(o[2] + a)])
        u = (end[0] - spec.origin[0]) / spec.resolution
        v = (end[1] - spec.origin[1]) / spec.resolution
        assert min(abs(u - round(u)), abs(v - round(v))) > margin, "endpoint on a cell edge: move it"
        row, col = math.floor(v), math.floor(u)
        d2 = int(hit[row, col]) if (0 <= row < h and 0 <= col < w) else FAR
        gauss = 0.0 if d2 == FAR else math.exp(-0.5 * d2 * spec.resolution**2 / sigma**2)
        total += math.log(z_hit * gauss + z_rand)
    return gain * total


def hit_map():
    hit = np.full(SPEC.shape, FAR, np.uint8)
    for (r, c), d2 in {(2, 3): 0, (5, 7): 1, (7, 2): 2, (4, 9): 5, (8, 10): 9, (0, 0): 0}.items():
        hit[r, c] = d2
    return hit


def scan():
    """Beams aimed at chosen points (angles in the laser frame, ranges), one per case."""
    o = np_compose(POSE, LASER_POSE)
    origin_cell = (math.floor((o[1] - SPEC.origin[1]) / SPEC.resolution),
                   math.floor((o[0] - SPEC.origin[0]) / SPEC.resolution))
    jitter = np.array([0.03, -0.02])
    targets = [cell_centre(*rc) + jitter for rc in [(2, 3), (5, 7), (7, 2), (4, 9), (8, 10), (1, 5)]]
    targets += [np.array([1.93, 0.62]), np.array([0.75, -0.35])]  # just outside the map (right, bottom)
    angles, ranges = [], []
    for t in targets:
        d = t - o[:2]
        angles.append(math.atan2(d[1], d[0]) - o[2])
        ranges.append(float(np.hypot(*d)))
    assert max(ranges) < RANGE_MAX
    # No return: aimed at the hit cell (0, 0), 1.41 m away (>= range_max). Would score log(z_hit + z_rand).
    d = cell_centre(0, 0) + jitter - o[:2]
    angles.append(math.atan2(d[1], d[0]) - o[2])
    ranges.append(float(np.hypot(*d)))
    assert ranges[-1] >= RANGE_MAX
    # Exactly range_max: no return.
    angles.append(0.3)
    ranges.append(RANGE_MAX)
    # Below range_min, ending in the laser's own cell, which we make a hit cell.
    angles.append(1.0)
    ranges.append(0.05)
    return np.array(angles, np.float32), np.array(ranges, np.float32), origin_cell


def setup():
    angles, ranges, origin_cell = scan()
    hit = hit_map()
    hit[origin_cell] = 0
    sensor = make_sensor(angles, RANGE_MIN, RANGE_MAX, LASER_POSE)
    return hit, ranges, sensor


def reference(hit, pose, ranges, sensor, params=PARAMS):
    return np_loglik(SPEC, hit, pose, ranges, np.asarray(sensor.beam_angles), RANGE_MIN, RANGE_MAX,
                     np.asarray(sensor.laser_pose), params)


def test_matches_numpy_reference():
    hit, ranges, sensor = setup()
    got = float(loglik(SPEC, jnp.asarray(hit), jnp.asarray(POSE), jnp.asarray(ranges), sensor, PARAMS))
    want = reference(hit, POSE, ranges, sensor)
    assert got == pytest.approx(want, rel=1e-5, abs=1e-5)


def test_beam_cases_one_by_one():
    hit, ranges, sensor = setup()
    angles = np.asarray(sensor.beam_angles)
    sigma, z_hit, z_rand, gain = 0.25, 0.8, 0.05, 0.7
    expected_d2 = [0, 1, 2, 5, 9, None, None, None]  # None: FAR or outside the map
    for b, d2 in enumerate(expected_d2):
        one = sensor._replace(beam_angles=jnp.asarray(angles[b:b + 1]))
        got = float(loglik(SPEC, jnp.asarray(hit), jnp.asarray(POSE), jnp.asarray(ranges[b:b + 1]), one, PARAMS))
        g = 0.0 if d2 is None else math.exp(-0.5 * d2 * 0.04 / sigma**2)
        assert got == pytest.approx(gain * math.log(z_hit * g + z_rand), rel=1e-5), b
    for b in (8, 9, 10):  # skipped (0), where scoring them would give 0.7 log(0.85) = -0.11
        one = sensor._replace(beam_angles=jnp.asarray(angles[b:b + 1]))
        got = float(loglik(SPEC, jnp.asarray(hit), jnp.asarray(POSE), jnp.asarray(ranges[b:b + 1]), one, PARAMS))
        assert got == 0.0, b


def test_laser_pose_offset():
    hit, ranges, sensor = setup()
    args = (SPEC, jnp.asarray(hit))
    with_offset = float(loglik(*args, jnp.asarray(POSE), jnp.asarray(ranges), sensor, PARAMS))
    moved = compose(jnp.asarray(POSE), jnp.asarray(LASER_POSE))
    without = float(loglik(*args, moved, jnp.asarray(ranges), sensor._replace(laser_pose=jnp.zeros(3)), PARAMS))
    assert with_offset == pytest.approx(without, rel=1e-5)
    # Ignoring the offset changes the answer (the endpoints move by up to 0.3 rad x 1.1 m).
    ignored = float(loglik(*args, jnp.asarray(POSE), jnp.asarray(ranges), sensor._replace(laser_pose=jnp.zeros(3)),
                           PARAMS))
    assert abs(ignored - with_offset) > 0.1


def test_vmap_over_poses_equals_loop_and_reference():
    hit, ranges, sensor = setup()
    rng = np.random.default_rng(0)
    poses = (POSE + rng.normal(0, [0.1, 0.1, 0.1], size=(16, 3))).astype(np.float32)
    f = jax.jit(jax.vmap(lambda p: S.endpoint_log_likelihood(SPEC, jnp.asarray(hit), p, jnp.asarray(ranges),
                                                             sensor, PARAMS)))
    batched = np.asarray(f(jnp.asarray(poses)))
    assert batched.shape == (16,)
    loop = np.array([float(loglik(SPEC, jnp.asarray(hit), jnp.asarray(p), jnp.asarray(ranges), sensor, PARAMS))
                     for p in poses])
    np.testing.assert_allclose(batched, loop, rtol=1e-6, atol=1e-6)
    want = np.array([np_loglik(SPEC, hit, p, ranges, np.asarray(sensor.beam_angles), RANGE_MIN, RANGE_MAX,
                               LASER_POSE, PARAMS, margin=1e-4) for p in poses])
    np.testing.assert_allclose(batched, want, rtol=1e-5, atol=1e-5)
    assert np.ptp(want) > 1.0  # the poses see different things


def test_vmap_over_maps():
    hit, ranges, sensor = setup()
    maps = np.stack([hit, np.full_like(hit, FAR), np.zeros_like(hit)])
    f = jax.jit(jax.vmap(lambda m: S.endpoint_log_likelihood(SPEC, m, jnp.asarray(POSE), jnp.asarray(ranges),
                                                             sensor, PARAMS)))
    got = np.asarray(f(jnp.asarray(maps)))
    want = [reference(m, POSE, ranges, sensor) for m in maps]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    # An all-FAR map scores log z_rand for each of the 8 valid beams.
    assert got[1] == pytest.approx(0.7 * 8 * math.log(0.05), rel=1e-5)


def test_gradient_wrt_sigma_is_finite_and_correct():
    hit, ranges, sensor = setup()

    def f(sigma):
        return S.endpoint_log_likelihood(SPEC, jnp.asarray(hit), jnp.asarray(POSE), jnp.asarray(ranges), sensor,
                                         PARAMS._replace(sigma=sigma))

    for sigma in (0.05, 0.25, 2.0):
        g = float(jax.jit(jax.grad(f))(jnp.float32(sigma)))
        assert math.isfinite(g)
        h = 1e-5 * sigma
        fd = (reference(hit, POSE, ranges, sensor, PARAMS._replace(sigma=sigma + h))
              - reference(hit, POSE, ranges, sensor, PARAMS._replace(sigma=sigma - h))) / (2 * h)
        assert g == pytest.approx(fd, rel=1e-3, abs=1e-4)
    # Gradients of the other parameters are finite too (differentiable-filter users need them).
    grads = jax.jit(jax.grad(lambda p: S.endpoint_log_likelihood(SPEC, jnp.asarray(hit), jnp.asarray(POSE),
                                                                 jnp.asarray(ranges), sensor, p)))(PARAMS)
    assert all(math.isfinite(float(v)) for v in grads)


def test_uniform_beams_and_subsample():
    a = np.asarray(uniform_beams(5, np.pi / 2))
    np.testing.assert_allclose(a, np.linspace(-np.pi / 4, np.pi / 4, 5), atol=1e-6)
    sensor = make_sensor(a)
    sub, r = subsample_beams(sensor, jnp.arange(10.0).reshape(2, 5), 2)
    np.testing.assert_allclose(np.asarray(sub.beam_angles), a[::2])
    np.testing.assert_allclose(np.asarray(r), [[0, 2, 4], [5, 7, 9]])


# ------------------------------------------------------------------ bilinear lookup


def np_bilinear_loglik(spec, hit, pose, ranges, angles, range_min, range_max, laser_pose, params):
    """Beam by beam, in float64: the per-beam term interpolated between the four cells whose
    centres surround the endpoint (cells outside the map count as FAR)."""
    sigma, z_hit, z_rand, gain = (float(v) for v in params[:4])
    o = np_compose(pose, laser_pose)
    h, w = spec.shape

    def term(row, col):
        d2 = int(hit[row, col]) if (0 <= row < h and 0 <= col < w) else FAR
        gauss = 0.0 if d2 == FAR else math.exp(-0.5 * d2 * spec.resolution**2 / sigma**2)
        return math.log(z_hit * gauss + z_rand)

    total = 0.0
    for r, a in zip(np.asarray(ranges, np.float64), np.asarray(angles, np.float64)):
        if not (range_min <= r < range_max):
            continue
        end = o[:2] + r * np.array([math.cos(o[2] + a), math.sin(o[2] + a)])
        u = (end[0] - spec.origin[0]) / spec.resolution - 0.5
        v = (end[1] - spec.origin[1]) / spec.resolution - 0.5
        c0, r0 = math.floor(u), math.floor(v)
        fu, fv = u - c0, v - r0
        total += ((1 - fu) * (1 - fv) * term(r0, c0) + fu * (1 - fv) * term(r0, c0 + 1)
                  + (1 - fu) * fv * term(r0 + 1, c0) + fu * fv * term(r0 + 1, c0 + 1))
    return gain * total


def test_bilinear_matches_numpy_reference_at_many_poses():
    hit, ranges, sensor = setup()
    rng = np.random.default_rng(3)
    poses = (POSE + rng.uniform([-0.3, -0.3, -0.5], [0.3, 0.3, 0.5], (20, 3))).astype(np.float32)
    got = np.asarray(jax.jit(S.endpoint_log_likelihoods, static_argnums=(0, 6))(
        SPEC, jnp.asarray(hit), jnp.asarray(poses), jnp.asarray(ranges), sensor, PARAMS, "bilinear"))
    want = [np_bilinear_loglik(SPEC, hit, p, ranges, np.asarray(sensor.beam_angles), RANGE_MIN, RANGE_MAX,
                               np.asarray(sensor.laser_pose), PARAMS) for p in poses]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
    # The poses reach the map's edges, so some beams interpolate with cells outside it.
    nearest = np.asarray(S.endpoint_log_likelihoods(SPEC, jnp.asarray(hit), jnp.asarray(poses), jnp.asarray(ranges),
                                                    sensor, PARAMS))
    assert np.abs(got - nearest).max() > 0.1  # the two lookups differ away from cell centres


def test_bilinear_equals_nearest_at_cell_centres_and_is_continuous():
    hit = hit_map()
    # One beam straight ahead from a laser at the origin of the robot; the endpoint is moved by
    # moving the robot along x.
    one = make_sensor(np.array([0.0], np.float32), RANGE_MIN, RANGE_MAX)
    ranges = jnp.array([0.5], jnp.float32)
    centre = cell_centre(5, 7)  # d2 = 1 there; its neighbours are FAR or 0 elsewhere

    def at(x, lookup):
        pose = jnp.array([[x - 0.5, centre[1], 0.0]], jnp.float32)
        return float(S.endpoint_log_likelihoods(SPEC, jnp.asarray(hit), pose, ranges, one, PARAMS, lookup)[0])

    assert at(centre[0], "bilinear") == pytest.approx(at(centre[0], "nearest"), abs=1e-5)
    # Crossing the cell edge halfway to the next centre: nearest jumps, bilinear does not.
    edge = centre[0] + 0.5 * SPEC.resolution
    # (The bilinear slope here is about 10 per metre: 2e-4 m changes it by about 0.002.)
    jump_nearest = abs(at(edge + 1e-4, "nearest") - at(edge - 1e-4, "nearest"))
    jump_bilinear = abs(at(edge + 1e-4, "bilinear") - at(edge - 1e-4, "bilinear"))
    assert jump_nearest > 0.5 and jump_bilinear < 0.01


def test_unknown_lookup_is_an_error():
    hit, ranges, sensor = setup()
    with pytest.raises(ValueError, match="lookup must be one of"):
        S.endpoint_log_likelihood(SPEC, jnp.asarray(hit), jnp.asarray(POSE), jnp.asarray(ranges), sensor, PARAMS,
                                  "cubic")


@pytest.mark.parametrize("lookup", S.FIELD_LOOKUPS)
def test_a_pose_far_outside_the_map_scores_the_floor(lookup):
    """Endpoints far outside the map (world_to_cell clips them) score log(z_rand) per beam,
    with either lookup: the bilinear weights stay a convex combination there."""
    hit, ranges, sensor = setup()
    far = jnp.array([[3.0e4, -2.0e4, 0.3]], jnp.float32)
    got = float(S.endpoint_log_likelihoods(SPEC, jnp.asarray(hit), far, jnp.asarray(ranges), sensor, PARAMS,
                                           lookup)[0])
    num_valid = int(np.sum((ranges >= RANGE_MIN) & (ranges < RANGE_MAX)))
    assert got == pytest.approx(0.7 * num_valid * math.log(0.05), rel=1e-5)


def test_normalizer_counts_the_scored_beams_and_makes_a_density_over_cells():
    """``endpoint_log_normalizer``: -gain * n * log Z over the n beams with a return, Z the
    Gaussian summed over cells of one width (against a NumPy sum to 10^5 cells); with it, a beam's
    term with z_rand = 0 is a density per metre over the cells at 0, 1, 2, ... cells' distance
    (sums to 1), from sigma well below a cell to sigma many cells wide. As sigma falls below a
    cell the constant tends to -log(cell), where a half-normal's would grow without bound."""
    _, ranges, sensor = setup()
    counted = np.sum((ranges >= RANGE_MIN) & (ranges < RANGE_MAX))
    sigma, _, _, gain = (float(v) for v in PARAMS[:4])
    cell = 0.05
    k = np.arange(100_000)

    def numpy_log_z(sigma):
        return np.log(cell * np.sum(np.exp(-0.5 * (k * cell / sigma) ** 2)))

    got = float(S.endpoint_log_normalizer(jnp.asarray(ranges), sensor, PARAMS, cell))
    assert got == pytest.approx(-gain * counted * numpy_log_z(sigma), rel=1e-4)

    one_beam = make_sensor(np.zeros(1, np.float32), RANGE_MIN, RANGE_MAX, LASER_POSE)
    for sigma, tolerance in ((0.3 * cell, 1e-5), (cell, 1e-5), (5 * cell, 1e-5), (20 * cell, 1e-4)):
        untempered = PARAMS._replace(gain=jnp.float32(1.0), sigma=jnp.float32(sigma))
        log_c = float(S.endpoint_log_normalizer(jnp.array([0.5], jnp.float32), one_beam, untempered, cell))
        assert cell * np.sum(np.exp(log_c - 0.5 * (k * cell / sigma) ** 2)) == pytest.approx(1.0, rel=tolerance)
    tiny = PARAMS._replace(gain=jnp.float32(1.0), sigma=jnp.float32(1e-4))
    assert float(S.endpoint_log_normalizer(jnp.array([0.5], jnp.float32), one_beam, tiny, cell)) == pytest.approx(
        -math.log(cell), rel=1e-6)


def np_cell_loglik(spec, hit, pose, ranges, angles, laser_pose, params, reach_xy, reach_theta, field_radius):
    """The cell log-likelihood beam by beam in float64: the centre's distance, the Gaussian
    widened by the reach of the beam's endpoint over the cell."""
    sigma, z_hit, z_rand, gain = (float(v) for v in params[:4])
    o = np_compose(pose, laser_pose)
    arm0 = math.hypot(float(laser_pose[0]), float(laser_pose[1]))
    h, w = spec.shape
    total = 0.0
    for r, a in zip(np.asarray(ranges, np.float64), np.asarray(angles, np.float64)):
        if not (RANGE_MIN <= r < RANGE_MAX):
            continue
        end = o[:2] + r * np.array([math.cos(o[2] + a), math.sin(o[2] + a)])
        row = math.floor((end[1] - spec.origin[1]) / spec.resolution)
        col = math.floor((end[0] - spec.origin[0]) / spec.resolution)
        d2 = int(hit[row, col]) if (0 <= row < h and 0 <= col < w) else FAR
        distance = (field_radius if d2 == FAR else math.sqrt(d2)) * spec.resolution
        reach = reach_xy + reach_theta * (arm0 + r)
        total += math.log(z_hit * math.exp(-0.5 * distance**2 / (sigma**2 + reach**2)) + z_rand)
    return gain * total


@pytest.mark.parametrize("reach", [(0.0, 0.0), (0.1, 0.05), (0.4, 0.3)])
def test_cell_log_likelihoods_match_numpy_reference_and_flatten_with_the_reach(reach):
    """endpoint_cell_log_likelihoods against the float64 reference; a larger cell never scores
    lower on these beams (every widened Gaussian is wider), and it is never below the nearest
    lookup at the centre."""
    hit, ranges, sensor = setup()
    cell = jax.jit(S.endpoint_cell_log_likelihoods, static_argnums=(0, 8))
    got = float(cell(SPEC, jnp.asarray(hit), jnp.asarray(POSE)[None], jnp.asarray(ranges), sensor, PARAMS,
                     jnp.float32(reach[0]), jnp.float32(reach[1]), 4)[0])
    want = np_cell_loglik(SPEC, hit, POSE, ranges, np.asarray(sensor.beam_angles), np.asarray(sensor.laser_pose),
                          PARAMS, reach[0], reach[1], 4)
    assert got == pytest.approx(want, rel=1e-5, abs=1e-5)
    assert got >= reference(hit, POSE, ranges, sensor) - 1e-5
    wider = float(cell(SPEC, jnp.asarray(hit), jnp.asarray(POSE)[None], jnp.asarray(ranges), sensor, PARAMS,
                       jnp.float32(reach[0] + 0.1), jnp.float32(reach[1] + 0.1), 4)[0])
    assert wider >= got - 1e-6
