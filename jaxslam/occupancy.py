"""Occupancy grid maps: what each particle carries, and how a scan enters it.

A map is a pair of (H, W) arrays per particle (stacked (N, H, W) in a filter) on a
:class:`~jaxslam.grid.GridSpec`:

* ``logodds`` float16 (:data:`LOGODDS_DTYPE`): the occupancy log-odds of each cell
  (0 = unknown), updated with the binary Bayes filter of :mod:`jaxslam.binary_bayes`.
  Half precision (resolution 0.002 at the default clamp of 4) because maps are copied
  at every resampling and the copies are memory-bound; the filter's weights never read
  it (they read ``hit_dist2``), it is the map a user looks at;
* ``hit_dist2`` uint8: the squared distance, in cells, from each cell to the nearest
  cell that has registered a laser endpoint, truncated at the field radius (:data:`FAR`
  beyond it). It is the likelihood field of the endpoint model
  (:mod:`jaxslam.likelihood_field`), kept up to date by a scatter-min at insertion time
  so that a likelihood evaluation is one lookup per beam.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, UInt8

from jaxslam.grid import GridSpec, flat_index, flat_index_of_floored, world_to_cell
from jaxslam.laser import SensorSpec, laser_rays

LOGODDS_DTYPE = jnp.float16
"""Storage type of the per-particle log-odds maps (see the module docstring)."""

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
    sensor: SensorSpec,
    params: InsertionParams,
    max_insert_range: float,
    field_radius: int,
    window_offset: Int[Array, "2"] | None = None,
) -> tuple[GridMap, Int[Array, ""]]:
    """Insert one scan taken at robot ``pose`` into one map.

    Every cell a beam crosses before its endpoint gets ``logodds_free`` once per beam;
    the endpoint cell of a returned beam (range_min <= r < min(range_max, max_insert_range))
    gets ``logodds_occupied`` and registers an endpoint in the likelihood field. A "no
    return" beam (r >= range_max) clears free space up to ``no_return_free_range``, but never
    past range_max (the laser says nothing of the space beyond its reach), and marks nothing
    occupied. Beams are traced up to ``max_insert_range`` metres (static:
    it sets the number of samples per beam, one per cell).

    The likelihood field registers every endpoint ever inserted (a scatter-min of the
    squared cell distances within ``field_radius`` cells of each endpoint).

    ``window_offset`` (row, col), traced: ``grid_map`` is a window of ``spec``'s grid whose cell
    (0, 0) is the grid's cell ``window_offset`` (its shape is the arrays'); cells are still
    computed in ``spec``'s frame, so a window gets exactly the updates the whole grid would
    (:mod:`jaxslam.paged_map` inserts into windows of its tiles). None: the map is the grid.

    Returns the new map and the number of beam samples (free or endpoint) that fell
    outside the map (or the window) and were dropped.
    """
    res = spec.resolution
    num_samples = int(math.ceil(max_insert_range / res)) + 1
    origin, angle = laser_rays(pose, sensor)
    no_return = ranges >= sensor.range_max
    returned = (~no_return) & (ranges >= sensor.range_min) & (ranges < max_insert_range)
    no_return_len = jnp.minimum(jnp.minimum(params.no_return_free_range, sensor.range_max), max_insert_range)
    free_len = jnp.where(no_return, no_return_len,
                         jnp.minimum(ranges, max_insert_range))
    free_len = jnp.where((ranges < sensor.range_min) & ~no_return, 0.0, free_len)
    direction = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)  # (B, 2)

    dist = jnp.arange(num_samples, dtype=jnp.float32) * res  # (S,)
    points = origin + dist[None, :, None] * direction[:, None, :]  # (B, S, 2)
    end_points = origin + ranges[:, None] * direction  # (B, 2)
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

    target = spec  # the array's grid: the whole grid, or a window of it
    if window_offset is not None:
        target = GridSpec(grid_map.logodds.shape, res, spec.origin)
        offset_xy = jnp.stack([window_offset[1], window_offset[0]]).astype(jnp.float32)  # (col, row)
        sample_cells = sample_cells - offset_xy  # exact: integer-valued floats below 2^24
        end_cells_f = end_cells_f - offset_xy
    free_cell_idx = flat_index_of_floored(target, sample_cells)
    end_cell_idx = flat_index_of_floored(target, end_cells_f)
    outside = (jnp.sum(free & (free_cell_idx == target.num_cells))
               + jnp.sum(returned & (end_cell_idx == target.num_cells)))
    # Samples that update nothing get the out-of-map index, so the scatters skip them
    # without touching memory (most of a short beam's samples lie past its end).
    free_idx = jnp.where(free, free_cell_idx, target.num_cells).reshape(-1)
    end_idx = jnp.where(returned, end_cell_idx, target.num_cells)

    # The static-state binary Bayes update in log-odds (an addition, see binary_bayes), then
    # the clamp as scatter-max / scatter-min on the touched cells: free cells only decrease
    # and endpoint cells only increase, so each needs one bound. All in place, O(B x S).
    dtype = grid_map.logodds.dtype
    flat = grid_map.logodds.reshape(-1)
    flat = flat.at[free_idx].add(params.logodds_free.astype(dtype), mode="drop")
    flat = flat.at[free_idx].max(params.logodds_min.astype(dtype), mode="drop")
    flat = flat.at[end_idx].add(params.logodds_occupied.astype(dtype), mode="drop")
    flat = flat.at[end_idx].min(params.logodds_max.astype(dtype), mode="drop")
    logodds = flat.reshape(target.shape)

    offsets, d2 = _field_kernel(field_radius)
    end_cells = world_to_cell(spec, end_points)
    if window_offset is not None:
        end_cells = end_cells - window_offset.astype(jnp.int32)
    splat_cells = end_cells[:, None, :] + jnp.asarray(offsets)[None]  # (B, K, 2)
    splat_idx = jnp.where(returned[:, None], flat_index(target, splat_cells), target.num_cells)
    hit_dist2 = grid_map.hit_dist2.reshape(-1).at[splat_idx.reshape(-1)].min(
        jnp.broadcast_to(jnp.asarray(d2), splat_idx.shape).reshape(-1), mode="drop"
    )
    return GridMap(logodds, hit_dist2.reshape(target.shape)), outside

