"""Paged maps against a dense NumPy-checked reference: identical log-odds and field in every
cell through random insertions and resamplings; copy on write; pool growth."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import paged_map as P
from jaxslam.config import default_params
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.occupancy import FAR, empty_map, insert_scan

SPEC = P.PagedGridSpec(resolution=0.05, tile_size=16, num_tiles=(12, 12), origin=(-4.8, -4.8))
SENSOR = make_sensor(uniform_beams(37, np.pi * 1.5), range_min=0.05, range_max=2.5)
INSERTION = default_params().insertion
MAX_RANGE, RADIUS = 2.0, 3
N = 4

insert_paged = jax.jit(P.insert_scans, static_argnums=(0, 6, 7))
insert_dense = jax.jit(jax.vmap(insert_scan, in_axes=(None, 0, 0, None, None, None, None, None)),
                       static_argnums=(0, 6, 7))
resample_paged = jax.jit(P.resample)


def dense_view(maps, particle):
    """Every cell of the virtual grid of one particle's paged map (log-odds, field)."""
    h, w = SPEC.grid.shape
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    cells = jnp.asarray(np.stack([rows, cols], -1))
    pages = maps.pages[particle]
    return (np.asarray(P.cell_values(SPEC, pages, maps.logodds, cells, 0.0)),
            np.asarray(P.cell_values(SPEC, pages, maps.hit_dist2, cells, FAR)))


def random_scan(rng, num):
    poses = np.column_stack([rng.uniform(-4.5, 4.5, num), rng.uniform(-4.5, 4.5, num),
                             rng.uniform(-np.pi, np.pi, num)]).astype(np.float32)
    ranges = rng.uniform(0.02, 3.0, SENSOR.beam_angles.shape).astype(np.float32)
    return jnp.asarray(poses), jnp.asarray(ranges)


def assert_same(maps, dense, particles=range(N)):
    for n in particles:
        logodds, field = dense_view(maps, n)
        np.testing.assert_array_equal(logodds, np.asarray(dense.logodds[n]), err_msg=f"log-odds of particle {n}")
        np.testing.assert_array_equal(field, np.asarray(dense.hit_dist2[n]), err_msg=f"field of particle {n}")


@pytest.mark.parametrize("seed", [0, 1])
def test_paged_maps_equal_dense_maps_through_insertions_and_resamplings(seed):
    rng = np.random.default_rng(seed)
    maps = P.empty(SPEC, N, capacity=600)
    dense = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,) + a.shape), empty_map(SPEC.grid))
    for step in range(8):
        poses, ranges = random_scan(rng, N)
        if step % 3 == 1:  # particles close together: their windows overlap and share tiles
            poses = poses.at[1:].set(poses[0] + jnp.asarray(rng.normal(0, 0.2, (N - 1, 3)), jnp.float32))
        maps, outside = insert_paged(SPEC, maps, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
        dense, dense_outside = insert_dense(SPEC.grid, dense, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
        np.testing.assert_array_equal(np.asarray(outside), np.asarray(dense_outside))
        if step % 2 == 1:
            ancestors = jnp.asarray(rng.integers(0, N, N), jnp.int32)
            maps = resample_paged(maps, ancestors)
            dense = jax.tree.map(lambda a: a[ancestors], dense)
        assert not bool(maps.overflow)
        assert_same(maps, dense)
    # The reference counts, holders and free list are the page tables'.
    assert_counts_match_page_tables(maps)


def assert_counts_match_page_tables(maps):
    pages = np.asarray(maps.pages)
    counts = np.bincount(pages[pages >= 0], minlength=maps.capacity)
    np.testing.assert_array_equal(np.asarray(maps.refcount), counts)
    holders = np.zeros((maps.capacity, pages.shape[0]), bool)
    for n in range(pages.shape[0]):
        holders[pages[n][pages[n] >= 0], n] = True
    np.testing.assert_array_equal(np.asarray(maps.holders), holders)
    free = np.flatnonzero(counts == 0)[:maps.max_new_tiles]
    expected = np.full(maps.max_new_tiles, maps.capacity)
    expected[:free.size] = free
    np.testing.assert_array_equal(np.asarray(maps.free_slots), expected)


def test_writing_a_shared_tile_copies_it_for_the_writer_only():
    rng = np.random.default_rng(5)
    maps = P.empty(SPEC, 2, capacity=200)
    poses, ranges = random_scan(rng, 2)
    maps, _ = insert_paged(SPEC, maps, poses.at[1].set(poses[0]), ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    maps = resample_paged(maps, jnp.array([0, 0], jnp.int32))  # both particles now share particle 0's map
    shared = int(P.tiles_in_use(maps))
    np.testing.assert_array_equal(np.asarray(maps.pages[0]), np.asarray(maps.pages[1]))
    assert_counts_match_page_tables(maps)
    before = dense_view(maps, 0)
    # Particle 1 alone inserts a scan near particle 0's; particle 0's scan lies outside the grid.
    nearby = jnp.stack([jnp.array([100.0, 100.0, 0.0]), poses[0] + jnp.array([0.3, -0.2, 0.5])])
    after_insert, outside = insert_paged(SPEC, maps, nearby, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert int(outside[0]) > 0
    after = dense_view(after_insert, 0)
    np.testing.assert_array_equal(after[0], before[0])  # particle 0's map did not change
    np.testing.assert_array_equal(after[1], before[1])
    changed = np.asarray(after_insert.pages[1]) != np.asarray(after_insert.pages[0])
    assert changed.any()  # particle 1 got copies of the tiles it wrote
    assert int(P.tiles_in_use(after_insert)) > shared
    assert_counts_match_page_tables(after_insert)


@pytest.mark.parametrize("limit", ["capacity", "max_new_tiles"])
def test_a_small_pool_overflows_and_a_grown_one_gives_the_same_maps(limit):
    rng = np.random.default_rng(3)
    poses, ranges = random_scan(rng, N)
    big, _ = insert_paged(SPEC, P.empty(SPEC, N, 400), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    needed = int(P.tiles_in_use(big))
    assert int(big.peak_request) == needed
    state = P.empty(SPEC, N, needed - 3) if limit == "capacity" else P.empty(SPEC, N, 400, max_new_tiles=needed - 3)
    attempt, _ = insert_paged(SPEC, state, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert bool(attempt.overflow)
    # All or nothing: the maps are as they were (and the host can insert again after growing).
    for name in ("pages", "logodds", "hit_dist2", "refcount", "holders", "free_slots"):
        np.testing.assert_array_equal(np.asarray(getattr(attempt, name)), np.asarray(getattr(state, name)), name)
    assert int(attempt.peak_request) == needed
    # The host grows the pool and repeats the step from the state before it.
    grown = P.grow(SPEC, state, max(needed + 10, state.capacity), needed + 10)
    again, _ = insert_paged(SPEC, grown, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert not bool(again.overflow)
    for n in range(N):
        for a, b in zip(dense_view(again, n), dense_view(big, n)):
            np.testing.assert_array_equal(a, b)
    assert_counts_match_page_tables(again)
    with pytest.raises(ValueError, match="capacity"):
        P.grow(SPEC, grown, 5, 5)


def test_to_dense_places_the_written_tiles():
    rng = np.random.default_rng(7)
    poses, ranges = random_scan(rng, 1)
    maps, _ = insert_paged(SPEC, P.empty(SPEC, 1, 100), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    logodds, field, box = P.to_dense(SPEC, maps, 0)
    full_logodds, full_field = dense_view(maps, 0)
    row0 = round((box.origin[1] - SPEC.origin[1]) / SPEC.resolution)
    col0 = round((box.origin[0] - SPEC.origin[0]) / SPEC.resolution)
    h, w = box.shape
    np.testing.assert_array_equal(logodds, full_logodds[row0:row0 + h, col0:col0 + w])
    np.testing.assert_array_equal(field, full_field[row0:row0 + h, col0:col0 + w])
    assert np.count_nonzero(full_logodds) == np.count_nonzero(logodds)  # nothing known lies outside the box


def test_spec_validation_and_window():
    with pytest.raises(ValueError, match="positive"):
        P.PagedGridSpec(tile_size=0)
    with pytest.raises(ValueError, match="int32"):
        P.PagedGridSpec(tile_size=64, num_tiles=(1000, 1000))
    spec = P.PagedGridSpec.centred((10.0, -3.0), 100.0, 0.05, 64)
    assert spec.num_tiles == (32, 32)
    x0, x1, y0, y1 = spec.grid.extent
    assert (x0 + x1) / 2 == pytest.approx(10.0) and (y0 + y1) / 2 == pytest.approx(-3.0)
    assert spec.window_tiles(15.0, 4) == 11


@pytest.mark.parametrize("lookup", ["nearest", "bilinear"])
def test_the_likelihood_reads_a_paged_field_as_the_dense_one(lookup):
    """endpoint_log_likelihoods on one particle's PagedField equals the dense map's, at poses
    inside the written area, across tile edges and outside the virtual grid."""
    from jaxslam.likelihood_field import endpoint_log_likelihoods

    rng = np.random.default_rng(11)
    poses, ranges = random_scan(rng, 2)
    maps, _ = insert_paged(SPEC, P.empty(SPEC, 2, 300), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    dense, _ = insert_dense(SPEC.grid, jax.tree.map(lambda a: jnp.broadcast_to(a, (2,) + a.shape),
                                                    empty_map(SPEC.grid)), poses, ranges, SENSOR, INSERTION,
                            MAX_RANGE, RADIUS)
    query = jnp.concatenate([poses[:1] + jnp.asarray(rng.normal(0, 0.3, (40, 3)), jnp.float32),
                             jnp.array([[4.7, 4.7, 0.3], [-6.0, 0.0, 0.0]], jnp.float32)])
    params = default_params().likelihood
    paged = endpoint_log_likelihoods(SPEC, P.PagedField(maps.pages[0], maps.hit_dist2), query, ranges, SENSOR,
                                     params, lookup)
    reference = endpoint_log_likelihoods(SPEC.grid, dense.hit_dist2[0], query, ranges, SENSOR, params, lookup)
    np.testing.assert_array_equal(np.asarray(paged), np.asarray(reference))
