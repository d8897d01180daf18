"""The pools of paged maps and what changes them whole.

The virtual grid (:class:`PagedGridSpec`), the pools' static sizes (:class:`PoolSize`) and the
maps themselves (:class:`PagedMaps`: directories, blocks and tiles, their reference counts and
free lists); :func:`empty` makes them, :func:`resample` shares them between particles,
:func:`grow` enlarges them. How slots are indexed (:data:`FLAT_INDEX_CELLS`, :func:`flat_pool`)
and bounded (:func:`max_pool_tiles`) is decided here too.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.grid import GridSpec
from jaxslam.occupancy import FAR, LOGODDS_DTYPE


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
    (what holds between operations: :func:`~jaxslam.maps.invariants.check_invariants`)."""

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
