"""Host-side views of one particle's paged map: its page table over the whole virtual grid
(:func:`page_table`) and a dense copy of the tiles it wrote (:func:`to_dense`), for outputs,
plots and tests."""

from __future__ import annotations

import numpy as np

from jaxslam.grid import GridSpec
from jaxslam.maps.pool import UNWRITTEN, PagedGridSpec, PagedMaps
from jaxslam.occupancy import FAR


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
