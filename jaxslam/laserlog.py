"""The one data type every reader and the simulator produce: :class:`LaserLog`.

A log lives on the host (NumPy). Update selection (GMapping's linear/angular
thresholds) happens here, before the filter: :func:`select_updates` picks the
scans the filter processes and composes the odometry between them into one
motion each.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from jaxslam.geometry import between
from jaxslam.laser import SensorSpec


class LogError(ValueError):
    """A log (file or in-memory) is malformed; the message names the source and the place."""


@dataclasses.dataclass(frozen=True, eq=False)
class LaserLog:
    """A 2-D laser log: one row per scan, odometry read at each scan's timestamp."""

    timestamps: np.ndarray
    """(T,) float64 seconds, non-decreasing."""
    odometry: np.ndarray
    """(T, 3) float64 odometry poses [x, y, theta] (m, m, rad) at each scan's timestamp."""
    ranges: np.ndarray
    """(T, B) float32 ranges in metres; ``>= sensor.range_max`` means "no return"."""
    sensor: SensorSpec
    """The laser: beam angles, valid range interval, mounting pose on the robot."""
    ground_truth: np.ndarray | None = None
    """Optional (T, 3) float64 true poses, for simulated logs."""
    source: str = "<memory>"
    """Where the log came from (a path), used in error messages."""
    notes: tuple[str, ...] = ()
    """What the reader changed or assumed while reading (e.g. scans padded to a common beam
    layout), one sentence each; ``jaxslam map`` records them in ``summary.json``."""

    def __post_init__(self):
        ts = np.asarray(self.timestamps, dtype=np.float64)
        odom = np.asarray(self.odometry, dtype=np.float64)
        ranges = np.asarray(self.ranges, dtype=np.float32)
        object.__setattr__(self, "timestamps", ts)
        object.__setattr__(self, "odometry", odom)
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))
        src = self.source
        if ts.ndim != 1:
            raise LogError(f"{src}: timestamps have shape {ts.shape}, expected (T,) (one per scan)")
        if ts.shape[0] == 0:
            raise LogError(f"{src}: the log is empty (no scans)")
        num_scans = ts.shape[0]
        num_beams = int(np.shape(self.sensor.beam_angles)[0])
        if ranges.shape != (num_scans, num_beams):
            raise LogError(
                f"{src}: ranges have shape {ranges.shape}, expected ({num_scans}, {num_beams}) "
                "(scans x beams of the sensor)"
            )
        if odom.shape != (num_scans, 3):
            raise LogError(f"{src}: odometry has shape {odom.shape}, expected ({num_scans}, 3)")
        _check_finite(src, "timestamp", ts)
        _check_finite(src, "odometry", odom)
        bad = ~np.isfinite(ranges) | (ranges < 0)
        if bad.any():
            scan, beam = np.argwhere(bad)[0]
            raise LogError(
                f"{src}: scan {scan} (t={ts[scan]:.6f}) beam {beam} has range {ranges[scan, beam]!r}: "
                "ranges must be finite and non-negative"
            )
        back = np.nonzero(np.diff(ts) < 0)[0]
        if back.size:
            i = int(back[0])
            raise LogError(
                f"{src}: timestamps go backwards at scan {i + 1} ({ts[i]:.6f} -> {ts[i + 1]:.6f})"
            )
        if self.ground_truth is not None:
            gt = np.asarray(self.ground_truth, dtype=np.float64)
            object.__setattr__(self, "ground_truth", gt)
            if gt.shape != (num_scans, 3):
                raise LogError(f"{src}: ground truth has shape {gt.shape}, expected ({num_scans}, 3)")
            _check_finite(src, "ground truth", gt)

    @property
    def num_scans(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def num_beams(self) -> int:
        return int(self.ranges.shape[1])

    @property
    def duration(self) -> float:
        """Seconds from the first to the last scan."""
        return float(self.timestamps[-1] - self.timestamps[0])

    def subset(self, indices) -> "LaserLog":
        """The scans at ``indices`` (sorted), as a new log."""
        idx = np.asarray(indices)
        gt = None if self.ground_truth is None else self.ground_truth[idx]
        return LaserLog(self.timestamps[idx], self.odometry[idx], self.ranges[idx], self.sensor, gt, self.source,
                        self.notes)


def _check_finite(src: str, what: str, values: np.ndarray) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.argwhere(bad)[0][0])
        raise LogError(f"{src}: scan {row} has a non-finite {what} {values[row]!r}")


class UpdateSelection(NamedTuple):
    """The scans the filter processes and the motion between them."""

    indices: np.ndarray
    """(S,) int indices into the log of the processed scans; the first is scan 0."""
    motions: np.ndarray
    """(S, 3) float32 odometry motion from the previous processed scan to this one, in the
    previous scan's robot frame; row 0 is zero."""


def select_updates(log: LaserLog, linear_update: float, angular_update: float) -> UpdateSelection:
    """GMapping's update rule: process a scan once the robot has moved ``linear_update``
    metres or turned ``angular_update`` radians (odometry, accumulated along the path)
    since the last processed scan. The first scan is always processed.

    Both thresholds <= 0 process every scan.
    """
    odom = log.odometry
    steps = np.asarray(between(odom[:-1], odom[1:]), dtype=np.float64)
    step_lin = np.hypot(steps[:, 0], steps[:, 1])
    step_ang = np.abs(steps[:, 2])
    indices = [0]
    lin = ang = 0.0
    for i in range(1, log.num_scans):
        lin += step_lin[i - 1]
        ang += step_ang[i - 1]
        if lin >= linear_update or ang >= angular_update:
            indices.append(i)
            lin = ang = 0.0
    idx = np.asarray(indices, dtype=np.int64)
    motions = np.zeros((idx.size, 3), dtype=np.float64)
    motions[1:] = np.asarray(between(odom[idx[:-1]], odom[idx[1:]]))
    return UpdateSelection(idx, motions.astype(np.float32))
