"""Accuracy metrics of estimated trajectories, one section per metric.

All metrics run on the host (NumPy) on per-scan trajectories: timestamps (T,) in
seconds and poses (T, 3) [x, y, theta] (m, m, rad), e.g. from
:func:`jaxslam.laserlog.trajectory_per_scan`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from jaxslam.geometry import between_np, wrap_angle_np
from jaxslam.io.relations import Relations

__all__ = [
    "RelationError", "absolute_trajectory_error", "checkpoint_passages", "lookup_indices", "lookup_poses",
    "motion_error_components", "motion_errors", "normalized_weights", "passage_errors", "relation_error", "revisiting_accuracy",
    "ScanSupport", "scan_support",
]


# ---------------------------------------------------------------------------
# Shared helpers
# ---------------------------------------------------------------------------


def lookup_indices(timestamps, query_times, time_tolerance: float = 1e-4) -> np.ndarray:
    """The index of each query's trajectory timestamp, matched exactly (within a tolerance).

    Args:
        timestamps: (T,) trajectory timestamps (s), any order, finite.
        query_times: (Q,) timestamps (s) to look up.
        time_tolerance: largest |query - trajectory timestamp| (s) that counts as a match.

    Returns:
        (Q,) int: for each query, the index into ``timestamps`` of the nearest one.

    Raises:
        ValueError: a query timestamp has no trajectory timestamp within the tolerance
            (the message names it): a metric never silently skips a pose.
    """
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    query = np.asarray(query_times, dtype=np.float64).reshape(-1)
    order = np.argsort(ts, kind="stable")
    sorted_ts = ts[order]
    right = np.clip(np.searchsorted(sorted_ts, query), 0, ts.size - 1)
    left = np.clip(right - 1, 0, ts.size - 1)
    nearest = np.where(np.abs(sorted_ts[left] - query) <= np.abs(sorted_ts[right] - query), left, right)
    gap = np.abs(sorted_ts[nearest] - query)
    missing = np.nonzero(~(gap <= time_tolerance))[0]
    if missing.size:
        k = int(missing[0])
        raise ValueError(
            f"timestamp {query[k]:.6f} (query {k}) is not in the trajectory: the nearest trajectory "
            f"timestamp is {sorted_ts[nearest[k]]:.6f} ({gap[k]:.3g} s away, tolerance {time_tolerance} s); "
            f"{missing.size} of {query.size} queries are missing"
        )
    return order[nearest]


def lookup_poses(timestamps, poses, query_times, time_tolerance: float = 1e-4) -> np.ndarray:
    """The poses of a trajectory at given timestamps, matched exactly (within a tolerance).

    Args:
        timestamps: (T,) trajectory timestamps (s), any order.
        poses: (T, 3) poses [x, y, theta] (m, m, rad) at ``timestamps``.
        query_times: (Q,) timestamps (s) to look up.
        time_tolerance: largest |query - trajectory timestamp| (s) that counts as a match.

    Returns:
        (Q, 3) float64: for each query, the pose at the nearest trajectory timestamp.

    Raises:
        ValueError: a query timestamp has no trajectory timestamp within the tolerance
            (the message names it, :func:`lookup_indices`).
    """
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    ps = np.asarray(poses, dtype=np.float64)
    if ts.size == 0 or ps.shape != (ts.size, 3):
        raise ValueError(f"need T >= 1 timestamps and (T, 3) poses, got {ts.shape} and {ps.shape}")
    if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(ps))):
        raise ValueError("trajectory timestamps and poses must be finite")
    return ps[lookup_indices(ts, query_times, time_tolerance)]


# ---------------------------------------------------------------------------
# Relation error (Kümmerle et al. 2009)
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class RelationError:
    """Errors of a trajectory's relative motions against ground-truth relations.

    Rotational values are in radians (``to_dict`` adds degrees). Standard deviations are
    population ones (ddof = 0) over the relations.
    """

    trans: np.ndarray
    """(R,) float64 translational error (m) of each relation."""
    rot: np.ndarray
    """(R,) float64 absolute rotational error (rad) of each relation, in [0, pi]."""
    trans_mean: float
    trans_std: float
    trans_max: float
    rot_mean: float
    rot_std: float
    rot_max: float
    trans2_mean: float
    """Mean of the squared translational errors (m^2)."""
    trans2_std: float
    rot2_mean: float
    """Mean of the squared rotational errors (rad^2)."""
    rot2_std: float
    count: int
    """Number of relations R."""

    def to_dict(self) -> dict:
        """Summary as plain floats (JSON-ready), with degree versions of the rotational ones
        (``*_deg``; squared ones in deg^2 as ``rot2_*_deg2``). Per-relation arrays are left out."""
        deg = 180.0 / math.pi
        summary = {
            f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("trans", "rot")
        }
        summary.update(
            rot_mean_deg=self.rot_mean * deg,
            rot_std_deg=self.rot_std * deg,
            rot_max_deg=self.rot_max * deg,
            rot2_mean_deg2=self.rot2_mean * deg**2,
            rot2_std_deg2=self.rot2_std * deg**2,
        )
        return summary


def motion_error_components(first, second, motion) -> np.ndarray:
    """The signed error of estimated motions against true ones, in ``first``'s frame:
    ``between(first, second) - motion`` with the heading wrapped (m, m, rad; along, across, heading
    for a robot's own frame).

    Args:
        first, second: (..., 3) the estimated poses at each motion's start and end.
        motion: (..., 3) the true motions (broadcast against them).

    Returns:
        (..., 3) float64, of the broadcast leading shape.
    """
    error = between_np(first, second) - np.asarray(motion, np.float64)
    error[..., 2] = wrap_angle_np(error[..., 2])
    return error


def motion_errors(first, second, motion) -> tuple[np.ndarray, np.ndarray]:
    """The relation errors of estimated poses: ``e_trans = || between(first, second)[:2] -
    motion[:2] ||`` (m) and ``e_rot = | wrap(between(first, second)[2] - motion[2]) |`` (rad).

    Args:
        first, second: (..., 3) the estimated poses at each relation's t1 and t2.
        motion: (..., 3) the relations' true motions (broadcast against them).

    Returns:
        ``(trans, rot)``, each of the broadcast leading shape.
    """
    error = motion_error_components(first, second, motion)
    return np.hypot(error[..., 0], error[..., 1]), np.abs(error[..., 2])


def relation_error(timestamps, poses, relations: Relations, time_tolerance: float = 1e-4) -> RelationError:
    """Kümmerle et al.'s relation-based error of a trajectory.

    For each relation (t1, t2, motion): the estimated motion is ``between(x(t1), x(t2))``
    (the pose at t2 in the frame of the pose at t1, also when t1 > t2), and

        e_trans = || est[:2] - motion[:2] ||,   e_rot = | wrap(est[2] - motion[2]) |.

    Args:
        timestamps: (T,) trajectory timestamps (s): a pose per scan of the log.
        poses: (T, 3) [x, y, theta] (m, m, rad).
        relations: R relations (:func:`jaxslam.io.relations.read_relations`), R >= 1.
        time_tolerance: largest gap (s) between a relation's timestamp and the trajectory's.

    Returns:
        :class:`RelationError` with per-relation errors and their summaries.

    Raises:
        ValueError: a relation timestamp is not in the trajectory (named in the message),
            or there are no relations.
    """
    t1 = np.asarray(relations.t1, dtype=np.float64).reshape(-1)
    t2 = np.asarray(relations.t2, dtype=np.float64).reshape(-1)
    motion = np.asarray(relations.motion, dtype=np.float64)
    if t1.size == 0:
        raise ValueError("relation_error needs at least one relation")
    if t2.shape != t1.shape or motion.shape != (t1.size, 3):
        raise ValueError(f"relations have inconsistent shapes {t1.shape}, {t2.shape}, {motion.shape}")
    x1 = lookup_poses(timestamps, poses, t1, time_tolerance)
    x2 = lookup_poses(timestamps, poses, t2, time_tolerance)
    trans, rot = motion_errors(x1, x2, motion)
    return RelationError(
        trans=trans,
        rot=rot,
        trans_mean=float(np.mean(trans)),
        trans_std=float(np.std(trans)),
        trans_max=float(np.max(trans)),
        rot_mean=float(np.mean(rot)),
        rot_std=float(np.std(rot)),
        rot_max=float(np.max(rot)),
        trans2_mean=float(np.mean(trans**2)),
        trans2_std=float(np.std(trans**2)),
        rot2_mean=float(np.mean(rot**2)),
        rot2_std=float(np.std(rot**2)),
        count=int(t1.size),
    )


class ScanSupport(NamedTuple):
    """Which motion each checked relation's own two scans favour (:func:`scan_support`)."""

    checked: np.ndarray
    """(R,) bool: the relations checked (near in time, and the trajectory off by more than ``min_error``)."""
    relation_inliers: np.ndarray
    """(R,) float64: the share of the second scan's points that the relation's motion lays near the
    first scan's (nan where not checked)."""
    trajectory_inliers: np.ndarray
    """(R,) float64: the same under the trajectory's motion (nan where not checked)."""

    def summary(self, trans: np.ndarray, margin: float = 0.05) -> dict:
        """Counts for ``jaxslam eval``: checked; favouring the trajectory, and the relation (the one
        whose inlier share is higher by more than ``margin``); and each group's share of the
        summed translational error ``trans`` (R,) m."""
        trajectory = self.checked & (self.trajectory_inliers > self.relation_inliers + margin)
        relation = self.checked & (self.relation_inliers > self.trajectory_inliers + margin)
        total = float(np.sum(trans))
        share = (lambda mask: float(np.sum(trans[mask]) / total) if total > 0 else 0.0)
        return {"checked": int(self.checked.sum()), "favour_trajectory": int(trajectory.sum()),
                "favour_relation": int(relation.sum()), "favour_trajectory_error_share": share(trajectory),
                "favour_relation_error_share": share(relation), "margin": float(margin)}


def scan_support(relations: Relations, timestamps, poses, trans: np.ndarray, scan_timestamps, ranges,
                 sensor, max_seconds: float = 60.0, min_error: float = 0.1, max_range: float = 15.0,
                 num_points: int = 180, inlier_distance: float = 0.1, time_tolerance: float = 1e-4) -> ScanSupport:
    """Whose error is it: for each relation whose two scans are at most ``max_seconds`` apart and
    on which the trajectory is more than ``min_error`` off, lay the second scan over the first
    under the relation's motion and under the trajectory's, and count the second scan's points
    within ``inlier_distance`` of the first's (:func:`jaxslam.laser.scan_inliers`).

    A relation is the motion that lays its two scans over each other, so where the trajectory's
    motion lays them better, the relation is the one off. Seed 0's closed trajectories (before
    the refinement), at the 0.05 margin of :meth:`ScanSupport.summary`:
    - Intel: the scans favour the relation in 133 of its 137 such relations;
    - MIT CSAIL: the relation in 95 of 107;
    - FR-clinic: the trajectory in 526 of 708, and the relation in 53
      (docs/design.md, "Whose error it is").

    It counts inliers rather than taking the capped squared distance of
    :func:`jaxslam.laser.scan_misfit`: on FR-clinic the long returns that one scan saw and the
    other did not swamped the latter.

    Args:
        relations: R relations, their timestamps on the log's clock.
        timestamps, poses: the trajectory (T,) s and (T, 3) (m, m, rad), a pose per scan.
        trans: (R,) the trajectory's translational error on each relation (m;
            :attr:`RelationError.trans`).
        scan_timestamps: (N,) the log's scan timestamps (s); ``ranges`` (N, B) its scans (m);
            ``sensor`` its laser (:class:`jaxslam.laser.SensorSpec`).
        max_range, num_points: the points taken of each scan (:func:`jaxslam.laser.scan_points`).

    Raises:
        ValueError: ``trans`` does not hold one error per relation, or a checked relation's scan is
            not in the log (named).
    """
    from jaxslam.laser import scan_inliers, scan_points  # here: the other metrics need no JAX

    t1, t2 = np.asarray(relations.t1, np.float64), np.asarray(relations.t2, np.float64)
    trans = np.asarray(trans, np.float64)
    if trans.shape != t1.shape:
        raise ValueError(f"scan_support: trans must hold one error per relation ({t1.shape}), got {trans.shape}")
    checked = (np.abs(t2 - t1) <= max_seconds) & (trans > min_error)
    relation_inliers = np.full(t1.shape, np.nan)
    trajectory_inliers = np.full(t1.shape, np.nan)
    rows = np.flatnonzero(checked)
    if rows.size:
        first = lookup_indices(scan_timestamps, t1[rows], time_tolerance)
        second = lookup_indices(scan_timestamps, t2[rows], time_tolerance)
        needed, inverse = np.unique(np.concatenate([first, second]), return_inverse=True)
        points, valid = scan_points(np.asarray(ranges)[needed], sensor, max_range, num_points)
        estimated = between_np(lookup_poses(timestamps, poses, t1[rows], time_tolerance),
                               lookup_poses(timestamps, poses, t2[rows], time_tolerance))
        motions = np.stack([np.asarray(relations.motion, np.float64)[rows], estimated], axis=1)  # (C, 2, 3)
        for k, row in enumerate(rows):
            a, b = inverse[k], inverse[rows.size + k]
            relation_inliers[row], trajectory_inliers[row] = scan_inliers(
                motions[k], points[a][valid[a]], points[b][valid[b]], inlier_distance)
    return ScanSupport(checked, relation_inliers, trajectory_inliers)


# ---------------------------------------------------------------------------
# Revisiting accuracy (Grzonka et al.)
# ---------------------------------------------------------------------------
# Revisiting accuracy (RA) of Grzonka et al.: how well a filter closes the loop at a checkpoint.
#
# The robot passes over a checkpoint X at the start and again at the end of a run. Every
# SLAM particle's path contains an estimate of both passages; a filter that kept the right
# hypothesis puts the two estimates in the same relation as the true poses (the same place,
# when the robot truly is back at X). For each particle i with normalised weight w_i,
#
#     e_i = || t_i || + lambda * | theta_i |,   (t_i, theta_i) = between(true_rel, est_rel_i)
#
# where ``est_rel_i = between(x_i[first], x_i[last])`` is the particle's relative pose
# between the first and last passage and ``true_rel`` the same from ground truth; then
#
#     RA = sum_i w_i e_i      (m, with lambda in m/rad).
#
# The paper counts a run as a success when RA < 0.2.


def checkpoint_passages(true_poses: np.ndarray, checkpoint, radius: float) -> np.ndarray:
    """Indices of the closest approaches of a path to ``checkpoint``.

    A passage is a maximal run of consecutive poses within ``radius`` metres of the
    checkpoint; each contributes the index of its closest pose (the first on a tie).

    Args:
      true_poses: (T, 3) or (T, 2) ground-truth path (m).
      checkpoint: (2,) position of X (m).
      radius: the disc (m) that counts as passing over X.

    Returns:
      (P,) int64 increasing indices (empty when the path never comes within ``radius``).
    """
    xy = np.asarray(true_poses, np.float64)[:, :2]
    dist = np.hypot(*(xy - np.asarray(checkpoint, np.float64)[None, :]).T)
    inside = np.concatenate([[0], (dist <= radius).astype(np.int8), [0]])
    edges = np.diff(inside)
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    return np.array([a + int(np.argmin(dist[a:b])) for a, b in zip(starts, stops)], dtype=np.int64)


def passage_errors(
    paths: np.ndarray,
    first: int,
    last: int,
    true_first,
    true_last,
    rotation_weight: float = 1.0,
) -> np.ndarray:
    """Per-particle error e_i (m) of the relative pose between two passages.

    Args:
      paths: (N, S, 3) every particle's path, indexed like ``first`` and ``last``.
      first, last: indices into the paths of the first and last passage.
      true_first, true_last: (3,) the true poses there.
      rotation_weight: lambda (m/rad) weighting the rotational error.

    Returns:
      (N,) ||translation error|| + lambda * |rotation error|.
    """
    paths = np.asarray(paths, np.float64)
    est = between_np(paths[:, first], paths[:, last])
    true = between_np(true_first, true_last)
    diff = between_np(np.broadcast_to(true, est.shape), est)
    return np.hypot(diff[:, 0], diff[:, 1]) + rotation_weight * np.abs(wrap_angle_np(diff[:, 2]))


def normalized_weights(log_weights) -> np.ndarray:
    """(N,) float64 weights summing to one from (N,) log-weights (any normalisation; -inf allowed,
    not all): host-side, for metrics over a filter's particles."""
    log_w = np.asarray(log_weights, np.float64)
    if not np.any(np.isfinite(log_w)):
        raise ValueError("every particle has weight zero")
    w = np.exp(log_w - np.max(log_w))
    return w / w.sum()


def revisiting_accuracy(
    paths: np.ndarray,
    log_weights: np.ndarray,
    first: int,
    last: int,
    true_first,
    true_last,
    rotation_weight: float = 1.0,
) -> float:
    """RA = sum_i w_i e_i: the weighted mean over particles of :func:`passage_errors`.

    Args:
      paths: (N, S, 3) each final particle's path (its ancestry).
      log_weights: (N,) log-weights (any normalisation; -inf allowed, not all).
      first, last: path indices of the first and last passage over X.
      true_first, true_last: (3,) ground-truth poses at those passages.
      rotation_weight: lambda (m/rad).

    Returns:
      RA in metres (lower is better; the paper's success threshold is 0.2).
    """
    errors = passage_errors(paths, first, last, true_first, true_last, rotation_weight)
    return float(np.sum(normalized_weights(log_weights) * errors))


# ---------------------------------------------------------------------------
# Absolute trajectory error (simulated runs, where the truth is known)
# ---------------------------------------------------------------------------


def absolute_trajectory_error(estimated, truth, align: bool = True) -> dict:
    """Position RMSE (m) and mean heading error (rad) of a trajectory against the truth.

    Args:
      estimated, truth: (T, 3) poses at the same instants.
      align: first move ``estimated`` by the rigid SE(2) motion that best fits it to the
        truth in least squares (a SLAM map's frame is arbitrary up to such a motion).

    Returns:
      ``{"rmse", "mean", "max"}`` of the position errors (m) and ``"rot_mean"`` (rad).
    """
    est = np.asarray(estimated, np.float64)
    ref = np.asarray(truth, np.float64)
    if est.shape != ref.shape or est.ndim != 2 or est.shape[1] != 3:
        raise ValueError(f"trajectories must both be (T, 3), got {est.shape} and {ref.shape}")
    if align:
        mu_e, mu_r = est[:, :2].mean(axis=0), ref[:, :2].mean(axis=0)
        cross = (est[:, :2] - mu_e).T @ (ref[:, :2] - mu_r)  # 2x2
        angle = math.atan2(cross[0, 1] - cross[1, 0], cross[0, 0] + cross[1, 1])
        c, s = math.cos(angle), math.sin(angle)
        xy = (est[:, :2] - mu_e) @ np.array([[c, s], [-s, c]]) + mu_r
        est = np.column_stack([xy, est[:, 2] + angle])
    dist = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
    rot = np.abs(wrap_angle_np(est[:, 2] - ref[:, 2]))
    return {"rmse": float(np.sqrt(np.mean(dist**2))), "mean": float(dist.mean()), "max": float(dist.max()),
            "rot_mean": float(rot.mean())}
