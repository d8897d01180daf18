"""Copy on write, the insertion's middle stages (:mod:`jaxslam.maps.insertion` lists them in
order): the tiles and blocks each particle writes but does not own get new slots
(:func:`_requests`, :func:`_grant_slots`: a prefix sum over all particles' requests, all or
nothing), which become copies of those they replace, or fresh ones (:func:`_copy_blocks`,
:func:`_copy_tiles`, :func:`_copy_tile_rounds`).

Copy on write, worked through. Particles 0, 1 and 2 come out of a resampling with the same
map: each directory's entry (0, 0) is block slot 5, so ``block_refcount[5] = 3``; block 5's
entry (1, 2) is tile slot 9, and ``refcount[9] = 1``: one *block* points at tile 9, however
many particles read it through that block. Now particle 2 alone inserts a scan that changes
cells of that tile (particles 0 and 1 write nothing under block 5 this time). Block 5 is shared
(refcount 3, not 1), so neither it nor tile 9 is particle 2's own: it requests one block and one
tile, and the prefix sum hands it the first free slots, say block 7 and tile 12.

* Block first: block 7 becomes a copy of block 5, so every tile block 5 points at gains a
  reference (``refcount[9]`` becomes 2); particle 2's directory entry (0, 0) becomes 7,
  ``block_refcount[5]`` drops to 2 and ``block_refcount[7]`` is 1.
* Then the tile: tile 12 becomes a copy of tile 9 (log-odds and field), block 7's entry (1, 2)
  becomes 12, ``refcount[9]`` is back to 1 (block 5 only) and ``refcount[12]`` is 1.
* Then the scan's cells are written into tile 12. Particles 0 and 1 still read tile 9 through
  block 5, unchanged. Had the tile been unwritten (-1 in block 5), tile 12 would have started
  unknown (log-odds 0, field ``FAR``) instead of as a copy.

The next time particle 2 writes that tile (no resampling having copied particle 2 meanwhile),
block 7 and tile 12 each have refcount 1: they are its own and are written in place, with no
copy. If a resampling then keeps only particle 2's descendants, block 5 loses its last
references and is free, and each tile it pointed at loses one reference: tile 9 drops to 0 and
is free; the tiles block 7 shares with it drop back to 1. (``tests/test_paged_map.py`` replays
this example on real scans.)
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.computed_once import loop_bound
from jaxslam.maps.lookup import _tile_values
from jaxslam.maps.pool import UNWRITTEN, PagedGridSpec, PagedMaps
from jaxslam.maps.window import _WindowLayout, _WindowPages
from jaxslam.occupancy import FAR


class _Requests(NamedTuple):
    """The new slots each particle needs before it writes (a copy of a shared one, or a fresh one)."""

    tiles: Bool[Array, "N KK"]
    """Window tiles it writes but does not own."""
    blocks: Bool[Array, "N KBB"]
    """Window blocks it does not own that hold such a tile (a new tile needs an owned block to point at it)."""


def _requests(touched: Bool[Array, "N KK"], active: Bool[Array, "N"], layout: _WindowLayout,
              pages: _WindowPages) -> _Requests:
    """The tiles and blocks each active particle writes but does not own: each needs a new slot."""
    tiles = touched & active[:, None] & ~pages.tile_owned
    num_blocks = pages.block_owned.shape[1]
    blocks = jnp.any(tiles[:, :, None] & (layout.tile_block[:, :, None] == jnp.arange(num_blocks)), axis=1)
    return _Requests(tiles, blocks & ~pages.block_owned)


class _PoolGrant(NamedTuple):
    """One pool's answer to all particles' requests."""

    count: Int[Array, ""]
    """The requests, all particles together."""
    fits: Bool[Array, ""]
    """They fit: at most the pool's per-insertion limit, and that many slots are free."""
    slots: Int[Array, "R"]
    """The j-th request's slot (the j-th free slot), for every request position in particle order."""


def _prefix_grant(wanted: Bool[Array, "..."], free: Int[Array, "M"], size: int) -> _PoolGrant:
    """The j-th request (in particle order) gets ``free[j]``: a prefix sum, no loop over particles.
    ``free`` holds the first free slots, padded with ``size`` (the pool's slot count)."""
    limit = free.shape[0]
    wanted = wanted.reshape(-1)
    count = jnp.sum(wanted).astype(jnp.int32)
    fits = ((count <= limit) & (free[jnp.clip(count - 1, 0, limit - 1)] < size)) | (count == 0)
    return _PoolGrant(count, fits, free[jnp.clip(jnp.cumsum(wanted) - 1, 0, limit - 1)])


class _Grants(NamedTuple):
    """The new slots the insertion hands out: all requests, or none (flat over N x window)."""

    fits: Bool[Array, ""]
    """Every tile and block request fits; else nothing is granted or written (``overflow``)."""
    tile_count: Int[Array, ""]
    """Tile requests, all particles together (granted or not)."""
    block_count: Int[Array, ""]
    """Block requests, likewise."""
    tiles: Bool[Array, "N*KK"]
    """Window tiles that get a new slot."""
    blocks: Bool[Array, "N*KBB"]
    """Window blocks that get a new slot."""
    tile_slots: Int[Array, "N*KK"]
    """The new tile slot of each, C (no slot: dropped) elsewhere."""
    block_slots: Int[Array, "N*KBB"]
    """The new block slot of each, B (no slot: dropped) elsewhere."""


def _grant_slots(maps: PagedMaps, requests: _Requests) -> _Grants:
    """Free slots for all particles' requests, all or nothing: an insertion that needs more new
    tiles or blocks than it may take or than are free grants nothing (and writes nothing)."""
    capacity, _, block_capacity, _ = maps.pool_size
    tiles = _prefix_grant(requests.tiles, maps.free_slots, capacity)
    blocks = _prefix_grant(requests.blocks, maps.free_blocks, block_capacity)
    fits = tiles.fits & blocks.fits
    granted_tiles, granted_blocks = requests.tiles.reshape(-1) & fits, requests.blocks.reshape(-1) & fits
    return _Grants(fits, tiles.count, blocks.count, granted_tiles, granted_blocks,
                   jnp.where(granted_tiles, tiles.slots, capacity),
                   jnp.where(granted_blocks, blocks.slots, block_capacity))


class _BlockCopies(NamedTuple):
    """The maps after the granted blocks are made (before any tile is)."""

    directory: Int[Array, "N DY DX"]
    """Directories pointing at the new blocks."""
    entries: Int[Array, "B S*S"]
    """The block pool (flat entries), with the new blocks."""
    block_refcount: Int[Array, "B"]
    """Block references after the directories moved to the new blocks."""
    refcount: Int[Array, "C"]
    """Tile references after the copies (one more each) and the freed blocks (one less each)."""
    window_blocks: Int[Array, "N KBB"]
    """Each particle's block slot of each window block, new or not."""


def _copy_blocks(spec: PagedGridSpec, maps: PagedMaps, layout: _WindowLayout, pages: _WindowPages,
                 grants: _Grants) -> _BlockCopies:
    """Each granted block slot becomes a copy of the block it replaces (or a fresh, unwritten
    one) and the writer's directory points at it. A copy points at the same tiles, so each gains
    a reference; a shared block every holder of which made its own copy is free now, and its
    tiles lose its reference."""
    n, num_window_blocks = pages.block_slots.shape
    capacity, _, block_capacity, max_new_blocks = maps.pool_size
    dy, _ = spec.num_blocks
    entries = maps.blocks.reshape(block_capacity, -1)
    old_blocks = pages.block_slots.reshape(-1)
    # The j-th granted block's request position, and its source: the block it replaces.
    requests = jnp.nonzero(grants.blocks, size=max_new_blocks, fill_value=n * num_window_blocks)[0]
    source = jnp.concatenate([old_blocks, jnp.full((1,), UNWRITTEN, old_blocks.dtype)])[requests]
    target = jnp.where(requests < n * num_window_blocks, maps.free_blocks, block_capacity)
    copied = jnp.where((source >= 0)[:, None], entries[jnp.maximum(source, 0)], UNWRITTEN)
    new_entries = entries.at[target].set(copied, mode="drop")
    refcount = maps.refcount.at[jnp.where((target < block_capacity)[:, None] & (copied >= 0), copied,
                                          capacity)].add(1, mode="drop")
    block_refcount = (maps.block_refcount.at[jnp.where(grants.blocks & (old_blocks >= 0), old_blocks, block_capacity)]
                      .add(-1, mode="drop").at[grants.block_slots].add(1, mode="drop"))
    freed = (maps.block_refcount > 0) & (block_refcount == 0)
    refcount = refcount.at[jnp.where(freed[:, None] & (entries >= 0), entries, capacity)].add(-1, mode="drop")
    window_blocks = jnp.where(grants.blocks, grants.block_slots, old_blocks).reshape(n, num_window_blocks)
    particle = jnp.arange(n)[:, None, None]
    side = layout.block_rows.shape[1]
    directory = maps.directory.at[particle, jnp.where(layout.block_rows < dy, layout.block_rows, dy)[:, :, None],
                                  layout.block_cols[:, None, :]].set(window_blocks.reshape(n, side, side),
                                                                     mode="drop")
    return _BlockCopies(directory, new_entries, block_refcount, refcount, window_blocks)


class _TileCopies(NamedTuple):
    """The maps' tiles after the granted tiles are made (before the scans are written)."""

    logodds: Float[Array, "C T T"]
    """The log-odds pool with the new tiles."""
    hit_dist2: UInt8[Array, "C T T"]
    """The field pool with the new tiles."""
    refcount: Int[Array, "C"]
    """Tile references after the writers' blocks moved to the new tiles."""
    entries: Int[Array, "B S*S"]
    """The block pool (flat entries), the writers' blocks pointing at their new tiles."""


def _copy_tiles(maps: PagedMaps, layout: _WindowLayout, pages: _WindowPages, grants: _Grants,
                blocks: _BlockCopies) -> _TileCopies:
    """Each granted tile slot becomes a copy of the tile it replaces (or a fresh one: unknown
    log-odds, ``FAR`` field), and the writer's block, its own now, points at it instead."""
    capacity, max_new_tiles, block_capacity, _ = maps.pool_size
    old_slots = pages.tile_slots.reshape(-1)
    num_window_tiles = old_slots.shape[0]
    # The j-th granted tile's request position, and its source: the tile it replaces.
    requests = jnp.nonzero(grants.tiles, size=max_new_tiles, fill_value=num_window_tiles)[0]
    source = jnp.concatenate([old_slots, jnp.full((1,), UNWRITTEN, old_slots.dtype)])[requests]
    target = jnp.where(requests < num_window_tiles, maps.free_slots, capacity)
    logodds, hit_dist2 = _copy_tile_rounds(maps.logodds, maps.hit_dist2, source, target,
                                           jnp.sum(grants.tiles).astype(jnp.int32))
    refcount = (blocks.refcount.at[jnp.where(grants.tiles & (old_slots >= 0), old_slots, capacity)]
                .add(-1, mode="drop").at[grants.tile_slots].add(1, mode="drop"))
    writer_block = jnp.take_along_axis(blocks.window_blocks, layout.tile_block, axis=1).reshape(-1)
    entries = blocks.entries.at[jnp.where(grants.tiles, writer_block, block_capacity),
                                layout.tile_in_block.reshape(-1)].set(grants.tile_slots, mode="drop")
    return _TileCopies(logodds, hit_dist2, refcount, entries)


TILES_PER_COPY_ROUND = 256
"""Tiles :func:`_copy_tile_rounds` copies per round (3 MB at 64-cell tiles)."""


def _copy_tile_rounds(logodds: Float[Array, "C T T"], hit_dist2: UInt8[Array, "C T T"], source: Int[Array, "M"],
                      target: Int[Array, "M"], count: Int[Array, ""]) -> tuple[Array, Array]:
    """Tile ``target[j]`` of both pools becomes a copy of tile ``source[j]`` (a fresh tile where
    the source is :data:`UNWRITTEN`) for the first ``count`` j, :data:`TILES_PER_COPY_ROUND` at a
    time in a ``while_loop`` of ``ceil(count / TILES_PER_COPY_ROUND)`` rounds: the gathered
    copies cost one round's memory, not the M tiles one insertion may request, and only the
    requested tiles are read. Targets are free slots and sources tiles in use, so no round reads
    what an earlier one wrote. Rounds past ``count`` (a batch of runs under ``vmap`` takes the
    most any run needs: :func:`~jaxslam.computed_once.loop_bound`) copy nothing: their targets
    are past the pool."""
    size = TILES_PER_COPY_ROUND
    padded = -(-source.shape[0] // size) * size
    capacity = logodds.shape[0]
    source = jnp.concatenate([source, jnp.full((padded - source.shape[0],), UNWRITTEN, source.dtype)])
    target = jnp.concatenate([target, jnp.full((padded - target.shape[0],), capacity, target.dtype)])

    def copy_round(carry):
        done, logodds, hit_dist2 = carry
        sources = jax.lax.dynamic_slice_in_dim(source, done, size)
        targets = jax.lax.dynamic_slice_in_dim(target, done, size)
        logodds = logodds.at[targets].set(_tile_values(logodds, sources, 0.0), mode="drop")
        hit_dist2 = hit_dist2.at[targets].set(_tile_values(hit_dist2, sources, FAR), mode="drop")
        return done + size, logodds, hit_dist2

    _, logodds, hit_dist2 = jax.lax.while_loop(lambda carry: carry[0] < loop_bound(count), copy_round,
                                               (jnp.int32(0), logodds, hit_dist2))
    return logodds, hit_dist2
