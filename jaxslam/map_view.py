"""One particle's map as a sensor model reads it: :class:`MapView`.

The SLAM filters keep their maps paged (:mod:`jaxslam.maps`: one particle's
:class:`~jaxslam.maps.PagedField` is its directory into pools shared by all particles);
tests, the refinement and the localization tools hold a dense ``(H, W)`` field on a
:class:`~jaxslam.grid.GridSpec`. A sensor model (:mod:`jaxslam.sensor_model`) reads either
through a view, so the difference between the two lives here and nowhere else.
"""

from __future__ import annotations

import dataclasses

import jax
from jaxtyping import Array, Int

from jaxslam.grid import GridSpec, flat_index
from jaxslam.maps import PagedField, PagedGridSpec, cell_values


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MapView:
    """A map quantity (one particle's) with the grid that indexes its cells."""

    spec: GridSpec | PagedGridSpec = dataclasses.field(metadata={"static": True})
    """The grid: a dense :class:`~jaxslam.grid.GridSpec` or a paged map's
    :class:`~jaxslam.maps.PagedGridSpec` (static)."""
    values: Array | PagedField
    """The quantity: a dense (H, W) array on ``spec``, or one particle's
    :class:`~jaxslam.maps.PagedField` (directory and shared pools) on a paged ``spec``."""

    def __post_init__(self):
        if isinstance(self.values, PagedField) != isinstance(self.spec, PagedGridSpec):
            raise TypeError(f"MapView: a {type(self.values).__name__} needs a "
                            f"{'PagedGridSpec' if isinstance(self.values, PagedField) else 'GridSpec'}, "
                            f"got {type(self.spec).__name__}")

    @property
    def paged(self) -> bool:
        """Whether the map is paged (its reads are gathers through a page table)."""
        return isinstance(self.values, PagedField)

    @property
    def grid(self) -> GridSpec:
        """The grid whose (row, col) cells index the map (a paged map's virtual grid)."""
        return self.spec.grid if self.paged else self.spec

    @property
    def resolution(self) -> float:
        """Cell side (m)."""
        return self.grid.resolution

    def read(self, cells: Int[Array, "... 2"], fill) -> Array:
        """The quantity at (row, col) ``cells``; ``fill`` outside the map (and, paged, in tiles
        nobody wrote)."""
        if self.paged:
            return cell_values(self.spec, self.values, cells, fill)
        return self.values.reshape(-1).at[flat_index(self.spec, cells)].get(mode="fill", fill_value=fill)
