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
