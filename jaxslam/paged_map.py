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
(:func:`insert_scans`) first makes every tile the scan touches the writer's own (a tile only
it uses is written in place; a shared tile is copied into a free slot, an unwritten one gets
a fresh slot), then scatters the scan's updates into the pool: the same cells get the same
updates as in a dense grid (:func:`jaxslam.occupancy.update_cells`), and the work is the
dense insertion's plus the copied tiles. Slots that no page table references any more are
free again at once.

Everything has a static shape and no sequential loop over particles: the free slots are
handed out by a prefix sum over the particles' requests. The pool's capacity C and the most
tiles one insertion may create or copy (M) are static; an insertion that needs more writes
nothing (all or nothing) and sets ``overflow``, and the host grows the pool (:func:`grow`) and
repeats it: never a silent overwrite.
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
from jaxslam.occupancy import FAR, LOGODDS_DTYPE, InsertionParams, field_kernel, scan_cells, update_cells

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
        if self.tile_size & (self.tile_size - 1):
            raise ValueError(f"PagedGridSpec: tile_size must be a power of two (cells are split into tile and "
                             f"place by shifts and masks), got {self.tile_size}")
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
    def tile_shift(self) -> int:
        """log2 of the tile size: a cell's tile is ``cell >> tile_shift``, its place ``cell & (T - 1)``
        (exact floor division for negative cells too, and cheaper than ``//`` and ``%`` on ints)."""
        return self.tile_size.bit_length() - 1

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
    holders: Bool[Array, "C N"]
    """``holders[s, n]``: particle n's page table points at slot s. Resampling recounts the
    references from it (C x N work) instead of from the page tables (N x TY x TX)."""
    free_slots: Int[Array, "M"]
    """The first M free slots (C where fewer are free), refreshed after every insertion and
    resampling. M, static, is the most tiles one insertion may create or copy, all particles
    together."""
    overflow: Bool[Array, ""]
    """The last insertion wanted more new tiles than M or than the pool had free, and wrote
    nothing. The host grows the pool (:func:`grow`) and repeats it."""
    peak_request: Int[Array, ""]
    """The most new tiles one insertion asked for (to size M)."""

    @property
    def capacity(self) -> int:
        """C, the pool's slots."""
        return self.refcount.shape[0]

    @property
    def max_new_tiles(self) -> int:
        """M, the most tiles one insertion may create or copy."""
        return self.free_slots.shape[0]


def _free_slots(refcount: Int[Array, "C"], max_new_tiles: int) -> Int[Array, "M"]:
    capacity = refcount.shape[0]
    return jnp.nonzero(refcount == 0, size=max_new_tiles, fill_value=capacity)[0].astype(jnp.int32)


def _check_pool(spec: PagedGridSpec, capacity: int, max_new_tiles: int) -> None:
    if capacity < 1 or max_new_tiles < 1:
        raise ValueError(f"a paged map's pool needs capacity >= 1 and max_new_tiles >= 1, got {capacity}, "
                         f"{max_new_tiles}")
    if capacity * spec.tile_size**2 >= 2**31:
        raise ValueError(f"a pool of {capacity} tiles of {spec.tile_size} x {spec.tile_size} cells exceeds int32 "
                         "indexing; use fewer particles or a larger resolution")


def empty(spec: PagedGridSpec, num_particles: int, capacity: int, max_new_tiles: int | None = None) -> PagedMaps:
    """N empty maps and a pool of ``capacity`` free tiles; an insertion may create or copy at
    most ``max_new_tiles`` tiles (default and cap: ``capacity``)."""
    m = capacity if max_new_tiles is None else min(int(max_new_tiles), capacity)
    _check_pool(spec, capacity, m)
    t = spec.tile_size
    refcount = jnp.zeros((capacity,), jnp.int32)
    return PagedMaps(
        pages=jnp.full((num_particles,) + spec.num_tiles, UNWRITTEN, jnp.int32),
        logodds=jnp.zeros((capacity, t, t), LOGODDS_DTYPE),
        hit_dist2=jnp.full((capacity, t, t), FAR, jnp.uint8),
        refcount=refcount,
        holders=jnp.zeros((capacity, num_particles), bool),
        free_slots=_free_slots(refcount, m),
        overflow=jnp.bool_(False),
        peak_request=jnp.int32(0),
    )


class PagedField(NamedTuple):
    """One particle's likelihood field (or log-odds) as the likelihood model reads it: its page
    table and the shared pool (vmap over particles with ``in_axes=PagedField(0, None)``)."""

    pages: Int[Array, "TY TX"]
    """The particle's page table."""
    pool: Array
    """(C, T, T) the pool's tiles of that quantity."""


def fields(maps: PagedMaps) -> PagedField:
    """Every particle's likelihood field (pages (N, TY, TX), the shared pool): vmap over it with
    ``in_axes=PagedField(0, None)``."""
    return PagedField(maps.pages, maps.hit_dist2)


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
    shift, mask = spec.tile_shift, t - 1
    slot = pages[row >> shift, col >> shift]
    value = pool[jnp.maximum(slot, 0), row & mask, col & mask]
    return jnp.where(inside & (slot >= 0), value, jnp.asarray(fill, pool.dtype))


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
    """
    shapes = jax.eval_shape(fn, first, *rest)
    init = jax.tree.map(lambda shape: jnp.zeros(shape.shape, shape.dtype), shapes)
    probe = first.reshape(-1)[0].astype(jnp.float32)
    trips = 1 + (probe > jnp.finfo(jnp.float32).max).astype(jnp.int32)
    _, out = jax.lax.while_loop(lambda c: c[0] < trips, lambda c: (c[0] + 1, fn(first, *rest)),
                                (jnp.int32(0), init))
    return out


def insert_scans(
    spec: PagedGridSpec,
    maps: PagedMaps,
    poses: Float[Array, "N 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: InsertionParams,
    max_insert_range: float,
    field_radius: int,
) -> tuple[PagedMaps, Int[Array, "N"]]:
    """Insert one scan into every particle's map, particle n's taken at ``poses[n]``.

    The same cells get the same updates as in a dense grid (:func:`jaxslam.occupancy.scan_cells`,
    :func:`jaxslam.occupancy.update_cells`). First every tile a particle's scan touches is made
    its own: a tile it alone uses is written in place; a shared or unwritten one gets a free
    slot (a copy of the shared tile, or a fresh one), handed out by a prefix sum over all
    particles' requests, at most ``maps.max_new_tiles`` in all. Then all particles' samples are
    scattered into the pool at once (no two particles write the same slot). All or nothing: an
    insertion whose requests do not fit writes nothing and sets ``overflow``; the maps are
    unchanged, so the caller can grow the pool (:func:`grow`) and insert again.

    Returns the new maps and, per particle, the beam samples that fell outside the virtual grid.
    """
    t = spec.tile_size
    k = spec.window_tiles(max_insert_range, field_radius)
    kk = k * k
    capacity, m = maps.capacity, maps.max_new_tiles
    n = poses.shape[0]
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
    slots = jax.vmap(lambda p, s: jax.lax.dynamic_slice(p, (s[0], s[1]), (k, k)))(maps.pages, starts).reshape(-1)
    owned = (slots >= 0) & (maps.refcount[jnp.maximum(slots, 0)] == 1)
    need = touched.reshape(-1) & ~owned  # (N K K,)

    # The j-th request (in particle order) gets free_slots[j]: a copy of its old tile, or a fresh
    # one. All or nothing: an insertion that needs more new tiles than it may take (M) or than
    # are free writes nothing at all and sets ``overflow``, so the maps stay as they were.
    rank = jnp.cumsum(need) - 1
    num_requests = jnp.sum(need).astype(jnp.int32)
    fits = (num_requests <= m) & (maps.free_slots[jnp.clip(num_requests - 1, 0, m - 1)] < capacity)
    fits = fits | (num_requests == 0)
    granted = jnp.where(need & fits, maps.free_slots[jnp.clip(rank, 0, m - 1)], capacity)
    placed = need & fits
    requests = jnp.nonzero(need & fits, size=m, fill_value=n * kk)[0]
    source = jnp.concatenate([slots, jnp.full((1,), UNWRITTEN, slots.dtype)])[requests]
    target = jnp.where(requests < n * kk, maps.free_slots, capacity)
    logodds = maps.logodds.at[target].set(_tile_values(maps.logodds, source, 0.0), mode="drop")
    hit_dist2 = maps.hit_dist2.at[target].set(_tile_values(maps.hit_dist2, source, FAR), mode="drop")

    particle = jnp.repeat(jnp.arange(n), kk)
    released = jnp.where(placed & (slots >= 0), slots, capacity)
    taken = jnp.where(placed, granted, capacity)
    refcount = maps.refcount.at[released].add(-1, mode="drop").at[taken].add(1, mode="drop")
    holders = maps.holders.at[released, particle].set(False, mode="drop").at[taken, particle].set(True, mode="drop")
    new_slots = jnp.where(placed, granted, slots).astype(jnp.int32)
    pages = jax.vmap(lambda p, s, start: jax.lax.dynamic_update_slice(p, s, (start[0], start[1])))(
        maps.pages, new_slots.reshape(n, k, k), starts)

    # Pool index of every updated cell: the slot of its tile (the particle's own, after the
    # copies above), or the pool's size (dropped) where its tile got no slot.
    writable_slot = jnp.where((owned & fits) | placed, new_slots, capacity).reshape(n, kk)
    writable_slot = jnp.concatenate([writable_slot, jnp.full((n, 1), capacity, jnp.int32)], axis=1).reshape(-1)

    def pool_index(tile, place):
        slot = writable_slot[tile]
        return jnp.where(slot < capacity, slot * (t * t) + place, capacity * t * t)

    flat_logodds, flat_field = update_cells(
        logodds.reshape(-1), hit_dist2.reshape(-1), pool_index(free_tile, free_within),
        pool_index(end_tile, end_within), pool_index(splat_tile, splat_within), d2, params)
    new_maps = PagedMaps(
        pages=pages,
        logodds=flat_logodds.reshape(logodds.shape),
        hit_dist2=flat_field.reshape(hit_dist2.shape),
        refcount=refcount,
        holders=holders,
        free_slots=_free_slots(refcount, m),
        overflow=~fits,
        peak_request=jnp.maximum(maps.peak_request, num_requests),
    )
    return new_maps, outside.astype(jnp.int32)


def resample(maps: PagedMaps, ancestors: Int[Array, "N2"]) -> PagedMaps:
    """Particle i takes particle ``ancestors[i]``'s map: page tables are copied, tiles shared.
    The reference counts are recounted from ``holders``; a slot nobody uses is free. ``ancestors``
    may have another length than the particles (N1 -> N2: e.g. one initial map to N particles)."""
    holders = maps.holders[:, ancestors]
    refcount = jnp.sum(holders, axis=1, dtype=jnp.int32)
    return maps._replace(pages=maps.pages[ancestors], holders=holders, refcount=refcount,
                         free_slots=_free_slots(refcount, maps.max_new_tiles))


def grow(spec: PagedGridSpec, maps: PagedMaps, capacity: int, max_new_tiles: int) -> PagedMaps:
    """The same maps in a pool of ``capacity`` slots, of which an insertion may take
    ``max_new_tiles`` (host side, between jitted calls; the new slots are free). Clears
    ``overflow``: the caller repeats the work that set it, from maps taken before it."""
    old = maps.capacity
    if capacity < old:
        raise ValueError(f"grow: capacity {capacity} is below the current {old}")
    m = min(int(max_new_tiles), capacity)
    _check_pool(spec, capacity, m)
    extra = capacity - old
    t = maps.logodds.shape[1]
    refcount = jnp.concatenate([maps.refcount, jnp.zeros((extra,), maps.refcount.dtype)])
    return PagedMaps(
        maps.pages,
        jnp.concatenate([maps.logodds, jnp.zeros((extra, t, t), maps.logodds.dtype)]),
        jnp.concatenate([maps.hit_dist2, jnp.full((extra, t, t), FAR, maps.hit_dist2.dtype)]),
        refcount,
        jnp.concatenate([maps.holders, jnp.zeros((extra, maps.holders.shape[1]), bool)]),
        _free_slots(refcount, m),
        jnp.bool_(False),
        maps.peak_request,
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
        # Tile by tile into one array (no gathered copy of the tiles: a campus map has 10^8 cells).
        out = np.full(((r1 - r0) * t, (c1 - c0) * t), fill, pool.dtype)
        for row, col in zip(*np.nonzero(slots >= 0)):
            out[row * t:(row + 1) * t, col * t:(col + 1) * t] = pool[slots[row, col]]
        return out

    box = GridSpec(((r1 - r0) * t, (c1 - c0) * t), spec.resolution,
                   (spec.origin[0] + c0 * t * spec.resolution, spec.origin[1] + r0 * t * spec.resolution))
    return dense(logodds_pool, 0.0), dense(field_pool, FAR), box
