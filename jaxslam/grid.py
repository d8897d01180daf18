"""Grids: the static :class:`GridSpec` and the maps between world and cell coordinates.

The maps stored on a grid (occupancy log-odds and the likelihood field) and their updates
live in :mod:`jaxslam.occupancy`.

Row ``i`` of a map is ``y = origin_y + (i + 0.5) * resolution`` and column ``j``
is ``x = origin_x + (j + 0.5) * resolution``: ``origin`` is the lower-left corner
of cell (0, 0), as in a ROS map_server YAML file (whose image rows run top-down).
Points outside the map are never wrapped: they are dropped and counted.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


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
