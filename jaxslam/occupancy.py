"""Occupancy grid maps: what a map's cells hold, and which cells a scan updates and how.

Every cell of a map holds two values on a :class:`~jaxslam.grid.GridSpec` grid:

* ``logodds`` float16 (:data:`LOGODDS_DTYPE`): the occupancy log-odds of the cell
  (0 = unknown), updated with the binary Bayes filter of :mod:`jaxslam.binary_bayes`.
  Half precision (resolution 0.002 at the default clamp of 4) halves the memory of the maps
  and of every tile copied on write; the filter's weights never read it (they read
  ``hit_dist2``), it is the map a user looks at;
* ``hit_dist2`` uint8: the squared distance, in cells, from the cell to the nearest
  cell that has registered a laser endpoint, truncated at the field radius (:data:`FAR`
  beyond it). It is the likelihood field of the endpoint model
  (:mod:`jaxslam.likelihood_field`), kept up to date by a scatter-min at insertion time
  so that a likelihood evaluation reads one cell per beam (in a paged map three gathers:
  directory, block, tile).

The SLAM filter's maps are paged (:mod:`jaxslam.maps`), not a dense grid per particle:
fixed-size tiles of these two arrays live in one pool shared by all particles, each particle
has a directory into shared blocks of page table that point at the tiles, and a particle that
inserts a scan into a tile or block it shares gets its own copy first (copy on write);
resampling copies directories only. This module holds what the paged maps and a dense map
share: which cells a scan clears and marks (:func:`scan_cells`) and the update of flat cell
storage (:func:`update_cells`, applied to the tile pool and to a dense map's cells alike).
A dense :class:`GridMap` with :func:`insert_scan` is a single map (tests, tools).
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.grid import GridSpec, cell_clip_bound, flat_index
from jaxslam.laser import SensorSpec, laser_rays, valid_returns

LOGODDS_DTYPE = jnp.float16
"""Storage type of the log-odds: a dense map's and the paged maps' tile pool (see the module docstring)."""

FAR = 255
"""Value of ``hit_dist2`` for a cell with no endpoint within the field radius."""


class GridMap(NamedTuple):
    """One occupancy grid map (or a stack of them along leading axes)."""

    logodds: Float[Array, "... H W"]
    """Occupancy log-odds per cell (0 = unknown, > 0 occupied), float16."""
    hit_dist2: UInt8[Array, "... H W"]
    """Squared distance in cells to the nearest registered endpoint, ``FAR`` beyond the field radius."""


def empty_map(spec: GridSpec) -> GridMap:
    """An all-unknown map with no registered endpoints."""
    return GridMap(jnp.zeros(spec.shape, LOGODDS_DTYPE), jnp.full(spec.shape, FAR, jnp.uint8))


class InsertionParams(NamedTuple):
    """Traced numbers of scan insertion (a view of the filter's ``Params``)."""

    logodds_occupied: Float[Array, ""]
    """Log-odds added to the endpoint cell of a returned beam."""
    logodds_free: Float[Array, ""]
    """Log-odds added (negative) to each cell a beam passes through."""
    logodds_min: Float[Array, ""]
    """Lower clamp of a cell's log-odds (keeps maps able to change)."""
    logodds_max: Float[Array, ""]
    """Upper clamp of a cell's log-odds."""
    no_return_free_range: Float[Array, ""]
    """Metres of free space cleared along a "no return" beam (range >= range_max)."""


def field_kernel(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (K, 2) (row, col) within ``radius`` cells and their squared lengths (K,) uint8:
    where an endpoint registers itself in the likelihood field."""
    r = np.arange(-radius, radius + 1)
    dr, dc = np.meshgrid(r, r, indexing="ij")
    d2 = dr**2 + dc**2
    keep = d2 <= radius**2
    return np.stack([dr[keep], dc[keep]], axis=-1).astype(np.int32), np.minimum(d2[keep], FAR).astype(np.uint8)


class ScanRays(NamedTuple):
    """One scan's beams as the insertion traces them (``B`` beams); every sample's cell follows
    from these (:func:`sample_floors`), so a caller can compute the samples it needs only."""

    origin: Float[Array, "2"]
    """The laser's world position (m)."""
    direction: Float[Array, "B 2"]
    """Each beam's unit direction in the world."""
    free_len: Float[Array, "B"]
    """Metres along each beam whose cells are cleared (0 for a beam below range_min)."""
    end_floor: Float[Array, "B 2"]
    """Each beam's endpoint as floored (x, y) cell coordinates, unclipped floats."""
    returned: Bool[Array, "B"]
    """Beams whose endpoint marks its cell occupied and registers in the field."""


def samples_per_beam(spec: GridSpec, max_insert_range: float) -> int:
    """Samples traced along every beam: one per cell length up to ``max_insert_range`` (static)."""
    return int(math.ceil(max_insert_range / spec.resolution)) + 1


def free_lengths(ranges: Float[Array, "B"], sensor: SensorSpec, params: InsertionParams,
                 max_insert_range: float) -> Float[Array, "B"]:
    """Metres along each beam whose cells a scan clears (the same at every pose): up to the
    endpoint, or ``no_return_free_range`` (never past range_max) for a "no return" beam; none
    for a beam below range_min."""
    no_return = ranges >= sensor.range_max
    no_return_len = jnp.minimum(jnp.minimum(params.no_return_free_range, sensor.range_max), max_insert_range)
    free_len = jnp.where(no_return, no_return_len, jnp.minimum(ranges, max_insert_range))
    return jnp.where((ranges < sensor.range_min) & ~no_return, 0.0, free_len)


def scan_rays(
    spec: GridSpec,
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: InsertionParams,
    max_insert_range: float,
) -> ScanRays:
    """The beams of one scan taken at robot ``pose``: where they start, where they point, how far
    they clear and which of them mark their endpoint (see :func:`scan_cells`)."""
    origin, angle = laser_rays(pose, sensor)
    returned = valid_returns(ranges, sensor) & (ranges < max_insert_range)
    direction = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)  # (B, 2)
    end_points = origin + ranges[:, None] * direction  # (B, 2)
    corner = jnp.asarray(spec.origin, jnp.float32)
    free_len = free_lengths(ranges, sensor, params, max_insert_range)
    return ScanRays(origin, direction, free_len, jnp.floor((end_points - corner) / spec.resolution), returned)


def sample_distances(spec: GridSpec, sample: Int[Array, "..."]) -> Float[Array, "..."]:
    """Metres from the laser to sample ``sample`` of a beam (one sample per cell length)."""
    return sample.astype(jnp.float32) * spec.resolution


def sample_floors(spec: GridSpec, rays: ScanRays, beam: Int[Array, "..."], sample: Int[Array, "..."]
                  ) -> Float[Array, "... 2"]:
    """Floored (x, y) cell coordinates, as unclipped floats, of sample ``sample`` of beam
    ``beam`` (broadcast together). Floats, so that the duplicate and endpoint tests do not merge
    distinct cells far outside the grid (the int cells are clipped there)."""
    points = rays.origin + sample_distances(spec, sample)[..., None] * rays.direction[beam]
    return jnp.floor((points - jnp.asarray(spec.origin, jnp.float32)) / spec.resolution)


def cleared_samples(spec: GridSpec, free_len: Float[Array, "B"], num_samples: int) -> Int[Array, "B"]:
    """How many of each beam's first samples lie before its free length ``free_len`` (m): those,
    and only those, may clear their cell (a prefix of the beam: the distances grow with the
    sample)."""
    dist = sample_distances(spec, jnp.arange(num_samples))
    return jnp.sum(dist[None, :] < free_len[:, None], axis=1).astype(jnp.int32)


def clears_cell(rays: ScanRays, beam: Int[Array, "..."], floors: Float[Array, "... 2"],
                previous_floors: Float[Array, "... 2"], first: Bool[Array, "..."]) -> Bool[Array, "..."]:
    """Whether a sample before its beam's free length clears its cell: it is the beam's first
    sample in that cell (``first``: the beam's first sample; ``previous_floors``: the sample
    before's cell) and not a returned beam's endpoint cell."""
    same_as_prev = ~first & jnp.all(floors == previous_floors, axis=-1)
    is_end = jnp.all(floors == rays.end_floor[beam], axis=-1) & rays.returned[beam]
    return ~same_as_prev & ~is_end


class ScanCells(NamedTuple):
    """The cells one scan updates, as (row, col) cells of a grid (they may lie outside it)."""

    free_cells: Int[Array, "B S 2"]
    """The cell of every sample along every beam (one sample per cell length)."""
    free: Bool[Array, "B S"]
    """Samples that clear their cell: before the beam's end, each cell once per beam."""
    end_cells: Int[Array, "B 2"]
    """The endpoint cell of every beam."""
    returned: Bool[Array, "B"]
    """Beams whose endpoint marks its cell occupied and registers in the field."""


def scan_cells(
    spec: GridSpec,
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: InsertionParams,
    max_insert_range: float,
) -> ScanCells:
    """Which cells of ``spec``'s grid one scan taken at robot ``pose`` clears and marks.

    Every cell a beam crosses before its endpoint is cleared once per beam; the endpoint cell
    of a returned beam (range_min <= r < min(range_max, max_insert_range)) is marked. A "no
    return" beam (r >= range_max) clears free space up to ``no_return_free_range``, but never
    past range_max (the laser says nothing of the space beyond its reach), and marks nothing.
    Beams are traced up to ``max_insert_range`` metres (static: it sets the number of samples
    per beam, one per cell, :func:`samples_per_beam`). Every sample of every beam: the paged
    maps compute the samples before each beam's free length only (the same cells, from the same
    :func:`sample_floors`).
    """
    rays = scan_rays(spec, pose, ranges, sensor, params, max_insert_range)
    num_samples = samples_per_beam(spec, max_insert_range)
    beam, sample = jnp.arange(ranges.shape[0])[:, None], jnp.arange(num_samples)[None, :]
    sample_xy = sample_floors(spec, rays, beam, sample)  # (B, S, 2)
    previous_xy = jnp.concatenate([sample_xy[:, :1], sample_xy[:, :-1]], axis=1)
    free = ((sample < cleared_samples(spec, rays.free_len, num_samples)[:, None])
            & clears_cell(rays, beam, sample_xy, previous_xy, sample == 0))  # (B, S)
    return ScanCells(floored_to_cells(spec, sample_xy), free, floored_to_cells(spec, rays.end_floor), rays.returned)


def floored_to_cells(spec: GridSpec, xy: Float[Array, "... 2"]) -> Int[Array, "... 2"]:
    """Floored float (x, y) cell coordinates as int32 (row, col), clipped as ``world_to_cell`` clips."""
    big = cell_clip_bound(spec)
    return jnp.clip(xy[..., ::-1], -big, big).astype(jnp.int32)


def _flat_index(index):
    """An index of cell storage, flattened: one array of flat indices, or (for a pool of tiles
    too large for one int32 index, ``jaxslam.maps.FLAT_INDEX_CELLS``) a tuple of per-axis arrays."""
    return tuple(i.reshape(-1) for i in index) if isinstance(index, tuple) else index.reshape(-1)


def clear_cells(logodds: Float[Array, "M"], free_idx: Int[Array, "..."], params: InsertionParams
                ) -> Float[Array, "M"]:
    """``logodds_free`` added to flat cells ``free_idx`` (once per entry), clamped below at
    ``logodds_min``; an index equal to the storage size (M) changes nothing. (Here and in
    :func:`mark_cells` and :func:`splat_field` an index may also be a tuple of per-axis arrays
    into storage of more axes.)"""
    free_idx, dtype = _flat_index(free_idx), logodds.dtype
    logodds = logodds.at[free_idx].add(params.logodds_free.astype(dtype), mode="drop")
    return logodds.at[free_idx].max(params.logodds_min.astype(dtype), mode="drop")


def mark_cells(logodds: Float[Array, "M"], end_idx: Int[Array, "..."], params: InsertionParams
               ) -> Float[Array, "M"]:
    """``logodds_occupied`` added to flat cells ``end_idx``, clamped above at ``logodds_max``."""
    end_idx, dtype = _flat_index(end_idx), logodds.dtype
    logodds = logodds.at[end_idx].add(params.logodds_occupied.astype(dtype), mode="drop")
    return logodds.at[end_idx].min(params.logodds_max.astype(dtype), mode="drop")


def splat_field(hit_dist2: UInt8[Array, "M"], splat_idx: Int[Array, "... K"], splat_d2: UInt8[Array, "K"]
                ) -> UInt8[Array, "M"]:
    """Flat cells ``splat_idx[..., k]`` take the min of their field and ``splat_d2[k]``."""
    shape = (splat_idx[0] if isinstance(splat_idx, tuple) else splat_idx).shape
    splat_d2 = jnp.broadcast_to(jnp.asarray(splat_d2), shape)
    return hit_dist2.at[_flat_index(splat_idx)].min(splat_d2.reshape(-1), mode="drop")


def update_cells(
    logodds: Float[Array, "M"],
    hit_dist2: UInt8[Array, "M"],
    free_idx: Int[Array, "..."],
    end_idx: Int[Array, "..."],
    splat_idx: Int[Array, "... K"],
    splat_d2: UInt8[Array, "K"],
    params: InsertionParams,
) -> tuple[Float[Array, "M"], UInt8[Array, "M"]]:
    """Apply scans' updates to flat cell storage (a dense map's cells, or a pool of tiles), in
    this order: :func:`clear_cells` ``free_idx``, :func:`mark_cells` ``end_idx``,
    :func:`splat_field` ``splat_idx``. An index equal to the storage size (M) updates nothing
    (the scatters skip it without touching memory). The static-state binary Bayes update in
    log-odds (an addition, see :mod:`jaxslam.binary_bayes`), then the clamp as scatter-max /
    scatter-min on the touched cells: free cells only decrease and endpoint cells only
    increase, so each needs one bound. The paged maps apply the same three in the same order,
    the cleared cells a chunk at a time: the same values, since a cell the lower bound clamps
    after one chunk is clamped to it again after the next (a clear only lowers a cell).
    """
    logodds = mark_cells(clear_cells(logodds, free_idx, params), end_idx, params)
    return logodds, splat_field(hit_dist2, splat_idx, splat_d2)


def insert_scan(
    spec: GridSpec,
    grid_map: GridMap,
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: InsertionParams,
    max_insert_range: float,
    field_radius: int,
) -> tuple[GridMap, Int[Array, ""]]:
    """Insert one scan taken at robot ``pose`` into one dense map (see :func:`scan_cells` for
    which cells change, :func:`update_cells` for how). The likelihood field registers every
    endpoint ever inserted (a scatter-min of the squared cell distances within
    ``field_radius`` cells of each endpoint).

    The filters keep their maps paged (:mod:`jaxslam.maps`, which applies the same
    updates to the same cells); a dense map is for a single map (tests, tools).

    Returns the new map and the number of beam samples (free or endpoint) that fell outside
    the map and were dropped.
    """
    cells = scan_cells(spec, pose, ranges, sensor, params, max_insert_range)
    free_cell_idx = flat_index(spec, cells.free_cells)
    end_cell_idx = flat_index(spec, cells.end_cells)
    outside = (jnp.sum(cells.free & (free_cell_idx == spec.num_cells))
               + jnp.sum(cells.returned & (end_cell_idx == spec.num_cells)))
    offsets, d2 = field_kernel(field_radius)
    splat_idx = flat_index(spec, cells.end_cells[:, None, :] + jnp.asarray(offsets)[None])
    logodds, hit_dist2 = update_cells(
        grid_map.logodds.reshape(-1), grid_map.hit_dist2.reshape(-1),
        jnp.where(cells.free, free_cell_idx, spec.num_cells),
        jnp.where(cells.returned, end_cell_idx, spec.num_cells),
        jnp.where(cells.returned[:, None], splat_idx, spec.num_cells), d2, params)
    return GridMap(logodds.reshape(spec.shape), hit_dist2.reshape(spec.shape)), outside


@partial(jax.jit, static_argnames=("spec", "max_insert_range", "field_radius"))
def _insert_scans(poses, ranges, sensor, params, spec: GridSpec, max_insert_range: float, field_radius: int) -> GridMap:
    def body(grid_map, xs):
        grid_map, _ = insert_scan(spec, grid_map, xs[0], xs[1], sensor, params, max_insert_range, field_radius)
        return grid_map, None

    grid_map, _ = jax.lax.scan(body, empty_map(spec), (poses, ranges))
    return grid_map


def map_from_scans(
    poses: Float[np.ndarray, "S 3"],
    ranges: Float[np.ndarray, "S B"],
    sensor: SensorSpec,
    params: InsertionParams,
    resolution: float,
    max_insert_range: float,
    field_radius: int,
) -> tuple[GridMap, GridSpec]:
    """One dense map of scans at known poses: each inserted in turn with :func:`insert_scan`
    (one compiled ``lax.scan``) into a grid of ``resolution`` (m) that covers every pose plus
    ``max_insert_range`` and a metre. Returns ``(map, grid)``, the grid in the poses' frame
    (metres, radians). This is how a map is drawn again at optimised or refined poses
    (:func:`jaxslam.graph.draw_map`, :func:`jaxslam.refine.refine_in_rounds`)."""
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3 or poses.shape[0] == 0 or np.shape(ranges)[0] != poses.shape[0]:
        raise ValueError(f"map_from_scans: poses {poses.shape} and ranges {np.shape(ranges)} do not match")
    reach = max_insert_range + 1.0
    lo = np.floor((poses[:, :2].min(axis=0) - reach) / resolution) * resolution
    hi = poses[:, :2].max(axis=0) + reach
    spec = GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], resolution)
    grid_map = _insert_scans(jnp.asarray(poses, jnp.float32), jnp.asarray(ranges), sensor, params, spec,
                             float(max_insert_range), int(field_radius))
    return grid_map, spec
