"""Read a 2-D laser log from a CARMEN text log (``.clf``, ``.log``).

Laser lines are ``FLASER`` (old front laser: 180 degrees, both ends included,
odometry inside the line) or ``ROBOTLASER1`` (beam geometry and robot odometry
inside the line); a log holds one kind, not both. ``ODOM`` lines are a separate
odometry stream (``odometry_source="odom"`` reads it at the laser timestamps);
``TRUEPOS`` lines, where present, fill the ground truth. Comments (``#``) and
other messages (PARAM, SYNC, RAWLASER*, ...) are ignored. Line formats
(``ipc_timestamp`` is the timestamp used, in seconds)::

    FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp
    ROBOTLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode
        n r_1 .. r_n n_rem rem_1 .. rem_n_rem laser_x laser_y laser_theta robot_x robot_y robot_theta
        tv rv forward_safety side_safety turn_axis ipc_timestamp hostname logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp hostname logger_timestamp
    TRUEPOS true_x true_y true_theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp

Every malformed line raises :class:`~jaxslam.laserlog.LogError` naming the file
and the (1-based) line number.

Lines whose beam count (or, for ROBOTLASER1, start_angle / angular_res) changes
within a log are padded to one common beam layout by the rule of
:func:`jaxslam.io.beam_layouts.pad_beam_layouts`; FLASER lines of n readings span
-90..+90 degrees with both ends included, so FLASER lines of 180 and 181 readings
lie on different grids and are refused, while 181 and 361 readings interleave.
"""

from __future__ import annotations

import io
import math
import os

import numpy as np

from jaxslam.geometry import between_np, compose_np
from jaxslam.io.beam_layouts import BeamLayout, pad_beam_layouts
from jaxslam.io.rosbag import check_laser_pose
from jaxslam.laserlog import LaserLog, LogError, last_of_each_timestamp, poses_at
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.warn import warn

__all__ = ["FLASER_NO_RETURN", "read_carmen", "text_problem", "write_carmen"]

FLASER_NO_RETURN = 81.91
"""Range (m) that old CARMEN logs write for a beam with no return (SICK LMS maximum)."""

LASER_MESSAGES = ("FLASER", "ROBOTLASER1")
"""The laser message types the reader understands."""

# Fields after the ranges of a FLASER line: x y theta odom_x odom_y odom_theta ipc host logger.
_FLASER_TAIL = 9
# Fields after the remissions of a ROBOTLASER1 line: 11 pose/velocity fields + ipc host logger.
_ROBOTLASER_TAIL = 14
# Fields of ODOM and TRUEPOS lines after the message name.
_ODOM_FIELDS = 9
_TRUEPOS_FIELDS = 9
# Laser mounting (between robot and laser pose) may vary by print rounding only.
_LASER_POSE_TOLERANCE = 0.01
# ODOM and laser-line odometry disagree when a step between laser lines differs by more than this
# (m or rad) plus 10 % of the step.
_ODOM_TOLERANCE = 0.05


def read_carmen(path, range_max: float | None = None, odometry_source: str = "laser", laser_pose=None) -> LaserLog:
    """Read a CARMEN log with ``FLASER`` or ``ROBOTLASER1`` laser lines.

    Args:
        path: the text log.
        range_max: ranges at or above this (m) are "no return" and stored as exactly
            ``range_max``. None: 81.91 for FLASER logs, the line's ``max_range`` for
            ROBOTLASER1 logs.
        odometry_source: ``"laser"`` takes the odometry written in each laser line;
            ``"odom"`` interpolates the ``ODOM`` lines at the laser timestamps (laser lines
            outside the ODOM time span are dropped with a ``UserWarning`` naming how many).
        laser_pose: None takes the laser's mounting from the log (ROBOTLASER1 lines; zero for
            FLASER); ``(x, y, theta)`` (m, m, rad) in the robot frame is used instead
            (``jaxslam map --laser-pose x,y,theta``).

    Returns:
        A :class:`~jaxslam.laserlog.LaserLog`: timestamps (T,) s (``ipc_timestamp``),
        odometry (T, 3) [x, y, theta] (m, m, rad), ranges (T, B) m. FLASER beams span
        -90..+90 degrees with both ends included; ROBOTLASER1 beams are
        ``start_angle + i * angular_res`` and the laser's mounting pose is read from the
        first line. Ground truth comes from TRUEPOS lines (interpolated) when they cover
        every scan, else it is None (with a warning if TRUEPOS lines exist). Lines of
        different beam layouts are padded to a common one
        (:func:`jaxslam.io.beam_layouts.pad_beam_layouts`; a line's missing beams read 0 m, an
        invalid reading, and range_min becomes 1 mm) with one ``UserWarning``, and the
        log's ``notes`` say so.

    Raises:
        LogError: naming file and line, for a truncated or over-long line, a non-numeric
            field, a NaN or negative range, a non-finite pose, beams that leave the widest
            line's angular grid or range, a max_range that changes, timestamps that go
            backwards, FLASER and ROBOTLASER1 mixed in one log, no laser lines (or no ODOM
            lines with ``"odom"``).
    """
    if odometry_source not in ("laser", "odom"):
        raise ValueError(f"odometry_source must be 'laser' or 'odom', got {odometry_source!r}")
    mount = None if laser_pose is None else check_laser_pose(laser_pose)
    src = os.fspath(path)
    try:
        with open(src, "rb") as f:
            raw = f.read()
    except FileNotFoundError:
        raise LogError(f"{src}: no such CARMEN log") from None
    except OSError as err:
        raise LogError(f"{src}: cannot read the log ({err})") from None
    problem = text_problem(raw)
    if problem:
        raise LogError(f"{src}: {problem}")
    try:
        lines = raw.decode("utf-8-sig", errors="strict").splitlines()  # a UTF-8 byte-order mark is skipped
    except UnicodeDecodeError as err:
        raise LogError(f"{src}: not a text file ({err})") from None

    laser = _LaserLines(src)
    odom = _PoseStream("ODOM")
    truth = _PoseStream("TRUEPOS")
    for line_no, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        kind = fields[0]
        where = f"{src}:{line_no}"
        if kind in LASER_MESSAGES:
            laser.add(kind, fields, where)
        elif kind == "ODOM":
            odom.add(fields, _ODOM_FIELDS, where)
        elif kind == "TRUEPOS":
            truth.add(fields, _TRUEPOS_FIELDS, where)
    if not laser.times:
        if not any(line.split() and not line.split()[0].startswith("#") for line in lines):
            raise LogError(f"{src}: {ONLY_COMMENTS}")
        raise LogError(f"{src}: no laser lines (expected {' or '.join(LASER_MESSAGES)})")
    return laser.build(range_max, odometry_source, odom, truth, mount)


ONLY_COMMENTS = "holds only comments: no FLASER, ROBOTLASER1 or ODOM line"
UTF16 = "looks like UTF-16 text; save it as UTF-8 (or ASCII)"


def text_problem(head: bytes) -> str | None:
    """Why the first bytes of a file cannot be a CARMEN log's text, or None: UTF-16 (a byte-order
    mark FF FE / FE FF, or NUL bytes every other byte) or an empty file. A UTF-8 byte-order
    mark is fine (it is skipped)."""
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):
        return UTF16
    sample = head[:4096]
    if len(sample) >= 4:
        even, odd = sample[0::2], sample[1::2]
        for zeros, other in ((even, odd), (odd, even)):  # text of UTF-16 BE / LE: NUL bytes on one side only
            if zeros.count(0) >= 0.4 * len(zeros) and other.count(0) <= 0.05 * len(other):
                return UTF16
    if not head.removeprefix(b"\xef\xbb\xbf").strip():
        return "is empty"
    return None


def _numbers(fields: list[str], start: int, stop: int, where: str, what: str) -> np.ndarray:
    """fields[start:stop] as float64, or a LogError naming the first bad field (1-based)."""
    try:
        return np.asarray(fields[start:stop], dtype=np.float64)
    except ValueError:
        for k in range(start, stop):
            try:
                float(fields[k])
            except ValueError:
                raise LogError(f"{where}: field {k + 1} ({what}) is not a number: {fields[k]!r}") from None
        raise  # unreachable: some field failed above


def _integer(fields: list[str], k: int, where: str, what: str) -> int:
    """fields[k] as a non-negative int, or a LogError naming it."""
    if k >= len(fields):
        raise LogError(f"{where}: truncated line: {len(fields)} fields, no field {k + 1} ({what})")
    try:
        value = int(fields[k])
    except ValueError:
        raise LogError(f"{where}: field {k + 1} ({what}) is not a non-negative integer: {fields[k]!r}") from None
    if value < 0:
        raise LogError(f"{where}: field {k + 1} ({what}) is negative: {value}")
    return value


def _check_length(fields: list[str], expected: int, where: str, what: str) -> None:
    if len(fields) < expected:
        raise LogError(f"{where}: truncated {what} line: {len(fields)} fields, expected {expected}")
    if len(fields) > expected:
        raise LogError(f"{where}: {what} line has {len(fields)} fields, expected {expected}")


def _check_finite(values: np.ndarray, where: str, what: str) -> None:
    if not np.all(np.isfinite(values)):
        raise LogError(f"{where}: non-finite {what} {values.tolist()}")


class _PoseStream:
    """Time-stamped poses of ODOM or TRUEPOS lines (x y theta first, ipc_timestamp 7th)."""

    def __init__(self, kind: str):
        self.kind = kind
        self.times: list[float] = []
        self.poses: list[np.ndarray] = []

    def add(self, fields: list[str], num_fields: int, where: str) -> None:
        _check_length(fields, 1 + num_fields, where, self.kind)
        # Pose fields, then the numeric fields after (velocities, odometry) up to ipc_timestamp.
        values = _numbers(fields, 1, num_fields - 1, where, f"{self.kind} number")
        _numbers(fields, num_fields, num_fields + 1, where, "logger_timestamp")
        _check_finite(values, where, f"{self.kind} values")
        stamp = float(values[-1])
        if self.times and stamp < self.times[-1]:
            raise LogError(f"{where}: {self.kind} timestamp goes backwards ({self.times[-1]:.6f} -> {stamp:.6f})")
        self.times.append(stamp)
        self.poses.append(values[:3])

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.times, dtype=np.float64), np.asarray(self.poses, dtype=np.float64).reshape(-1, 3)


class _LaserLines:
    """Laser lines accumulated while reading, validated against the first one."""

    def __init__(self, src: str):
        self.src = src
        self.kind: str | None = None
        self.first_where = ""
        self.layouts: list[BeamLayout] = []  # in order of first appearance
        self.layout_keys: dict[tuple[float, float, int], int] = {}
        self.layout_of: list[int] = []
        self.geometry: tuple[float, float, float] | None = None  # first ROBOTLASER1 start, res, max_range
        self.laser_pose: np.ndarray | None = None  # ROBOTLASER1 mounting, robot frame
        self.laser_pose_varies = ""
        self.times: list[float] = []
        self.odometry: list[np.ndarray] = []
        self.ranges: list[np.ndarray] = []
        self.wheres: list[str] = []

    def add(self, kind: str, fields: list[str], where: str) -> None:
        if self.kind is None:
            self.kind, self.first_where = kind, where
        elif kind != self.kind:
            raise LogError(
                f"{where}: {kind} line in a log of {self.kind} lines (first at {self.first_where}); "
                "a log must hold one laser message type"
            )
        if kind == "FLASER":
            ranges, odometry, stamp = self._flaser(fields, where)
            start, resolution = -math.pi / 2, math.pi / max(ranges.size - 1, 1)
        else:
            ranges, odometry, stamp, (start, resolution) = self._robotlaser(fields, where)
        key = (start, resolution, int(ranges.size))
        if key not in self.layout_keys:
            if kind == "FLASER":
                angles = np.asarray(uniform_beams(ranges.size, math.pi), dtype=np.float64)
            else:
                angles = start + resolution * np.arange(ranges.size, dtype=np.float64)
            self.layout_keys[key] = len(self.layouts)
            self.layouts.append(BeamLayout(angles, resolution, where))
        if np.any(np.isnan(ranges)) or np.any(ranges < 0):
            beam = int(np.argmax(np.isnan(ranges) | (ranges < 0)))
            raise LogError(f"{where}: beam {beam} has range {float(ranges[beam])!r} (NaN or negative)")
        _check_finite(odometry, where, "odometry pose")
        if not math.isfinite(stamp):
            raise LogError(f"{where}: non-finite ipc_timestamp {stamp!r}")
        if self.times and stamp < self.times[-1]:
            raise LogError(f"{where}: timestamp goes backwards ({self.times[-1]:.6f} -> {stamp:.6f})")
        self.times.append(stamp)
        self.odometry.append(odometry)
        self.ranges.append(ranges)
        self.layout_of.append(self.layout_keys[key])
        self.wheres.append(where)

    def _flaser(self, fields: list[str], where: str):
        num_beams = _integer(fields, 1, where, "number of readings")
        if num_beams == 0:
            raise LogError(f"{where}: FLASER line with 0 readings")
        _check_length(fields, 2 + num_beams + _FLASER_TAIL, where, f"FLASER (n={num_beams})")
        ranges = _numbers(fields, 2, 2 + num_beams, where, "range")
        tail = 2 + num_beams
        poses = _numbers(fields, tail, tail + 7, where, "pose or ipc_timestamp")
        _numbers(fields, tail + 8, tail + 9, where, "logger_timestamp")
        return ranges, poses[3:6], float(poses[6])

    def _robotlaser(self, fields: list[str], where: str):
        header = _numbers(fields, 1, min(8, len(fields)), where, "laser settings")
        num_beams = _integer(fields, 8, where, "number of readings")
        if num_beams == 0:
            raise LogError(f"{where}: ROBOTLASER1 line with 0 readings")
        num_rem = _integer(fields, 9 + num_beams, where, "number of remissions")
        expected = 10 + num_beams + num_rem + _ROBOTLASER_TAIL
        _check_length(fields, expected, where, f"ROBOTLASER1 (n={num_beams}, n_remissions={num_rem})")
        _check_finite(header, where, "laser settings")
        start_angle, resolution, max_range = header[1], header[3], header[4]  # header[2]: the fov, implied
        ranges = _numbers(fields, 9, 9 + num_beams, where, "range")
        tail = 10 + num_beams + num_rem
        _numbers(fields, 10 + num_beams, tail, where, "remission")
        numbers = _numbers(fields, tail, tail + 12, where, "pose, velocity or ipc_timestamp")
        _numbers(fields, tail + 13, tail + 14, where, "logger_timestamp")
        laser_world, robot_world = numbers[0:3], numbers[3:6]
        _check_finite(laser_world, where, "laser pose")
        geometry = (float(start_angle), float(resolution), float(max_range))
        if self.geometry is None:
            if resolution == 0 or not max_range > 0:
                raise LogError(f"{where}: bad laser settings angular_res={resolution} max_range={max_range}")
            self.geometry = geometry
            self.laser_pose = between_np(robot_world, laser_world)  # float64: world poses
        else:
            # start_angle / angular_res may change (the beam layouts are merged in build).
            if resolution == 0:
                raise LogError(f"{where}: bad laser settings angular_res={resolution}")
            if geometry[2] != self.geometry[2]:
                raise LogError(f"{where}: max_range changes from {self.geometry[2]} to {geometry[2]}")
            mounting = between_np(robot_world, laser_world)
            if not self.laser_pose_varies and np.max(np.abs(mounting - self.laser_pose)) > _LASER_POSE_TOLERANCE:
                self.laser_pose_varies = where
        return ranges, robot_world, float(numbers[11]), geometry[:2]

    def build(self, range_max, odometry_source, odom: _PoseStream, truth: _PoseStream, mount=None) -> LaserLog:
        src = self.src
        found = []
        last = last_of_each_timestamp(self.times)
        if not last.all():
            i = int(np.argmin(last))
            found.append(
                f"{src}: {int(np.sum(~last))} laser lines repeat the timestamp of the next laser line (first: lines "
                f"{_line(self.wheres[i])} and {_line(self.wheres[i + 1])} at t={self.times[i]:.6f}); of each repeated "
                "timestamp only the last line is kept"
            )
            kept_lines = np.nonzero(last)[0]
            for name in ("times", "odometry", "ranges", "layout_of", "wheres"):
                values = getattr(self, name)
                setattr(self, name, [values[k] for k in kept_lines])
        times = np.asarray(self.times, dtype=np.float64)
        odometry = np.stack(self.odometry)
        if self.kind == "FLASER":
            default_max, laser_pose = FLASER_NO_RETURN, (0.0, 0.0, 0.0)
        else:
            default_max = self.geometry[2]
            laser_pose = tuple(self.laser_pose)
            if self.laser_pose_varies and mount is None:
                warn(
                    f"{self.laser_pose_varies}: the laser's pose on the robot differs by more than "
                    f"{_LASER_POSE_TOLERANCE} from the first line's; the first line's is used")
        if mount is not None:
            laser_pose = mount
        limit = default_max if range_max is None else float(range_max)
        if not limit > 0:
            raise ValueError(f"range_max must be positive, got {range_max!r}")
        limit32 = np.float32(limit)
        # Every layout must fit (the error names its first line); the kept lines' are merged below.
        layout_of = np.asarray(self.layout_of, dtype=np.int64)
        pad_beam_layouts(src, self.layouts, layout_of, [], 0.0)
        keep = np.ones(times.size, dtype=bool)
        if odometry_source == "odom":
            if not odom.times:
                raise LogError(f"{src}: odometry_source='odom' but the log has no ODOM lines")
            paired = poses_at(times, *odom.arrays())
            keep = paired.covered
            dropped = int(np.sum(~keep))
            if dropped == times.size:
                raise LogError(
                    f"{src}: no laser line ({times[0]:.6f}..{times[-1]:.6f} s) lies within the time span "
                    f"of the ODOM lines ({odom.times[0]:.6f}..{odom.times[-1]:.6f} s)"
                )
            if dropped:
                early = int(np.sum(times < odom.times[0]))
                warn(
                    f"{src}: dropped {dropped} of {times.size} laser lines outside the ODOM lines' time "
                    f"span ({early} before the first, {dropped - early} after the last): odometry is "
                    "interpolated, never extrapolated")
            odometry = paired.poses
            found.append(f"{src}: the odometry of the ODOM lines is used (odometry_source='odom'), not that of the "
                         f"{self.kind} lines")
        elif odom.times:
            found.extend(self._compare_odometry(times, odometry, odom))
        ground_truth = None
        if truth.times:
            true_at = poses_at(times[keep], *truth.arrays())
            if np.all(true_at.covered):
                ground_truth = true_at.poses
            else:
                warn(f"{src}: TRUEPOS lines do not cover every laser timestamp; no ground truth is returned")
        kept = np.nonzero(keep)[0]
        # Readings at or beyond the limit are "no return": exactly range_max in the log.
        scans = [np.where(self.ranges[i] >= limit32, limit32, self.ranges[i].astype(np.float32)) for i in kept]
        beam_angles, ranges, range_min, note = pad_beam_layouts(src, self.layouts, layout_of[kept], scans, 0.0)
        if note:
            warn(note)
        sensor = make_sensor(beam_angles, range_min=range_min, range_max=limit, laser_pose=laser_pose)
        return LaserLog(times[keep], odometry[keep], ranges, sensor, ground_truth, src, (note,) if note else (),
                        tuple(found))

    def _compare_odometry(self, times, odometry, odom: _PoseStream) -> list[str]:
        """A warning if the ODOM lines' motion between laser lines contradicts the laser lines' odometry."""
        src, kind = self.src, self.kind
        chosen = (f"the odometry of the {kind} lines is used (jaxslam map --odometry odom, or "
                  "odometry_source='odom', uses the ODOM lines)")
        paired = poses_at(times, *odom.arrays())
        both = paired.covered[:-1] & paired.covered[1:]
        if not both.any():
            return [f"{src}: the log's ODOM lines do not overlap its {kind} lines in time; {chosen}"]
        laser_step = between_np(odometry[:-1], odometry[1:])
        odom_step = between_np(paired.poses[:-1], paired.poses[1:])
        trans = np.hypot(*(laser_step[:, :2] - odom_step[:, :2]).T)
        rot = np.abs(np.angle(np.exp(1j * (laser_step[:, 2] - odom_step[:, 2]))))
        size = np.hypot(laser_step[:, 0], laser_step[:, 1])
        bad = both & ((trans > _ODOM_TOLERANCE + 0.1 * size) | (rot > _ODOM_TOLERANCE + 0.1 * np.abs(laser_step[:, 2])))
        if not bad.any():
            return []
        i = int(np.argmax(bad))
        return [
            f"{src}: the ODOM lines contradict the {kind} lines' odometry at {int(bad.sum())} of {int(both.sum())} "
            f"steps (first: lines {_line(self.wheres[i])} -> {_line(self.wheres[i + 1])}, {kind} moves "
            f"{size[i]:.3f} m / {laser_step[i, 2]:.3f} rad, ODOM {np.hypot(*odom_step[i, :2]):.3f} m / "
            f"{odom_step[i, 2]:.3f} rad); {chosen}"
        ]


def _line(where: str) -> str:
    """The line number of a ``file:line`` location."""
    return where.rsplit(":", 1)[-1]


# Beam angles must lie on start + i * resolution to within this (rad) to be written as ROBOTLASER1.
_UNIFORM_BEAMS_TOLERANCE = 1e-5


def write_carmen(path, log: LaserLog) -> None:
    """Write ``log`` as a CARMEN text log of ``ROBOTLASER1`` lines (and ``TRUEPOS`` lines for
    its ground truth), which :func:`read_carmen` reads back as the same log.

    One ROBOTLASER1 line per scan carries the beam geometry (first angle, angular resolution,
    ``range_max`` as max_range), the ranges, the laser's and the robot's odometry poses (the
    laser's mounting is the difference) and the timestamp; velocities are written as 0.
    Numbers are written so that they read back exactly: timestamps and poses as float64 (17
    significant digits), ranges as float32 (9). Used to map a log edited in memory (e.g. an
    odometry with injected faults, ``experiments/faults.py``) with ``jaxslam map``.

    What does not survive: ``range_min`` (CARMEN lines carry none; the reader gives 0, so a
    log with a reading below a positive range_min is refused, since that reading would turn
    valid), ``notes`` and ``warnings`` (the reader makes its own), and ``source``.

    Args:
        path: the file to write (``.clf``); overwritten if it exists.
        log: the log; its beams must be evenly spaced (start + i * resolution).

    Raises:
        LogError: beams not evenly spaced, fewer than 2 beams, or a reading below a positive
            ``range_min`` (the message names the scan and beam), before anything is written.
    """
    src = log.source
    angles = np.asarray(log.sensor.beam_angles, dtype=np.float64)
    if angles.size < 2:
        raise LogError(f"{src}: a CARMEN ROBOTLASER1 line needs at least 2 beams, the log has {angles.size}")
    start, resolution = float(angles[0]), float((angles[-1] - angles[0]) / (angles.size - 1))
    off_grid = np.abs(angles - (start + resolution * np.arange(angles.size)))
    if off_grid.max() > _UNIFORM_BEAMS_TOLERANCE:
        beam = int(np.argmax(off_grid))
        raise LogError(f"{src}: beam {beam} lies {off_grid[beam]:.3g} rad off the even grid start + i * resolution "
                       "that a ROBOTLASER1 line describes; the log cannot be written as CARMEN")
    range_min = float(np.asarray(log.sensor.range_min))
    if range_min > 0:
        below = log.ranges < np.float32(range_min)
        if below.any():
            scan, beam = (int(v) for v in np.argwhere(below)[0])
            raise LogError(f"{src}: scan {scan} beam {beam} reads {float(log.ranges[scan, beam]):g} m, below range_min="
                           f"{range_min:g} m; CARMEN lines carry no range_min (it reads back as 0, making such "
                           "readings valid), so the log cannot be written as CARMEN")
    range_max = float(np.asarray(log.sensor.range_max))
    mount = np.asarray(log.sensor.laser_pose, dtype=np.float64)
    laser_world = compose_np(log.odometry, mount)
    num_beams = angles.size
    head = (f"ROBOTLASER1 0 {start!r} {resolution * (num_beams - 1)!r} {resolution!r} {range_max!r} 0.01 0 "
            f"{num_beams}")
    ranges_text = io.StringIO()
    np.savetxt(ranges_text, log.ranges.astype(np.float32), fmt="%.9g")
    rows = ranges_text.getvalue().splitlines()
    origin = " ".join(str(src).split())  # one line, whatever the source's name holds
    out = [f"# written by jaxslam.io.write_carmen from {origin}",
           "# ROBOTLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode n ranges "
           "n_remissions laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv forward_safety side_safety "
           "turn_axis ipc_timestamp hostname logger_timestamp"]
    truth = log.ground_truth
    for i in range(log.num_scans):
        lx, ly, lth = (repr(float(v)) for v in laser_world[i])
        rx, ry, rth = (repr(float(v)) for v in log.odometry[i])
        stamp = repr(float(log.timestamps[i]))
        out.append(f"{head} {rows[i]} 0 {lx} {ly} {lth} {rx} {ry} {rth} 0 0 0 0 0 {stamp} jaxslam {stamp}")
        if truth is not None:
            tx, ty, tth = (repr(float(v)) for v in truth[i])
            out.append(f"TRUEPOS {tx} {ty} {tth} {rx} {ry} {rth} {stamp} jaxslam {stamp}")
    with open(os.fspath(path), "w", encoding="ascii") as f:
        f.write("\n".join(out) + "\n")
