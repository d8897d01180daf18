"""How fast the filter's heading and the odometry's drift, as the loops measure them, and the
chain of steps that weighs the two by it (:func:`heading_drift_rates`, :func:`reweighted_chain`).

The pose graph's chain between loops is the filter's steps. Where the filter's heading drifts
faster than the robot's odometry (on FR-clinic 34 degrees after 1.4 km against the odometry's
1.3), the chain carries the filter's drift to every loop that no window reaches. Which of the two
drifts slower differs from robot to robot, and no single step says it: a step's difference
between them is mostly the filter's white jitter about its map, which the map cancels over the
next steps (the particles' spread at a step measures that jitter, not the drift: weighing each
step by it took Intel from 0.051 to 2.04 m; docs/notes/2026-11-28-whose-heading-drifts.md). Drift shows
over long spans, and a kept loop is a long span measured: its heading against each chain's
relative heading from the loop's submap node to its query is one sample of each chain's drift
over that many steps.

Modelling each chain's heading error as a random walk, the loops give each one's variance per
step (:func:`heading_drift_rates`); the minimum-variance chain takes each step's heading
change as the filter's plus the odometry's share ``w = v_filter / (v_filter + v_odometry)`` of
their difference (:func:`reweighted_chain`), the translation staying the filter's. A step where
the two disagree far beyond the log's usual (a wheel slip, which the filter's slip search took)
keeps the filter's heading (:func:`odometry_slips`). The loop closure searches again from that
chain, and measures the rates again from its loops, until the share settles
(:func:`jaxslam.graph.closure.close_trajectory_loops`). On the classic logs the odometry's
heading drifts 40-170 times faster than the filter's (std per square-root step; w under 0.001):
one pass, nothing changes. On FR-clinic the filter's drifts 5.8 times faster (w 0.97).
"""

from __future__ import annotations

import numpy as np

from jaxslam.geometry import between_np, chain_np, wrap_angle_np


def heading_drift_rates(first: np.ndarray, second: np.ndarray, measured_heading: np.ndarray,
                        filter_headings: np.ndarray, odometry_headings: np.ndarray) -> tuple[float, float]:
    """Each chain's heading variance per step (rad^2), from loops: loop ``l`` measures the
    heading of node ``second[l]`` relative to node ``first[l]`` as ``measured_heading[l]``;
    a chain's error over the loop is its own relative heading minus that, and under a random
    walk its variance is the rate times the steps spanned: the maximum-likelihood rate is the
    sum of squared errors over the sum of the spans.

    Args:
        first, second: (L,) int node indices, ``first < second``.
        measured_heading: (L,) rad.
        filter_headings: (S,) the filter's heading at each node (rad).
        odometry_headings: (S,) the odometry's heading at each node, in any frame (rad).

    Returns:
        ``(filter_rate, odometry_rate)`` in rad^2 per step; nan for no loops.
    """
    first, second = np.asarray(first), np.asarray(second)
    if first.shape != second.shape or np.shape(measured_heading) != first.shape:
        raise ValueError(f"heading_drift_rates: first, second and measured_heading must have one shape, got "
                         f"{first.shape}, {second.shape} and {np.shape(measured_heading)}")
    if np.any(second <= first):
        raise ValueError("heading_drift_rates: every loop's second node must come after its first")
    spans = np.sum(second - first)
    if spans == 0:
        return float("nan"), float("nan")

    def rate(headings):
        err = wrap_angle_np(headings[second] - headings[first] - measured_heading)
        return float(np.sum(err ** 2) / spans)

    return rate(np.asarray(filter_headings, np.float64)), rate(np.asarray(odometry_headings, np.float64))


def odometry_slips(filter_steps: np.ndarray, odometry_steps: np.ndarray, slip_z: float = 4.0) -> np.ndarray:
    """(S-1,) bool: the steps whose heading change the odometry and the filter disagree on by more
    than ``slip_z`` robust stds (1.4826 times the median absolute deviation) of all the steps'
    disagreements: where the wheels slipped, or the filter jumped, the odometry's heading is
    no measurement of the step ((S-1, 3) relative steps each)."""
    diff = wrap_angle_np(np.asarray(odometry_steps)[:, 2] - np.asarray(filter_steps)[:, 2])
    spread = 1.4826 * np.median(np.abs(diff - np.median(diff)))
    return np.abs(diff - np.median(diff)) > slip_z * spread


def reweighted_chain(filter_poses: np.ndarray, motions: np.ndarray, odometry_share: float,
                     slips: np.ndarray) -> np.ndarray:
    """(S, 3) the chain from the filter's first pose whose steps are the filter's, each heading
    change moved by ``odometry_share`` (0..1) of the way to the odometry's, but at ``slips``.

    Args:
        filter_poses: (S, 3) the filter's node poses (m, m, rad).
        motions: (S, 3) the odometry's motion from the previous node in its frame (row 0 unused).
        odometry_share: the odometry's share w of each heading change.
        slips: (S-1,) bool: :func:`odometry_slips`.
    """
    filter_poses = np.asarray(filter_poses, np.float64)
    steps = between_np(filter_poses[:-1], filter_poses[1:])
    diff = wrap_angle_np(np.asarray(motions, np.float64)[1:, 2] - steps[:, 2])
    steps[:, 2] += np.where(slips, 0.0, odometry_share * diff)
    return chain_np(filter_poses[0], steps)
