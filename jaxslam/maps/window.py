"""The insertion's first stages (:mod:`jaxslam.maps.insertion` lists them in order): the window
of K x K tiles that holds every cell one scan can change (:class:`_Window`, :func:`_window_start`),
where an updated cell falls in it (:func:`_window_tile`, :func:`_place_in_tile`), the tiles each
particle's scan touches (:func:`_scan_summaries`), where the window's tiles lie in a particle's
blocks (:func:`_window_layout`) and the slots its directory and blocks give them now
(:func:`_window_pages`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxslam.grid import world_to_cell
from jaxslam.laser import SensorSpec, laser_rays
from jaxslam.maps.pool import UNWRITTEN, PagedGridSpec, PagedMaps
from jaxslam.occupancy import (InsertionParams, ScanRays, cleared_samples, floored_to_cells, free_lengths,
                               sample_floors, samples_per_beam, scan_rays)
from jaxslam.particle_filter import map_in_blocks


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


class _Window(NamedTuple):
    """The static size of the window of tiles that holds every cell one scan can change, and of
    the window of blocks that holds that window (Python ints: changing one recompiles)."""

    tiles_per_side: int
    """K, tiles per side of the window."""
    tiles: int
    """K K, tiles in the window; also the index that stands for "no tile"."""
    blocks_per_side: int
    """Blocks per side of the window of blocks."""
    blocks: int
    """Blocks in the window of blocks."""


def _window_shape(spec: PagedGridSpec, max_insert_range: float, field_radius: int) -> _Window:
    """The window's static size: its side is fixed by the scan's reach, so shapes stay static."""
    side = spec.window_tiles(max_insert_range, field_radius)
    block_side = spec.window_blocks(side)
    return _Window(side, side * side, block_side, block_side * block_side)


class _CellTargets(NamedTuple):
    """Where some updated cells go, as (window tile, place in the tile)."""

    window_tile: Int[Array, "..."]
    """The cell's tile as a flat index over all particles' windows: particle p's window tile
    (row, col) is p (K K + 1) + row K + col; p (K K + 1) + K K stands for no tile (a cell masked
    out or off the window), whose updates are dropped."""
    place: Int[Array, "..."]
    """The cell's place in its tile, row T + col."""


def _window_tile(spec: PagedGridSpec, window: _Window, start: Int[Array, "2"], cells: Int[Array, "... 2"],
                 mask: Bool[Array, "..."]) -> Int[Array, "..."]:
    """Each (row, col) cell's tile in a window starting at tile ``start``, row K + col; K K (no
    tile) where ``mask`` is False or the cell is off the window."""
    shift, side = spec.tile_shift, window.tiles_per_side
    tile_row, tile_col = (cells[..., 0] >> shift) - start[0], (cells[..., 1] >> shift) - start[1]
    inside = mask & (tile_row >= 0) & (tile_row < side) & (tile_col >= 0) & (tile_col < side)
    return jnp.where(inside, tile_row * side + tile_col, window.tiles)


def _place_in_tile(spec: PagedGridSpec, cells: Int[Array, "... 2"]) -> Int[Array, "..."]:
    """Each (row, col) cell's place in its tile, row T + col (by masks: tile sizes are powers of two)."""
    t, shift = spec.tile_size, spec.tile_shift
    return ((cells[..., 0] & (t - 1)) << shift) + (cells[..., 1] & (t - 1))


def _tiles_touched(spec: PagedGridSpec, window: _Window, start: Int[Array, "2"], rays: ScanRays,
                   cleared: Int[Array, "B"], num_samples: int, field_radius: int) -> Bool[Array, "KK"]:
    """The window tiles one scan may change, found from a few points per beam instead of every
    sample (cheaper, and a superset is harmless: an extra tile copied).

    Cells along a ray move monotonically in row and column, so the samples between two points
    less than a tile side apart lie in the tiles of the four (row, column) combinations of the
    two points' tiles; those are marked where the first of the samples between the points lies
    before the beam's free length (``cleared``, samples per beam). An endpoint's field splat
    (radius below a tile side) lies in the tiles of its box's four corners.
    """
    stride = max(spec.tile_size // 2, 1)
    num_points = -(-(num_samples - 1) // stride) + 1
    index = jnp.minimum(jnp.arange(num_points) * stride, num_samples - 1)
    beams = jnp.arange(cleared.shape[0])[:, None]
    points = floored_to_cells(spec.grid, sample_floors(spec.grid, rays, beams, index[None, :]))  # (B, P, 2)
    # Segment i spans samples index[i] .. index[i + 1], both ends included.
    segment_free = index[None, :-1] < cleared[:, None]
    a, b = points[:, :-1], points[:, 1:]
    corners = [jnp.stack([x[..., 0], y[..., 1]], -1) for x in (a, b) for y in (a, b)]
    free_touched = jnp.stack([_window_tile(spec, window, start, c, segment_free) for c in corners], -1)
    r = jnp.asarray([field_radius, -field_radius])
    end_cells = floored_to_cells(spec.grid, rays.end_floor)
    box = [end_cells + jnp.stack([dr, dc]) for dr in r for dc in r]
    splat_touched = jnp.stack([_window_tile(spec, window, start, c, rays.returned) for c in box], -1)
    return (jnp.zeros(window.tiles + 1, bool).at[free_touched.reshape(-1)].set(True)
            .at[splat_touched.reshape(-1)].set(True)[:window.tiles])


class _ScanSummary(NamedTuple):
    """What the insertion needs of every particle's scan before it writes (``N`` leading): the
    beam samples themselves are computed chunk by chunk when it writes
    (:func:`~jaxslam.maps.writes._write_cells`)."""

    touched: Bool[Array, "N KK"]
    """The window tiles the scan may change."""
    window_start: Int[Array, "N 2"]
    """(row, col) of each window's first tile in the virtual grid."""


def _scan_summaries(spec: PagedGridSpec, window: _Window, poses: Float[Array, "N 3"], ranges: Float[Array, "B"],
                    sensor: SensorSpec, params: InsertionParams, max_insert_range: float, field_radius: int,
                    particle_block: int | None) -> _ScanSummary:
    """Every particle's window and touched tiles, ``particle_block`` particles at a time."""
    num_samples = samples_per_beam(spec.grid, max_insert_range)
    cleared = cleared_samples(spec.grid, free_lengths(ranges, sensor, params, max_insert_range), num_samples)

    def one(pose):
        rays = scan_rays(spec.grid, pose, ranges, sensor, params, max_insert_range)
        start = _window_start(spec, pose, sensor, window.tiles_per_side, max_insert_range, field_radius)
        return _ScanSummary(_tiles_touched(spec, window, start, rays, cleared, num_samples, field_radius), start)

    return map_in_blocks(one, poses, particle_block)


class _WindowLayout(NamedTuple):
    """Where each particle's window tiles lie in its directory (geometry only, no map read)."""

    tile_block: Int[Array, "N KK"]
    """The block of the window of blocks (row times blocks per side + col) each window tile lies in."""
    tile_in_block: Int[Array, "N KK"]
    """Each window tile's entry in its block, row S + col."""
    block_rows: Int[Array, "N KB"]
    """The directory row of each row of the window of blocks (past the directory's edge: dropped)."""
    block_cols: Int[Array, "N KB"]
    """The directory column of each column of the window of blocks (likewise)."""
    in_directory: Bool[Array, "N KBB"]
    """Each window block lies inside the directory."""


def _window_layout(spec: PagedGridSpec, window: _Window, window_start: Int[Array, "N 2"]) -> _WindowLayout:
    """Where each window tile lies: in which block of the particle's window of blocks, at which
    entry. The window of blocks starts at the block of the window's first tile, so one gather of
    the directory serves all the window's tiles."""
    n = window_start.shape[0]
    s, shift = spec.block_size, spec.block_shift
    dy, dx = spec.num_blocks
    side, block_side = window.tiles_per_side, window.blocks_per_side
    tile_rows, tile_cols = window_start[:, :1] + jnp.arange(side), window_start[:, 1:] + jnp.arange(side)  # (N, K)
    block_start = window_start >> shift  # (N, 2)
    tile_block = (((tile_rows >> shift) - block_start[:, :1])[:, :, None] * block_side
                  + ((tile_cols >> shift) - block_start[:, 1:])[:, None, :]).reshape(n, window.tiles)
    tile_in_block = ((tile_rows & (s - 1))[:, :, None] * s + (tile_cols & (s - 1))[:, None, :]).reshape(n, window.tiles)
    block_rows = block_start[:, :1] + jnp.arange(block_side)
    block_cols = block_start[:, 1:] + jnp.arange(block_side)
    in_directory = ((block_rows < dy)[:, :, None] & (block_cols < dx)[:, None, :]).reshape(n, window.blocks)
    return _WindowLayout(tile_block, tile_in_block, block_rows, block_cols, in_directory)


class _WindowPages(NamedTuple):
    """What each particle's directory and the blocks give its window before the insertion."""

    block_slots: Int[Array, "N KBB"]
    """The block slot of each window block; :data:`UNWRITTEN` where none (or off the directory)."""
    block_owned: Bool[Array, "N KBB"]
    """The block is the particle's alone (no other directory points at it): written in place."""
    tile_slots: Int[Array, "N KK"]
    """The tile slot of each window tile; :data:`UNWRITTEN` where none."""
    tile_owned: Bool[Array, "N KK"]
    """The tile is the particle's alone: its block is, and no other block points at the tile."""


def _window_pages(spec: PagedGridSpec, maps: PagedMaps, layout: _WindowLayout) -> _WindowPages:
    """The slots each particle's window reads now, and which of them it owns (refcount 1): those
    it may write in place; the others it must be given before it writes."""
    dy, dx = spec.num_blocks
    block_slots = jax.vmap(lambda d, r, c: d[jnp.minimum(r, dy - 1)[:, None], jnp.minimum(c, dx - 1)[None, :]])(
        maps.directory, layout.block_rows, layout.block_cols).reshape(layout.in_directory.shape)
    block_slots = jnp.where(layout.in_directory, block_slots, UNWRITTEN)
    block_owned = (block_slots >= 0) & (maps.block_refcount[jnp.maximum(block_slots, 0)] == 1)
    entries = maps.blocks.reshape(maps.blocks.shape[0], -1)
    block_of_tile = jnp.take_along_axis(block_slots, layout.tile_block, axis=1)
    tile_slots = jnp.where(block_of_tile >= 0, entries[jnp.maximum(block_of_tile, 0), layout.tile_in_block],
                           UNWRITTEN)
    tile_owned = (jnp.take_along_axis(block_owned, layout.tile_block, axis=1) & (tile_slots >= 0)
                  & (maps.refcount[jnp.maximum(tile_slots, 0)] == 1))
    return _WindowPages(block_slots, block_owned, tile_slots, tile_owned)
