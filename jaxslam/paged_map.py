"""Paged occupancy maps: fixed-size tiles in one pool shared by all particles, copy on write.

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
(the memory figures are in ``docs/notes/2026-11-23-two-level-page-tables.md``). Resampling
copies directories only (:func:`resample`): particles share the blocks and tiles of their
common past, as GMapping's reference-counted patches do. Inserting a scan (:func:`insert_scans`)
first makes every block and tile it writes the writer's own (one only it uses is written in
place; a shared one is copied into a free slot; an unwritten one gets a fresh slot), then
scatters the scan's updates into the tile pool: the same cells get the same updates as in a
dense grid (:func:`jaxslam.occupancy.update_cells`). A slot nothing references any more is free
again at once. :func:`check_invariants` states what holds between any two operations.

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

Everything has a static shape and no sequential loop over particles: free slots are handed
out by a prefix sum over the particles' requests. The pools' capacities and the most tiles and
blocks one insertion may create or copy are static (:class:`PoolSize`); an insertion that needs
more writes nothing (all or nothing) and sets ``overflow``, and the host grows the pools
(:func:`grow`) and repeats it: never a silent overwrite.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.computed_once import computed_once, loop_bound
from jaxslam.grid import GridSpec, world_to_cell
from jaxslam.laser import SensorSpec, laser_rays
from jaxslam.occupancy import (FAR, LOGODDS_DTYPE, InsertionParams, ScanRays, clear_cells, cleared_samples,
                               clears_cell, field_kernel, floored_to_cells, free_lengths, mark_cells, sample_floors,
                               samples_per_beam, scan_rays, splat_field)
from jaxslam.particle_filter import even_block_size, map_in_blocks

UNWRITTEN = -1
"""Directory or block entry of a block or tile the particle never wrote."""


@dataclasses.dataclass(frozen=True)
class PagedGridSpec:
    """The virtual grid of a paged map. Static (hashable): changing it recompiles."""

    resolution: float = 0.05
    """Cell side (m)."""
    tile_size: int = 64
    """T, cells per tile side (a power of two)."""
    num_tiles: tuple[int, int] = (400, 400)
    """(TY, TX): tiles along y (rows) and x (columns); the default covers 1.28 km x 1.28 km at 5 cm."""
    origin: tuple[float, float] = (-640.0, -640.0)
    """World (x, y) in metres of the lower-left corner of the virtual grid."""
    block_size: int = 16
    """S, tiles per block side (a power of two): the unit of page table particles share and copy
    on write."""

    def __post_init__(self):
        ty, tx = self.num_tiles
        if not (self.resolution > 0 and self.tile_size >= 1 and self.block_size >= 1 and ty >= 1 and tx >= 1):
            raise ValueError(f"PagedGridSpec needs a positive resolution, tile size, block size and tile counts, "
                             f"got {self}")
        for name in ("tile_size", "block_size"):
            size = getattr(self, name)
            if size & (size - 1):
                raise ValueError(f"PagedGridSpec: {name} must be a power of two (cells and tiles are split by "
                                 f"shifts and masks), got {size}")
        if ty * self.tile_size * tx * self.tile_size >= 2**31:
            raise ValueError(f"PagedGridSpec: {ty * self.tile_size} x {tx * self.tile_size} cells exceed int32 indexing")
        object.__setattr__(self, "num_tiles", (int(ty), int(tx)))
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))

    @classmethod
    def centred(cls, center_xy, extent: float, resolution: float = 0.05, tile_size: int = 64,
                block_size: int = 16) -> "PagedGridSpec":
        """A square virtual grid of at least ``extent`` metres a side, centred on ``center_xy`` (m)."""
        tiles = int(math.ceil(extent / (tile_size * resolution)))
        half = tiles * tile_size * resolution / 2.0
        return cls(resolution, tile_size, (tiles, tiles), (float(center_xy[0]) - half, float(center_xy[1]) - half),
                   block_size)

    @property
    def tile_shift(self) -> int:
        """log2 of the tile size: a cell's tile is ``cell >> tile_shift``, its place ``cell & (T - 1)``
        (exact floor division for negative cells too, and cheaper than ``//`` and ``%`` on ints)."""
        return self.tile_size.bit_length() - 1

    @property
    def block_shift(self) -> int:
        """log2 of the block size: a tile's block is ``tile >> block_shift``."""
        return self.block_size.bit_length() - 1

    @property
    def num_blocks(self) -> tuple[int, int]:
        """(DY, DX): the directory's shape, blocks along y and x."""
        s = self.block_size
        return (-(-self.num_tiles[0] // s), -(-self.num_tiles[1] // s))

    @property
    def grid(self) -> GridSpec:
        """The virtual grid as a dense :class:`~jaxslam.grid.GridSpec` (for cell coordinates only)."""
        t = self.tile_size
        return GridSpec((self.num_tiles[0] * t, self.num_tiles[1] * t), self.resolution, self.origin)

    def window_tiles(self, max_insert_range: float, field_radius: int) -> int:
        """K: tiles per side of the window that holds everything one scan can change."""
        reach = int(math.ceil(max_insert_range / self.resolution)) + field_radius + 1
        return min(2 * reach // self.tile_size + 2, min(self.num_tiles))

    def window_blocks(self, window_tiles: int) -> int:
        """Blocks per side of the window of blocks that holds a window of ``window_tiles`` tiles."""
        return min((window_tiles + self.block_size - 2) // self.block_size + 1, min(self.num_blocks))


class PoolSize(NamedTuple):
    """The static sizes of the maps' pools (changing one recompiles)."""

    capacity: int
    """C, tile slots."""
    max_new_tiles: int
    """M, the most tiles one insertion may create or copy, all particles together."""
    block_capacity: int
    """B, block slots."""
    max_new_blocks: int
    """The most blocks one insertion may create or copy, all particles together."""


class PagedMaps(NamedTuple):
    """The maps of N particles: directories of shared blocks of page table into one pool of tiles
    (what holds between operations: :func:`check_invariants`)."""

    directory: Int[Array, "N DY DX"]
    """Block-pool slot of each block of each particle's map; :data:`UNWRITTEN` (-1) where none."""
    blocks: Int[Array, "B S S"]
    """Tile-pool slot of each tile of each block; :data:`UNWRITTEN` for a tile never written."""
    block_refcount: Int[Array, "B"]
    """How many directory entries point at each block slot; 0: free."""
    logodds: Float[Array, "C T T"]
    """Occupancy log-odds of every pool tile (float16, 0 = unknown)."""
    hit_dist2: UInt8[Array, "C T T"]
    """Likelihood field of every pool tile (squared cell distance to the nearest endpoint, FAR beyond)."""
    refcount: Int[Array, "C"]
    """How many block entries (of blocks in use) point at each tile slot; 0: free."""
    free_slots: Int[Array, "M"]
    """The first M free tile slots (C where fewer are free), refreshed after every insertion and
    resampling."""
    free_blocks: Int[Array, "MB"]
    """The first MB free block slots (B where fewer are free), refreshed likewise."""
    overflow: Bool[Array, ""]
    """The last insertion wanted more new tiles or blocks than it may take or than were free, and
    wrote nothing. The host grows the pools (:func:`grow`) and repeats it."""
    peak_request: Int[Array, ""]
    """The most new tiles one insertion asked for (to size M)."""
    peak_block_request: Int[Array, ""]
    """The most new blocks one insertion asked for."""

    @property
    def capacity(self) -> int:
        """C, the tile pool's slots."""
        return self.refcount.shape[0]

    @property
    def max_new_tiles(self) -> int:
        """M, the most tiles one insertion may create or copy."""
        return self.free_slots.shape[0]

    @property
    def pool_size(self) -> PoolSize:
        """The pools' static sizes."""
        return PoolSize(self.capacity, self.max_new_tiles, self.block_refcount.shape[0], self.free_blocks.shape[0])


def first_free(refcount: Int[Array, "C"], size: int) -> Int[Array, "M"]:
    """The first ``size`` slots of refcount 0 (the slot count where fewer are free)."""
    return jnp.nonzero(refcount == 0, size=size, fill_value=refcount.shape[0])[0].astype(jnp.int32)


FLAT_INDEX_CELLS = 2**31
"""A pool of fewer cells is read and written through one flat int32 index a cell (slot *
tile_size**2 + cell: XLA's CPU gathers and scatters cost less so); a larger one (524,288 tiles of
64 x 64 cells and more: Intel's pools from about N = 7,300, FR-clinic's from N = 1,000) through
(slot, cell in the tile) pairs, each within int32."""


def flat_pool(spec: PagedGridSpec, capacity: int) -> bool:
    """Whether a pool of ``capacity`` tile slots is indexed by one flat int32 (:data:`FLAT_INDEX_CELLS`)."""
    return capacity * spec.tile_size**2 < FLAT_INDEX_CELLS


def max_pool_tiles(spec: PagedGridSpec) -> int:
    """The most tile slots a pool may have: slots are int32 (the blocks hold them). Beyond
    :data:`FLAT_INDEX_CELLS` cells a pool is indexed by (slot, cell) pairs, so its size is bounded
    by the device's memory (12 KB a 64 x 64 tile) long before this."""
    return 2**31 - 1


def _check_pool(spec: PagedGridSpec, pool: PoolSize) -> None:
    """ValueError unless ``pool`` has positive sizes within their capacities and int32 slots suffice."""
    if min(pool) < 1 or pool.max_new_tiles > pool.capacity or pool.max_new_blocks > pool.block_capacity:
        raise ValueError(f"a paged map's pools need positive sizes and at most their capacity new per insertion, "
                         f"got {pool}")
    if pool.capacity > max_pool_tiles(spec):
        raise ValueError(f"a pool of {pool.capacity} tiles exceeds int32 slot indices; use fewer particles or a "
                         "larger resolution")


def empty(spec: PagedGridSpec, num_particles: int, capacity: int, max_new_tiles: int | None = None,
          block_capacity: int | None = None, max_new_blocks: int | None = None) -> PagedMaps:
    """N empty maps and pools of ``capacity`` free tiles and ``block_capacity`` free blocks; an
    insertion may create or copy at most ``max_new_tiles`` tiles and ``max_new_blocks`` blocks
    (defaults: the capacities; the block capacity's default is the tile capacity's)."""
    block_capacity = capacity if block_capacity is None else int(block_capacity)
    pool = PoolSize(int(capacity), capacity if max_new_tiles is None else min(int(max_new_tiles), capacity),
                    block_capacity,
                    block_capacity if max_new_blocks is None else min(int(max_new_blocks), block_capacity))
    _check_pool(spec, pool)
    t, s = spec.tile_size, spec.block_size
    # Every slot is free, so the free lists are the first slots. Searched for with first_free, the
    # refcounts are constants that XLA may fold at compile time (an H100 log at N = 10,000 showed
    # about 10 s folding an s32[10005, 16] cumulative sum, the block pool's shape; not re-measured).
    return PagedMaps(
        directory=jnp.full((num_particles,) + spec.num_blocks, UNWRITTEN, jnp.int32),
        blocks=jnp.full((pool.block_capacity, s, s), UNWRITTEN, jnp.int32),
        block_refcount=jnp.zeros((pool.block_capacity,), jnp.int32),
        logodds=jnp.zeros((pool.capacity, t, t), LOGODDS_DTYPE),
        hit_dist2=jnp.full((pool.capacity, t, t), FAR, jnp.uint8),
        refcount=jnp.zeros((pool.capacity,), jnp.int32),
        free_slots=jnp.arange(pool.max_new_tiles, dtype=jnp.int32),
        free_blocks=jnp.arange(pool.max_new_blocks, dtype=jnp.int32),
        overflow=jnp.bool_(False),
        peak_request=jnp.int32(0),
        peak_block_request=jnp.int32(0),
    )


class PagedField(NamedTuple):
    """One particle's likelihood field (or log-odds) as the likelihood model reads it: its
    directory, the shared blocks and the shared tile pool (vmap over particles with
    ``in_axes=FIELD_AXES``)."""

    directory: Int[Array, "DY DX"]
    """The particle's directory."""
    blocks: Int[Array, "B S S"]
    """The shared block pool."""
    pool: Array
    """(C, T, T) the tile pool of that quantity."""


FIELD_AXES = PagedField(0, None, None)
"""``in_axes`` of a ``vmap`` over the particles of :func:`fields`."""


def fields(maps: PagedMaps) -> PagedField:
    """Every particle's likelihood field (directories (N, DY, DX), the shared pools): vmap over it
    with ``in_axes=FIELD_AXES``."""
    return PagedField(maps.directory, maps.blocks, maps.hit_dist2)


def particle_field(maps: PagedMaps, particle, quantity: str = "hit_dist2") -> PagedField:
    """Particle ``particle``'s field (``quantity="logodds"``: its log-odds) as a :class:`PagedField`."""
    return PagedField(maps.directory[particle], maps.blocks, getattr(maps, quantity))


def _tile_values(pool: Array, slots: Int[Array, "..."], fill) -> Array:
    """``pool[slots]`` with ``fill`` where a slot is unwritten: (..., T, T)."""
    values = pool[jnp.maximum(slots, 0)]
    return jnp.where((slots >= 0)[..., None, None], values, jnp.asarray(fill, pool.dtype))


def tile_slots(spec: PagedGridSpec, directory: Int[Array, "DY DX"], blocks: Int[Array, "B S S"],
               tiles: Int[Array, "... 2"]) -> Int[Array, "..."]:
    """The tile-pool slots of (row, col) tiles of one particle's map (inside the grid), -1 where unwritten."""
    shift, mask = spec.block_shift, spec.block_size - 1
    row, col = tiles[..., 0], tiles[..., 1]
    block = directory.reshape(-1)[(row >> shift) * directory.shape[1] + (col >> shift)]
    # One flat index per read: XLA's CPU gathers are cheaper on a 1-D operand than on (B, S, S).
    slot = blocks.reshape(-1)[(jnp.maximum(block, 0) * spec.block_size + (row & mask)) * spec.block_size
                              + (col & mask)]
    return jnp.where(block >= 0, slot, UNWRITTEN)


def cell_values(spec: PagedGridSpec, field: PagedField, cells: Int[Array, "... 2"], fill):
    """One particle's map at (row, col) cells of the virtual grid: ``field.pool`` (its log-odds or
    its field) read through its directory and the blocks; ``fill`` outside the grid and in
    unwritten tiles."""
    t = spec.tile_size
    ty, tx = spec.num_tiles
    row, col = cells[..., 0], cells[..., 1]
    inside = (row >= 0) & (row < ty * t) & (col >= 0) & (col < tx * t)
    row, col = jnp.clip(row, 0, ty * t - 1), jnp.clip(col, 0, tx * t - 1)
    shift, mask = spec.tile_shift, t - 1
    slot = tile_slots(spec, field.directory, field.blocks, jnp.stack([row >> shift, col >> shift], -1))
    if flat_pool(spec, field.pool.shape[0]):
        value = field.pool.reshape(-1)[(jnp.maximum(slot, 0) * t + (row & mask)) * t + (col & mask)]
    else:
        value = field.pool[jnp.maximum(slot, 0), row & mask, col & mask]
    return jnp.where(inside & (slot >= 0), value, jnp.asarray(fill, field.pool.dtype))


def _window_start(spec: PagedGridSpec, pose: Float[Array, "3"], sensor: SensorSpec, num_window: int,
                  max_insert_range: float, field_radius: int) -> Int[Array, "2"]:
    """(row, col) tile of the window's first tile: the window (K x K tiles) holds every cell one
    scan from ``pose`` can change; it is centred on the laser and clamped inside the virtual grid
    (cells beyond the grid's edge are then outside it, and counted)."""
    origin, _ = laser_rays(pose, sensor)
    center = world_to_cell(spec.grid, origin)
    reach = int(math.ceil(max_insert_range / spec.resolution)) + field_radius + 1
    start = jnp.floor_divide(center - reach, spec.tile_size)
    high = jnp.asarray([spec.num_tiles[0] - num_window, spec.num_tiles[1] - num_window])
    return jnp.clip(start, 0, high).astype(jnp.int32)


# Inserting scans. insert_scans runs the stages below in this order, each a function of the
# previous stages' NamedTuples:
#   _window_shape     the static size of the window of tiles (and of blocks) one scan can change
#   _scan_summaries   the window and the tiles each particle's scan touches, a block of particles at a time
#   _window_layout    where each window tile lies: a block of the window of blocks, an entry in it
#   _window_pages     the slots each particle's directory and blocks give its window now
#   _requests         the tiles and blocks a particle writes but does not own
#   _grant_slots      free slots for all particles' requests, by prefix sums; all or nothing
#   _copy_blocks      granted blocks become copies (or fresh); directories and references follow
#   _copy_tiles       granted tiles become copies (or fresh); the writers' blocks point at them
#   _write_cells      the scans' updates, scattered into tiles each writer now owns, a block of
#                     particles at a time, the cleared cells a chunk of samples at a time


class _Window(NamedTuple):
    """The static size of the window of tiles that holds every cell one scan can change, and of
    the window of blocks that holds that window (Python ints: changing one recompiles)."""

    tiles_per_side: int
    """K, tiles per side of the window."""
    tiles: int
    """K K, tiles in the window; also the index that stands for "no tile"."""
    blocks_per_side: int
    """Blocks per side of the window of blocks."""
    blocks: int
    """Blocks in the window of blocks."""


def _window_shape(spec: PagedGridSpec, max_insert_range: float, field_radius: int) -> _Window:
    """The window's static size: its side is fixed by the scan's reach, so shapes stay static."""
    side = spec.window_tiles(max_insert_range, field_radius)
    block_side = spec.window_blocks(side)
    return _Window(side, side * side, block_side, block_side * block_side)


class _CellTargets(NamedTuple):
    """Where some updated cells go, as (window tile, place in the tile)."""

    window_tile: Int[Array, "..."]
    """The cell's tile as a flat index over all particles' windows: particle p's window tile
    (row, col) is p (K K + 1) + row K + col; p (K K + 1) + K K stands for no tile (a cell masked
    out or off the window), whose updates are dropped."""
    place: Int[Array, "..."]
    """The cell's place in its tile, row T + col."""


def _window_tile(spec: PagedGridSpec, window: _Window, start: Int[Array, "2"], cells: Int[Array, "... 2"],
                 mask: Bool[Array, "..."]) -> Int[Array, "..."]:
    """Each (row, col) cell's tile in a window starting at tile ``start``, row K + col; K K (no
    tile) where ``mask`` is False or the cell is off the window."""
    shift, side = spec.tile_shift, window.tiles_per_side
    tile_row, tile_col = (cells[..., 0] >> shift) - start[0], (cells[..., 1] >> shift) - start[1]
    inside = mask & (tile_row >= 0) & (tile_row < side) & (tile_col >= 0) & (tile_col < side)
    return jnp.where(inside, tile_row * side + tile_col, window.tiles)


def _place_in_tile(spec: PagedGridSpec, cells: Int[Array, "... 2"]) -> Int[Array, "..."]:
    """Each (row, col) cell's place in its tile, row T + col (by masks: tile sizes are powers of two)."""
    t, shift = spec.tile_size, spec.tile_shift
    return ((cells[..., 0] & (t - 1)) << shift) + (cells[..., 1] & (t - 1))


def _tiles_touched(spec: PagedGridSpec, window: _Window, start: Int[Array, "2"], rays: ScanRays,
                   cleared: Int[Array, "B"], num_samples: int, field_radius: int) -> Bool[Array, "KK"]:
    """The window tiles one scan may change, found from a few points per beam instead of every
    sample (cheaper, and a superset is harmless: an extra tile copied).

    Cells along a ray move monotonically in row and column, so the samples between two points
    less than a tile side apart lie in the tiles of the four (row, column) combinations of the
    two points' tiles; those are marked where the first of the samples between the points lies
    before the beam's free length (``cleared``, samples per beam). An endpoint's field splat
    (radius below a tile side) lies in the tiles of its box's four corners.
    """
    stride = max(spec.tile_size // 2, 1)
    num_points = -(-(num_samples - 1) // stride) + 1
    index = jnp.minimum(jnp.arange(num_points) * stride, num_samples - 1)
    beams = jnp.arange(cleared.shape[0])[:, None]
    points = floored_to_cells(spec.grid, sample_floors(spec.grid, rays, beams, index[None, :]))  # (B, P, 2)
    # Segment i spans samples index[i] .. index[i + 1], both ends included.
    segment_free = index[None, :-1] < cleared[:, None]
    a, b = points[:, :-1], points[:, 1:]
    corners = [jnp.stack([x[..., 0], y[..., 1]], -1) for x in (a, b) for y in (a, b)]
    free_touched = jnp.stack([_window_tile(spec, window, start, c, segment_free) for c in corners], -1)
    r = jnp.asarray([field_radius, -field_radius])
    end_cells = floored_to_cells(spec.grid, rays.end_floor)
    box = [end_cells + jnp.stack([dr, dc]) for dr in r for dc in r]
    splat_touched = jnp.stack([_window_tile(spec, window, start, c, rays.returned) for c in box], -1)
    return (jnp.zeros(window.tiles + 1, bool).at[free_touched.reshape(-1)].set(True)
            .at[splat_touched.reshape(-1)].set(True)[:window.tiles])


class _ScanSummary(NamedTuple):
    """What the insertion needs of every particle's scan before it writes (``N`` leading): the
    beam samples themselves are computed chunk by chunk when it writes (:func:`_write_cells`)."""

    touched: Bool[Array, "N KK"]
    """The window tiles the scan may change."""
    window_start: Int[Array, "N 2"]
    """(row, col) of each window's first tile in the virtual grid."""


def _scan_summaries(spec: PagedGridSpec, window: _Window, poses: Float[Array, "N 3"], ranges: Float[Array, "B"],
                    sensor: SensorSpec, params: InsertionParams, max_insert_range: float, field_radius: int,
                    particle_block: int | None) -> _ScanSummary:
    """Every particle's window and touched tiles, ``particle_block`` particles at a time."""
    num_samples = samples_per_beam(spec.grid, max_insert_range)
    cleared = cleared_samples(spec.grid, free_lengths(ranges, sensor, params, max_insert_range), num_samples)

    def one(pose):
        rays = scan_rays(spec.grid, pose, ranges, sensor, params, max_insert_range)
        start = _window_start(spec, pose, sensor, window.tiles_per_side, max_insert_range, field_radius)
        return _ScanSummary(_tiles_touched(spec, window, start, rays, cleared, num_samples, field_radius), start)

    return map_in_blocks(one, poses, particle_block)


class _WindowLayout(NamedTuple):
    """Where each particle's window tiles lie in its directory (geometry only, no map read)."""

    tile_block: Int[Array, "N KK"]
    """The block of the window of blocks (row times blocks per side + col) each window tile lies in."""
    tile_in_block: Int[Array, "N KK"]
    """Each window tile's entry in its block, row S + col."""
    block_rows: Int[Array, "N KB"]
    """The directory row of each row of the window of blocks (past the directory's edge: dropped)."""
    block_cols: Int[Array, "N KB"]
    """The directory column of each column of the window of blocks (likewise)."""
    in_directory: Bool[Array, "N KBB"]
    """Each window block lies inside the directory."""


def _window_layout(spec: PagedGridSpec, window: _Window, window_start: Int[Array, "N 2"]) -> _WindowLayout:
    """Where each window tile lies: in which block of the particle's window of blocks, at which
    entry. The window of blocks starts at the block of the window's first tile, so one gather of
    the directory serves all the window's tiles."""
    n = window_start.shape[0]
    s, shift = spec.block_size, spec.block_shift
    dy, dx = spec.num_blocks
    side, block_side = window.tiles_per_side, window.blocks_per_side
    tile_rows, tile_cols = window_start[:, :1] + jnp.arange(side), window_start[:, 1:] + jnp.arange(side)  # (N, K)
    block_start = window_start >> shift  # (N, 2)
    tile_block = (((tile_rows >> shift) - block_start[:, :1])[:, :, None] * block_side
                  + ((tile_cols >> shift) - block_start[:, 1:])[:, None, :]).reshape(n, window.tiles)
    tile_in_block = ((tile_rows & (s - 1))[:, :, None] * s + (tile_cols & (s - 1))[:, None, :]).reshape(n, window.tiles)
    block_rows = block_start[:, :1] + jnp.arange(block_side)
    block_cols = block_start[:, 1:] + jnp.arange(block_side)
    in_directory = ((block_rows < dy)[:, :, None] & (block_cols < dx)[:, None, :]).reshape(n, window.blocks)
    return _WindowLayout(tile_block, tile_in_block, block_rows, block_cols, in_directory)


class _WindowPages(NamedTuple):
    """What each particle's directory and the blocks give its window before the insertion."""

    block_slots: Int[Array, "N KBB"]
    """The block slot of each window block; :data:`UNWRITTEN` where none (or off the directory)."""
    block_owned: Bool[Array, "N KBB"]
    """The block is the particle's alone (no other directory points at it): written in place."""
    tile_slots: Int[Array, "N KK"]
    """The tile slot of each window tile; :data:`UNWRITTEN` where none."""
    tile_owned: Bool[Array, "N KK"]
    """The tile is the particle's alone: its block is, and no other block points at the tile."""


def _window_pages(spec: PagedGridSpec, maps: PagedMaps, layout: _WindowLayout) -> _WindowPages:
    """The slots each particle's window reads now, and which of them it owns (refcount 1): those
    it may write in place; the others it must be given before it writes."""
    dy, dx = spec.num_blocks
    block_slots = jax.vmap(lambda d, r, c: d[jnp.minimum(r, dy - 1)[:, None], jnp.minimum(c, dx - 1)[None, :]])(
        maps.directory, layout.block_rows, layout.block_cols).reshape(layout.in_directory.shape)
    block_slots = jnp.where(layout.in_directory, block_slots, UNWRITTEN)
    block_owned = (block_slots >= 0) & (maps.block_refcount[jnp.maximum(block_slots, 0)] == 1)
    entries = maps.blocks.reshape(maps.blocks.shape[0], -1)
    block_of_tile = jnp.take_along_axis(block_slots, layout.tile_block, axis=1)
    tile_slots = jnp.where(block_of_tile >= 0, entries[jnp.maximum(block_of_tile, 0), layout.tile_in_block],
                           UNWRITTEN)
    tile_owned = (jnp.take_along_axis(block_owned, layout.tile_block, axis=1) & (tile_slots >= 0)
                  & (maps.refcount[jnp.maximum(tile_slots, 0)] == 1))
    return _WindowPages(block_slots, block_owned, tile_slots, tile_owned)


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
    :data:`FLAT_INDEX_CELLS`, a (slot, cell in the tile) pair of arrays into its (C, T * T) view."""
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
    the cleared cells a chunk of samples at a time (:func:`_write_cells`). All or nothing: an
    insertion whose requests do not fit writes nothing and sets ``overflow``; the maps are
    unchanged, so the caller can grow the pools (:func:`grow`) and insert again.

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


def resample(maps: PagedMaps, ancestors: Int[Array, "N2"]) -> PagedMaps:
    """Particle i takes particle ``ancestors[i]``'s map: directories are copied, blocks and tiles
    shared. The blocks' references are recounted from the directories; a block nobody uses any
    more is free, and the tiles it pointed at lose a reference each (a tile nothing points at is
    free). ``ancestors`` may have another length than the particles (N1 -> N2: e.g. one initial
    map to N particles)."""
    capacity, m, block_capacity, mb = maps.pool_size
    directory = maps.directory[ancestors]
    block_refcount = jnp.zeros_like(maps.block_refcount).at[
        jnp.where(directory >= 0, directory, block_capacity)].add(1, mode="drop")
    freed = (maps.block_refcount > 0) & (block_refcount == 0)
    refcount = maps.refcount.at[jnp.where(freed[:, None, None] & (maps.blocks >= 0), maps.blocks, capacity)].add(
        -1, mode="drop")
    return maps._replace(directory=directory, block_refcount=block_refcount, refcount=refcount,
                         free_slots=first_free(refcount, m), free_blocks=first_free(block_refcount, mb))


def grow(spec: PagedGridSpec, maps: PagedMaps, pool: PoolSize) -> PagedMaps:
    """The same maps in pools of ``pool``'s sizes (host side, between jitted calls; the new slots
    are free). Clears ``overflow``: the caller repeats the work that set it, from maps taken before it."""
    old = maps.pool_size
    pool = PoolSize(*(int(v) for v in pool))
    if pool.capacity < old.capacity or pool.block_capacity < old.block_capacity:
        raise ValueError(f"grow: the new pool {pool} is smaller than the current capacity {old}")
    _check_pool(spec, pool)
    extra, extra_blocks = pool.capacity - old.capacity, pool.block_capacity - old.block_capacity
    t, s = spec.tile_size, spec.block_size
    refcount = jnp.concatenate([maps.refcount, jnp.zeros((extra,), maps.refcount.dtype)])
    block_refcount = jnp.concatenate([maps.block_refcount, jnp.zeros((extra_blocks,), maps.block_refcount.dtype)])
    return PagedMaps(
        maps.directory,
        jnp.concatenate([maps.blocks, jnp.full((extra_blocks, s, s), UNWRITTEN, maps.blocks.dtype)]),
        block_refcount,
        jnp.concatenate([maps.logodds, jnp.zeros((extra, t, t), maps.logodds.dtype)]),
        jnp.concatenate([maps.hit_dist2, jnp.full((extra, t, t), FAR, maps.hit_dist2.dtype)]),
        refcount,
        first_free(refcount, pool.max_new_tiles),
        first_free(block_refcount, pool.max_new_blocks),
        jnp.bool_(False),
        maps.peak_request,
        maps.peak_block_request,
    )


def tiles_in_use(maps: PagedMaps) -> Int[Array, ""]:
    """Tile slots some block in use points at."""
    return jnp.sum(maps.refcount > 0)


def blocks_in_use(maps: PagedMaps) -> Int[Array, ""]:
    """Block slots some particle's directory points at."""
    return jnp.sum(maps.block_refcount > 0)


def page_table(spec: PagedGridSpec, maps: PagedMaps, particle: int) -> np.ndarray:
    """Host-side (TY, TX) int32: the tile-pool slot of each tile of one particle's map (-1 unwritten)."""
    directory, blocks = np.asarray(maps.directory[particle]), np.asarray(maps.blocks)
    s = spec.block_size
    dy, dx = directory.shape
    table = np.where((directory >= 0)[:, :, None, None], blocks[np.maximum(directory, 0)], UNWRITTEN)
    ty, tx = spec.num_tiles
    return table.transpose(0, 2, 1, 3).reshape(dy * s, dx * s)[:ty, :tx]


def to_dense(spec: PagedGridSpec, maps: PagedMaps, particle: int) -> tuple[np.ndarray, np.ndarray, GridSpec]:
    """Host-side dense copy of one particle's written tiles: its log-odds and field over the
    bounding box of those tiles, and that box's :class:`~jaxslam.grid.GridSpec`. A particle
    that wrote nothing gives one unknown tile at the grid's corner."""
    pages = page_table(spec, maps, particle)
    t = spec.tile_size
    rows, cols = np.nonzero(pages >= 0)
    if rows.size == 0:
        rows, cols = np.array([0]), np.array([0])
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    slots = pages[r0:r1, c0:c1]
    logodds_pool, field_pool = np.asarray(maps.logodds), np.asarray(maps.hit_dist2)

    def dense(pool, fill):
        # Tile by tile into one array (no gathered copy of the tiles: a campus map has 10^8 cells).
        out = np.full(((r1 - r0) * t, (c1 - c0) * t), fill, pool.dtype)
        for row, col in zip(*np.nonzero(slots >= 0)):
            out[row * t:(row + 1) * t, col * t:(col + 1) * t] = pool[slots[row, col]]
        return out

    box = GridSpec(((r1 - r0) * t, (c1 - c0) * t), spec.resolution,
                   (spec.origin[0] + c0 * t * spec.resolution, spec.origin[1] + r0 * t * spec.resolution))
    return dense(logodds_pool, 0.0), dense(field_pool, FAR), box


def check_invariants(spec: PagedGridSpec, maps: PagedMaps, before_insertion: PagedMaps | None = None) -> None:
    """Check on the host that ``maps`` are consistent; raise AssertionError naming the first
    broken invariant (ValueError if the arrays are not shaped as ``spec``'s maps are).

    These hold after :func:`empty`, :func:`insert_scans`, :func:`resample` and :func:`grow`:

    1. *directory entries*: every directory entry is :data:`UNWRITTEN` or a block slot (0 <= b < B).
    2. *block references*: ``block_refcount[b]`` is the number of directory entries equal to b
       (a block is *in use* when it is > 0; a free block slot is in no directory).
    3. *block entries*: every entry of a block in use is :data:`UNWRITTEN` or a tile slot
       (0 <= c < C). A free block's entries are stale: never read, overwritten whole when granted.
    4. *tile references*: ``refcount[c]`` is the number of entries of blocks in use equal to c
       (blocks, not particles: particles sharing a block share its tiles' references); a free
       tile slot is in no block in use. A free tile's cells are stale likewise.
    5. *one place per block*: a block in use sits at the same directory entry (row, col) in every
       directory that points at it (a copy is made for the place of the block it replaces).
    6. *tiles beyond the grid*: the entries of a block in use for tiles past the virtual grid's
       last row or column (where the block size does not divide the tile counts) are
       :data:`UNWRITTEN`.
    7. *one place per tile*: every block entry that points at a tile slot stands for the same
       (row, col) tile of the virtual grid.
    8. *free lists*: ``free_slots`` is the first M slots of refcount 0 in order, padded with C;
       ``free_blocks`` the first MB of block refcount 0, padded with B.
    9. *peak requests*: ``peak_request`` and ``peak_block_request`` are not negative.

    With ``before_insertion``, the maps the :func:`insert_scans` call that gave ``maps`` started
    from (not across a :func:`resample`, which keeps ``overflow`` as it was), also:

    10. *peaks never fall*: each peak request is at least its value before.
    11. *peaks cover the growth*: the tiles (blocks) in use grew by at most ``peak_request``
        (``peak_block_request``): every slot newly in use was requested.
    12. *all or nothing*: with ``overflow`` set, the directories, pools, reference counts and
        free lists are exactly those before, and a request did not fit: ``peak_request`` exceeds
        M or the free tile slots before, or ``peak_block_request`` MB or the free block slots.
    """
    _check_shapes(spec, maps)
    blocks_in_use = _check_references(maps)
    _check_places(spec, maps, blocks_in_use)
    _check_free_lists_and_peaks(maps)
    if before_insertion is not None:
        _check_insertion(spec, before_insertion, maps)


def _broken(invariant: str, detail: str):
    """Fail with the invariant's name (as :func:`check_invariants` lists it) and what broke it."""
    raise AssertionError(f"paged maps: invariant '{invariant}' is broken: {detail}")


def _check_shapes(spec: PagedGridSpec, maps: PagedMaps) -> None:
    """ValueError unless every array of ``maps`` has the shape and type of ``spec``'s maps."""
    n, t, s = maps.directory.shape[0], spec.tile_size, spec.block_size
    capacity, block_capacity = maps.refcount.shape[0], maps.block_refcount.shape[0]
    expected = {"directory": ((n,) + spec.num_blocks, np.int32), "blocks": ((block_capacity, s, s), np.int32),
                "block_refcount": ((block_capacity,), np.int32), "logodds": ((capacity, t, t), LOGODDS_DTYPE),
                "hit_dist2": ((capacity, t, t), np.uint8), "refcount": ((capacity,), np.int32),
                "free_slots": ((maps.free_slots.shape[0],), np.int32),
                "free_blocks": ((maps.free_blocks.shape[0],), np.int32), "overflow": ((), np.bool_),
                "peak_request": ((), np.int32), "peak_block_request": ((), np.int32)}
    for name, (shape, dtype) in expected.items():
        value = getattr(maps, name)
        if tuple(value.shape) != shape or np.dtype(value.dtype) != np.dtype(dtype):
            raise ValueError(f"paged maps: {name} is {np.dtype(value.dtype)}{tuple(value.shape)}, expected "
                             f"{np.dtype(dtype)}{shape} for {spec}")
    if maps.max_new_tiles > capacity or maps.pool_size.max_new_blocks > block_capacity:
        raise ValueError(f"paged maps: free lists longer than their pools ({maps.pool_size})")


def _check_references(maps: PagedMaps) -> np.ndarray:
    """Invariants 1 to 4: entries in range, reference counts equal to a recount. Returns the
    block slots in use."""
    directory, blocks = np.asarray(maps.directory), np.asarray(maps.blocks)
    refcount, block_refcount = np.asarray(maps.refcount), np.asarray(maps.block_refcount)
    capacity, block_capacity = refcount.size, block_refcount.size
    bad = (directory < UNWRITTEN) | (directory >= block_capacity)
    if bad.any():
        _broken("directory entries", f"{np.count_nonzero(bad)} entries neither UNWRITTEN nor in [0, "
                f"{block_capacity}), e.g. {directory[bad][:4]}")
    counted = np.bincount(directory[directory >= 0], minlength=block_capacity)
    if not np.array_equal(block_refcount, counted):
        wrong = np.flatnonzero(block_refcount != counted)[:4]
        _broken("block references", f"block slots {wrong} have refcount {block_refcount[wrong]}, but "
                f"{counted[wrong]} directory entries point at them")
    in_use = np.flatnonzero(counted > 0)
    entries = blocks[in_use]
    bad = (entries < UNWRITTEN) | (entries >= capacity)
    if bad.any():
        _broken("block entries", f"{np.count_nonzero(bad)} entries of blocks in use neither UNWRITTEN nor in "
                f"[0, {capacity}), e.g. {entries[bad][:4]}")
    counted = np.bincount(entries[entries >= 0], minlength=capacity)
    if not np.array_equal(refcount, counted):
        wrong = np.flatnonzero(refcount != counted)[:4]
        _broken("tile references", f"tile slots {wrong} have refcount {refcount[wrong]}, but {counted[wrong]} "
                "entries of blocks in use point at them")
    return in_use


def _one_place_each(slots: np.ndarray, places: np.ndarray, num_slots: int) -> np.ndarray:
    """Per slot: every occurrence of it in ``slots`` (>= 0) comes with the same value of ``places``."""
    used = slots >= 0
    low, high = np.full(num_slots, np.iinfo(np.int64).max), np.full(num_slots, -1)
    np.minimum.at(low, slots[used], places[used])
    np.maximum.at(high, slots[used], places[used])
    return (high < 0) | (low == high)


def _check_places(spec: PagedGridSpec, maps: PagedMaps, in_use: np.ndarray) -> None:
    """Invariants 5 to 7: each block and tile slot in use stands for one place of the grid."""
    directory, entries = np.asarray(maps.directory), np.asarray(maps.blocks)[in_use]
    s, (ty, tx), (dy, dx) = spec.block_size, spec.num_tiles, spec.num_blocks
    place = np.broadcast_to(np.arange(dy * dx).reshape(dy, dx), directory.shape)
    one_place = _one_place_each(directory, place, maps.block_refcount.shape[0])
    if not one_place.all():
        _broken("one place per block", f"block slots {np.flatnonzero(~one_place)[:4]} sit at different "
                "directory entries in different directories")
    block_place = np.zeros(maps.block_refcount.shape[0], np.int64)
    block_place[directory[directory >= 0]] = place[directory >= 0]
    tile_rows = (block_place[in_use] // dx)[:, None, None] * s + np.arange(s)[None, :, None]  # (U, S, 1)
    tile_cols = (block_place[in_use] % dx)[:, None, None] * s + np.arange(s)[None, None, :]  # (U, 1, S)
    bad = ((tile_rows >= ty) | (tile_cols >= tx)) & (entries != UNWRITTEN)
    if bad.any():
        _broken("tiles beyond the grid", f"blocks in use point at tile slots {entries[bad][:4]} for tiles past the "
                "virtual grid's edge")
    one_place = _one_place_each(entries, np.broadcast_to(tile_rows * (dx * s) + tile_cols, entries.shape),
                                maps.capacity)
    if not one_place.all():
        _broken("one place per tile", f"tile slots {np.flatnonzero(~one_place)[:4]} stand for different tiles of "
                "the virtual grid in different block entries")


def _check_free_lists_and_peaks(maps: PagedMaps) -> None:
    """Invariants 8 and 9."""
    for name, free, refcount in (("free_slots", maps.free_slots, maps.refcount),
                                 ("free_blocks", maps.free_blocks, maps.block_refcount)):
        refcount = np.asarray(refcount)
        expected = np.flatnonzero(refcount == 0)[:free.shape[0]]
        expected = np.concatenate([expected, np.full(free.shape[0] - expected.size, refcount.size)])
        if not np.array_equal(np.asarray(free), expected):
            _broken("free lists", f"{name} is {np.asarray(free)}, but the first slots of refcount 0 are {expected}")
    peaks = int(maps.peak_request), int(maps.peak_block_request)
    if min(peaks) < 0:
        _broken("peak requests", f"negative peak requests {peaks}")


def _check_insertion(spec: PagedGridSpec, before: PagedMaps, after: PagedMaps) -> None:
    """Invariants 10 to 12 of :func:`check_invariants`, across one insertion."""
    _check_shapes(spec, before)
    if before.pool_size != after.pool_size or before.directory.shape != after.directory.shape:
        raise ValueError(f"paged maps: an insertion keeps the pools' sizes and the particles, but "
                         f"{before.pool_size} became {after.pool_size}")
    peaks = int(after.peak_request), int(after.peak_block_request)
    peaks_before = int(before.peak_request), int(before.peak_block_request)
    if peaks[0] < peaks_before[0] or peaks[1] < peaks_before[1]:
        _broken("peaks never fall", f"peak requests (tiles, blocks) {peaks_before} fell to {peaks}")
    growth = (int(tiles_in_use(after)) - int(tiles_in_use(before)),
              int(blocks_in_use(after)) - int(blocks_in_use(before)))
    if growth[0] > peaks[0] or growth[1] > peaks[1]:
        _broken("peaks cover the growth", f"(tiles, blocks) in use grew by {growth}, more than the peak requests "
                f"{peaks}")
    if bool(after.overflow):
        for name in ("directory", "blocks", "block_refcount", "logodds", "hit_dist2", "refcount", "free_slots",
                     "free_blocks"):
            if not np.array_equal(np.asarray(getattr(after, name)), np.asarray(getattr(before, name))):
                _broken("all or nothing", f"overflow is set, but the insertion changed {name}")
        _, max_new_tiles, _, max_new_blocks = after.pool_size
        free_tiles = int(np.count_nonzero(np.asarray(before.refcount) == 0))
        free_blocks = int(np.count_nonzero(np.asarray(before.block_refcount) == 0))
        if peaks[0] <= min(max_new_tiles, free_tiles) and peaks[1] <= min(max_new_blocks, free_blocks):
            _broken("all or nothing", f"overflow is set, but peak requests {peaks} fit (at most "
                    f"{min(max_new_tiles, free_tiles)} tiles and {min(max_new_blocks, free_blocks)} blocks)")
