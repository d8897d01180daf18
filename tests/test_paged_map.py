"""Paged maps against a dense NumPy-checked reference: identical log-odds and field in every
cell through random insertions and resamplings; reference counts against a recount of the
directories and blocks; copy on write of blocks and tiles; inactive particles; pool growth."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import paged_map as P
from jaxslam.config import default_params
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.occupancy import FAR, empty_map, insert_scan

# 12 x 12 tiles of 16 cells in blocks of 4 x 4 tiles: a scan's window (7 x 7 tiles) spans up to 3 x 3 blocks.
SPEC = P.PagedGridSpec(resolution=0.05, tile_size=16, num_tiles=(12, 12), origin=(-4.8, -4.8), block_size=4)
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
    return (np.asarray(P.cell_values(SPEC, P.particle_field(maps, particle, "logodds"), cells, 0.0)),
            np.asarray(P.cell_values(SPEC, P.particle_field(maps, particle), cells, FAR)))


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
    maps = P.empty(SPEC, N, capacity=600, block_capacity=60)
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
        assert_counts_match_the_maps(maps)


def assert_counts_match_the_maps(maps):
    """Block references are the directories' entries, tile references the entries of the blocks
    in use, and the free lists the first slots with no reference."""
    directory, blocks = np.asarray(maps.directory), np.asarray(maps.blocks)
    block_counts = np.bincount(directory[directory >= 0], minlength=blocks.shape[0])
    np.testing.assert_array_equal(np.asarray(maps.block_refcount), block_counts)
    entries = blocks[block_counts > 0]
    counts = np.bincount(entries[entries >= 0], minlength=maps.capacity)
    np.testing.assert_array_equal(np.asarray(maps.refcount), counts)
    for got, used in ((maps.free_slots, counts), (maps.free_blocks, block_counts)):
        free = np.flatnonzero(used == 0)[:got.shape[0]]
        expected = np.full(got.shape[0], used.shape[0])
        expected[:free.size] = free
        np.testing.assert_array_equal(np.asarray(got), expected)


def test_writing_a_shared_tile_copies_it_for_the_writer_only():
    rng = np.random.default_rng(5)
    maps = P.empty(SPEC, 2, capacity=200)
    poses, ranges = random_scan(rng, 2)
    maps, _ = insert_paged(SPEC, maps, poses.at[1].set(poses[0]), ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    maps = resample_paged(maps, jnp.array([0, 0], jnp.int32))  # both particles now share particle 0's map
    shared = int(P.tiles_in_use(maps))
    np.testing.assert_array_equal(np.asarray(maps.directory[0]), np.asarray(maps.directory[1]))
    assert_counts_match_the_maps(maps)
    before = dense_view(maps, 0)
    # Particle 1 alone inserts a scan near particle 0's; particle 0's scan lies outside the grid.
    nearby = jnp.stack([jnp.array([100.0, 100.0, 0.0]), poses[0] + jnp.array([0.3, -0.2, 0.5])])
    after_insert, outside = insert_paged(SPEC, maps, nearby, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert int(outside[0]) > 0
    after = dense_view(after_insert, 0)
    np.testing.assert_array_equal(after[0], before[0])  # particle 0's map did not change
    np.testing.assert_array_equal(after[1], before[1])
    changed = P.page_table(SPEC, after_insert, 1) != P.page_table(SPEC, after_insert, 0)
    assert changed.any()  # particle 1 got copies of the tiles it wrote
    assert (np.asarray(after_insert.directory[1]) != np.asarray(after_insert.directory[0])).any()  # and blocks
    assert int(P.tiles_in_use(after_insert)) > shared
    assert_counts_match_the_maps(after_insert)


@pytest.mark.parametrize("limit", ["capacity", "max_new_tiles", "max_new_blocks"])
def test_a_small_pool_overflows_and_a_grown_one_gives_the_same_maps(limit):
    rng = np.random.default_rng(3)
    poses, ranges = random_scan(rng, N)
    big, _ = insert_paged(SPEC, P.empty(SPEC, N, 400), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    needed, needed_blocks = int(P.tiles_in_use(big)), int(P.blocks_in_use(big))
    assert int(big.peak_request) == needed and int(big.peak_block_request) == needed_blocks
    state = {"capacity": P.empty(SPEC, N, needed - 3),
             "max_new_tiles": P.empty(SPEC, N, 400, max_new_tiles=needed - 3),
             "max_new_blocks": P.empty(SPEC, N, 400, max_new_blocks=needed_blocks - 1)}[limit]
    attempt, _ = insert_paged(SPEC, state, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert bool(attempt.overflow)
    # All or nothing: the maps are as they were (and the host can insert again after growing).
    for name in ("directory", "blocks", "block_refcount", "logodds", "hit_dist2", "refcount", "free_slots",
                 "free_blocks"):
        np.testing.assert_array_equal(np.asarray(getattr(attempt, name)), np.asarray(getattr(state, name)), name)
    assert int(attempt.peak_request) == needed
    # The host grows the pool and repeats the step from the state before it.
    grown = P.grow(SPEC, state, P.PoolSize(max(needed + 10, state.capacity), needed + 10, 400, 400))
    again, _ = insert_paged(SPEC, grown, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert not bool(again.overflow)
    for n in range(N):
        for a, b in zip(dense_view(again, n), dense_view(big, n)):
            np.testing.assert_array_equal(a, b)
    assert_counts_match_the_maps(again)
    with pytest.raises(ValueError, match="smaller"):
        P.grow(SPEC, grown, P.PoolSize(5, 5, 400, 400))


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
    with pytest.raises(ValueError, match="block_size must be a power of two"):
        P.PagedGridSpec(block_size=12)
    spec = P.PagedGridSpec.centred((10.0, -3.0), 100.0, 0.05, 64)
    assert spec.num_tiles == (32, 32)
    x0, x1, y0, y1 = spec.grid.extent
    assert (x0 + x1) / 2 == pytest.approx(10.0) and (y0 + y1) / 2 == pytest.approx(-3.0)
    assert spec.window_tiles(15.0, 4) == 11
    assert spec.num_blocks == (2, 2) and spec.window_blocks(11) == 2
    assert P.PagedGridSpec().num_blocks == (25, 25) and SPEC.window_blocks(7) == 3


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
    paged = endpoint_log_likelihoods(SPEC, P.particle_field(maps, 0), query, ranges, SENSOR,
                                     params, lookup)
    reference = endpoint_log_likelihoods(SPEC.grid, dense.hit_dist2[0], query, ranges, SENSOR, params, lookup)
    np.testing.assert_array_equal(np.asarray(paged), np.asarray(reference))


def test_inactive_particles_keep_their_maps_and_take_no_tiles():
    """A particle the resampling drops does not insert: its map is unchanged, it asks for no tile
    or block, and the active particles' maps are what a full insertion gives them."""
    rng = np.random.default_rng(13)
    poses, ranges = random_scan(rng, N)
    start, _ = insert_paged(SPEC, P.empty(SPEC, N, 600), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    start = resample_paged(start, jnp.array([0, 0, 1, 1], jnp.int32))
    moved = poses + jnp.asarray(rng.normal(0, 0.3, (N, 3)), jnp.float32)
    full, _ = insert_paged(SPEC, start, moved, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    active = jnp.array([True, False, True, False])
    part, _ = jax.jit(P.insert_scans, static_argnums=(0, 6, 7))(SPEC, start, moved, ranges, SENSOR, INSERTION,
                                                                MAX_RANGE, RADIUS, active)
    for n in range(N):
        expected = dense_view(full if bool(active[n]) else start, n)
        for got, want in zip(dense_view(part, n), expected):
            np.testing.assert_array_equal(got, want, err_msg=f"particle {n}")
    assert int(P.tiles_in_use(part)) < int(P.tiles_in_use(full)) and int(P.blocks_in_use(part)) < int(P.blocks_in_use(full))
    assert_counts_match_the_maps(part)


def test_a_dropped_block_frees_the_tiles_only_it_held():
    rng = np.random.default_rng(17)
    poses, ranges = random_scan(rng, 2)
    maps, _ = insert_paged(SPEC, P.empty(SPEC, 2, 600), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    before = int(P.tiles_in_use(maps))
    only_first = resample_paged(maps, jnp.array([0, 0], jnp.int32))  # particle 1's own tiles and blocks go
    assert_counts_match_the_maps(only_first)
    np.testing.assert_array_equal(np.asarray(only_first.directory[0]), np.asarray(only_first.directory[1]))
    assert int(P.tiles_in_use(only_first)) == int(np.count_nonzero(P.page_table(SPEC, maps, 0) >= 0)) < before
