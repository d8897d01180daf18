"""Inserting scans into paged maps: :func:`insert_scans`, which runs the stages listed below in
order, one concern per module (:mod:`jaxslam.maps.window`, :mod:`jaxslam.maps.copy_on_write`,
:mod:`jaxslam.maps.writes`)."""

# Inserting scans. insert_scans runs the stages below in this order, each a function of the
# previous stages' NamedTuples. In jaxslam/maps/window.py:
#   _window_shape     the static size of the window of tiles (and of blocks) one scan can change
#   _scan_summaries   the window and the tiles each particle's scan touches, a block of particles at a time
#   _window_layout    where each window tile lies: a block of the window of blocks, an entry in it
#   _window_pages     the slots each particle's directory and blocks give its window now
# In jaxslam/maps/copy_on_write.py:
#   _requests         the tiles and blocks a particle writes but does not own
#   _grant_slots      free slots for all particles' requests, by prefix sums; all or nothing
#   _copy_blocks      granted blocks become copies (or fresh); directories and references follow
#   _copy_tiles       granted tiles become copies (or fresh); the writers' blocks point at them
# In jaxslam/maps/writes.py:
#   _write_cells      the scans' updates, scattered into tiles each writer now owns, a block of
#                     particles at a time, the cleared cells a chunk of samples at a time

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxslam.laser import SensorSpec
from jaxslam.maps.copy_on_write import _copy_blocks, _copy_tiles, _grant_slots, _requests
from jaxslam.maps.pool import PagedGridSpec, PagedMaps, first_free
from jaxslam.maps.window import _scan_summaries, _window_layout, _window_pages, _window_shape
from jaxslam.maps.writes import _write_cells
from jaxslam.occupancy import InsertionParams


def insert_scans(
    spec: PagedGridSpec,
    maps: PagedMaps,
    poses: Float[Array, "N 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: InsertionParams,
    max_insert_range: float,
    field_radius: int,
    active: Bool[Array, "N"] | None = None,
    particle_block: int | None = None,
) -> tuple[PagedMaps, Int[Array, "N"]]:
    """Insert one scan into every ``active`` particle's map (default all), particle n's taken at
    ``poses[n]``; an inactive particle's map is left as it was.

    The same cells get the same updates as in a dense grid (:func:`jaxslam.occupancy.scan_cells`,
    :func:`jaxslam.occupancy.update_cells`). First every block and tile a particle's scan touches
    is made its own: one it alone uses is written in place; a shared or unwritten one gets a free
    slot (a copy of the shared one, or a fresh one), handed out by a prefix sum over all
    particles' requests, at most ``max_new_tiles`` tiles and ``max_new_blocks`` blocks in all.
    Then all particles' cells are scattered into the pool (no two particles write the same slot),
    the cleared cells a chunk of samples at a time (:func:`~jaxslam.maps.writes._write_cells`).
    All or nothing: an insertion whose requests do not fit writes nothing and sets ``overflow``;
    the maps are unchanged, so the caller can grow the pools (:func:`~jaxslam.maps.pool.grow`)
    and insert again.

    ``active`` (e.g. the particles a resampling keeps) saves the tiles of maps about to be
    dropped, and orders the insertion after whatever computed it: XLA then updates the pools in
    place instead of copying them (a read of a pool that no data dependence places before its
    in-place update forces a copy of the whole pool).

    ``particle_block`` (static; None: all at once) particles are handled at a time, in two
    passes (the tiles each touches, from a few points per beam; then, once the slots are
    granted, the writes); the result is the same bit for bit.

    Returns the new maps and, per particle, the beam samples that fell outside the virtual grid.
    """
    window = _window_shape(spec, max_insert_range, field_radius)
    active = jnp.ones((poses.shape[0],), bool) if active is None else jnp.asarray(active, bool)
    summary = _scan_summaries(spec, window, poses, ranges, sensor, params, max_insert_range, field_radius,
                              particle_block)
    layout = _window_layout(spec, window, summary.window_start)
    pages = _window_pages(spec, maps, layout)
    grants = _grant_slots(maps, _requests(summary.touched, active, layout, pages))
    blocks = _copy_blocks(spec, maps, layout, pages, grants)
    tiles = _copy_tiles(maps, layout, pages, grants, blocks)
    logodds, hit_dist2, outside = _write_cells(spec, window, tiles, poses, summary.window_start, ranges, sensor,
                                               pages, grants, active, params, max_insert_range, field_radius,
                                               particle_block)
    new_maps = PagedMaps(
        directory=blocks.directory,
        blocks=tiles.entries.reshape(maps.blocks.shape),
        block_refcount=blocks.block_refcount,
        logodds=logodds,
        hit_dist2=hit_dist2,
        refcount=tiles.refcount,
        free_slots=first_free(tiles.refcount, maps.max_new_tiles),
        free_blocks=first_free(blocks.block_refcount, maps.pool_size.max_new_blocks),
        overflow=~grants.fits,
        peak_request=jnp.maximum(maps.peak_request, grants.tile_count),
        peak_block_request=jnp.maximum(maps.peak_block_request, grants.block_count),
    )
    return new_maps, outside
