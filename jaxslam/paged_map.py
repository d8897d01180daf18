"""Paged occupancy maps: fixed-size tiles in one pool shared by all particles, copy on write.

A dense map per particle costs the grid's bounding box times the particle count, and every
resampling copies whole maps. Here the grid is a large *virtual* grid cut into square tiles
of ``tile_size`` cells, grouped into square blocks of ``block_size`` tiles
(:class:`PagedGridSpec`), and the particles' maps are:

* one **tile pool**, ``(C, T, T)`` log-odds (float16) and likelihood field (uint8), with a
  reference count per tile (how many blocks point at it);
* one **block pool**, ``(B, S, S)`` int32: a block is a piece of page table, the tile-pool slot
  of each of its S x S tiles (-1: a tile never written), with a reference count per block (how
  many particles point at it);
* one **directory** per particle, ``(DY, DX)`` int32: the block-pool slot of each of its blocks
  (-1: a block it never wrote).

A page table with an entry for every tile of a 1.28 km grid would cost 0.64 MB per particle,
0.64 GB at N = 1,000, copied at every resampling; the directory costs 2.5 KB and the blocks a
particle writes 1 KB each, so the memory grows with the area mapped, not with the extent times
the particles. Resampling copies directories only (:func:`resample`): particles share the blocks
and tiles of their common past, as GMapping's reference-counted patches do. Inserting a scan
(:func:`insert_scans`) first makes every block and tile it writes the writer's own (a block or
tile only it uses is written in place; a shared one is copied into a free slot, an unwritten one
gets a fresh slot), then scatters the scan's updates into the tile pool: the same cells get the
same updates as in a dense grid (:func:`jaxslam.occupancy.update_cells`), and the work is the
dense insertion's plus the copied tiles. Slots nothing references any more are free again at
once.

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

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.grid import GridSpec, world_to_cell
from jaxslam.laser import SensorSpec, laser_rays
from jaxslam.occupancy import FAR, LOGODDS_DTYPE, InsertionParams, field_kernel, scan_cells, update_cells

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
    on write (16 x 16 tiles of 64 cells: 51.2 m at 5 cm, 1 KB of page table)."""

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
    """The maps of N particles: directories of shared blocks of page table into one pool of tiles."""

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


def _check_pool(spec: PagedGridSpec, pool: PoolSize) -> None:
    if min(pool) < 1 or pool.max_new_tiles > pool.capacity or pool.max_new_blocks > pool.block_capacity:
        raise ValueError(f"a paged map's pools need positive sizes and at most their capacity new per insertion, "
                         f"got {pool}")
    if pool.capacity * spec.tile_size**2 >= 2**31:
        raise ValueError(f"a pool of {pool.capacity} tiles of {spec.tile_size} x {spec.tile_size} cells exceeds "
                         "int32 indexing; use fewer particles or a larger resolution")


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
    refcount = jnp.zeros((pool.capacity,), jnp.int32)
    block_refcount = jnp.zeros((pool.block_capacity,), jnp.int32)
    return PagedMaps(
        directory=jnp.full((num_particles,) + spec.num_blocks, UNWRITTEN, jnp.int32),
        blocks=jnp.full((pool.block_capacity, s, s), UNWRITTEN, jnp.int32),
        block_refcount=block_refcount,
        logodds=jnp.zeros((pool.capacity, t, t), LOGODDS_DTYPE),
        hit_dist2=jnp.full((pool.capacity, t, t), FAR, jnp.uint8),
        refcount=refcount,
        free_slots=first_free(refcount, pool.max_new_tiles),
        free_blocks=first_free(block_refcount, pool.max_new_blocks),
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
    block = directory[row >> shift, col >> shift]
    slot = blocks[jnp.maximum(block, 0), row & mask, col & mask]
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


def computed_once(fn, first, *rest):
    """``fn(first, *rest)``, computed into memory once, before anything reads it.

    XLA fuses a cheap-looking elementwise producer into every consumer. For the beam samples of
    an insertion (a few dozen operations per sample, 10^6 samples) and the beam endpoints of a
    likelihood (read by a page-table gather and then a pool gather, four times with bilinear
    reads) that means recomputing them inside each gather and scatter that reads them, in
    scalar loops: measured, it doubled the insertion's time on Intel and cost the scan matcher
    about 5 ms a step. The outputs of a loop whose trip count XLA cannot know are always
    materialised, by vectorised code, once; so ``fn`` runs in a ``while_loop`` whose trip count
    depends on the data (1, or 2 if ``first``'s first element is +inf: the same result).
    ``jax.lax.optimization_barrier`` does not do this: XLA's CPU pipeline drops it before fusion.
    Reverse-mode autodiff cannot go through a ``while_loop``, so the derivative is ``fn``'s own
    (a custom JVP): the forward values are the loop's, gradients flow as if ``fn`` were called.
    """
    # closure_convert: the custom JVP must not close over traced values (fn often does).
    converted, consts = jax.closure_convert(fn, first, *rest)
    return _computed_once(converted, first, *rest, *consts)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _computed_once(fn, first, *rest):
    shapes = jax.eval_shape(fn, first, *rest)
    init = jax.tree.map(lambda shape: jnp.zeros(shape.shape, shape.dtype), shapes)
    probe = first.reshape(-1)[0].astype(jnp.float32)
    trips = 1 + (probe > jnp.finfo(jnp.float32).max).astype(jnp.int32)
    _, out = jax.lax.while_loop(lambda c: c[0] < trips, lambda c: (c[0] + 1, fn(first, *rest)),
                                (jnp.int32(0), init))
    return out


@_computed_once.defjvp
def _computed_once_jvp(fn, primals, tangents):
    _, tangents_out = jax.jvp(fn, primals, tangents)
    return _computed_once(fn, *primals), tangents_out


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
) -> tuple[PagedMaps, Int[Array, "N"]]:
    """Insert one scan into every ``active`` particle's map (default all), particle n's taken at
    ``poses[n]``; an inactive particle's map is left as it was.

    The same cells get the same updates as in a dense grid (:func:`jaxslam.occupancy.scan_cells`,
    :func:`jaxslam.occupancy.update_cells`). First every block and tile a particle's scan touches
    is made its own: one it alone uses is written in place; a shared or unwritten one gets a free
    slot (a copy of the shared one, or a fresh one), handed out by a prefix sum over all
    particles' requests, at most ``max_new_tiles`` tiles and ``max_new_blocks`` blocks in all.
    Then all particles' samples are scattered into the pool at once (no two particles write the
    same slot). All or nothing: an insertion whose requests do not fit writes nothing and sets
    ``overflow``; the maps are unchanged, so the caller can grow the pools (:func:`grow`) and
    insert again.

    ``active`` (e.g. the particles a resampling keeps) saves the tiles of maps about to be
    dropped, and orders the insertion after whatever computed it: XLA then updates the pools in
    place instead of copying them (a read of a pool that no data dependence places before its
    in-place update forces a copy of the whole pool).

    Returns the new maps and, per particle, the beam samples that fell outside the virtual grid.
    """
    t = spec.tile_size
    k = spec.window_tiles(max_insert_range, field_radius)
    kk = k * k
    s, bshift = spec.block_size, spec.block_shift
    kb = spec.window_blocks(k)
    kbb = kb * kb
    dy, dx = spec.num_blocks
    capacity, m, block_capacity, mb = maps.pool_size
    n = poses.shape[0]
    active = jnp.ones((n,), bool) if active is None else jnp.asarray(active, bool)
    grid = spec.grid

    offsets, d2 = field_kernel(field_radius)
    shift = spec.tile_shift

    stride = max(t // 2, 1)  # samples between the points that bound a beam's tiles (< a tile side)

    def where_cells_go(pose, particle):
        """One particle's updated cells as (tile, place): the tile's flat index among all particles'
        windows (N x (K K + 1); the last of each particle's K K + 1: no tile, dropped) and the
        cell's place in its tile; the tiles its scan may touch, and the samples outside the grid.

        The window holds every cell of the grid the scan can reach (it is clamped inside the
        grid), so a cell off the window's tiles is off the grid."""
        cells = scan_cells(grid, pose, ranges, sensor, params, max_insert_range)
        start = _window_start(spec, pose, sensor, k, max_insert_range, field_radius)
        base = particle * (kk + 1)

        def tile_of(c, mask):
            tile_row, tile_col = (c[..., 0] >> shift) - start[0], (c[..., 1] >> shift) - start[1]
            ok = mask & (tile_row >= 0) & (tile_row < k) & (tile_col >= 0) & (tile_col < k)
            return jnp.where(ok, tile_row * k + tile_col, kk)

        def place_of(c):
            return ((c[..., 0] & (t - 1)) << shift) + (c[..., 1] & (t - 1))

        free_tile = tile_of(cells.free_cells, cells.free)
        end_tile = tile_of(cells.end_cells, cells.returned)
        splat_cells = cells.end_cells[:, None, :] + jnp.asarray(offsets)  # (B, K, 2)
        outside = jnp.sum(cells.free & (free_tile == kk)) + jnp.sum(cells.returned & (end_tile == kk))

        # The tiles the scan touches, from a few points per beam instead of every sample: cells
        # along a ray move monotonically in row and column, so the samples between two points
        # under a tile side apart lie in the tiles of the four (row, column) combinations of the
        # two points' tiles. Marked where any sample between them is free (a superset is
        # harmless: an extra tile copied). An endpoint's field splat (radius < a tile side) lies
        # in the tiles of its box's four corners.
        num_points = -(-(cells.free.shape[1] - 1) // stride) + 1
        index = jnp.minimum(jnp.arange(num_points) * stride, cells.free.shape[1] - 1)
        points = cells.free_cells[:, index]  # (B, P, 2)
        padded = jnp.pad(cells.free, ((0, 0), (0, (num_points - 1) * stride + 1 - cells.free.shape[1])))
        # Segment i spans samples i * stride .. (i + 1) * stride, both ends included.
        starts_of_segments = padded[:, :-1].reshape(padded.shape[0], num_points - 1, stride)
        segment_free = jnp.any(starts_of_segments, axis=2) | padded[:, stride::stride]
        a, b = points[:, :-1], points[:, 1:]
        corners = [jnp.stack([x[..., 0], y[..., 1]], -1) for x in (a, b) for y in (a, b)]
        free_touched = jnp.stack([tile_of(c, segment_free) for c in corners], -1)  # (B, P - 1, 4)
        r = jnp.asarray([field_radius, -field_radius])
        box = [cells.end_cells + jnp.stack([dr, dc]) for dr in r for dc in r]
        splat_touched = jnp.stack([tile_of(c, cells.returned) for c in box], -1)  # (B, 4)
        touched = (jnp.zeros(kk + 1, bool).at[free_touched.reshape(-1)].set(True)
                   .at[splat_touched.reshape(-1)].set(True)[:kk])
        return ((free_tile + base, place_of(cells.free_cells)), (end_tile + base, place_of(cells.end_cells)),
                (tile_of(splat_cells, cells.returned[:, None]) + base, place_of(splat_cells)), touched, start,
                outside)

    (free_tile, free_within), (end_tile, end_within), (splat_tile, splat_within), touched, starts, outside = (
        computed_once(jax.vmap(where_cells_go), poses, jnp.arange(n, dtype=jnp.int32)))
    touched = touched & active[:, None]

    # Where each window tile lies: its block in the particle's window of kb x kb blocks, and its
    # place in that block.
    window = jnp.arange(k)
    tile_rows, tile_cols = starts[:, :1] + window, starts[:, 1:] + window  # (N, K)
    block_start = starts >> bshift  # (N, 2)
    tile_block = (((tile_rows >> bshift) - block_start[:, :1])[:, :, None] * kb
                  + ((tile_cols >> bshift) - block_start[:, 1:])[:, None, :]).reshape(n, kk)
    in_block = ((tile_rows & (s - 1))[:, :, None] * s + (tile_cols & (s - 1))[:, None, :]).reshape(n, kk)
    block_rows, block_cols = block_start[:, :1] + jnp.arange(kb), block_start[:, 1:] + jnp.arange(kb)  # (N, kb)
    in_directory = ((block_rows < dy)[:, :, None] & (block_cols < dx)[:, None, :]).reshape(n, kbb)
    blocks_now = jax.vmap(lambda d, r, c: d[jnp.minimum(r, dy - 1)[:, None], jnp.minimum(c, dx - 1)[None, :]])(
        maps.directory, block_rows, block_cols).reshape(n, kbb)
    blocks_now = jnp.where(in_directory, blocks_now, UNWRITTEN)
    block_owned = (blocks_now >= 0) & (maps.block_refcount[jnp.maximum(blocks_now, 0)] == 1)
    blocks_before = maps.blocks.reshape(block_capacity, s * s)
    block_of_tile = jnp.take_along_axis(blocks_now, tile_block, axis=1)
    slots = jnp.where(block_of_tile >= 0, blocks_before[jnp.maximum(block_of_tile, 0), in_block], UNWRITTEN)
    # A tile is the particle's own when its block is (no other particle's directory points at it)
    # and no other block points at the tile.
    owned = (jnp.take_along_axis(block_owned, tile_block, axis=1) & (slots >= 0)
             & (maps.refcount[jnp.maximum(slots, 0)] == 1))
    need = touched & ~owned  # (N, K K)
    # A block must be made the particle's own when a tile in it is to be replaced.
    need_block = jnp.any(need[:, :, None] & (tile_block[:, :, None] == jnp.arange(kbb)), axis=1) & ~block_owned

    # The j-th request (in particle order) gets free_slots[j] (free_blocks[j]): a copy of the old
    # tile (block), or a fresh one. All or nothing: an insertion that needs more new tiles or
    # blocks than it may take or than are free writes nothing at all and sets ``overflow``.
    def grant(wanted, free, size, limit):
        wanted = wanted.reshape(-1)
        count = jnp.sum(wanted).astype(jnp.int32)
        fits = ((count <= limit) & (free[jnp.clip(count - 1, 0, limit - 1)] < size)) | (count == 0)
        return count, fits, free[jnp.clip(jnp.cumsum(wanted) - 1, 0, limit - 1)]

    num_requests, tiles_fit, tile_grants = grant(need, maps.free_slots, capacity, m)
    num_block_requests, blocks_fit, block_grants = grant(need_block, maps.free_blocks, block_capacity, mb)
    fits = tiles_fit & blocks_fit
    placed, placed_block = need.reshape(-1) & fits, need_block.reshape(-1) & fits
    old_slots, old_blocks = slots.reshape(-1), blocks_now.reshape(-1)
    granted = jnp.where(placed, tile_grants, capacity)
    granted_block = jnp.where(placed_block, block_grants, block_capacity)

    # Blocks first: a copy points at the same tiles (each gains a reference), a fresh one at none.
    block_requests = jnp.nonzero(placed_block, size=mb, fill_value=n * kbb)[0]
    block_source = jnp.concatenate([old_blocks, jnp.full((1,), UNWRITTEN, old_blocks.dtype)])[block_requests]
    block_target = jnp.where(block_requests < n * kbb, maps.free_blocks, block_capacity)
    copied = jnp.where((block_source >= 0)[:, None], blocks_before[jnp.maximum(block_source, 0)], UNWRITTEN)
    flat_blocks = blocks_before.at[block_target].set(copied, mode="drop")
    refcount = maps.refcount.at[jnp.where((block_target < block_capacity)[:, None] & (copied >= 0), copied,
                                          capacity)].add(1, mode="drop")
    block_refcount = (maps.block_refcount.at[jnp.where(placed_block & (old_blocks >= 0), old_blocks, block_capacity)]
                      .add(-1, mode="drop").at[granted_block].add(1, mode="drop"))
    # A shared block every holder of which made its own copy is free now: its tiles lose its reference.
    freed = (maps.block_refcount > 0) & (block_refcount == 0)
    refcount = refcount.at[jnp.where(freed[:, None] & (blocks_before >= 0), blocks_before, capacity)].add(
        -1, mode="drop")
    new_blocks = jnp.where(placed_block, granted_block, old_blocks).reshape(n, kbb)
    particle = jnp.arange(n)[:, None, None]
    directory = maps.directory.at[particle, jnp.where(block_rows < dy, block_rows, dy)[:, :, None],
                                  block_cols[:, None, :]].set(new_blocks.reshape(n, kb, kb), mode="drop")

    # Then tiles: copies of the replaced tiles (or fresh ones) into their new slots, which the
    # particle's own blocks now point at.
    requests = jnp.nonzero(placed, size=m, fill_value=n * kk)[0]
    source = jnp.concatenate([old_slots, jnp.full((1,), UNWRITTEN, old_slots.dtype)])[requests]
    target = jnp.where(requests < n * kk, maps.free_slots, capacity)
    logodds = maps.logodds.at[target].set(_tile_values(maps.logodds, source, 0.0), mode="drop")
    hit_dist2 = maps.hit_dist2.at[target].set(_tile_values(maps.hit_dist2, source, FAR), mode="drop")
    refcount = (refcount.at[jnp.where(placed & (old_slots >= 0), old_slots, capacity)].add(-1, mode="drop")
                .at[granted].add(1, mode="drop"))
    writer_block = jnp.take_along_axis(new_blocks, tile_block, axis=1).reshape(-1)
    flat_blocks = flat_blocks.at[jnp.where(placed, writer_block, block_capacity), in_block.reshape(-1)].set(
        granted, mode="drop")

    # Pool index of every updated cell: the slot of its tile (the particle's own, after the
    # copies above), or the pool's size (dropped) where its tile got no slot.
    new_slots = jnp.where(placed, granted, old_slots)
    writable = (owned.reshape(-1) & fits) | placed
    writable_slot = jnp.where(writable & jnp.repeat(active, kk), new_slots, capacity).reshape(n, kk)
    writable_slot = jnp.concatenate([writable_slot, jnp.full((n, 1), capacity, jnp.int32)], axis=1).reshape(-1)

    def pool_index(tile, place):
        slot = writable_slot[tile]
        return jnp.where(slot < capacity, slot * (t * t) + place, capacity * t * t)

    flat_logodds, flat_field = update_cells(
        logodds.reshape(-1), hit_dist2.reshape(-1), pool_index(free_tile, free_within),
        pool_index(end_tile, end_within), pool_index(splat_tile, splat_within), d2, params)
    new_maps = PagedMaps(
        directory=directory,
        blocks=flat_blocks.reshape(maps.blocks.shape),
        block_refcount=block_refcount,
        logodds=flat_logodds.reshape(logodds.shape),
        hit_dist2=flat_field.reshape(hit_dist2.shape),
        refcount=refcount,
        free_slots=first_free(refcount, m),
        free_blocks=first_free(block_refcount, mb),
        overflow=~fits,
        peak_request=jnp.maximum(maps.peak_request, num_requests),
        peak_block_request=jnp.maximum(maps.peak_block_request, num_block_requests),
    )
    return new_maps, outside.astype(jnp.int32)


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
