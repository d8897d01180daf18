"""A small room for tests: its segments, a laser, a grid, scans cast in it and a map built from them."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.config import default_params
from jaxslam.grid import GridSpec
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.occupancy import empty_map, insert_scan
from jaxslam.segment_map import expected_ranges

ROOM = np.array([
    [0.0, 0.0, 6.0, 0.0], [6.0, 0.0, 6.0, 4.0], [6.0, 4.0, 0.0, 4.0], [0.0, 4.0, 0.0, 0.0],
    [2.0, 1.5, 2.6, 1.5], [2.6, 1.5, 2.6, 2.1],  # a box
    [4.2, 3.0, 4.8, 2.6],  # a slanted panel
], np.float32)
SENSOR = make_sensor(uniform_beams(61, math.pi), range_min=0.05, range_max=8.0)
SPEC = GridSpec.from_bounds(-1.0, -1.0, 7.0, 5.0, 0.05)


def scan_at(pose):
    """The exact scan (61 beams, m) from robot ``pose`` in the room."""
    return expected_ranges(jnp.asarray(ROOM), jnp.asarray(pose, jnp.float32), SENSOR)[0]


def room_path(num):
    """A path along the room (poses (num, 3)), turning slowly."""
    s = np.linspace(0.0, 1.0, num)
    x = 1.0 + 3.5 * s
    y = 0.8 + 2.0 * s**2
    theta = np.arctan2(np.gradient(y), np.gradient(x))
    return np.stack([x, y, theta], axis=-1).astype(np.float32)


def build_room_map(num_scans: int = 3):
    """The map of the first ``num_scans`` scans along ``room_path(6)``, inserted at their true poses."""
    params = default_params()
    grid_map = empty_map(SPEC)
    insert = jax.jit(insert_scan, static_argnums=(0, 6, 7))
    for pose in room_path(6)[:num_scans]:
        grid_map, _ = insert(SPEC, grid_map, jnp.asarray(pose), scan_at(pose), SENSOR, params.insertion, 10.0, 4)
    return grid_map


ROOM_EXTENT = 20.0
"""``map_extent`` (m) of configs used with :func:`paged_field` (a virtual grid of 7 x 7 tiles at 5 cm)."""


def paged_maps(grid_map, config, num_particles: int = 1, spare_tiles: int = 200):
    """The dense room map ``grid_map`` (on ``SPEC``) as ``num_particles`` particles' shared paged
    maps on ``config.grid`` (NumPy; every tile of the virtual grid gets a slot, and
    ``spare_tiles`` free slots follow): the maps a filter's particles would hold."""
    from jaxslam.maps import empty, first_free
    from jaxslam.occupancy import FAR

    spec = config.grid
    t = spec.tile_size
    row0 = round((SPEC.origin[1] - spec.origin[1]) / spec.resolution)
    col0 = round((SPEC.origin[0] - spec.origin[0]) / spec.resolution)
    assert spec.resolution == SPEC.resolution and row0 >= 0 and col0 >= 0
    assert abs(row0 * spec.resolution - (SPEC.origin[1] - spec.origin[1])) < 1e-6  # cells line up
    ty, tx = spec.num_tiles
    h, w = SPEC.shape

    def tiles(dense, fill):
        full = np.full((ty * t, tx * t), fill, dense.dtype)
        full[row0:row0 + h, col0:col0 + w] = dense
        return full.reshape(ty, t, tx, t).transpose(0, 2, 1, 3).reshape(ty * tx, t, t)

    used = ty * tx
    s = spec.block_size
    dy, dx = spec.num_blocks
    spare_blocks = 4 * num_particles + 4
    base = empty(spec, num_particles, used + spare_tiles, block_capacity=dy * dx + spare_blocks)
    refcount = np.zeros(used + spare_tiles, np.int32)
    refcount[:used] = 1  # each tile is in one block
    # Every block of the virtual grid holds its tiles' slots; every particle's directory points at all of them.
    slots = np.full((dy * s, dx * s), -1, np.int32)
    slots[:ty, :tx] = np.arange(used, dtype=np.int32).reshape(ty, tx)
    blocks = np.asarray(base.blocks).copy()
    blocks[:dy * dx] = slots.reshape(dy, s, dx, s).transpose(0, 2, 1, 3).reshape(dy * dx, s, s)
    block_refcount = np.zeros(dy * dx + spare_blocks, np.int32)
    block_refcount[:dy * dx] = num_particles
    return base._replace(
        directory=jnp.asarray(np.broadcast_to(np.arange(dy * dx, dtype=np.int32).reshape(dy, dx),
                                              (num_particles, dy, dx))),
        blocks=jnp.asarray(blocks), block_refcount=jnp.asarray(block_refcount),
        logodds=base.logodds.at[:used].set(tiles(np.asarray(grid_map.logodds), 0.0)),
        hit_dist2=base.hit_dist2.at[:used].set(tiles(np.asarray(grid_map.hit_dist2), FAR)),
        refcount=jnp.asarray(refcount), free_slots=first_free(jnp.asarray(refcount), base.max_new_tiles),
        free_blocks=first_free(jnp.asarray(block_refcount), base.pool_size.max_new_blocks))


def paged_field(grid_map, config):
    """The dense room map ``grid_map`` (on ``SPEC``) as one particle's paged likelihood field on
    ``config.grid``: what a proposal reads in a filter."""
    from jaxslam.maps import particle_field

    return particle_field(paged_maps(grid_map, config, 1, spare_tiles=1), 0)
