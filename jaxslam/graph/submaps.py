"""Submaps: small local grids of consecutive scans at the filter's poses, what the loop search
matches scans against (:mod:`jaxslam.graph.loop_search`).

A submap holds ``nodes_per_submap`` consecutive processed scans (fewer or more where the chain's
heading jumps: :func:`submap_ranges`), inserted with the filter's own
insertion (:func:`jaxslam.occupancy.insert_scan`) into a dense grid in the frame of its first
node. Its cells keep what the search reads:

* ``field`` uint8: the squared distance in cells from each cell to the nearest occupied cell
  (log-odds > 0 after all the submap's scans, so that a person walking through is cleared again),
  capped at :data:`jaxslam.occupancy.FAR`: the likelihood field the endpoint model reads;
* ``fit`` uint8: 255 times each cell's per-beam fit ``exp(-d^2 / (2 sigma^2))``, the quantity the
  branch and bound sums, and ``bounds[h]`` for h = 1..levels: at each cell the largest fit over
  the 2^h x 2^h square of cells whose lower corner it is (Hess et al.'s precomputation grids),
  so that one read bounds the fit of a point shifted by any of 2^h x 2^h offsets.

The grids of all submaps share one static shape (the largest submap's footprint), so that the
search vmaps over pairs of any submap; every submap's frame is shifted so that its grid's
lower-left corner is the origin (``corner``).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage

from jaxslam.geometry import between_np, compose_np
from jaxslam.grid import GridSpec
from jaxslam.laser import SensorSpec
from jaxslam.occupancy import FAR, InsertionParams, empty_map, insert_scan


class Submaps(NamedTuple):
    """M submaps on one static grid shape (host arrays unless noted)."""

    first_node: np.ndarray
    """(M,) int: each submap's first node (its frame)."""
    last_node: np.ndarray
    """(M,) int: each submap's last node (inclusive)."""
    corner: np.ndarray
    """(M, 2) float64: the grid's lower-left corner in the submap's frame (m); a pose in the
    submap frame minus this is its pose on the grid (origin (0, 0))."""
    grid: GridSpec
    """The grid every submap uses, origin (0, 0) (static)."""
    field: jax.Array
    """(M, H, W) uint8 squared cell distance to the nearest occupied cell, ``FAR`` beyond."""
    fit: jax.Array
    """(M, H, W) uint8: 255 x the per-beam fit of each cell."""
    bounds: tuple[jax.Array, ...]
    """``levels`` arrays, level h = 1..levels: (M, H, W) uint8 bounds of the fit (see the
    module docstring)."""


def submap_ranges(num_nodes: int, nodes_per_submap: int, cuts=()) -> tuple[np.ndarray, np.ndarray]:
    """First and last node (inclusive) of each submap: consecutive runs of ``nodes_per_submap``
    nodes, the last run possibly shorter, and a submap begun at each node of ``cuts``.

    A cut is a step the chain's heading may have jumped at (:func:`jaxslam.graph.jumps.heading_jumps`):
    a submap across it would hold scans placed in two frames, and a loop into it, measured in its
    first node's frame, would carry the jump (the simulated worlds turned 0.5 rad inside a submap
    kept loops 2-3 m off the truth into it, none where the turn fell on a submap's first node).
    A piece a cut leaves shorter than half a run joins the run on its side of the cut, so a
    submap holds at most about twice ``nodes_per_submap`` nodes; without cuts the runs are as
    before.
    """
    regular = set(range(0, num_nodes, nodes_per_submap))
    cuts = {int(c) for c in cuts if 0 < int(c) < num_nodes}
    starts = sorted(regular | cuts)
    shortest = nodes_per_submap // 2
    k = 1
    while k < len(starts):
        before, after = starts[k - 1], starts[k + 1] if k + 1 < len(starts) else num_nodes
        if starts[k] not in cuts and ((before in cuts and starts[k] - before < shortest)
                                      or (after in cuts and after - starts[k] < shortest)):
            del starts[k]  # the short piece joins the run beside it, on its side of the cut
        else:
            k += 1
    first = np.array(starts, int)
    return first, np.append(first[1:] - 1, num_nodes - 1)


def _fit_table(resolution: float, sigma: float) -> np.ndarray:
    """(256,) uint8: 255 x exp(-d^2 / (2 sigma^2)) for a squared cell distance d2 (FAR: 0)."""
    d2 = np.arange(256, dtype=np.float64)
    fit = np.exp(-0.5 * d2 * resolution**2 / sigma**2)
    fit[FAR] = 0.0
    return np.round(255 * fit).astype(np.uint8)


def square_bounds(fit: np.ndarray, levels: int) -> list[np.ndarray]:
    """The bounds of :class:`Submaps` from (..., H, W) fits: level h holds at cell (r, c) the
    largest fit over cells [r, r + 2^h) x [c, c + 2^h) (0 beyond the grid), built by doubling,
    rows then columns (the fits are at least 0, so a window cut by the grid's edge keeps its
    cells' maximum)."""
    out, current = [], fit
    for level in range(1, levels + 1):
        step = 2 ** (level - 1)
        rows = current.copy()
        np.maximum(rows[..., :-step, :], current[..., step:, :], out=rows[..., :-step, :])
        current = rows.copy()
        np.maximum(current[..., :, :-step], rows[..., :, step:], out=current[..., :, :-step])
        out.append(current)
    return out


@partial(jax.jit, static_argnames=("grid", "max_insert_range", "field_radius"))
def _insert_submaps(poses, ranges, sensor, params: InsertionParams, grid: GridSpec, max_insert_range: float,
                    field_radius: int):
    """Log-odds (m, H, W) of m submaps, each the scans (m, n, B) at grid poses (m, n, 3); a scan of
    ranges 0 (a padded node) inserts nothing."""

    def one(poses_k, ranges_k):
        def body(grid_map, xs):
            pose, scan = xs
            grid_map, _ = insert_scan(grid, grid_map, pose, scan, sensor, params, max_insert_range, field_radius)
            return grid_map, None

        grid_map, _ = jax.lax.scan(body, empty_map(grid), (poses_k, ranges_k))
        return grid_map.logodds

    return jax.vmap(one)(poses, ranges)


def build_submaps(poses: np.ndarray, ranges: np.ndarray, sensor: SensorSpec, insertion: InsertionParams,
                  resolution: float, max_insert_range: float, nodes_per_submap: int, sigma: float, levels: int,
                  batch: int = 8, cuts=()) -> Submaps:
    """Build the submaps of a trajectory.

    Args:
        poses: (S, 3) node poses (m, m, rad), the filter's.
        ranges: (S, B) the nodes' scans (m).
        sensor: the laser.
        insertion: the filter's insertion parameters.
        resolution: cell side (m).
        max_insert_range: beams are inserted up to this range (m).
        nodes_per_submap: consecutive nodes per submap.
        sigma: the fit's width (m).
        levels: bound levels to keep (the branch and bound's depth).
        batch: submaps inserted at once (memory).
        cuts: nodes that begin a submap (:func:`submap_ranges`).

    Returns:
        :class:`Submaps`.
    """
    poses = np.asarray(poses, np.float64)
    ranges = np.asarray(ranges, np.float32)
    first, last = submap_ranges(poses.shape[0], nodes_per_submap, cuts)
    num = first.size
    longest = int(np.max(last - first)) + 1
    # Every node in its submap's frame, and the footprint: the nodes plus the insertion's reach.
    idx = np.minimum(first[:, None] + np.arange(longest)[None], last[:, None])  # (M, n)
    padded = (first[:, None] + np.arange(longest)[None]) > last[:, None]
    rel = between_np(poses[first][:, None, :], poses[idx])  # (M, n, 3)
    reach = max_insert_range + float(np.max(np.abs(np.asarray(sensor.laser_pose)[:2]))) + 2 * resolution
    lo = np.min(rel[..., :2], axis=1) - reach
    hi = np.max(rel[..., :2], axis=1) + reach
    block = 2**levels
    cells = np.ceil((hi - lo) / resolution).max(axis=0)
    width, height = (int(np.ceil(c / block) * block) for c in cells)
    grid = GridSpec((height, width), resolution, (0.0, 0.0))
    corner = lo
    grid_poses = rel.copy()
    grid_poses[..., :2] -= corner[:, None, :]
    scans = np.where(padded[..., None], 0.0, ranges[idx]).astype(np.float32)
    fit_table = _fit_table(resolution, sigma)
    fields, fits = [], []
    for start in range(0, num, batch):
        stop = min(start + batch, num)
        take = np.arange(start, start + batch).clip(max=num - 1)  # the last batch padded by repeats
        logodds = np.asarray(_insert_submaps(jnp.asarray(grid_poses[take], jnp.float32), jnp.asarray(scans[take]),
                                             sensor, insertion, grid, float(max_insert_range), 1))
        for k in range(stop - start):
            occupied = logodds[k].astype(np.float32) > 0
            if occupied.any():
                d = scipy.ndimage.distance_transform_edt(~occupied)
                d2 = np.minimum(np.round(d**2), FAR).astype(np.uint8)
            else:
                d2 = np.full(grid.shape, FAR, np.uint8)
            fields.append(d2)
            fits.append(fit_table[d2])
    field = np.stack(fields)
    fit = np.stack(fits)
    bounds = tuple(jnp.asarray(b) for b in square_bounds(fit, levels))
    return Submaps(first, last, corner, grid, jnp.asarray(field), jnp.asarray(fit), bounds)


def submap_pose(submaps: Submaps, submap: int, world_pose: np.ndarray, origin_pose: np.ndarray) -> np.ndarray:
    """A world pose (3,) on submap ``submap``'s grid, its frame at ``origin_pose`` (3,)."""
    rel = between_np(origin_pose, world_pose)
    return np.concatenate([rel[:2] - submaps.corner[submap], rel[2:]])


def world_pose(submaps: Submaps, submap: int, grid_pose: np.ndarray, origin_pose: np.ndarray) -> np.ndarray:
    """The inverse of :func:`submap_pose`."""
    rel = np.concatenate([grid_pose[:2] + submaps.corner[submap], grid_pose[2:]])
    return compose_np(origin_pose, rel)
