"""Paged occupancy maps: the particles' maps as fixed-size tiles in one pool shared by all
particles, copy on write.

A dense map per particle costs the grid's bounding box times the particle count, and every
resampling copies whole maps. Here the grid is a large *virtual* grid cut into square tiles
of ``tile_size`` cells, grouped into square blocks of ``block_size`` tiles
(:class:`PagedGridSpec`), and the particles' maps are (:class:`PagedMaps`):

* one **tile pool**, ``(C, T, T)`` log-odds (float16) and likelihood field (uint8), with a
  reference count per tile slot: how many blocks (in use) point at it;
* one **block pool**, ``(B, S, S)`` int32: a block is a piece of page table, the tile-pool slot
  of each of its S x S tiles (:data:`UNWRITTEN`, -1: a tile never written), with a reference
  count per block slot: how many particles' directories point at it;
* one **directory** per particle, ``(DY, DX)`` int32: the block-pool slot of each of its blocks
  (:data:`UNWRITTEN`: a block it never wrote).

Two levels, so that what a particle owns alone is small: a page table over the whole grid per
particle would cost the grid's extent times the particles again, copied at every resampling
(the memory figures are in ``docs/design.md``, "Maps are paged"). Resampling
copies directories only (:func:`resample`): particles share the blocks and tiles of their
common past, as GMapping's reference-counted patches do. Inserting a scan (:func:`insert_scans`)
first makes every block and tile it writes the writer's own (one only it uses is written in
place; a shared one is copied into a free slot; an unwritten one gets a fresh slot), then
scatters the scan's updates into the tile pool: the same cells get the same updates as in a
dense grid (:func:`jaxslam.occupancy.update_cells`). A slot nothing references any more is free
again at once. :func:`check_invariants` states what holds between any two operations; a worked
example of copy on write opens :mod:`jaxslam.maps.copy_on_write`.

Everything has a static shape and no sequential loop over particles: free slots are handed
out by a prefix sum over the particles' requests. The pools' capacities and the most tiles and
blocks one insertion may create or copy are static (:class:`PoolSize`); an insertion that needs
more writes nothing (all or nothing) and sets ``overflow``, and the host grows the pools
(:func:`grow`) and repeats it: never a silent overwrite.

The modules, one concern each (this package re-exports their public names):

* :mod:`~jaxslam.maps.pool`: the virtual grid (:class:`PagedGridSpec`), the pools' sizes
  (:class:`PoolSize`) and the maps (:class:`PagedMaps`); what changes the pools whole:
  :func:`empty`, :func:`resample`, :func:`grow`, and the slots in use.
* :mod:`~jaxslam.maps.lookup`: one particle's map as a model reads it (:class:`PagedField`,
  :func:`fields`, :func:`cell_values`): gathers through directory, block and tile.
* :mod:`~jaxslam.maps.insertion`: :func:`insert_scans` and the order of its stages, which live in
  :mod:`~jaxslam.maps.window` (the window of tiles one scan can change, and the slots it reads
  now), :mod:`~jaxslam.maps.copy_on_write` (new slots for what a particle writes but does not own,
  and their copies) and :mod:`~jaxslam.maps.writes` (the scans' updates scattered into the pools).
* :mod:`~jaxslam.maps.dense`: host-side dense views of one particle's map (:func:`page_table`,
  :func:`to_dense`).
* :mod:`~jaxslam.maps.invariants`: :func:`check_invariants`, what holds between any two operations.

Constants a test or benchmark patches (``FLAT_INDEX_CELLS``, ``TILES_PER_COPY_ROUND``,
``SAMPLES_PER_CHUNK``, ``tile_slots``) must be patched in the module that defines and reads them
(:mod:`~jaxslam.maps.pool`, :mod:`~jaxslam.maps.copy_on_write`, :mod:`~jaxslam.maps.writes`,
:mod:`~jaxslam.maps.lookup`), not here.
"""

from __future__ import annotations

from jaxslam.maps.copy_on_write import TILES_PER_COPY_ROUND
from jaxslam.maps.dense import page_table, to_dense
from jaxslam.maps.insertion import insert_scans
from jaxslam.maps.invariants import check_invariants
from jaxslam.maps.lookup import FIELD_AXES, PagedField, cell_values, fields, particle_field, tile_slots
from jaxslam.maps.pool import (FLAT_INDEX_CELLS, UNWRITTEN, PagedGridSpec, PagedMaps, PoolSize, blocks_in_use, empty,
                               first_free, flat_pool, grow, max_pool_tiles, resample, tiles_in_use)
from jaxslam.maps.writes import SAMPLES_PER_CHUNK

__all__ = [
    "FIELD_AXES", "FLAT_INDEX_CELLS", "SAMPLES_PER_CHUNK", "TILES_PER_COPY_ROUND", "UNWRITTEN", "PagedField",
    "PagedGridSpec", "PagedMaps", "PoolSize", "blocks_in_use", "cell_values", "check_invariants", "empty", "fields",
    "first_free", "flat_pool", "grow", "insert_scans", "max_pool_tiles", "page_table", "particle_field", "resample",
    "tile_slots", "tiles_in_use", "to_dense",
]
