"""Grid maps (jaxslam.grid): cell maths, out-of-map handling, scan insertion against NumPy."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import grid as G
from jaxslam import occupancy as O
from jaxslam.laser import make_sensor

SPEC = G.GridSpec((12, 16), 0.25, (-1.3, -0.7))  # x in [-1.3, 2.7], y in [-0.7, 2.3]
PARAMS = O.InsertionParams(*(jnp.float32(v) for v in (0.9, -0.4, -2.0, 3.5, 1.3)))
MAX_RANGE = 2.6  # max_insert_range: 12 samples per beam, 0 .. 2.75 m
RADIUS = 3

insert = jax.jit(O.insert_scan, static_argnums=(0, 6, 7))


# ----------------------------------------------------------------------------- cell maths

def test_gridspec_validation_and_geometry():
    with pytest.raises(ValueError):
        G.GridSpec((0, 3), 0.1, (0, 0))
    with pytest.raises(ValueError):
        G.GridSpec((3, 3), 0.0, (0, 0))
    spec = G.GridSpec.from_bounds(-1.0, 2.0, 3.05, 4.0, 0.5)
    assert spec.shape == (4, 9) and spec.origin == (-1.0, 2.0)
    xmin, xmax, ymin, ymax = spec.extent
    assert xmin == -1.0 and xmax >= 3.05 and ymin == 2.0 and ymax >= 4.0
    assert spec.num_cells == 36
    assert hash(spec) == hash(G.GridSpec((4, 9), 0.5, (-1, 2)))  # static, hashable


def test_cell_to_world_to_cell_round_trip_including_outside_cells():
    h, w = SPEC.shape
    rows, cols = np.meshgrid(np.arange(-5, h + 5), np.arange(-5, w + 5), indexing="ij")
    cells = np.stack([rows, cols], axis=-1).astype(np.int32)
    xy = np.asarray(G.cell_to_world(SPEC, cells))
    np.testing.assert_allclose(xy[..., 0], SPEC.origin[0] + (cols + 0.5) * SPEC.resolution, atol=1e-6)
    np.testing.assert_allclose(xy[..., 1], SPEC.origin[1] + (rows + 0.5) * SPEC.resolution, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(G.world_to_cell(SPEC, xy)), cells)


def test_world_to_cell_contains_the_point():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-4, 5, size=(2000, 2)).astype(np.float32)
    cells = np.asarray(G.world_to_cell(SPEC, xy))
    assert cells.dtype == np.int32
    centre = np.asarray(G.cell_to_world(SPEC, cells))
    assert np.all(np.abs(xy - centre) <= SPEC.resolution / 2 + 1e-5)
    # Row follows y, column follows x.
    np.testing.assert_array_equal(cells[:, 1], np.floor((xy[:, 0] + 1.3) / 0.25).astype(int))


def test_flat_index_in_map_and_out_of_map_cells():
    h, w = SPEC.shape
    for r in range(-2, h + 2):
        for c in range(-2, w + 2):
            got = int(G.flat_index(SPEC, jnp.array([r, c], jnp.int32)))
            want = r * w + c if (0 <= r < h and 0 <= c < w) else SPEC.num_cells
            assert got == want, (r, c)
    # Just right of row 0 is not row 1, column 0; just left of row 1 is not the end of row 0.
    assert int(G.flat_index(SPEC, jnp.array([0, w]))) == SPEC.num_cells
    assert int(G.flat_index(SPEC, jnp.array([1, -1]))) == SPEC.num_cells


def test_far_away_points_are_out_of_map_without_overflow():
    xy = jnp.array([[1e9, 0.0], [-1e9, 0.0], [0.0, 1e30], [0.0, -1e30], [3e38, -3e38]], jnp.float32)
    idx = np.asarray(G.flat_index(SPEC, G.world_to_cell(SPEC, xy)))
    np.testing.assert_array_equal(idx, SPEC.num_cells)


def test_empty_map():
    m = O.empty_map(SPEC)
    assert m.logodds.shape == SPEC.shape and m.logodds.dtype == O.LOGODDS_DTYPE
    assert m.hit_dist2.dtype == jnp.uint8 and np.all(np.asarray(m.hit_dist2) == O.FAR)
    assert np.all(np.asarray(m.logodds) == 0)


# ----------------------------------------------------------------------------- NumPy reference

def np_compose(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


class Reference:
    """Slow, loop-by-loop scan insertion following insert_scan's docstring."""

    def __init__(self, spec, margin=1e-4):
        self.spec = spec
        self.margin = margin  # in cells: points this close to a cell edge make the comparison ill-posed
        self.closest = np.inf

    def cell(self, p):
        u = (p[0] - self.spec.origin[0]) / self.spec.resolution
        v = (p[1] - self.spec.origin[1]) / self.spec.resolution
        self.closest = min(self.closest, abs(u - round(u)), abs(v - round(v)))
        return (int(math.floor(v)), int(math.floor(u)))

    def inside(self, c):
        h, w = self.spec.shape
        return 0 <= c[0] < h and 0 <= c[1] < w

    def insert(self, logodds, hit, pose, ranges, sensor, params, max_range, radius):
        spec, res = self.spec, self.spec.resolution
        occ, free, lo, hi, nrfr = (float(v) for v in params)
        rmin, rmax = float(sensor.range_min), float(sensor.range_max)
        angles = np.asarray(sensor.beam_angles, np.float64)
        origin = np_compose(pose, np.asarray(sensor.laser_pose, np.float64))
        num_samples = int(math.ceil(max_range / res)) + 1
        inc = np.zeros(spec.shape)
        outside = 0
        ends = []
        for b, r in enumerate(np.asarray(ranges, np.float64)):
            d = np.array([math.cos(origin[2] + angles[b]), math.sin(origin[2] + angles[b])])
            no_return = r >= rmax
            returned = (not no_return) and rmin <= r < max_range
            if no_return:
                length = min(nrfr, rmax, max_range)
            elif r < rmin:
                length = 0.0
            else:
                length = min(r, max_range)
            end = self.cell(origin[:2] + r * d) if returned else None
            prev = None
            for s in range(num_samples):
                dist = s * res
                if not dist < length:
                    break
                c = self.cell(origin[:2] + dist * d)
                if c == prev:  # consecutive duplicate: counted once
                    continue
                prev = c
                if c == end:  # the endpoint cell is not free
                    continue
                if self.inside(c):
                    inc[c] += free
                else:
                    outside += 1
            if returned:
                if self.inside(end):
                    inc[end] += occ
                else:
                    outside += 1
                ends.append(end)
        new_logodds = np.clip(np.asarray(logodds, np.float64) + inc, lo, hi)
        new_hit = np.asarray(hit).astype(np.int64).copy()
        h, w = spec.shape
        for er, ec in ends:
            for dr in range(-radius, radius + 1):
                for dc in range(-radius, radius + 1):
                    d2 = dr * dr + dc * dc
                    r, c = er + dr, ec + dc
                    if d2 <= radius * radius and 0 <= r < h and 0 <= c < w:
                        new_hit[r, c] = min(new_hit[r, c], d2, O.FAR)
        assert self.closest > self.margin, "a sample lies on a cell edge: move the test scan"
        return new_logodds, new_hit, outside, inc


# Beam angles (laser frame) and ranges: every case of the docstring.
BEAMS = [
    (-2.9, 1.07),    # ordinary return
    (-1.7, 0.93),    # ordinary return
    (-0.6, 2.2),     # long return
    (0.05, 3.3),     # beyond max_insert_range, below range_max: free up to 2.6 m, leaves the map, no hit
    (0.9, 4.0),      # range == range_max: no return, free up to no_return_free_range
    (1.4, 0.05),     # below range_min: nothing
    (1.9, 2.1),      # return outside the map (top edge): endpoint dropped and counted
    (2.6, 1.38),     # two beams ending in the same cell: two increments
    (2.6001, 1.381),
    (-2.2, 6.0),     # beyond range_max: no return
    (3.1, 0.0),      # zero range: below range_min
]
SENSOR = make_sensor([a for a, _ in BEAMS], range_min=0.12, range_max=4.0, laser_pose=(0.11, -0.04, 0.21))
RANGES = np.array([r for _, r in BEAMS], np.float32)
POSE = np.array([0.37, 0.81, 0.13], np.float32)


def prior_map(seed=0):
    rng = np.random.default_rng(seed)
    logodds = rng.uniform(-2.0, 3.5, SPEC.shape).astype(np.float32)
    logodds[rng.random(SPEC.shape) < 0.15] = -2.0  # at the clamps: insertion saturates here
    logodds[rng.random(SPEC.shape) < 0.15] = 3.5
    hit = np.full(SPEC.shape, O.FAR, np.uint8)
    hit[3, 4] = 0
    hit[9, 12] = 2
    hit[6, 10] = 1
    return O.GridMap(jnp.asarray(logodds), jnp.asarray(hit))


def check_against_reference(spec, grid_map, pose, ranges, sensor, max_range=MAX_RANGE, radius=RADIUS):
    new, outside = insert(spec, grid_map, jnp.asarray(pose), jnp.asarray(ranges), sensor, PARAMS,
                          max_range, radius)
    ref_lo, ref_hit, ref_out, inc = Reference(spec).insert(
        np.asarray(grid_map.logodds), np.asarray(grid_map.hit_dist2), pose, ranges, sensor, PARAMS,
        max_range, radius)
    assert new.logodds.dtype == grid_map.logodds.dtype and new.hit_dist2.dtype == jnp.uint8
    # Half-precision maps: a few roundings of at most half an ulp (2^-10 at |l| < 4) each.
    atol = 4e-3 if grid_map.logodds.dtype == jnp.float16 else 1e-5
    np.testing.assert_allclose(np.asarray(new.logodds, np.float64), ref_lo, rtol=0, atol=atol)
    np.testing.assert_array_equal(np.asarray(new.hit_dist2), ref_hit)
    assert int(outside) == ref_out
    return new, int(outside), inc


def test_insert_scan_matches_reference():
    m = prior_map()
    # Put the endpoint cells near the upper clamp, so that the occupied update saturates there.
    _, _, _, inc = Reference(SPEC).insert(np.asarray(m.logodds), np.asarray(m.hit_dist2), POSE, RANGES, SENSOR,
                                          PARAMS, MAX_RANGE, RADIUS)
    m = m._replace(logodds=jnp.where(jnp.asarray(inc > 0), 3.2, m.logodds))
    new, outside, inc = check_against_reference(SPEC, m, POSE, RANGES, SENSOR)
    # The scene exercises what it claims to.
    assert outside >= 3
    assert inc.max() >= 2 * float(PARAMS.logodds_occupied) - 1e-6  # two endpoints in one cell
    assert np.any(np.isclose(inc, -0.4)) and np.any(inc < -0.4 - 1e-6)  # cells freed by several beams
    prior = np.asarray(m.logodds)
    assert np.any((prior + inc < -2.0) & (inc != 0)) and np.any((prior + inc > 3.5) & (inc != 0))  # clamping
    assert np.asarray(new.hit_dist2).min() == 0 and (np.asarray(new.hit_dist2) != np.asarray(m.hit_dist2)).any()


def test_no_return_clears_no_further_than_range_max():
    # A short-range laser (range_max 1.0 m < no_return_free_range 1.3 m < max_insert_range):
    # a no-return beam says only that nothing lies within 1.0 m, so no cell beyond is cleared
    # (a 4 m laser with the default 5 m would erase obstacles it cannot see).
    short = make_sensor(SENSOR.beam_angles, range_min=0.12, range_max=1.0, laser_pose=(0.11, -0.04, 0.21))
    _, _, inc = check_against_reference(SPEC, O.empty_map(SPEC), POSE, np.full_like(RANGES, 1.0), short)
    rows, cols = np.nonzero(inc)
    assert rows.size > 0 and np.all(inc[rows, cols] < 0)
    origin = np_compose(POSE.astype(np.float64), np.asarray(short.laser_pose, np.float64))
    centers = np.stack([cols + 0.5, rows + 0.5], -1) * SPEC.resolution + np.asarray(SPEC.origin)
    # A cleared cell's centre is at most half a cell diagonal past the range.
    reach = np.linalg.norm(centers - origin[:2], axis=-1)
    assert reach.max() <= 1.0 + SPEC.resolution / np.sqrt(2) + 1e-6
    assert reach.max() > 1.0 - 2 * SPEC.resolution  # and the beams do reach range_max


def test_insert_scan_into_empty_map_and_accumulation():
    m = O.empty_map(SPEC)
    m1, _, _ = check_against_reference(SPEC, m, POSE, RANGES, SENSOR)
    # A second scan from elsewhere, on top of the first.
    check_against_reference(SPEC, m1, np.array([1.2, 1.5, -2.0], np.float32), RANGES, SENSOR)


def test_insert_scan_pose_rotations_match_reference():
    for k, theta in enumerate([-3.0, -1.1, 0.8, 2.4]):
        pose = np.array([0.2 + 0.1 * k, 0.5 + 0.07 * k, theta], np.float32)
        check_against_reference(SPEC, prior_map(k + 1), pose, RANGES, SENSOR)


def test_insert_scan_vmaps_over_particles():
    poses = np.array([[0.37, 0.81, 0.13], [1.21, 1.52, -2.0], [0.1, 0.2, 2.9]], np.float32)
    maps = O.GridMap(jnp.stack([prior_map(i).logodds for i in range(3)]),
                     jnp.stack([prior_map(i).hit_dist2 for i in range(3)]))
    batched = jax.jit(jax.vmap(lambda m, p: O.insert_scan(SPEC, m, p, jnp.asarray(RANGES), SENSOR, PARAMS,
                                                          MAX_RANGE, RADIUS)))
    new, outside = batched(maps, jnp.asarray(poses))
    for i in range(3):
        lo, hit, out, _ = Reference(SPEC).insert(np.asarray(maps.logodds[i]), np.asarray(maps.hit_dist2[i]),
                                                 poses[i], RANGES, SENSOR, PARAMS, MAX_RANGE, RADIUS)
        np.testing.assert_allclose(np.asarray(new.logodds[i], np.float64), lo,
                                   atol=4e-3 if new.logodds.dtype == jnp.float16 else 1e-5)
        np.testing.assert_array_equal(np.asarray(new.hit_dist2[i]), hit)
        assert int(outside[i]) == out


@pytest.mark.parametrize("x", [4.0, 5.5])
def test_scan_entirely_outside_leaves_logodds_unchanged_and_counts_samples(x):
    # Robot right of the map (x = 2.7 is its edge): every sample and endpoint is outside.
    m = prior_map()
    pose = np.array([x, 0.81, 0.1], np.float32)
    new, outside, inc = check_against_reference(SPEC, m, pose, RANGES, SENSOR)
    np.testing.assert_array_equal(np.asarray(new.logodds), np.asarray(m.logodds))
    assert not inc.any()
    assert outside > 20
    if x == 5.5:  # every endpoint more than field_radius cells beyond the edge: the field is untouched too
        np.testing.assert_array_equal(np.asarray(new.hit_dist2), np.asarray(m.hit_dist2))


def test_scan_far_outside_counts_every_sample():
    m = prior_map()
    pose = np.array([100.0, 100.0, 0.1], np.float32)
    new, outside, _ = check_against_reference(SPEC, m, pose, RANGES, SENSOR)
    np.testing.assert_array_equal(np.asarray(new.logodds), np.asarray(m.logodds))


def test_returned_endpoint_just_outside_registers_field_inside():
    """An endpoint just beyond the map edge is dropped from the log-odds (and counted) but
    still registers in the likelihood field of the in-map cells near it, as the reference does."""
    sensor = make_sensor([0.0], range_min=0.1, range_max=10.0)
    pose = np.array([1.9, 0.81, 0.0], np.float32)  # the endpoint at x = 2.84 > 2.7
    new, outside, inc = check_against_reference(SPEC, prior_map(), pose, np.array([0.94], np.float32), sensor)
    assert outside == 1 and not (inc > 0).any()
    assert (np.asarray(new.hit_dist2)[:, -1] == 1).any()


def test_field_radius_larger_than_uint8_squares():
    """field_radius = 16 has squared offsets up to 256, which does not fit a uint8: the field
    must never claim an endpoint closer than it is (cells at distance 16 must read FAR, not 0)."""
    spec = G.GridSpec((40, 40), 0.25, (0.0, 0.0))
    sensor = make_sensor([0.0], range_min=0.1, range_max=10.0)
    pose = np.array([3.06, 5.06, 0.0], np.float32)  # endpoint in cell (20, 20)
    ranges = np.array([2.0], np.float32)
    try:
        new, _ = insert(spec, O.empty_map(spec), jnp.asarray(pose), jnp.asarray(ranges), sensor, PARAMS,
                        4.0, 16)
    except ValueError:
        return  # refusing a radius whose squares do not fit is also correct
    _, ref_hit, _, _ = Reference(spec).insert(np.zeros(spec.shape), np.full(spec.shape, O.FAR), pose, ranges,
                                              sensor, PARAMS, 4.0, 16)
    got = np.asarray(new.hit_dist2)
    assert got[20, 4] == O.FAR, f"cell 16 cells from the only endpoint reads {got[20, 4]}"
    np.testing.assert_array_equal(got, ref_hit)


def test_insert_scan_is_traced_once_per_spec():
    """Changing pose, ranges or params does not recompile (they are traced)."""
    traces = []

    def counted(*args):
        traces.append(1)
        return O.insert_scan(*args)

    f = jax.jit(counted, static_argnums=(0, 6, 7))
    m = O.empty_map(SPEC)
    f(SPEC, m, jnp.asarray(POSE), jnp.asarray(RANGES), SENSOR, PARAMS, MAX_RANGE, RADIUS)
    p2 = PARAMS._replace(logodds_free=jnp.float32(-0.7))
    f(SPEC, m, jnp.asarray(POSE) + 0.1, jnp.asarray(RANGES) * 0.9, SENSOR, p2, MAX_RANGE, RADIUS)
    f(SPEC, m, jnp.asarray(POSE), jnp.asarray(RANGES), SENSOR._replace(laser_pose=jnp.zeros(3)), PARAMS,
      MAX_RANGE, RADIUS)
    assert len(traces) == 1
