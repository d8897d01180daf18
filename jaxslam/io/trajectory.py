"""Trajectories as text: one line ``timestamp x y theta`` (s, m, m, rad) per scan, after ``#``
comment lines. The pose of every scan is filled in from the processed ones by
:func:`jaxslam.laserlog.trajectory_per_scan`.
"""

from __future__ import annotations

import os
import numpy as np

from jaxslam.laserlog import LogError, last_of_each_timestamp
from jaxslam.warn import warn

__all__ = [
    "read_trajectory",
    "write_trajectory",
]


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
