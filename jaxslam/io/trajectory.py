"""Trajectories: a pose per scan of a log, read and written as text.

A filter processes only the scans that :func:`jaxslam.laserlog.select_updates`
picks, but the relations of Kümmerle et al. (and any per-scan metric) need a pose
at every scan's timestamp. :func:`trajectory_per_scan` fills the skipped scans in
with the odometry motion since the nearest processed scan.

The text format is one line ``timestamp x y theta`` (s, m, m, rad) per scan,
after ``#`` comment lines.

:func:`poses_at` reads a time-stamped pose stream (odometry, ground truth) at
other timestamps; the log readers use it to pair each scan with odometry.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from jaxslam.geometry import between, compose, interpolate, wrap_angle_np
from jaxslam.laserlog import LaserLog, LogError, last_of_each_timestamp
from jaxslam.warn import warn

__all__ = [
    "PosesAt",
    "poses_at",
    "read_trajectory",
    "trajectory_per_scan",
    "write_trajectory",
]


class PosesAt(NamedTuple):
    """Poses of a time-stamped stream read at query timestamps."""

    poses: np.ndarray
    """(Q, 3) float64 [x, y, theta] (m, m, rad) at each query time; rows outside the stream's
    time span are zero (see ``covered``)."""
    covered: np.ndarray
    """(Q,) bool: whether the query time lies within [first, last] stream timestamp."""


def poses_at(query_times, stream_times, stream_poses) -> PosesAt:
    """Interpolate a pose stream at ``query_times`` with :func:`jaxslam.geometry.interpolate`.

    Args:
        query_times: (Q,) seconds, any order.
        stream_times: (M,) seconds, non-decreasing (equal neighbours allowed), M >= 1.
        stream_poses: (M, 3) poses [x, y, theta] (m, m, rad) at ``stream_times``.

    Returns:
        :class:`PosesAt`: (Q, 3) float64 poses and a (Q,) mask of the query times inside the
        stream's span. A query equal to a stream timestamp gets that stream pose exactly;
        one strictly between two stream messages gets the pose that fraction of the way
        along the relative motion between them. Queries outside the span are not
        extrapolated: the caller decides what to do with them (the readers drop and warn).
    """
    query = np.asarray(query_times, dtype=np.float64).reshape(-1)
    times = np.asarray(stream_times, dtype=np.float64).reshape(-1)
    poses = np.asarray(stream_poses, dtype=np.float64).reshape(-1, 3)
    if times.size == 0 or poses.shape[0] != times.size:
        raise ValueError(f"poses_at needs M >= 1 times and (M, 3) poses, got {times.shape} and {poses.shape}")
    if np.any(np.diff(times) < 0):
        raise ValueError("poses_at needs non-decreasing stream timestamps")
    covered = (query >= times[0]) & (query <= times[-1])
    # Index of the last stream message at or before each query (side="right" so that with
    # equal neighbours the later one is taken; then times[j + 1] > query strictly).
    before = np.clip(np.searchsorted(times, query, side="right") - 1, 0, times.size - 1)
    after = np.minimum(before + 1, times.size - 1)
    span = times[after] - times[before]
    exact = (query == times[before]) | (span <= 0)
    fraction = np.where(exact, 0.0, (query - times[before]) / np.where(span > 0, span, 1.0))
    fraction = np.clip(fraction, 0.0, 1.0)
    result = np.asarray(interpolate(poses[before], poses[after], fraction), dtype=np.float64)
    # Exact hits keep the stream pose bit for bit (interpolate runs in float32).
    result = np.where(exact[:, None], poses[before], result)
    result = np.where(covered[:, None], result, 0.0)
    return PosesAt(result, covered)


def trajectory_per_scan(log: LaserLog, processed_indices, processed_poses) -> np.ndarray:
    """A pose for every scan of ``log`` from the poses of the processed scans.

    At a processed scan the result is its pose. At a skipped scan ``i`` it is the pose of
    the nearest processed scan ``k`` before it composed with the odometry motion since:
    ``compose(pose[k], between(odom[k], odom[i]))``. Scans before the first processed one
    use the first processed scan the same way (the motion is then backwards in time).

    Args:
        log: the log the filter ran on (T scans).
        processed_indices: (S,) int, strictly increasing scan indices in [0, T), S >= 1.
        processed_poses: (S, 3) poses [x, y, theta] (m, m, rad) estimated at those scans.

    Returns:
        (T, 3) float64 poses (m, m, rad), theta wrapped to (-pi, pi].
    """
    idx = np.asarray(processed_indices).reshape(-1)
    poses = np.asarray(processed_poses, dtype=np.float64)
    if idx.size == 0:
        raise ValueError("trajectory_per_scan needs at least one processed scan")
    if not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"processed_indices must be integers, got dtype {idx.dtype}")
    if poses.shape != (idx.size, 3):
        raise ValueError(f"processed_poses has shape {poses.shape}, expected ({idx.size}, 3)")
    if np.any(np.diff(idx) <= 0):
        raise ValueError("processed_indices must be strictly increasing")
    if idx[0] < 0 or idx[-1] >= log.num_scans:
        raise ValueError(f"processed_indices must lie in [0, {log.num_scans}), got {idx[0]}..{idx[-1]}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("processed_poses must be finite")
    scans = np.arange(log.num_scans)
    # The processed scan each scan hangs off: the last one at or before it, else the first.
    anchor = np.clip(np.searchsorted(idx, scans, side="right") - 1, 0, idx.size - 1)
    odom = log.odometry
    motion = between(odom[idx[anchor]], odom)
    result = np.asarray(compose(poses[anchor], motion), dtype=np.float64)
    # Processed scans keep their pose exactly (compose runs in float32).
    result[idx] = poses
    result[idx, 2] = wrap_angle_np(poses[:, 2])
    return result


def write_trajectory(path, timestamps, poses) -> None:
    """Write a trajectory as text: a header comment, then ``timestamp x y theta`` per line.

    Args:
        path: file to write (overwritten).
        timestamps: (T,) seconds, written with 9 decimals (nanoseconds).
        poses: (T, 3) [x, y, theta] (m, m, rad), written with 9 decimals.
    """
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    ps = np.asarray(poses, dtype=np.float64)
    if ps.shape != (ts.size, 3):
        raise ValueError(f"poses has shape {ps.shape}, expected ({ts.size}, 3) to match the timestamps")
    if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(ps))):
        raise ValueError("timestamps and poses must be finite")
    table = np.column_stack([ts, ps])
    header = "jaxslam trajectory: one pose per scan\ntimestamp x y theta  (s, m, m, rad)"
    np.savetxt(os.fspath(path), table, fmt="%.9f", header=header, comments="# ")


def read_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a trajectory written by :func:`write_trajectory` (or any ``t x y theta`` text).

    Blank lines and lines starting with ``#`` are skipped. Every other line must hold
    exactly four finite numbers, and timestamps must not decrease; a line that breaks
    this raises :class:`~jaxslam.laserlog.LogError` naming the file and line. Of poses that
    share a timestamp only the last is kept, with a ``UserWarning`` naming the lines (the
    rule ``jaxslam map`` applies to a log's scans).

    Returns:
        timestamps (T,) float64 seconds and poses (T, 3) float64 [x, y, theta] (m, m, rad).
    """
    src = os.fspath(path)
    rows: list[list[float]] = []
    try:
        with open(src, encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        raise LogError(f"{src}: no such trajectory file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise LogError(f"{src}: cannot read the trajectory file ({err})") from None
    last_time = -np.inf
    line_of: list[int] = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.split()
        if len(fields) != 4:
            raise LogError(f"{src}:{line_no}: expected 4 fields 'timestamp x y theta', got {len(fields)}")
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise LogError(f"{src}:{line_no}: non-numeric field in {stripped!r}") from None
        if not all(np.isfinite(values)):
            raise LogError(f"{src}:{line_no}: non-finite value in {stripped!r}")
        if values[0] < last_time:
            raise LogError(f"{src}:{line_no}: timestamp goes backwards ({last_time:.9f} -> {values[0]:.9f})")
        last_time = values[0]
        rows.append(values)
        line_of.append(line_no)
    if not rows:
        raise LogError(f"{src}: the trajectory file holds no poses")
    table = np.asarray(rows, dtype=np.float64)
    last = last_of_each_timestamp(table[:, 0])
    if not last.all():
        i = int(np.argmin(last))
        warn(
            f"{src}: {int(np.sum(~last))} poses repeat the timestamp of the next pose (first: lines {line_of[i]} and "
            f"{line_of[i + 1]} at t={table[i, 0]:.9f}); of each repeated timestamp only the last pose is kept "
            "(the rule jaxslam map applies to the scans of a log)")
        table = table[last]
    return table[:, 0].copy(), table[:, 1:].copy()
