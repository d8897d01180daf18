"""Paged maps against a dense NumPy-checked reference: identical log-odds and field in every
cell through random insertions and resamplings; the pools' invariants (``check_invariants``:
reference counts against a recount of the directories and blocks, free lists, all or nothing)
after every step, and a corrupted pool caught; copy on write of blocks and tiles, as the worked
example in :mod:`jaxslam.maps.copy_on_write` tells it; inactive particles; pool growth."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import maps as paged
from jaxslam.config import default_params
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.occupancy import FAR, empty_map, insert_scan

# 12 x 12 tiles of 16 cells in blocks of 4 x 4 tiles: a scan's window (7 x 7 tiles) spans up to 3 x 3 blocks.
SPEC = paged.PagedGridSpec(resolution=0.05, tile_size=16, num_tiles=(12, 12), origin=(-4.8, -4.8), block_size=4)
SENSOR = make_sensor(uniform_beams(37, np.pi * 1.5), range_min=0.05, range_max=2.5)
INSERTION = default_params().insertion
MAX_RANGE, RADIUS = 2.0, 3
N = 4

insert_paged = jax.jit(paged.insert_scans, static_argnums=(0, 6, 7))
insert_dense = jax.jit(jax.vmap(insert_scan, in_axes=(None, 0, 0, None, None, None, None, None)),
                       static_argnums=(0, 6, 7))
resample_paged = jax.jit(paged.resample)


def dense_view(maps, particle):
    """Every cell of the virtual grid of one particle's paged map (log-odds, field)."""
    h, w = SPEC.grid.shape
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    cells = jnp.asarray(np.stack([rows, cols], -1))
    return (np.asarray(paged.cell_values(SPEC, paged.particle_field(maps, particle, "logodds"), cells, 0.0)),
            np.asarray(paged.cell_values(SPEC, paged.particle_field(maps, particle), cells, FAR)))


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
    maps = paged.empty(SPEC, N, capacity=600, block_capacity=60)
    paged.check_invariants(SPEC, maps)  # the empty pools' free lists are their first slots
    paged.check_invariants(SPEC, paged.empty(SPEC, N, capacity=600, max_new_tiles=250, block_capacity=60,
                                             max_new_blocks=25))
    dense = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,) + a.shape), empty_map(SPEC.grid))
    for step in range(8):
        poses, ranges = random_scan(rng, N)
        if step % 3 == 1:  # particles close together: their windows overlap and share tiles
            poses = poses.at[1:].set(poses[0] + jnp.asarray(rng.normal(0, 0.2, (N - 1, 3)), jnp.float32))
        before = maps
        maps, outside = insert_paged(SPEC, maps, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
        paged.check_invariants(SPEC, maps, before_insertion=before)
        dense, dense_outside = insert_dense(SPEC.grid, dense, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
        np.testing.assert_array_equal(np.asarray(outside), np.asarray(dense_outside))
        if step % 2 == 1:
            ancestors = jnp.asarray(rng.integers(0, N, N), jnp.int32)
            maps = resample_paged(maps, ancestors)
            dense = jax.tree.map(lambda a: a[ancestors], dense)
        assert not bool(maps.overflow)
        assert_same(maps, dense)
        paged.check_invariants(SPEC, maps)


def test_writing_a_shared_tile_copies_it_for_the_writer_only():
    rng = np.random.default_rng(5)
    maps = paged.empty(SPEC, 2, capacity=200)
    poses, ranges = random_scan(rng, 2)
    maps, _ = insert_paged(SPEC, maps, poses.at[1].set(poses[0]), ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    maps = resample_paged(maps, jnp.array([0, 0], jnp.int32))  # both particles now share particle 0's map
    shared = int(paged.tiles_in_use(maps))
    np.testing.assert_array_equal(np.asarray(maps.directory[0]), np.asarray(maps.directory[1]))
    paged.check_invariants(SPEC, maps)
    before = dense_view(maps, 0)
    # Particle 1 alone inserts a scan near particle 0's; particle 0's scan lies outside the grid.
    nearby = jnp.stack([jnp.array([100.0, 100.0, 0.0]), poses[0] + jnp.array([0.3, -0.2, 0.5])])
    after_insert, outside = insert_paged(SPEC, maps, nearby, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    paged.check_invariants(SPEC, after_insert, before_insertion=maps)
    assert int(outside[0]) > 0
    after = dense_view(after_insert, 0)
    np.testing.assert_array_equal(after[0], before[0])  # particle 0's map did not change
    np.testing.assert_array_equal(after[1], before[1])
    changed = paged.page_table(SPEC, after_insert, 1) != paged.page_table(SPEC, after_insert, 0)
    assert changed.any()  # particle 1 got copies of the tiles it wrote
    assert (np.asarray(after_insert.directory[1]) != np.asarray(after_insert.directory[0])).any()  # and blocks
    assert int(paged.tiles_in_use(after_insert)) > shared


@pytest.mark.parametrize("limit", ["capacity", "max_new_tiles", "max_new_blocks"])
def test_a_small_pool_overflows_and_a_grown_one_gives_the_same_maps(limit):
    rng = np.random.default_rng(3)
    poses, ranges = random_scan(rng, N)
    big, _ = insert_paged(SPEC, paged.empty(SPEC, N, 400), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    needed, needed_blocks = int(paged.tiles_in_use(big)), int(paged.blocks_in_use(big))
    assert int(big.peak_request) == needed and int(big.peak_block_request) == needed_blocks
    state = {"capacity": paged.empty(SPEC, N, needed - 3),
             "max_new_tiles": paged.empty(SPEC, N, 400, max_new_tiles=needed - 3),
             "max_new_blocks": paged.empty(SPEC, N, 400, max_new_blocks=needed_blocks - 1)}[limit]
    attempt, _ = insert_paged(SPEC, state, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert bool(attempt.overflow)
    # All or nothing: the maps are as they were (and the host can insert again after growing).
    paged.check_invariants(SPEC, attempt, before_insertion=state)
    assert int(attempt.peak_request) == needed
    # The host grows the pool and repeats the step from the state before it.
    grown = paged.grow(SPEC, state, paged.PoolSize(max(needed + 10, state.capacity), needed + 10, 400, 400))
    again, _ = insert_paged(SPEC, grown, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    assert not bool(again.overflow)
    for n in range(N):
        for a, b in zip(dense_view(again, n), dense_view(big, n)):
            np.testing.assert_array_equal(a, b)
    paged.check_invariants(SPEC, again)
    with pytest.raises(ValueError, match="smaller"):
        paged.grow(SPEC, grown, paged.PoolSize(5, 5, 400, 400))


def test_to_dense_places_the_written_tiles():
    rng = np.random.default_rng(7)
    poses, ranges = random_scan(rng, 1)
    maps, _ = insert_paged(SPEC, paged.empty(SPEC, 1, 100), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    logodds, field, box = paged.to_dense(SPEC, maps, 0)
    full_logodds, full_field = dense_view(maps, 0)
    row0 = round((box.origin[1] - SPEC.origin[1]) / SPEC.resolution)
    col0 = round((box.origin[0] - SPEC.origin[0]) / SPEC.resolution)
    h, w = box.shape
    np.testing.assert_array_equal(logodds, full_logodds[row0:row0 + h, col0:col0 + w])
    np.testing.assert_array_equal(field, full_field[row0:row0 + h, col0:col0 + w])
    assert np.count_nonzero(full_logodds) == np.count_nonzero(logodds)  # nothing known lies outside the box


def test_spec_validation_and_window():
    with pytest.raises(ValueError, match="positive"):
        paged.PagedGridSpec(tile_size=0)
    with pytest.raises(ValueError, match="int32"):
        paged.PagedGridSpec(tile_size=64, num_tiles=(1000, 1000))
    with pytest.raises(ValueError, match="block_size must be a power of two"):
        paged.PagedGridSpec(block_size=12)
    spec = paged.PagedGridSpec.centred((10.0, -3.0), 100.0, 0.05, 64)
    assert spec.num_tiles == (32, 32)
    x0, x1, y0, y1 = spec.grid.extent
    assert (x0 + x1) / 2 == pytest.approx(10.0) and (y0 + y1) / 2 == pytest.approx(-3.0)
    assert spec.window_tiles(15.0, 4) == 11
    assert spec.num_blocks == (2, 2) and spec.window_blocks(11) == 2
    assert paged.PagedGridSpec().num_blocks == (25, 25) and SPEC.window_blocks(7) == 3


@pytest.mark.parametrize("lookup", ["nearest", "bilinear"])
def test_the_likelihood_reads_a_paged_field_as_the_dense_one(lookup):
    """endpoint_log_likelihoods on one particle's PagedField equals the dense map's, at poses
    inside the written area, across tile edges and outside the virtual grid."""
    from jaxslam.likelihood_field import endpoint_log_likelihoods

    rng = np.random.default_rng(11)
    poses, ranges = random_scan(rng, 2)
    maps, _ = insert_paged(SPEC, paged.empty(SPEC, 2, 300), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    dense, _ = insert_dense(SPEC.grid, jax.tree.map(lambda a: jnp.broadcast_to(a, (2,) + a.shape),
                                                    empty_map(SPEC.grid)), poses, ranges, SENSOR, INSERTION,
                            MAX_RANGE, RADIUS)
    query = jnp.concatenate([poses[:1] + jnp.asarray(rng.normal(0, 0.3, (40, 3)), jnp.float32),
                             jnp.array([[4.7, 4.7, 0.3], [-6.0, 0.0, 0.0]], jnp.float32)])
    params = default_params().likelihood
    from_pages = endpoint_log_likelihoods(SPEC, paged.particle_field(maps, 0), query, ranges, SENSOR,
                                     params, lookup)
    reference = endpoint_log_likelihoods(SPEC.grid, dense.hit_dist2[0], query, ranges, SENSOR, params, lookup)
    np.testing.assert_array_equal(np.asarray(from_pages), np.asarray(reference))


def test_inactive_particles_keep_their_maps_and_take_no_tiles():
    """A particle the resampling drops does not insert: its map is unchanged, it asks for no tile
    or block, and the active particles' maps are what a full insertion gives them."""
    rng = np.random.default_rng(13)
    poses, ranges = random_scan(rng, N)
    start, _ = insert_paged(SPEC, paged.empty(SPEC, N, 600), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    start = resample_paged(start, jnp.array([0, 0, 1, 1], jnp.int32))
    moved = poses + jnp.asarray(rng.normal(0, 0.3, (N, 3)), jnp.float32)
    full, _ = insert_paged(SPEC, start, moved, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    active = jnp.array([True, False, True, False])
    part, _ = jax.jit(paged.insert_scans, static_argnums=(0, 6, 7))(SPEC, start, moved, ranges, SENSOR, INSERTION,
                                                                MAX_RANGE, RADIUS, active)
    for n in range(N):
        expected = dense_view(full if bool(active[n]) else start, n)
        for got, want in zip(dense_view(part, n), expected):
            np.testing.assert_array_equal(got, want, err_msg=f"particle {n}")
    assert int(paged.tiles_in_use(part)) < int(paged.tiles_in_use(full))
    assert int(paged.blocks_in_use(part)) < int(paged.blocks_in_use(full))
    paged.check_invariants(SPEC, part, before_insertion=start)


def test_a_dropped_block_frees_the_tiles_only_it_held():
    rng = np.random.default_rng(17)
    poses, ranges = random_scan(rng, 2)
    maps, _ = insert_paged(SPEC, paged.empty(SPEC, 2, 600), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    before = int(paged.tiles_in_use(maps))
    only_first = resample_paged(maps, jnp.array([0, 0], jnp.int32))  # particle 1's own tiles and blocks go
    paged.check_invariants(SPEC, only_first)
    np.testing.assert_array_equal(np.asarray(only_first.directory[0]), np.asarray(only_first.directory[1]))
    assert int(paged.tiles_in_use(only_first)) == int(np.count_nonzero(paged.page_table(SPEC, maps, 0) >= 0)) < before


def test_copy_on_write_as_the_module_docstring_tells_it():
    """Three particles share one map; particle 2 alone writes near it. Its copies of the shared
    blocks point at the same tiles (one more reference each) except the tiles it wrote, which
    are copies of their own; the others' maps are unchanged. Writing again copies nothing, and
    keeping only particle 2's descendants frees the blocks and tiles it replaced."""
    rng = np.random.default_rng(19)
    poses, ranges = random_scan(rng, 3)
    only_0 = jnp.array([True, False, False])
    first, _ = insert_paged(SPEC, paged.empty(SPEC, 3, 300), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS,
                            only_0)
    shared = resample_paged(first, jnp.zeros((3,), jnp.int32))
    paged.check_invariants(SPEC, shared)
    moved = poses.at[2].set(poses[0] + jnp.array([0.2, -0.1, 0.3]))
    only_2 = jnp.array([False, False, True])
    after, _ = insert_paged(SPEC, shared, moved, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS, only_2)
    paged.check_invariants(SPEC, after, before_insertion=shared)
    for n in (0, 1):
        np.testing.assert_array_equal(np.asarray(after.directory[n]), np.asarray(shared.directory[n]))
        for got, want in zip(dense_view(after, n), dense_view(shared, n)):
            np.testing.assert_array_equal(got, want)
    old_dir, new_dir = np.asarray(shared.directory[2]), np.asarray(after.directory[2])
    blocks_before, blocks_after = np.asarray(shared.blocks), np.asarray(after.blocks)
    refs_before, refs_after = np.asarray(shared.refcount), np.asarray(after.refcount)
    block_refs_before, block_refs_after = np.asarray(shared.block_refcount), np.asarray(after.block_refcount)
    copied_blocks = [(o, w) for o, w in zip(old_dir.ravel(), new_dir.ravel()) if o >= 0 and o != w]
    assert copied_blocks, "particle 2 wrote no shared block"
    kept_tiles, replaced_tiles = [], []  # (old tile slot, new tile slot) of the copied blocks' entries
    for old, new in copied_blocks:
        assert (block_refs_before[old], block_refs_after[old], block_refs_after[new]) == (3, 2, 1)
        for old_tile, new_tile in zip(blocks_before[old].ravel(), blocks_after[new].ravel()):
            if old_tile >= 0:
                (kept_tiles if new_tile == old_tile else replaced_tiles).append((old_tile, new_tile))
    assert kept_tiles and replaced_tiles
    for old_tile, _ in kept_tiles:  # block 5 and its copy 7 both point at it
        assert (refs_before[old_tile], refs_after[old_tile]) == (1, 2)
    for old_tile, new_tile in replaced_tiles:  # tile 9 stays block 5's, tile 12 is block 7's
        assert (refs_before[old_tile], refs_after[old_tile], refs_after[new_tile]) == (1, 1, 1)
    # Writing the same scan again: block 7 and tile 12 are particle 2's own, written in place.
    again, _ = insert_paged(SPEC, after, moved, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS, only_2)
    np.testing.assert_array_equal(np.asarray(again.directory), np.asarray(after.directory))
    np.testing.assert_array_equal(np.asarray(again.blocks), np.asarray(after.blocks))
    np.testing.assert_array_equal(np.asarray(again.refcount), np.asarray(after.refcount))
    # Keeping only particle 2's descendants: block 5 and tile 9 are free, the kept tiles back to 1.
    descendants = resample_paged(after, jnp.full((3,), 2, jnp.int32))
    paged.check_invariants(SPEC, descendants)
    refs = np.asarray(descendants.refcount)
    assert all(np.asarray(descendants.block_refcount)[old] == 0 for old, _ in copied_blocks)
    assert all(refs[old_tile] == 0 and refs[new_tile] == 1 for old_tile, new_tile in replaced_tiles)
    assert all(refs[old_tile] == 1 for old_tile, _ in kept_tiles)


@pytest.fixture(scope="module")
def cow_maps():
    """Four particles' maps after an insertion, a resampling to two ancestors and another
    insertion (shared, copied and fresh blocks and tiles), and the maps before that insertion."""
    rng = np.random.default_rng(23)
    poses, ranges = random_scan(rng, N)
    maps, _ = insert_paged(SPEC, paged.empty(SPEC, N, 600), poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    before = resample_paged(maps, jnp.array([0, 0, 1, 1], jnp.int32))
    moved = poses[jnp.array([0, 0, 1, 1])] + jnp.asarray(rng.normal(0, 0.3, (N, 3)), jnp.float32)
    after, _ = insert_paged(SPEC, before, moved, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
    paged.check_invariants(SPEC, after, before_insertion=before)
    return before, after


def recounted(maps):
    """``maps`` with the reference counts and free lists recomputed from the directories and
    blocks: a corruption of where things point then breaks only the invariant it is meant to."""
    directory, blocks = np.asarray(maps.directory), np.asarray(maps.blocks)
    block_refcount = np.bincount(directory[directory >= 0], minlength=blocks.shape[0]).astype(np.int32)
    entries = blocks[block_refcount > 0]
    refcount = np.bincount(entries[entries >= 0], minlength=maps.capacity).astype(np.int32)
    return maps._replace(block_refcount=jnp.asarray(block_refcount), refcount=jnp.asarray(refcount),
                         free_slots=paged.first_free(jnp.asarray(refcount), maps.max_new_tiles),
                         free_blocks=paged.first_free(jnp.asarray(block_refcount), maps.pool_size.max_new_blocks))


def _set(maps, name, index, value):
    return maps._replace(**{name: getattr(maps, name).at[index].set(value)})


def _in_use(maps):
    """A tile slot and a block slot in use, and the directory position (particle, row, col) of that block."""
    directory = np.asarray(maps.directory)
    particle, row, col = np.argwhere(directory >= 0)[0]
    block = directory[particle, row, col]
    tile = np.asarray(maps.blocks[block])[np.asarray(maps.blocks[block]) >= 0][0]
    return int(tile), int(block), (int(particle), int(row), int(col))


def _moved_block(maps):
    """A directory pointing at a block in use from another position."""
    _, block, (particle, row, col) = _in_use(maps)
    directory = np.asarray(maps.directory)
    other = np.argwhere((directory[particle] != block))[0]
    return recounted(_set(maps, "directory", (particle, other[0], other[1]), block))


def _moved_tile(maps):
    """A block in use pointing at one of its tiles from a second entry."""
    _, block, _ = _in_use(maps)
    entries = np.asarray(maps.blocks[block]).ravel()
    tile, unwritten = entries[entries >= 0][0], np.flatnonzero(entries < 0)[0]
    return recounted(_set(maps, "blocks", (block,) + divmod(int(unwritten), SPEC.block_size), tile))


def _tile_beyond_the_grid():
    """A block at the directory's last corner pointing at a tile past the grid's edge."""
    spec = paged.PagedGridSpec(0.05, 16, (10, 10), (-4.0, -4.0), 4)  # 3 x 3 blocks: tiles 10 and 11 are beyond
    maps = _set(paged.empty(spec, 1, 10, block_capacity=4), "directory", (0, 2, 2), 0)
    return spec, recounted(_set(maps, "blocks", (0, 3, 3), 0))


CORRUPTIONS = {
    "a tile refcount one too high": ("tile references",
                                     lambda m: _set(m, "refcount", _in_use(m)[0], m.refcount[_in_use(m)[0]] + 1)),
    "a tile refcount one too low": ("tile references",
                                    lambda m: _set(m, "refcount", _in_use(m)[0], m.refcount[_in_use(m)[0]] - 1)),
    "a block refcount one too high": ("block references",
                                      lambda m: _set(m, "block_refcount", _in_use(m)[1],
                                                     m.block_refcount[_in_use(m)[1]] + 1)),
    "a block pointing at a free tile": ("tile references",
                                        lambda m: _set(m, "blocks", (_in_use(m)[1], 0, 0), m.free_slots[0])),
    "a directory entry past the block pool": ("directory entries",
                                              lambda m: _set(m, "directory", _in_use(m)[2], m.block_refcount.shape[0])),
    "a block entry below UNWRITTEN": ("block entries", lambda m: _set(m, "blocks", (_in_use(m)[1], 0, 0), -2)),
    "a free list out of order": ("free lists", lambda m: m._replace(free_slots=m.free_slots[::-1])),
    "a block in two places": ("one place per block", _moved_block),
    "a tile in two places": ("one place per tile", _moved_tile),
    "a negative peak": ("peak requests", lambda m: m._replace(peak_block_request=jnp.int32(-1))),
}


@pytest.mark.parametrize("corruption", list(CORRUPTIONS))
def test_the_checker_names_the_invariant_a_corrupted_pool_breaks(cow_maps, corruption):
    _, maps = cow_maps
    invariant, corrupt = CORRUPTIONS[corruption]
    with pytest.raises(AssertionError, match=f"invariant '{invariant}'"):
        paged.check_invariants(SPEC, corrupt(maps))


def test_the_checker_catches_a_broken_insertion(cow_maps):
    before, after = cow_maps
    spec, beyond = _tile_beyond_the_grid()
    with pytest.raises(AssertionError, match="'tiles beyond the grid'"):
        paged.check_invariants(spec, beyond)
    with pytest.raises(AssertionError, match="'all or nothing'"):  # an overflow that wrote
        paged.check_invariants(SPEC, after._replace(overflow=jnp.bool_(True)), before_insertion=before)
    with pytest.raises(AssertionError, match="'all or nothing'"):  # an overflow of requests that fit
        paged.check_invariants(SPEC, before._replace(overflow=jnp.bool_(True)), before_insertion=before)
    with pytest.raises(AssertionError, match="'peaks never fall'"):
        paged.check_invariants(SPEC, after._replace(peak_request=before.peak_request - 1), before_insertion=before)
    no_peaks = {"peak_request": jnp.int32(0), "peak_block_request": jnp.int32(0)}
    with pytest.raises(AssertionError, match="'peaks cover the growth'"):
        paged.check_invariants(SPEC, after._replace(**no_peaks), before_insertion=before._replace(**no_peaks))
    with pytest.raises(ValueError, match="logodds"):
        paged.check_invariants(SPEC, after._replace(logodds=after.logodds.astype(jnp.float32)))


@pytest.mark.parametrize("block", [1, 3, 7])
def test_an_insertion_in_blocks_of_particles_gives_the_same_maps_bit_for_bit(block):
    """``particle_block`` changes no bit: blocks of 1, of 3 (7 particles as 3 blocks of 3, two
    padding particles) and of all 7, against the insertion of all at once, through insertions
    (some particles inactive, some close together) and resamplings."""
    rng = np.random.default_rng(11)
    num = 7
    whole = blocked = paged.empty(SPEC, num, capacity=900, block_capacity=90)
    for step in range(4):
        poses, ranges = random_scan(rng, num)
        poses = poses.at[1:4].set(poses[0] + jnp.asarray(rng.normal(0, 0.2, (3, 3)), jnp.float32))
        active = jnp.asarray(rng.random(num) < 0.8)
        whole, outside = insert_paged(SPEC, whole, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS, active)
        blocked, blocked_outside = jax.jit(paged.insert_scans, static_argnums=(0, 6, 7, 9))(
            SPEC, blocked, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS, active, block)
        ancestors = jnp.asarray(rng.integers(0, num, num), jnp.int32)
        whole, blocked = resample_paged(whole, ancestors), resample_paged(blocked, ancestors)
        np.testing.assert_array_equal(np.asarray(outside), np.asarray(blocked_outside))
        for a, b, name in zip(whole, blocked, paged.PagedMaps._fields):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f"{name} after step {step}")


def test_tile_copies_in_rounds_copy_exactly_the_requested_tiles():
    """More requested tiles than one round holds: every target gets its source (or a fresh tile),
    nothing else changes."""
    rng = np.random.default_rng(2)
    capacity, count = 3 * paged.copy_on_write.TILES_PER_COPY_ROUND, paged.copy_on_write.TILES_PER_COPY_ROUND + 5
    logodds = jnp.asarray(rng.normal(size=(capacity, 4, 4)), jnp.float16)
    field = jnp.asarray(rng.integers(0, 255, (capacity, 4, 4)), jnp.uint8)
    source = np.concatenate([np.arange(count) % 50, np.full(10, 3)]).astype(np.int32)
    source[7] = paged.UNWRITTEN
    target = np.concatenate([capacity - 1 - np.arange(count), np.full(10, capacity)]).astype(np.int32)
    copy_tile_rounds = jax.jit(paged.copy_on_write._copy_tile_rounds)
    new_logodds, new_field = copy_tile_rounds(logodds, field, jnp.asarray(source), jnp.asarray(target),
                                              jnp.int32(count))
    expected_logodds, expected_field = np.array(logodds), np.array(field)
    for s, t in zip(source[:count], target[:count]):
        expected_logodds[t] = 0.0 if s < 0 else np.asarray(logodds)[s]
        expected_field[t] = FAR if s < 0 else np.asarray(field)[s]
    np.testing.assert_array_equal(np.asarray(new_logodds), expected_logodds)
    np.testing.assert_array_equal(np.asarray(new_field), expected_field)


def test_even_block_size_cuts_into_as_few_and_as_even_blocks_as_possible():
    from jaxslam.particle_filter import even_block_size

    assert [even_block_size(n, 128) for n in (30, 128, 129, 300, 1000, 1001)] == [30, 128, 65, 100, 125, 126]
    with pytest.raises(ValueError, match="positive count and block size"):
        even_block_size(10, 0)


def test_a_sample_chunk_is_the_cleared_samples_in_beam_order_with_the_one_before():
    """Against a NumPy enumeration of (beam, sample) with sample < cleared[beam]: beams that
    clear nothing, a chunk that starts mid-beam, one that runs past the last sample."""
    cleared = np.array([3, 0, 5, 1, 0, 4], np.int32)
    pairs = [(b, s) for b in range(len(cleared)) for s in range(cleared[b])]
    total = len(pairs)
    for first, size in [(0, 4), (2, 5), (9, 6), (total - 1, 3)]:
        chunk = paged.writes._sample_chunk(jnp.asarray(cleared), jnp.int32(first), size)
        assert chunk.beam.shape == (size + 1,)
        for k, flat in enumerate(range(first - 1, first + size)):
            live = bool(chunk.live[k])
            assert live == (flat < total), (first, flat)
            if 0 <= flat < total:
                assert (int(chunk.beam[k]), int(chunk.sample[k])) == pairs[flat], (first, flat)


@pytest.mark.parametrize("chunk", [5, 64])
def test_the_chunk_size_changes_no_bit(monkeypatch, chunk):
    """The cleared cells written a few samples at a time (chunks that split beams, many rounds)
    give the dense maps' cells bit for bit; so do scans that clear nothing (every beam below
    range_min: no round) and scans of "no return" beams only."""
    monkeypatch.setattr(paged.writes, "SAMPLES_PER_CHUNK", chunk)
    insert = jax.jit(paged.insert_scans, static_argnums=(0, 6, 7))  # traced anew: the chunk size is read when traced
    rng = np.random.default_rng(5)
    maps = paged.empty(SPEC, N, capacity=600, block_capacity=60)
    dense = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,) + a.shape), empty_map(SPEC.grid))
    for step in range(4):
        poses, ranges = random_scan(rng, N)
        if step == 1:
            ranges = jnp.full_like(ranges, 0.5 * SENSOR.range_min)
        if step == 2:
            ranges = jnp.full_like(ranges, SENSOR.range_max)
        maps, outside = insert(SPEC, maps, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
        dense, dense_outside = insert_dense(SPEC.grid, dense, poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
        np.testing.assert_array_equal(np.asarray(outside), np.asarray(dense_outside))
        assert_same(maps, dense)


def test_a_batch_of_runs_inserts_as_each_run_alone(monkeypatch):
    """Under ``vmap`` over runs whose scans clear different numbers of samples (and request
    different numbers of tiles), the loops take the batch's most rounds (``loop_bound``, one
    number: no select of the pools at every round) and each run's maps are its own insertion's,
    bit for bit. Small rounds, so that the runs need different numbers of them."""
    from jaxslam.computed_once import loop_bound

    monkeypatch.setattr(paged.writes, "SAMPLES_PER_CHUNK", 64)
    monkeypatch.setattr(paged.copy_on_write, "TILES_PER_COPY_ROUND", 4)
    insert_alone = jax.jit(paged.insert_scans, static_argnums=(0, 6, 7))  # traced anew with the small rounds

    assert int(jax.vmap(loop_bound, out_axes=None)(jnp.asarray([3, 7, 5]))) == 7
    rng = np.random.default_rng(8)
    runs = 3
    alone = [paged.empty(SPEC, N, capacity=600, block_capacity=60) for _ in range(runs)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *alone)
    insert_batch = jax.jit(jax.vmap(paged.insert_scans, in_axes=(None, 0, 0, 0, None, None, None, None)),
                           static_argnums=(0, 6, 7))
    for step in range(3):
        scans = [random_scan(rng, N) for _ in range(runs)]
        scans[step % runs] = (scans[step % runs][0], jnp.full_like(scans[0][1], 0.2))  # one short scan
        batch, batch_outside = insert_batch(SPEC, batch, jnp.stack([p for p, _ in scans]),
                                            jnp.stack([r for _, r in scans]), SENSOR, INSERTION, MAX_RANGE, RADIUS)
        for run, (poses, ranges) in enumerate(scans):
            alone[run], outside = insert_alone(SPEC, alone[run], poses, ranges, SENSOR, INSERTION, MAX_RANGE, RADIUS)
            np.testing.assert_array_equal(np.asarray(outside), np.asarray(batch_outside[run]))
            for a, b, name in zip(alone[run], jax.tree.map(lambda x: x[run], batch), paged.PagedMaps._fields):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f"{name}, run {run}, step {step}")
