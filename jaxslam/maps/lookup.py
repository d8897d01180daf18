"""Reading one particle's paged map: :class:`PagedField` (its directory and the shared pools, as
the likelihood models read it, vmapped over particles with :data:`FIELD_AXES`) and the gathers
through directory, block and tile (:func:`tile_slots`, :func:`cell_values`)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Int

from jaxslam.maps.pool import UNWRITTEN, PagedGridSpec, PagedMaps, flat_pool


class PagedField(NamedTuple):
    """One particle's likelihood field (or log-odds) as the likelihood model reads it: its
    directory, the shared blocks and the shared tile pool (vmap over particles with
    ``in_axes=FIELD_AXES``)."""

    directory: Int[Array, "DY DX"]
    """The particle's directory."""
    blocks: Int[Array, "B S S"]
    """The shared block pool."""
    pool: Array
    """(C, T, T) the tile pool of that quantity."""


FIELD_AXES = PagedField(0, None, None)
"""``in_axes`` of a ``vmap`` over the particles of :func:`fields`."""


def fields(maps: PagedMaps) -> PagedField:
    """Every particle's likelihood field (directories (N, DY, DX), the shared pools): vmap over it
    with ``in_axes=FIELD_AXES``."""
    return PagedField(maps.directory, maps.blocks, maps.hit_dist2)


def particle_field(maps: PagedMaps, particle, quantity: str = "hit_dist2") -> PagedField:
    """Particle ``particle``'s field (``quantity="logodds"``: its log-odds) as a :class:`PagedField`."""
    return PagedField(maps.directory[particle], maps.blocks, getattr(maps, quantity))


def _tile_values(pool: Array, slots: Int[Array, "..."], fill) -> Array:
    """``pool[slots]`` with ``fill`` where a slot is unwritten: (..., T, T)."""
    values = pool[jnp.maximum(slots, 0)]
    return jnp.where((slots >= 0)[..., None, None], values, jnp.asarray(fill, pool.dtype))


def tile_slots(spec: PagedGridSpec, directory: Int[Array, "DY DX"], blocks: Int[Array, "B S S"],
               tiles: Int[Array, "... 2"]) -> Int[Array, "..."]:
    """The tile-pool slots of (row, col) tiles of one particle's map (inside the grid), -1 where unwritten."""
    shift, mask = spec.block_shift, spec.block_size - 1
    row, col = tiles[..., 0], tiles[..., 1]
    block = directory.reshape(-1)[(row >> shift) * directory.shape[1] + (col >> shift)]
    # One flat index per read: XLA's CPU gathers are cheaper on a 1-D operand than on (B, S, S).
    slot = blocks.reshape(-1)[(jnp.maximum(block, 0) * spec.block_size + (row & mask)) * spec.block_size
                              + (col & mask)]
    return jnp.where(block >= 0, slot, UNWRITTEN)


def cell_values(spec: PagedGridSpec, field: PagedField, cells: Int[Array, "... 2"], fill):
    """One particle's map at (row, col) cells of the virtual grid: ``field.pool`` (its log-odds or
    its field) read through its directory and the blocks; ``fill`` outside the grid and in
    unwritten tiles."""
    t = spec.tile_size
    ty, tx = spec.num_tiles
    row, col = cells[..., 0], cells[..., 1]
    inside = (row >= 0) & (row < ty * t) & (col >= 0) & (col < tx * t)
    row, col = jnp.clip(row, 0, ty * t - 1), jnp.clip(col, 0, tx * t - 1)
    shift, mask = spec.tile_shift, t - 1
    slot = tile_slots(spec, field.directory, field.blocks, jnp.stack([row >> shift, col >> shift], -1))
    if flat_pool(spec, field.pool.shape[0]):
        value = field.pool.reshape(-1)[(jnp.maximum(slot, 0) * t + (row & mask)) * t + (col & mask)]
    else:
        value = field.pool[jnp.maximum(slot, 0), row & mask, col & mask]
    return jnp.where(inside & (slot >= 0), value, jnp.asarray(fill, field.pool.dtype))
