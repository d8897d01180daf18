"""Paged occupancy maps: fixed-size tiles in one pool shared by all particles, copy on write.

A dense map per particle costs the grid's bounding box times the particle count, and every
resampling copies whole maps. Here the grid is a large *virtual* grid cut into square tiles
of ``tile_size`` cells (:class:`PagedGridSpec`), and the particles' maps are:

* one **pool** of tiles, ``(capacity, T, T)`` log-odds (float16) and likelihood field (uint8),
  with a reference count per tile;
* one **page table** per particle, ``(TY, TX)`` int32: the pool slot of each of its tiles, -1
  for a tile it never wrote (all unknown, no endpoint).

Resampling copies page tables only (:func:`resample`), so particles share the tiles of their
common past, as GMapping's reference-counted patches do. Inserting a scan
(:func:`insert_scans`) gathers the tiles the scan can reach into a dense window, inserts the
scan there with :func:`jaxslam.occupancy.insert_scan` (the same cells get the same updates as
in a dense grid), and writes back only the tiles that changed: in place where the particle
is the tile's only user, into a free slot otherwise (a fresh tile, or a copy of a shared one).
Slots that no page table references any more are free again at the next step.

Everything has a static shape and no sequential loop over particles: the free slots are
handed out by a prefix sum over the particles' requests. The pool's capacity is static; a
step that needs more free slots than the pool has sets ``overflow`` (the tiles it could not
place keep their old content), and the host grows the pool (:func:`grow`) and repeats the
work since its last good state: never a silent overwrite.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.grid import GridSpec, world_to_cell
from jaxslam.laser import SensorSpec, laser_rays
from jaxslam.occupancy import FAR, LOGODDS_DTYPE, GridMap, InsertionParams, insert_scan

UNWRITTEN = -1
"""Page-table entry of a tile the particle never wrote."""


@dataclasses.dataclass(frozen=True)
class PagedGridSpec:
    """The virtual grid of a paged map. Static (hashable): changing it recompiles."""

    resolution: float = 0.05
    """Cell side (m)."""
    tile_size: int = 64
    """T, cells per tile side."""
    num_tiles: tuple[int, int] = (400, 400)
    """(TY, TX): tiles along y (rows) and x (columns); the default covers 1.28 km x 1.28 km at 5 cm."""
    origin: tuple[float, float] = (-640.0, -640.0)
    """World (x, y) in metres of the lower-left corner of the virtual grid."""

    def __post_init__(self):
        ty, tx = self.num_tiles
        if not (self.resolution > 0 and self.tile_size >= 1 and ty >= 1 and tx >= 1):
            raise ValueError(f"PagedGridSpec needs a positive resolution, tile size and tile counts, got {self}")
        if ty * self.tile_size * tx * self.tile_size >= 2**31:
            raise ValueError(f"PagedGridSpec: {ty * self.tile_size} x {tx * self.tile_size} cells exceed int32 indexing")
        object.__setattr__(self, "num_tiles", (int(ty), int(tx)))
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))

    @classmethod
    def centred(cls, center_xy, extent: float, resolution: float = 0.05, tile_size: int = 64) -> "PagedGridSpec":
        """A square virtual grid of at least ``extent`` metres a side, centred on ``center_xy`` (m)."""
        tiles = int(math.ceil(extent / (tile_size * resolution)))
        half = tiles * tile_size * resolution / 2.0
        return cls(resolution, tile_size, (tiles, tiles), (float(center_xy[0]) - half, float(center_xy[1]) - half))

    @property
    def grid(self) -> GridSpec:
        """The virtual grid as a dense :class:`~jaxslam.grid.GridSpec` (for cell coordinates only)."""
        t = self.tile_size
        return GridSpec((self.num_tiles[0] * t, self.num_tiles[1] * t), self.resolution, self.origin)

    def window_tiles(self, max_insert_range: float, field_radius: int) -> int:
        """K: tiles per side of the window that holds everything one scan can change."""
        reach = int(math.ceil(max_insert_range / self.resolution)) + field_radius + 1
        return min(2 * reach // self.tile_size + 2, min(self.num_tiles))


class PagedMaps(NamedTuple):
    """The maps of N particles: page tables into one shared pool of tiles."""

    pages: Int[Array, "N TY TX"]
    """Pool slot of each tile of each particle's map; :data:`UNWRITTEN` (-1) for a tile never written."""
    logodds: Float[Array, "C T T"]
    """Occupancy log-odds of every pool tile (float16, 0 = unknown)."""
    hit_dist2: UInt8[Array, "C T T"]
    """Likelihood field of every pool tile (squared cell distance to the nearest endpoint, FAR beyond)."""
    refcount: Int[Array, "C"]
    """How many page-table entries point at each slot; 0: free."""
    overflow: Bool[Array, ""]
    """A step wanted more free slots than the pool had (some tiles kept their old content)."""


def empty(spec: PagedGridSpec, num_particles: int, capacity: int) -> PagedMaps:
    """N empty maps and a pool of ``capacity`` free tiles."""
    t = spec.tile_size
    return PagedMaps(
        pages=jnp.full((num_particles,) + spec.num_tiles, UNWRITTEN, jnp.int32),
        logodds=jnp.zeros((capacity, t, t), LOGODDS_DTYPE),
        hit_dist2=jnp.full((capacity, t, t), FAR, jnp.uint8),
        refcount=jnp.zeros((capacity,), jnp.int32),
        overflow=jnp.bool_(False),
    )


class PagedField(NamedTuple):
    """One particle's likelihood field (or log-odds) as the likelihood model reads it: its page
    table and the shared pool (vmap over particles with ``in_axes=PagedField(0, None)``)."""

    pages: Int[Array, "TY TX"]
    """The particle's page table."""
    pool: Array
    """(C, T, T) the pool's tiles of that quantity."""


def _tile_values(pool: Array, slots: Int[Array, "..."], fill) -> Array:
    """``pool[slots]`` with ``fill`` where a slot is unwritten: (..., T, T)."""
    values = pool[jnp.maximum(slots, 0)]
    return jnp.where((slots >= 0)[..., None, None], values, jnp.asarray(fill, pool.dtype))


def cell_values(spec: PagedGridSpec, pages: Int[Array, "TY TX"], pool: Array, cells: Int[Array, "... 2"], fill):
    """One particle's map at (row, col) cells of the virtual grid: ``pool`` (its log-odds or its
    field) read through its page table ``pages``; ``fill`` outside the grid and in unwritten tiles."""
    t = spec.tile_size
    ty, tx = spec.num_tiles
    row, col = cells[..., 0], cells[..., 1]
    inside = (row >= 0) & (row < ty * t) & (col >= 0) & (col < tx * t)
    row, col = jnp.clip(row, 0, ty * t - 1), jnp.clip(col, 0, tx * t - 1)
    slot = pages[row // t, col // t]
    value = pool[jnp.maximum(slot, 0), row % t, col % t]
    return jnp.where(inside & (slot >= 0), value, jnp.asarray(fill, pool.dtype))


def _window_start(spec: PagedGridSpec, pose: Float[Array, "3"], sensor: SensorSpec, num_window: int,
                  max_insert_range: float, field_radius: int) -> Int[Array, "2"]:
    """(row, col) tile of the window's first tile: the window is centred on the laser, clamped
    inside the virtual grid (samples beyond the grid's edge are then outside it, and counted)."""
    origin, _ = laser_rays(pose, sensor)
    center = world_to_cell(spec.grid, origin)
    reach = int(math.ceil(max_insert_range / spec.resolution)) + field_radius + 1
    start = jnp.floor_divide(center - reach, spec.tile_size)
    high = jnp.asarray([spec.num_tiles[0] - num_window, spec.num_tiles[1] - num_window])
    return jnp.clip(start, 0, high).astype(jnp.int32)


def _window(spec: PagedGridSpec, maps: PagedMaps, pages: Int[Array, "TY TX"], start: Int[Array, "2"], k: int):
    """The (K, K) slots of a window and its dense (K T, K T) log-odds and field."""
    t = spec.tile_size
    slots = jax.lax.dynamic_slice(pages, (start[0], start[1]), (k, k))

    def dense(pool, fill):
        tiles = _tile_values(pool, slots, fill)  # (K, K, T, T)
        return tiles.transpose(0, 2, 1, 3).reshape(k * t, k * t)

    return slots, GridMap(dense(maps.logodds, 0.0), dense(maps.hit_dist2, FAR))


def _tiles_of(window: Array, k: int, t: int) -> Array:
    """(K T, K T) -> (K, K, T, T)."""
    return window.reshape(k, t, k, t).transpose(0, 2, 1, 3)


class _Insertion(NamedTuple):
    start: Int[Array, "2"]
    slots: Int[Array, "K K"]
    logodds: Float[Array, "K K T T"]
    hit_dist2: UInt8[Array, "K K T T"]
    changed: Bool[Array, "K K"]
    outside: Int[Array, ""]


def insert_scans(
    spec: PagedGridSpec,
    maps: PagedMaps,
    poses: Float[Array, "N 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: InsertionParams,
    max_insert_range: float,
    field_radius: int,
    batch_size: int | None = None,
) -> tuple[PagedMaps, Int[Array, "N"]]:
    """Insert one scan into every particle's map, particle n's taken at ``poses[n]``.

    Each particle's window of K x K tiles round its laser (:meth:`PagedGridSpec.window_tiles`)
    is gathered, the scan inserted as in a dense grid (:func:`jaxslam.occupancy.insert_scan`),
    and the changed tiles written back: in place into a tile only this particle uses, into a
    free slot otherwise. ``batch_size`` (static) bounds how many particles' windows exist at
    once (``lax.map``; None: all N).

    Returns the new maps and, per particle, the beam samples that fell outside the virtual grid.
    """
    t = spec.tile_size
    k = spec.window_tiles(max_insert_range, field_radius)
    capacity = maps.refcount.shape[0]
    num = poses.shape[0]

    def one(args):
        pages, pose = args
        start = _window_start(spec, pose, sensor, k, max_insert_range, field_radius)
        slots, window = _window(spec, maps, pages, start, k)
        new, outside = insert_scan(spec.grid, window, pose, ranges, sensor, params, max_insert_range,
                                   field_radius, window_offset=start * t)
        new_lo, new_field = _tiles_of(new.logodds, k, t), _tiles_of(new.hit_dist2, k, t)
        old_lo, old_field = _tiles_of(window.logodds, k, t), _tiles_of(window.hit_dist2, k, t)
        changed = jnp.any((new_lo != old_lo) | (new_field != old_field), axis=(2, 3))
        return _Insertion(start, slots, new_lo, new_field, changed, outside)

    ins = jax.lax.map(one, (maps.pages, poses), batch_size=batch_size)

    # Hand out free slots: a changed tile needs one unless its particle is its only user.
    owned = (ins.slots >= 0) & (maps.refcount[jnp.maximum(ins.slots, 0)] == 1)
    need = ins.changed & ~owned
    free_list = jnp.nonzero(maps.refcount == 0, size=min(num * k * k, capacity), fill_value=capacity)[0]
    rank = jnp.cumsum(need.reshape(-1)).reshape(need.shape) - 1
    granted = jnp.where(need, free_list[jnp.clip(rank, 0, free_list.shape[0] - 1)], capacity)
    granted = jnp.where(rank < free_list.shape[0], granted, capacity)
    placed = need & (granted < capacity)
    overflow = maps.overflow | jnp.any(need & ~placed)
    new_slots = jnp.where(placed, granted, ins.slots)
    write = jnp.where(ins.changed & (owned | placed), new_slots, capacity).reshape(-1)

    logodds = maps.logodds.at[write].set(ins.logodds.reshape((-1, t, t)), mode="drop")
    hit_dist2 = maps.hit_dist2.at[write].set(ins.hit_dist2.reshape((-1, t, t)), mode="drop")
    released = jnp.where(placed & (ins.slots >= 0), ins.slots, capacity).reshape(-1)
    refcount = maps.refcount.at[released].add(-1, mode="drop")
    refcount = refcount.at[jnp.where(placed, granted, capacity).reshape(-1)].add(1, mode="drop")
    pages = jax.vmap(lambda p, s, start: jax.lax.dynamic_update_slice(p, s, (start[0], start[1])))(
        maps.pages, new_slots.astype(jnp.int32), ins.start)
    return PagedMaps(pages, logodds, hit_dist2, refcount, overflow), ins.outside


def resample(maps: PagedMaps, ancestors: Int[Array, "N"]) -> PagedMaps:
    """Particle i takes particle ``ancestors[i]``'s map: page tables are copied, tiles shared.
    The reference counts are recounted from the page tables (a slot nobody uses is free)."""
    pages = maps.pages[ancestors]
    capacity = maps.refcount.shape[0]
    refcount = jnp.zeros_like(maps.refcount).at[jnp.where(pages >= 0, pages, capacity).reshape(-1)].add(
        1, mode="drop")
    return maps._replace(pages=pages, refcount=refcount)


def grow(maps: PagedMaps, capacity: int) -> PagedMaps:
    """The same maps in a pool of ``capacity`` slots (host side, between jitted calls; the new
    slots are free). Clears ``overflow``: the caller repeats the step that set it."""
    old = maps.refcount.shape[0]
    if capacity < old:
        raise ValueError(f"grow: capacity {capacity} is below the current {old}")
    extra = capacity - old
    t = maps.logodds.shape[1]
    return PagedMaps(
        maps.pages,
        jnp.concatenate([maps.logodds, jnp.zeros((extra, t, t), maps.logodds.dtype)]),
        jnp.concatenate([maps.hit_dist2, jnp.full((extra, t, t), FAR, maps.hit_dist2.dtype)]),
        jnp.concatenate([maps.refcount, jnp.zeros((extra,), maps.refcount.dtype)]),
        jnp.bool_(False),
    )


def tiles_in_use(maps: PagedMaps) -> Int[Array, ""]:
    """Pool slots some particle references."""
    return jnp.sum(maps.refcount > 0)


def to_dense(spec: PagedGridSpec, maps: PagedMaps, particle: int) -> tuple[np.ndarray, np.ndarray, GridSpec]:
    """Host-side dense copy of one particle's written tiles: its log-odds and field over the
    bounding box of those tiles, and that box's :class:`~jaxslam.grid.GridSpec`. A particle
    that wrote nothing gives one unknown tile at the grid's corner."""
    pages = np.asarray(maps.pages[particle])
    t = spec.tile_size
    rows, cols = np.nonzero(pages >= 0)
    if rows.size == 0:
        rows, cols = np.array([0]), np.array([0])
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    slots = pages[r0:r1, c0:c1]
    logodds_pool, field_pool = np.asarray(maps.logodds), np.asarray(maps.hit_dist2)

    def dense(pool, fill):
        tiles = np.where((slots >= 0)[..., None, None], pool[np.maximum(slots, 0)], np.asarray(fill, pool.dtype))
        return tiles.transpose(0, 2, 1, 3).reshape((r1 - r0) * t, (c1 - c0) * t)

    box = GridSpec(((r1 - r0) * t, (c1 - c0) * t), spec.resolution,
                   (spec.origin[0] + c0 * t * spec.resolution, spec.origin[1] + r0 * t * spec.resolution))
    return dense(logodds_pool, 0.0), dense(field_pool, FAR), box
