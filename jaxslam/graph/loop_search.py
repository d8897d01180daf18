"""The loop search: one scan against one submap over a wide window, coarse to fine with a bound
(branch and bound after Olson 2009 and Hess et al. 2016), batched over pairs with ``vmap``.

The search space is every angle ``theta_0 + k * angular_step`` within the pair's angular
window and every translation of whole cells within its square window, on the submap's grid
(:mod:`jaxslam.graph.submaps`). A candidate's score is the mean over the scan's points of the
submap's quantised fit at the point's cell. A node of the search at level h is an angle and a
2^h x 2^h square of translations; its bound, the sum of the submap's level-h bounds at the
points' cells (each the largest fit over that square), is at least the score of every candidate in the square, so discarding a node whose
bound is below a score already found loses nothing.

Exact branch and bound is a depth-first loop of data-dependent length. Here every level keeps
a fixed number of nodes (``keep``, static), the best by bound, and splits each into four; the
best bound among the nodes dropped on the way (``dropped_bound``) is returned. Where the best
score found is at least that bound, no dropped node held a better candidate and the result is
the exact optimum of the window (``certified``); where the dropped bound is below the
acceptance threshold, no candidate the search could have missed would have been accepted. Both
are reported per pair (docs/design.md, "Loop closure", measures how often each holds).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.graph.submaps import Submaps


class SearchWindow(NamedTuple):
    """The static shape of a search (hashable)."""

    half_cells: int
    """Largest translation window, cells either side (a pair's own window may be smaller)."""
    half_angles: int
    """Largest angular window, steps either side."""
    angular_step: float
    """Angle between candidate headings (rad)."""
    levels: int
    """Levels of the bound (the top node covers 2^levels cells a side)."""
    keep: int
    """Nodes kept per level."""
    ambiguity_cells: int
    """A second candidate counts as another mode when it lies more than this many cells, or
    more than ``ambiguity_angles`` steps, from the best."""
    ambiguity_angles: int
    """See ``ambiguity_cells``."""
    top_squares: int = 0
    """:func:`search_pairs` searches a window whose top level would take more than this many
    squares a side with more levels (:func:`class_shape`; 0: ``levels`` for every window)."""
    recheck_score: float = 0.0
    """Least score at which :func:`search_pairs` searches a deepened class's pair again at
    ``levels``."""


class SearchResult(NamedTuple):
    """The outcome of P searches (arrays with a leading P axis)."""

    pose: jax.Array
    """(P, 3) the best candidate's pose on the submap's grid (m, m, rad)."""
    score: jax.Array
    """(P,) its score, the mean fit in [0, 1] over the scan's points."""
    second_score: jax.Array
    """(P,) the best score among the evaluated candidates of another mode (0 if none)."""
    dropped_bound: jax.Array
    """(P,) the largest bound among dropped nodes, in score units (0 if none was dropped)."""

    @property
    def certified(self) -> jax.Array:
        """(P,) the score is the exact optimum of the window."""
        return self.score >= self.dropped_bound


def _read(grid: jax.Array, rows: jax.Array, cols: jax.Array) -> jax.Array:
    """grid[rows, cols] as int32, 0 outside the grid."""
    h, w = grid.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    return jnp.where(inside, grid[jnp.clip(rows, 0, h - 1), jnp.clip(cols, 0, w - 1)], 0).astype(jnp.int32)


def _scan_cells(points: jax.Array, guess: jax.Array, resolution: float, half_theta: jax.Array,
                window: SearchWindow) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The window's A headings round ``guess[2]`` (A,), which lie within ``half_theta`` (A,), and
    the scan's (P, 2) points at each heading from ``guess``'s position as (row, col) cells (A, P, 2)."""
    steps = jnp.arange(-window.half_angles, window.half_angles + 1)
    angles = guess[2] + steps * window.angular_step
    angle_ok = jnp.abs(steps * window.angular_step) <= half_theta
    c, s = jnp.cos(angles)[:, None], jnp.sin(angles)[:, None]
    x = guess[0] + c * points[None, :, 0] - s * points[None, :, 1]
    y = guess[1] + s * points[None, :, 0] + c * points[None, :, 1]
    return angles, angle_ok, jnp.stack([jnp.floor(y / resolution), jnp.floor(x / resolution)], -1).astype(jnp.int32)


def search_one(fit: jax.Array, bounds: tuple[jax.Array, ...], resolution: float, points: jax.Array,
               valid: jax.Array, guess: jax.Array, half_cells: jax.Array, half_theta: jax.Array,
               window: SearchWindow) -> tuple[jax.Array, ...]:
    """One scan against one submap (see the module docstring).

    Args:
        fit: (H, W) uint8 the submap's fit.
        bounds: its block bounds, levels 1..``window.levels``.
        resolution: cell side (m), static.
        points: (P, 2) the scan's points in the robot frame (m).
        valid: (P,) which points count.
        guess: (3,) the scan's pose on the submap's grid (m, m, rad): the window's centre.
        half_cells: () int, this pair's translation window (cells either side, at most
            ``window.half_cells``).
        half_theta: () this pair's angular window (rad either side).
        window: the static shape.

    Returns:
        pose (3,), score, second_score, dropped_bound (see :class:`SearchResult`).
    """
    top = window.levels
    side = 2**top
    num_points = jnp.maximum(jnp.sum(valid), 1).astype(jnp.float32)
    angles, angle_ok, cells = _scan_cells(points, guess, resolution, half_theta, window)

    def node_bounds(level, angle, corner):
        """Bounds (n,) of nodes (angle (n,), corner (n, 2) = (row, col) offset of the square)."""
        shifted = cells[angle] + corner[:, None, :]  # (n, P, 2)
        grid = fit if level == 0 else bounds[level - 1]
        values = _read(grid, shifted[..., 0], shifted[..., 1])
        return jnp.sum(jnp.where(valid[None], values, 0), axis=-1)

    def in_window(corner, size):
        lo, hi = corner, corner + size - 1
        return jnp.all((hi >= -half_cells) & (lo <= half_cells), axis=-1)

    span = 2 * window.half_cells + 1
    per_axis = -(-span // side)
    start = -window.half_cells
    offs = start + side * jnp.arange(per_axis)
    grid_r, grid_c = jnp.meshgrid(offs, offs, indexing="ij")
    corners = jnp.stack([grid_r.ravel(), grid_c.ravel()], -1)  # (T, 2)
    num_angles = angles.shape[0]
    angle = jnp.repeat(jnp.arange(num_angles), corners.shape[0])
    corner = jnp.tile(corners, (num_angles, 1))
    value = node_bounds(top, angle, corner)
    value = jnp.where(angle_ok[angle] & in_window(corner, side), value, -1)
    keep = min(window.keep, value.shape[0])

    def select(value, angle, corner, dropped):
        if value.shape[0] > keep:
            best, order = jax.lax.top_k(value, keep + 1)
            dropped = jnp.maximum(dropped, best[keep])
            order = order[:keep]
        else:
            order = jnp.arange(value.shape[0])
        return value[order], angle[order], corner[order], dropped

    value, angle, corner, dropped = select(value, angle, corner, jnp.int32(0))
    children = jnp.array([[0, 0], [0, 1], [1, 0], [1, 1]], jnp.int32)
    for level in range(top - 1, -1, -1):
        size = 2**level
        parent_ok = value >= 0
        angle = jnp.repeat(angle, 4)
        corner = (corner[:, None, :] + size * children[None]).reshape(-1, 2)
        ok = jnp.repeat(parent_ok, 4) & in_window(corner, size)
        value = jnp.where(ok, node_bounds(level, angle, corner), -1)
        if level > 0:
            value, angle, corner, dropped = select(value, angle, corner, dropped)
    best = jnp.argmax(value)
    far = ((jnp.max(jnp.abs(corner - corner[best]), axis=-1) > window.ambiguity_cells)
           | (jnp.abs(angle - angle[best]) > window.ambiguity_angles))
    second = jnp.max(jnp.where(far, value, 0))
    scale = 255.0 * num_points
    offset = corner[best].astype(jnp.float32) * resolution
    pose = jnp.stack([guess[0] + offset[1], guess[1] + offset[0], angles[angle[best]]])
    return pose, jnp.maximum(value[best], 0) / scale, second / scale, dropped / scale


@partial(jax.jit, static_argnames=("resolution", "window"))
def search_batch(fit, bounds, submap, points, valid, guess, half_cells, half_theta, resolution: float,
                 window: SearchWindow) -> SearchResult:
    """P searches at once: pair p matches scan points (P, N, 2) / valid (P, N) against submap
    ``submap[p]`` of the stacked ``fit`` (M, H, W) and ``bounds`` around ``guess[p]`` (P, 3),
    windows ``half_cells`` (P,) and ``half_theta`` (P,) (see :func:`search_one`)."""

    def one(j, pts, ok, g, hc, ht):
        return search_one(fit[j], tuple(b[j] for b in bounds), resolution, pts, ok, g, hc, ht, window)

    return SearchResult(*jax.vmap(one)(submap, points, valid, guess, half_cells, half_theta))


def window_classes(half_cells: np.ndarray, levels: int) -> np.ndarray:
    """(P,) the static translation window each pair is searched with: its own rounded up to a
    power of two times the top node's side (few classes, few compilations)."""
    side = 2**levels
    return (side * 2 ** np.ceil(np.log2(np.maximum(half_cells, 1) / side)).clip(min=0)).astype(np.int64)


def class_shape(half_cells: int, window: SearchWindow) -> SearchWindow:
    """The search's shape for a translation window of ``half_cells`` cells either side: the
    fewest levels, and at least ``window.levels``, whose top level tiles the window with at most
    ``window.top_squares`` squares a side (``window.levels`` where that is 0), and twice the
    nodes kept for each level added. The top level's squares are coarser there and their bounds
    flatter, so the best candidate's node ranks lower among them: with ``keep`` nodes a level, a
    third of FR-clinic's promising 12.8 and 20 m matches came out elsewhere
    (docs/design.md, "Loop closure behind the filter")."""
    levels = int(window.levels)
    span = 2 * int(half_cells) + 1
    while window.top_squares and -(-span // 2**levels) > window.top_squares:
        levels += 1
    return window._replace(half_cells=int(half_cells), levels=levels, keep=window.keep * 2 ** (levels - window.levels))


def search_pairs(submaps: Submaps, submap, points, valid, guess, half_cells, half_theta, window: SearchWindow,
                 batch: int = 16, progress=None) -> SearchResult:
    """:func:`search_batch` over any number of pairs on host arrays, grouped by
    :func:`window_classes` (``window.half_cells`` caps them), each of the :func:`class_shape`
    (``submaps.bounds`` must hold its levels), ``batch`` at a time (the last batch of a class
    padded); ``progress`` (a tqdm bar or None) is advanced by the pairs done.

    A deepened class's search screens: its pairs that score ``window.recheck_score`` or more are
    searched again at ``window.levels`` and ``window.keep``, and that search's result is
    returned. Even with ``keep`` doubled, the deeper search finds another best in about one
    promising pair in eight (FR-clinic), now and then a corridor's alias where the shallower
    search finds the true match (MIT Killian); the acceptance was measured on the shallower one."""
    num = len(submap)
    out = SearchResult(np.zeros((num, 3), np.float32), np.zeros(num, np.float32), np.zeros(num, np.float32),
                       np.zeros(num, np.float32))
    arrays = (submap, points, valid, guess, half_cells, half_theta)
    classes = np.minimum(window_classes(half_cells, window.levels), window.half_cells)
    for size in np.unique(classes):
        members = np.nonzero(classes == size)[0]
        shape = class_shape(int(size), window)
        _search_members(out, members, submaps, arrays, shape, batch, progress)
        if shape.levels > window.levels:
            again = members[out.score[members] >= window.recheck_score]
            _search_members(out, again, submaps, arrays, window._replace(half_cells=int(size)), batch, None)
    return out


def _search_members(out: SearchResult, members: np.ndarray, submaps: Submaps, arrays: tuple, shape: SearchWindow,
                    batch: int, progress) -> None:
    """Search the pairs ``members`` of ``arrays`` (submap, points, valid, guess, half_cells,
    half_theta) with one static shape, writing into ``out``."""
    submap, points, valid, guess, half_cells, half_theta = arrays
    for start in range(0, members.size, batch):
        take = members[np.arange(start, start + batch).clip(max=members.size - 1)]
        found = search_batch(submaps.fit, submaps.bounds, jnp.asarray(submap[take]), jnp.asarray(points[take]),
                             jnp.asarray(valid[take]), jnp.asarray(guess[take], jnp.float32),
                             jnp.asarray(half_cells[take], jnp.int32), jnp.asarray(half_theta[take], jnp.float32),
                             submaps.grid.resolution, shape)
        n = min(batch, members.size - start)
        for field, value in zip(out, found):
            field[take[:n]] = np.asarray(value)[:n]
        if progress is not None:
            progress.update(n)
