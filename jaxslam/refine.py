"""Refining a trajectory in the final map: every scan scan-matched against one particle's map.

The RBPF estimates a pose only for the scans it processes (GMapping's 1 m / 0.5 rad rule
keeps about one scan in ten); the others get the odometry composed onto the last processed
pose (:func:`jaxslam.io.trajectory.trajectory_per_scan`), so between processed scans the
trajectory is as good as the odometry. Once the filter is done, its best particle's map is
a consistent model of the whole environment, and every scan can be localised in it: start
the hill climber of :mod:`jaxslam.scan_matching` at the scan's trajectory pose and keep the
result where the match is good (score >= ``min_score``), the old pose elsewhere. This is
localisation in a fixed map, not a second SLAM pass: the map is not changed.

The matching is vmapped over a fixed-size chunk of scans (the last chunk padded), so it
compiles once per map and scan shape, whatever the number of scans.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt8

from jaxslam.geometry import wrap_angle_np
from jaxslam.grid import GridSpec
from jaxslam.scan_matching import match
from jaxslam.sensor import SensorSpec, subsample_beams


class RefinedTrajectory(NamedTuple):
    """A trajectory after localisation in the final map."""

    poses: np.ndarray
    """(T, 3) float64 poses (m, m, rad): the matched pose where the match held, else the input."""
    matched: np.ndarray
    """(T,) bool: the scan's match held (score >= ``min_score``)."""
    scores: np.ndarray
    """(T,) float: the match score (mean per-beam fit, 0..1) at the matched pose."""


def refine_trajectory(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    poses: Float[np.ndarray, "T 3"],
    ranges: Float[np.ndarray, "T B"],
    sensor: SensorSpec,
    params,
    config,
    chunk_size: int = 256,
) -> RefinedTrajectory:
    """Scan-match every scan against one map, starting at its trajectory pose.

    Args:
      spec: the map's grid.
      hit_dist2: (H, W) that map's likelihood field (e.g. the final best particle's).
      poses: (T, 3) the trajectory to refine, one pose per scan.
      ranges: (T, B) the scans (m).
      sensor: the laser.
      params: ``SlamParams``: the likelihood and the scan matcher's steps and ``min_score``.
      config: ``SlamConfig``: ``beam_stride`` and ``match_iterations``.
      chunk_size: scans matched per compiled call (static).

    Returns:
      A :class:`RefinedTrajectory`.
    """
    poses = np.asarray(poses, np.float64)
    ranges = np.asarray(ranges, np.float32)
    if poses.ndim != 2 or poses.shape[1] != 3 or ranges.shape[0] != poses.shape[0]:
        raise ValueError(f"refine_trajectory: poses {poses.shape} and ranges {ranges.shape} do not match")
    num = poses.shape[0]
    lik_sensor, lik_ranges = subsample_beams(sensor, ranges, config.beam_stride)
    padded = -(-num // chunk_size) * chunk_size
    pose_in = np.zeros((padded, 3), np.float32)
    pose_in[:num] = poses
    ranges_in = np.zeros((padded, lik_ranges.shape[1]), np.float32)
    ranges_in[:num] = lik_ranges
    out_pose, out_score = [], []
    for start in range(0, padded, chunk_size):
        sl = slice(start, start + chunk_size)
        p, s = _match_chunk(spec, hit_dist2, jnp.asarray(pose_in[sl]), jnp.asarray(ranges_in[sl]), lik_sensor,
                            params, config.match_iterations)
        out_pose.append(np.asarray(p))
        out_score.append(np.asarray(s))
    matched_pose = np.concatenate(out_pose)[:num].astype(np.float64)
    scores = np.concatenate(out_score)[:num]
    ok = scores >= float(params.scan_match.min_score)
    refined = np.where(ok[:, None], matched_pose, poses)
    refined[:, 2] = wrap_angle_np(refined[:, 2])
    return RefinedTrajectory(refined, ok, scores)


@functools.partial(jax.jit, static_argnums=(0, 6))
def _match_chunk(spec, hit_dist2, poses, ranges, sensor, params, iterations):
    sm = params.scan_match

    def one(pose, scan):
        result = match(spec, hit_dist2, pose, scan, sensor, params.likelihood, sm.linear_step, sm.angular_step,
                       iterations)
        return result.pose, result.score

    return jax.vmap(one)(poses, ranges)

