"""The planar laser scanner: its description and all beam geometry.

A leaf module (it imports only :mod:`jaxslam.geometry`): the grid maps, the likelihood
models, the ray caster, the simulator and the log readers all take a :class:`SensorSpec`
and ask this module where the beams start and where they end.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.spatial
from jaxtyping import Array, Bool, Float

from jaxslam.geometry import compose


class SensorSpec(NamedTuple):
    """A planar laser scanner (a pytree of arrays: traced, not static)."""

    beam_angles: Float[Array, "B"]
    """Angle of each beam in the laser frame (rad), counter-clockwise from the laser's x axis."""
    range_min: Float[Array, ""]
    """Ranges below this (m) are invalid readings."""
    range_max: Float[Array, ""]
    """Ranges at or above this (m) mean "no return"."""
    laser_pose: Float[Array, "3"]
    """Pose [x, y, theta] of the laser in the robot frame (m, m, rad)."""


def make_sensor(beam_angles, range_min=0.0, range_max=30.0, laser_pose=(0.0, 0.0, 0.0)) -> SensorSpec:
    """A :class:`SensorSpec` with float32 arrays."""
    return SensorSpec(
        jnp.asarray(beam_angles, jnp.float32),
        jnp.asarray(range_min, jnp.float32),
        jnp.asarray(range_max, jnp.float32),
        jnp.asarray(laser_pose, jnp.float32),
    )


def uniform_beams(num_beams: int, fov: float = jnp.pi) -> Float[Array, "B"]:
    """``num_beams`` angles spanning ``fov`` radians centred on the laser's x axis, both ends included."""
    return jnp.linspace(-fov / 2, fov / 2, num_beams, dtype=jnp.float32)


def subsample_beams(sensor: SensorSpec, ranges: Float[Array, "... B"], stride: int):
    """Every ``stride``-th beam (static stride), for a likelihood; maps get all beams.

    Returns ``(sensor, ranges)`` with B' = ceil(B / stride) beams.
    """
    if stride == 1:
        return sensor, ranges
    return sensor._replace(beam_angles=sensor.beam_angles[::stride]), ranges[..., ::stride]


def within_usable_range(ranges: Float[Array, "... B"], usable_range: float) -> Float[Array, "... B"]:
    """``ranges`` with every reading at or beyond ``usable_range`` (m) made invalid (-1, below any
    ``range_min``): the beams a match score counts against a map that registers endpoints only up
    to that range (GMapping's usable range). A longer beam's endpoint lies where the map can only
    know it from a closer pose; counted, it mostly scores nothing and dilutes the score, so with a
    long-range laser in large rooms most matches fail."""
    return jnp.where(ranges < usable_range, ranges, -1.0)


def laser_rays(pose: Float[Array, "3"], sensor: SensorSpec) -> tuple[Float[Array, "2"], Float[Array, "B"]]:
    """Where the beams of a scan taken at robot ``pose`` start: the laser's world position
    (2,) in metres and the world angle (B,) of every beam in radians."""
    origin = compose(pose, sensor.laser_pose)
    return origin[:2], origin[2] + sensor.beam_angles


def valid_returns(ranges: Float[Array, "... B"], sensor: SensorSpec) -> Bool[Array, "... B"]:
    """The beams that returned an endpoint: range_min <= r < range_max."""
    return (ranges < sensor.range_max) & (ranges >= sensor.range_min)


def beam_endpoints(
    poses: Float[Array, "L 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
) -> tuple[Float[Array, "L B 2"], Bool[Array, "B"]]:
    """World (x, y) in metres of every beam's endpoint for L robot poses, and which beams
    returned one (:func:`valid_returns`). The endpoints are computed once in the robot frame
    (B trig calls, shared by all poses and, under vmap, by all particles), after which a pose
    costs one rotation per beam."""
    valid = valid_returns(ranges, sensor)
    beam_x = ranges * jnp.cos(sensor.beam_angles)  # (B,) endpoints in the laser frame (m)
    beam_y = ranges * jnp.sin(sensor.beam_angles)
    lc, ls = jnp.cos(sensor.laser_pose[2]), jnp.sin(sensor.laser_pose[2])
    robot_x = sensor.laser_pose[0] + lc * beam_x - ls * beam_y  # laser -> robot frame, once per scan
    robot_y = sensor.laser_pose[1] + ls * beam_x + lc * beam_y
    c, s = jnp.cos(poses[:, 2:3]), jnp.sin(poses[:, 2:3])  # (L, 1)
    ends = jnp.stack([poses[:, 0:1] + c * robot_x - s * robot_y,
                      poses[:, 1:2] + s * robot_x + c * robot_y], axis=-1)  # (L, B, 2)
    return ends, valid


def scan_points(ranges: np.ndarray, sensor: SensorSpec, max_range: float, num_points: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Each scan's returns as points in the robot frame, thinned to ``num_points`` evenly spread
    over the valid returns shorter than ``max_range`` (what the loop search matches, and what the
    relations' clock lays over each other).

    Args:
        ranges: (S, B) scans (m).
        sensor: the laser (its beam angles and mounting).
        max_range: longest return used (m).
        num_points: points per scan (static shape of the search).

    Returns:
        ``(points (S, P, 2) float32, valid (S, P) bool)``.
    """
    ranges = np.asarray(ranges, np.float32)
    ok = (ranges >= float(sensor.range_min)) & (ranges < min(float(sensor.range_max), max_range))
    ends = np.asarray(jax.vmap(lambda r: beam_endpoints(jnp.zeros((1, 3)), r, sensor)[0][0])(
        jnp.asarray(ranges)))  # (S, B, 2) in the robot frame
    # Each scan's valid beams first, in beam order; then num_points ranks spread over them (all
    # of them where there are fewer), vectorised over the scans.
    count = ok.sum(axis=1)
    used = np.minimum(count, num_points)
    order = np.argsort(~ok, axis=1, kind="stable")
    slot = np.arange(num_points)
    rank = np.round(slot[None] * (count[:, None] - 1) / np.maximum(used[:, None] - 1, 1)).astype(np.int64)
    valid = slot[None] < used[:, None]
    beam = np.take_along_axis(order, np.where(valid, rank, 0), axis=1)
    points = np.where(valid[..., None], np.take_along_axis(ends, beam[..., None], axis=1), 0.0).astype(np.float32)
    return points, valid


def _overlay_distances(motion: np.ndarray, first_points, second_points, radius: float) -> np.ndarray:
    """(..., P2) the distance from each of the second scan's points, laid over the first scan by
    each ``motion`` (..., 3), to the nearest first-scan point (inf beyond ``radius``); one tree."""
    cos, sin = np.cos(motion[..., 2, None]), np.sin(motion[..., 2, None])  # (..., 1)
    x, y = second_points[:, 0], second_points[:, 1]
    moved = np.stack([cos * x - sin * y + motion[..., 0, None], sin * x + cos * y + motion[..., 1, None]], -1)
    return scipy.spatial.cKDTree(first_points).query(moved, distance_upper_bound=radius)[0]


def scan_misfit(motion, first_points, second_points, radius: float):
    """How badly ``motion`` (..., 3), the second scan's robot pose in the first's frame, lays the
    second scan's points (P2, 2) over the first scan's (P1, 2), both in their robot frames (m, from
    :func:`scan_points`): the mean over the second scan's points of the squared distance to the
    nearest first-scan point, capped at ``radius`` (m²; a point the first scan did not see costs
    ``radius ** 2``). Several motions share one nearest-point tree. NumPy and
    ``scipy.spatial.cKDTree``, on the host: a check, not the filter's.

    Returns:
        float for one motion (3,), else (...) float64.
    """
    motion = np.asarray(motion, np.float64)
    if len(first_points) == 0 or len(second_points) == 0:
        misfit = np.full(motion.shape[:-1], radius ** 2)
    else:
        misfit = np.mean(np.minimum(_overlay_distances(motion, first_points, second_points, radius), radius) ** 2,
                         axis=-1)
    return float(misfit) if motion.ndim == 1 else misfit


def scan_inliers(motion, first_points, second_points, distance: float):
    """The share of the second scan's points (P2, 2) that ``motion`` (..., 3) lays within
    ``distance`` (m) of a first-scan point (P1, 2), both in their robot frames (:func:`scan_misfit`'s
    overlay, counted rather than averaged: a long return that the other scan did not see costs a
    point, not the cap squared). 0 where either scan is empty.

    Returns:
        float for one motion (3,), else (...) float64 in [0, 1].
    """
    motion = np.asarray(motion, np.float64)
    if len(first_points) == 0 or len(second_points) == 0:
        share = np.zeros(motion.shape[:-1])
    else:
        share = np.mean(_overlay_distances(motion, first_points, second_points, distance) <= distance, axis=-1)
    return float(share) if motion.ndim == 1 else share
