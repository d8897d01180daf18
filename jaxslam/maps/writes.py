"""The insertion's last stage (:mod:`jaxslam.maps.insertion` lists them in order): the scans'
updates scattered into the tiles each writer now owns (:func:`_write_cells`), a block of
particles at a time, the cleared cells :data:`SAMPLES_PER_CHUNK` samples at a time."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.computed_once import computed_once, loop_bound
from jaxslam.laser import SensorSpec
from jaxslam.maps.copy_on_write import _Grants, _TileCopies
from jaxslam.maps.pool import PagedGridSpec, flat_pool
from jaxslam.maps.window import _CellTargets, _place_in_tile, _Window, _window_tile, _WindowPages
from jaxslam.occupancy import (InsertionParams, ScanRays, clear_cells, cleared_samples, clears_cell, field_kernel,
                               floored_to_cells, free_lengths, mark_cells, sample_floors, samples_per_beam, scan_rays,
                               splat_field)
from jaxslam.particle_filter import even_block_size


SAMPLES_PER_CHUNK = 2048
"""Beam samples per particle that :func:`_write_cells` computes and scatters per round."""


class _SampleChunk(NamedTuple):
    """A run of a scan's cleared samples (beam b's first ``cleared[b]`` samples, beam after
    beam), the same for every particle: which samples clear depends on the ranges alone."""

    beam: Int[Array, "C"]
    """Each sample's beam."""
    sample: Int[Array, "C"]
    """Each sample's place along its beam (one per cell length)."""
    live: Bool[Array, "C"]
    """Samples within the scan's cleared samples (the last chunk runs past them)."""


def _sample_chunk(cleared: Int[Array, "B"], first: Int[Array, ""], size: int) -> _SampleChunk:
    """Cleared samples ``first - 1`` .. ``first + size - 1`` (``size + 1``: the one before the
    chunk too) of a scan that clears ``cleared[b]`` samples of beam b, in the order of a (beam,
    sample) array with the samples past each beam's free length left out."""
    ends = jnp.cumsum(cleared)
    flat = first + jnp.arange(-1, size, dtype=jnp.int32)
    beam = jnp.minimum(jnp.searchsorted(ends, flat, side="right"), cleared.shape[0] - 1).astype(jnp.int32)
    return _SampleChunk(beam, flat - (ends[beam] - cleared[beam]), flat < ends[-1])


def _cleared_targets(spec: PagedGridSpec, window: _Window, start: Int[Array, "2"], rays: ScanRays,
                     first_tile: Int[Array, ""], chunk: _SampleChunk) -> tuple[_CellTargets, Int[Array, ""]]:
    """One particle's cells a chunk of samples clears, as (window tile, place) offset by
    ``first_tile`` (the particle's first tile in the flat index over the block's windows), and
    how many of them fall outside the virtual grid (the window holds every cell of the grid the
    scan can reach, so a cell off the window is off the grid)."""
    # The chunk starts one sample early: each sample's predecessor along its beam is the one
    # before it in the chunk (where the sample is not its beam's first).
    with_previous = sample_floors(spec.grid, rays, chunk.beam, chunk.sample)
    floors, previous = with_previous[1:], with_previous[:-1]
    chunk = jax.tree.map(lambda x: x[1:], chunk)
    free = chunk.live & clears_cell(rays, chunk.beam, floors, previous, chunk.sample == 0)
    cells = floored_to_cells(spec.grid, floors)
    tile = _window_tile(spec, window, start, cells, free)
    return _CellTargets(tile + first_tile, _place_in_tile(spec, cells)), jnp.sum(free & (tile == window.tiles))


def _marked_targets(spec: PagedGridSpec, window: _Window, start: Int[Array, "2"], rays: ScanRays,
                    first_tile: Int[Array, ""], field_radius: int
                    ) -> tuple[_CellTargets, _CellTargets, Int[Array, ""]]:
    """One particle's endpoint cells (B) and their field splats (B, kernel) as (window tile,
    place) offset by ``first_tile``, and its endpoints outside the virtual grid."""
    offsets, _ = field_kernel(field_radius)
    end_cells = floored_to_cells(spec.grid, rays.end_floor)
    splat_cells = end_cells[:, None, :] + jnp.asarray(offsets)  # (B, kernel, 2)
    end_tile = _window_tile(spec, window, start, end_cells, rays.returned)
    splat_tile = _window_tile(spec, window, start, splat_cells, rays.returned[:, None])
    return (_CellTargets(end_tile + first_tile, _place_in_tile(spec, end_cells)),
            _CellTargets(splat_tile + first_tile, _place_in_tile(spec, splat_cells)),
            jnp.sum(rays.returned & (end_tile == window.tiles)))


def _pool_index(spec: PagedGridSpec, writable_slot: Int[Array, "N*(KK+1)"], cells: _CellTargets,
                capacity: int):
    """Each cell's index in the tile pool, one past its end (dropped) where its tile has no
    writable slot: a flat index into the flattened pool, or, for a pool beyond
    :data:`~jaxslam.maps.pool.FLAT_INDEX_CELLS`, a (slot, cell in the tile) pair of arrays into
    its (C, T * T) view."""
    t = spec.tile_size
    slot = writable_slot[cells.window_tile]
    if not flat_pool(spec, capacity):
        return jnp.minimum(slot, capacity), cells.place
    return jnp.where(slot < capacity, slot * (t * t) + cells.place, capacity * t * t)


def _write_cells(spec: PagedGridSpec, window: _Window, tiles: _TileCopies, poses: Float[Array, "N 3"],
                 window_start: Int[Array, "N 2"], ranges: Float[Array, "B"], sensor: SensorSpec,
                 pages: _WindowPages, grants: _Grants, active: Bool[Array, "N"], params: InsertionParams,
                 max_insert_range: float, field_radius: int, particle_block: int | None
                 ) -> tuple[Float[Array, "C T T"], UInt8[Array, "C T T"], Int[Array, "N"]]:
    """All particles' updates scattered into the pools, each into tiles its writer owns (no two
    particles write one slot): the same updates as a dense grid's, in the same order
    (:func:`jaxslam.occupancy.update_cells`). Cells of inactive particles, and all cells when
    the grants did not fit, are dropped.

    ``particle_block`` particles at a time (a ``lax.scan`` over blocks, the pools its carry;
    particles write disjoint cells, so the blocks' order changes no bit), and within a block the
    cleared cells :data:`SAMPLES_PER_CHUNK` samples at a time, in a ``while_loop`` over the
    scan's cleared samples only: a sample past its beam's free length clears nothing, and
    those are most of a beam traced to ``max_insert_range`` (about 70 % on Intel). The work then
    follows the scan's free space, and the memory is a chunk's, not N x beams x
    ``max_insert_range`` samples'. (Under
    ``vmap`` a batch of runs takes as many rounds as its longest scan needs,
    :func:`~jaxslam.computed_once.loop_bound`; a run's extra chunks hold no live sample.) Returns
    the log-odds and field pools and, per particle, its samples that fell outside the virtual
    grid."""
    capacity = tiles.refcount.shape[0]
    n, num_window_tiles = pages.tile_slots.shape
    slots = jnp.where(grants.tiles, grants.tile_slots, pages.tile_slots.reshape(-1))
    writable = (pages.tile_owned.reshape(-1) & grants.fits) | grants.tiles
    writable_slot = jnp.where(writable & jnp.repeat(active, num_window_tiles), slots, capacity)
    # One more per particle: its "no tile" index (K K), never writable.
    writable_slot = jnp.concatenate([writable_slot.reshape(n, num_window_tiles),
                                     jnp.full((n, 1), capacity, jnp.int32)], axis=1)
    _, d2 = field_kernel(field_radius)
    num_samples = samples_per_beam(spec.grid, max_insert_range)
    cleared = cleared_samples(spec.grid, free_lengths(ranges, sensor, params, max_insert_range), num_samples)
    total = jnp.sum(cleared)

    def write_block(pools, block):
        block_poses, block_start, block_writable = block
        size = block_poses.shape[0]
        rays = jax.vmap(lambda pose: scan_rays(spec.grid, pose, ranges, sensor, params, max_insert_range))(block_poses)
        first_tile = jnp.arange(size, dtype=jnp.int32) * (window.tiles + 1)
        writable = block_writable.reshape(-1)

        def clear_chunk(carry):
            first, logodds, outside = carry
            chunk = _sample_chunk(cleared, first, SAMPLES_PER_CHUNK)
            targets, chunk_outside = computed_once(
                jax.vmap(lambda start, r, f: _cleared_targets(spec, window, start, r, f, chunk)),
                block_start, rays, first_tile)
            logodds = clear_cells(logodds, _pool_index(spec, writable, targets, capacity), params)
            return first + SAMPLES_PER_CHUNK, logodds, outside + chunk_outside

        logodds, hit_dist2 = pools
        _, logodds, outside = jax.lax.while_loop(lambda carry: carry[0] < loop_bound(total), clear_chunk,
                                                 (jnp.int32(0), logodds, jnp.zeros(size, jnp.int32)))
        ends, splats, end_outside = computed_once(
            jax.vmap(lambda start, r, f: _marked_targets(spec, window, start, r, f, field_radius)),
            block_start, rays, first_tile)
        logodds = mark_cells(logodds, _pool_index(spec, writable, ends, capacity), params)
        hit_dist2 = splat_field(hit_dist2, _pool_index(spec, writable, splats, capacity), d2)
        return (logodds, hit_dist2), outside + end_outside

    view = (-1,) if flat_pool(spec, capacity) else (capacity, spec.tile_size**2)  # as _pool_index indexes
    pools = (tiles.logodds.reshape(view), tiles.hit_dist2.reshape(view))
    size = n if particle_block is None else even_block_size(n, particle_block)
    if size >= n:
        (logodds, hit_dist2), outside = write_block(pools, (poses, window_start, writable_slot))
    else:
        # Padding particles (past N) write nothing: every tile of theirs is unwritable.
        num_blocks = -(-n // size)
        pad = num_blocks * size - n

        def padded(x, fill):
            return jnp.concatenate([x, jnp.broadcast_to(fill, (pad,) + x.shape[1:]).astype(x.dtype)])

        xs = (padded(poses, poses[0]), padded(window_start, window_start[0]), padded(writable_slot, capacity))
        (logodds, hit_dist2), outside = jax.lax.scan(
            write_block, pools, jax.tree.map(lambda x: x.reshape((num_blocks, size) + x.shape[1:]), xs))
        outside = outside.reshape(-1)[:n]
    return logodds.reshape(tiles.logodds.shape), hit_dist2.reshape(tiles.hit_dist2.shape), outside
