"""Occupancy grids: the static :class:`GridSpec`, world <-> cell maps, scan insertion.

A map is a pair of (H, W) arrays per particle (stacked (N, H, W) in a filter):

* ``logodds`` float16 (:data:`LOGODDS_DTYPE`): the occupancy log-odds of each cell
  (0 = unknown), updated with the binary Bayes filter of :mod:`jaxslam.binary_bayes`.
  Half precision (resolution 0.002 at the default clamp of 4) because maps are copied
  at every resampling and the copies are memory-bound; the filter's weights never read
  it (they read ``hit_dist2``), it is the map a user looks at;
* ``hit_dist2`` uint8: the squared distance, in cells, from each cell to the
  nearest cell that has registered a laser endpoint, truncated at the field
  radius (:data:`FAR` beyond it). It is the likelihood field of the endpoint
  model (:mod:`jaxslam.sensor`), kept up to date by a scatter-min at insertion
  time so that a likelihood evaluation is one lookup per beam.

Row ``i`` of a map is ``y = origin_y + (i + 0.5) * resolution`` and column ``j``
is ``x = origin_x + (j + 0.5) * resolution``: ``origin`` is the lower-left corner
of cell (0, 0), as in a ROS map_server YAML file (whose image rows run top-down).
Points outside the map are never wrapped: they are dropped and counted.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxslam.geometry import compose

if TYPE_CHECKING:
    from jaxslam.sensor import SensorSpec

LOGODDS_DTYPE = jnp.float16
"""Storage type of the per-particle log-odds maps (see the module docstring)."""

FAR = 255
"""Value of ``hit_dist2`` for a cell with no endpoint within the field radius."""

LIKELIHOOD_FIELDS = ("endpoints", "occupied")
"""What ``hit_dist2`` measures distances to (see :func:`insert_scan`)."""


@dataclasses.dataclass(frozen=True)
class GridSpec:
    """Shape and placement of a grid map. Static (hashable): changing it recompiles."""

    shape: tuple[int, int]
    """(height, width) in cells: rows along y, columns along x."""
    resolution: float
    """Cell side in metres."""
    origin: tuple[float, float]
    """World (x, y) in metres of the lower-left corner of cell (0, 0)."""

    def __post_init__(self):
        h, w = self.shape
        if h <= 0 or w <= 0 or not self.resolution > 0:
            raise ValueError(f"GridSpec needs a positive shape and resolution, got {self}")
        object.__setattr__(self, "shape", (int(h), int(w)))
        object.__setattr__(self, "resolution", float(self.resolution))
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))

    @classmethod
    def from_bounds(cls, xmin: float, ymin: float, xmax: float, ymax: float, resolution: float) -> "GridSpec":
        """The smallest grid at ``resolution`` covering the rectangle (m)."""
        w = int(math.ceil((xmax - xmin) / resolution))
        h = int(math.ceil((ymax - ymin) / resolution))
        return cls((max(h, 1), max(w, 1)), resolution, (xmin, ymin))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) in metres, as matplotlib's ``imshow(extent=...)`` takes it."""
        x0, y0 = self.origin
        h, w = self.shape
        return (x0, x0 + w * self.resolution, y0, y0 + h * self.resolution)

    @property
    def num_cells(self) -> int:
        return self.shape[0] * self.shape[1]


def cell_clip_bound(spec: GridSpec) -> int:
    """Cell coordinates are clipped to +-this before an int cast, so that far-away points
    cannot overflow; every clipped cell still lies outside the map."""
    return 4 * max(spec.shape) + 4


def world_to_cell(spec: GridSpec, xy: Float[Array, "... 2"]) -> Int[Array, "... 2"]:
    """(row, col) int32 of the cells containing world points (m). May lie outside the map."""
    col = jnp.floor((xy[..., 0] - spec.origin[0]) / spec.resolution)
    row = jnp.floor((xy[..., 1] - spec.origin[1]) / spec.resolution)
    big = cell_clip_bound(spec)
    return jnp.stack([jnp.clip(row, -big, big), jnp.clip(col, -big, big)], axis=-1).astype(jnp.int32)


def cell_to_world(spec: GridSpec, cell: Int[Array, "... 2"]) -> Float[Array, "... 2"]:
    """World (x, y) in metres of the centres of cells given as (row, col)."""
    x = spec.origin[0] + (cell[..., 1] + 0.5) * spec.resolution
    y = spec.origin[1] + (cell[..., 0] + 0.5) * spec.resolution
    return jnp.stack([x, y], axis=-1)


def in_bounds(spec: GridSpec, cell: Int[Array, "... 2"]) -> Bool[Array, "..."]:
    """Whether (row, col) cells lie inside the map."""
    h, w = spec.shape
    return (cell[..., 0] >= 0) & (cell[..., 0] < h) & (cell[..., 1] >= 0) & (cell[..., 1] < w)


def flat_index(spec: GridSpec, cell: Int[Array, "... 2"]) -> Int[Array, "..."]:
    """Row-major flat index of (row, col) cells; out-of-map cells get ``num_cells`` (dropped by scatters)."""
    idx = cell[..., 0] * spec.shape[1] + cell[..., 1]
    return jnp.where(in_bounds(spec, cell), idx, spec.num_cells)


def _flat_index_of_float_cells(spec: GridSpec, cell_xy: Float[Array, "... 2"]) -> Int[Array, "..."]:
    """Flat index of cells given as floored float (col, row) = (x, y) cell coordinates;
    out-of-map cells get ``num_cells``. Same result as ``flat_index(world_to_cell(...))``
    without computing the cell coordinates twice (the insertion's hot loop)."""
    h, w = spec.shape
    col, row = cell_xy[..., 0], cell_xy[..., 1]
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    # Integer arithmetic on clipped values: float32 row * w + col is inexact past 2^24 cells.
    row_i = jnp.clip(row, 0, h - 1).astype(jnp.int32)
    col_i = jnp.clip(col, 0, w - 1).astype(jnp.int32)
    return jnp.where(inside, row_i * w + col_i, spec.num_cells)


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


def _field_kernel(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (K, 2) within ``radius`` cells and their squared lengths (K,)."""
    r = np.arange(-radius, radius + 1)
    dr, dc = np.meshgrid(r, r, indexing="ij")
    d2 = dr**2 + dc**2
    keep = d2 <= radius**2
    return np.stack([dr[keep], dc[keep]], axis=-1).astype(np.int32), np.minimum(d2[keep], FAR).astype(np.uint8)


def insert_scan(
    spec: GridSpec,
    grid_map: GridMap,
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: "SensorSpec",
    params: InsertionParams,
    max_insert_range: float,
    field_radius: int,
    likelihood_field: str = "endpoints",
) -> tuple[GridMap, Int[Array, ""]]:
    """Insert one scan taken at robot ``pose`` into one map.

    Every cell a beam crosses before its endpoint gets ``logodds_free`` once per beam;
    the endpoint cell of a returned beam (range_min <= r < min(range_max, max_insert_range))
    gets ``logodds_occupied`` and registers an endpoint in the likelihood field. A "no
    return" beam (r >= range_max) clears free space up to ``no_return_free_range``, but never
    past range_max (the laser says nothing of the space beyond its reach), and marks nothing
    occupied. Beams are traced up to ``max_insert_range`` metres (static:
    it sets the number of samples per beam, one per cell).

    ``likelihood_field`` (static) says what the likelihood field measures distances to:
    "endpoints", every endpoint ever registered (a scatter-min, the cheapest); "occupied", the
    cells whose log-odds is now above 0, so an endpoint that later beams see through leaves the
    field (as GMapping's matcher, which skips cells under its occupancy threshold). With
    "endpoints" a particle whose pose drifts keeps its old endpoints and adds the new ones, its
    obstacles thicken, and the drift is never penalised; "occupied" recomputes the field in the
    window the scan can have changed (:func:`refresh_field`).

    Returns the new map and the number of beam samples (free or endpoint) that fell
    outside the map and were dropped.
    """
    if likelihood_field not in LIKELIHOOD_FIELDS:
        raise ValueError(f"likelihood_field must be one of {LIKELIHOOD_FIELDS}, got {likelihood_field!r}")
    res = spec.resolution
    num_samples = int(math.ceil(max_insert_range / res)) + 1
    origin = compose(pose, sensor.laser_pose)
    no_return = ranges >= sensor.range_max
    returned = (~no_return) & (ranges >= sensor.range_min) & (ranges < max_insert_range)
    no_return_len = jnp.minimum(jnp.minimum(params.no_return_free_range, sensor.range_max), max_insert_range)
    free_len = jnp.where(no_return, no_return_len,
                         jnp.minimum(ranges, max_insert_range))
    free_len = jnp.where((ranges < sensor.range_min) & ~no_return, 0.0, free_len)
    angle = origin[2] + sensor.beam_angles
    direction = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)  # (B, 2)

    dist = jnp.arange(num_samples, dtype=jnp.float32) * res  # (S,)
    points = origin[:2] + dist[None, :, None] * direction[:, None, :]  # (B, S, 2)
    end_points = origin[:2] + ranges[:, None] * direction  # (B, 2)
    # Cell coordinates as unclipped floats for the duplicate and endpoint tests (world_to_cell
    # clips far-away points, which would merge distinct cells outside the map).
    corner = jnp.asarray(spec.origin, jnp.float32)
    sample_cells = jnp.floor((points - corner) / res)
    end_cells_f = jnp.floor((end_points - corner) / res)
    same_as_prev = jnp.concatenate(
        [jnp.zeros((sample_cells.shape[0], 1), bool),
         jnp.all(sample_cells[:, 1:] == sample_cells[:, :-1], axis=-1)], axis=1)
    is_end = jnp.all(sample_cells == end_cells_f[:, None, :], axis=-1) & returned[:, None]
    free = (dist[None, :] < free_len[:, None]) & ~same_as_prev & ~is_end  # (B, S)

    free_cell_idx = _flat_index_of_float_cells(spec, sample_cells)
    end_cell_idx = _flat_index_of_float_cells(spec, end_cells_f)
    outside = (jnp.sum(free & (free_cell_idx == spec.num_cells))
               + jnp.sum(returned & (end_cell_idx == spec.num_cells)))
    # Samples that update nothing get the out-of-map index, so the scatters skip them
    # without touching memory (most of a short beam's samples lie past its end).
    free_idx = jnp.where(free, free_cell_idx, spec.num_cells).reshape(-1)
    end_idx = jnp.where(returned, end_cell_idx, spec.num_cells)

    # The static-state binary Bayes update in log-odds (an addition, see binary_bayes), then
    # the clamp as scatter-max / scatter-min on the touched cells: free cells only decrease
    # and endpoint cells only increase, so each needs one bound. All in place, O(B x S).
    dtype = grid_map.logodds.dtype
    flat = grid_map.logodds.reshape(-1)
    flat = flat.at[free_idx].add(params.logodds_free.astype(dtype), mode="drop")
    flat = flat.at[free_idx].max(params.logodds_min.astype(dtype), mode="drop")
    flat = flat.at[end_idx].add(params.logodds_occupied.astype(dtype), mode="drop")
    flat = flat.at[end_idx].min(params.logodds_max.astype(dtype), mode="drop")
    logodds = flat.reshape(spec.shape)

    if likelihood_field == "occupied":
        reach = int(math.ceil(max_insert_range / res)) + 1  # cells this scan can have changed
        center = world_to_cell(spec, origin[:2])
        return GridMap(logodds, refresh_field(logodds, grid_map.hit_dist2, center, reach, field_radius)), outside

    offsets, d2 = _field_kernel(field_radius)
    splat_cells = world_to_cell(spec, end_points)[:, None, :] + jnp.asarray(offsets)[None]  # (B, K, 2)
    splat_idx = jnp.where(returned[:, None], flat_index(spec, splat_cells), spec.num_cells)
    hit_dist2 = grid_map.hit_dist2.reshape(-1).at[splat_idx.reshape(-1)].min(
        jnp.broadcast_to(jnp.asarray(d2), splat_idx.shape).reshape(-1), mode="drop"
    )
    return GridMap(logodds, hit_dist2.reshape(spec.shape)), outside


def occupied_field(occupied: Bool[Array, "h w"], radius: int) -> UInt8[Array, "h w"]:
    """Squared distance (cells) from each cell to the nearest occupied cell, ``FAR`` beyond
    ``radius``: the likelihood field of :func:`insert_scan`'s "occupied" mode, exact.

    Two 1-D passes of 2 * radius + 1 shifts each (the squared Euclidean distance is separable:
    min over rows of dr^2 + min over columns of dc^2), so O(h w radius), not O(h w radius^2).
    Cells outside the array count as unoccupied.
    """
    big = jnp.int32(1 << 20)
    field = jnp.where(occupied, 0, big).astype(jnp.int32)
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (radius, radius)
        padded = jnp.pad(field, pad, constant_values=big)
        n = field.shape[axis]
        field = functools.reduce(jnp.minimum, [
            jax.lax.slice_in_dim(padded, radius + d, radius + d + n, axis=axis) + d * d
            for d in range(-radius, radius + 1)])
    return jnp.where(field <= radius * radius, jnp.minimum(field, FAR), FAR).astype(jnp.uint8)


def refresh_field(
    logodds: Float[Array, "H W"],
    hit_dist2: UInt8[Array, "H W"],
    center: Int[Array, "2"],
    reach: int,
    radius: int,
) -> UInt8[Array, "H W"]:
    """Recompute ``hit_dist2`` from the occupied cells (log-odds > 0) within ``reach`` + ``radius``
    cells (Chebyshev) of ``center`` (row, col); the rest of the field is kept.

    The window is static in size (``reach`` and ``radius`` are static), so this jits to one
    fixed-size slice, two 1-D passes and one write-back. A window that would cross the map's
    edge is moved inside it; the cells within ``radius`` of a window side that is not the
    map's edge are not written (their occupied neighbours may lie outside the window).
    """
    height, width = logodds.shape
    half = reach + 2 * radius
    size_r, size_c = min(2 * half + 1, height), min(2 * half + 1, width)
    start_r = jnp.clip(center[0] - half, 0, height - size_r)
    start_c = jnp.clip(center[1] - half, 0, width - size_c)
    window = jax.lax.dynamic_slice(logodds, (start_r, start_c), (size_r, size_c))
    fresh = occupied_field(window > 0, radius)
    old = jax.lax.dynamic_slice(hit_dist2, (start_r, start_c), (size_r, size_c))

    def inner(start, size, total):  # window cells whose whole field neighbourhood is in view
        i = jnp.arange(size)
        low_ok = (i >= radius) | (start == 0)
        high_ok = (i < size - radius) | (start + size == total)
        return low_ok & high_ok

    keep_fresh = inner(start_r, size_r, height)[:, None] & inner(start_c, size_c, width)[None, :]
    return jax.lax.dynamic_update_slice(hit_dist2, jnp.where(keep_fresh, fresh, old), (start_r, start_c))


def occupancy_probability(logodds: Float[Array, "... H W"]) -> Float[Array, "... H W"]:
    """p(occupied) of each cell from its log-odds."""
    return jax.nn.sigmoid(logodds)
