"""Read a 2-D laser log from a ROS bag (ROS 1 ``.bag`` file or ROS 2 bag folder).

Scans come from a ``sensor_msgs/LaserScan`` topic, odometry from a
``nav_msgs/Odometry`` topic, both through :class:`rosbags.highlevel.AnyReader`.
Each scan is paired with the odometry interpolated at its header timestamp
(:func:`jaxslam.io.trajectory.poses_at`); scans outside the odometry's time span
are dropped with a warning. Every malformed message raises
:class:`~jaxslam.laserlog.LogError` naming the bag, the topic, the message index
and its timestamp.

Scans whose beam count or beam angles change within a log are padded to one
common layout by :func:`pad_beam_layouts` (shared with the CARMEN reader) when
every scan's beams lie on the widest scan's angular grid within its angular
range; any other change is a LogError.
"""

from __future__ import annotations

import math
import os
import warnings
from collections import Counter
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxslam.io.trajectory import poses_at
from jaxslam.laserlog import LaserLog, LogError
from jaxslam.laser import make_sensor

__all__ = ["read_rosbag"]

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"

# Tolerance (rad) when telling whether two scans have the same beam layout: the fields are
# float32 in the message, so identical settings compare exactly; this only forgives a
# re-serialisation through float64.
_ANGLE_TOLERANCE = 1e-7

PAD_RANGE = 0.0
"""Range (m) of a padded beam (one a scan lacks): below ``range_min``, so invalid: it
neither clears nor marks a cell and never counts in a likelihood. (A no-return reading,
``>= range_max``, would not do: insertion clears free space along it.)"""
PAD_RANGE_MIN = 1e-3
"""``range_min`` (m) of a padded log whose sensor says 0, so that :data:`PAD_RANGE` lies
below it; readings under 1 mm are no real return."""
# Most a beam's angle may miss the common grid (rad): 1e-4 rad is 1 mm at 10 m, far below a
# laser beam's width; it forgives increments printed with few digits.
_GRID_TOLERANCE = 1e-4
# Finest subdivision of the widest scan's increment that interleaved scans may sit on
# (a SICK LMS interlaces 4 scans 0.25 degrees apart in its 0.25-degree mode).
_MAX_SUBDIVISION = 4


def read_rosbag(path, scan_topic: str = "/scan", odom_topic: str = "/odom", max_scans: int | None = None) -> LaserLog:
    """Read laser scans and odometry from a ROS 1 ``.bag`` file or a ROS 2 bag folder.

    Args:
        path: a ROS 1 bag file (its name must end in ``.bag``) or a ROS 2 bag folder
            (with ``metadata.yaml``).
        scan_topic: topic of ``sensor_msgs/LaserScan`` messages.
        odom_topic: topic of ``nav_msgs/Odometry`` messages.
        max_scans: read only the first ``max_scans`` scans of the topic (and the odometry
            needed to bracket them); None reads all.

    Returns:
        A :class:`~jaxslam.laserlog.LaserLog` with T scans of B beams: timestamps (T,) s
        from the scan headers (bag time where a header stamp is 0); odometry (T, 3)
        [x, y, yaw] (m, m, rad) interpolated at each scan's timestamp; ranges (T, B) m,
        where +inf and readings >= ``range_max`` are exactly ``range_max`` ("no return").
        Beam angles are ``angle_min + i * angle_increment`` (rad); range_min/range_max
        come from the messages. Scans before the first or after the last odometry message
        are dropped, with a ``UserWarning`` saying how many.

        Scans whose beam count, angle_min or angle_increment change within the log are
        padded to a common beam layout (:func:`pad_beam_layouts`: B is then the widest
        scan's beam count, or more for interleaved scans; a scan's missing beams read
        :data:`PAD_RANGE`, an invalid reading) with one ``UserWarning``, and the log's
        ``notes`` say so.

    Raises:
        LogError: the bag cannot be opened; a topic is missing or has the wrong type
            (the message lists the topics there are); there are no scans or no odometry;
            a message cannot be deserialised; a range is NaN or negative; a scan has no
            beams; a scan's beams leave the widest scan's angular grid or range (see
            :func:`pad_beam_layouts`); range_min or range_max change mid-log; header
            timestamps go backwards.
    """
    src = os.fspath(path)
    if max_scans is not None and (not isinstance(max_scans, int) or max_scans < 1):
        raise ValueError(f"max_scans must be a positive int or None, got {max_scans!r}")
    bag_path = Path(src)
    if not bag_path.exists():
        raise LogError(f"{src}: no such bag file or folder")
    if bag_path.is_dir():
        if not (bag_path / "metadata.yaml").is_file():
            raise LogError(f"{src}: a ROS 2 bag folder needs a metadata.yaml, there is none")
    elif bag_path.suffix != ".bag":
        # AnyReader tells ROS 1 from ROS 2 by the ".bag" suffix alone.
        raise LogError(f"{src}: expected a ROS 1 '.bag' file or a ROS 2 bag folder")

    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    # A ROS 2 bag may lack embedded message definitions; the standard ones are then used.
    reader = AnyReader([bag_path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as err:  # rosbags raises several error types for unreadable bags
        raise LogError(f"{src}: cannot open the bag ({type(err).__name__}: {err})") from None
    try:
        scans, odometry = _read_messages(reader, src, scan_topic, odom_topic, max_scans)
    finally:
        reader.close()
    return _assemble(src, scan_topic, odom_topic, scans, odometry)


class _Scans:
    """Scan fields accumulated while reading (host lists, turned into arrays at the end)."""

    def __init__(self):
        self.times: list[float] = []
        self.ranges: list[np.ndarray] = []  # one (B_i,) array per scan
        self.layout_of: list[int] = []  # index into self.layouts, per scan
        self.layouts: list[BeamLayout] = []  # in order of first appearance
        self.first = None  # (range_min, range_max) of the first scan


def _read_messages(reader, src, scan_topic, odom_topic, max_scans):
    """Iterate the two topics in bag order; returns (_Scans, (odom_times, odom_poses))."""
    topics = reader.topics
    listing = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"
    for topic, expected in ((scan_topic, SCAN_TYPE), (odom_topic, ODOM_TYPE)):
        if topic not in topics:
            raise LogError(f"{src}: no topic {topic!r} in the bag; its topics are: {listing}")
        if topics[topic].msgtype != expected:
            raise LogError(
                f"{src}: topic {topic!r} holds {topics[topic].msgtype}, expected {expected}; "
                f"the bag's topics are: {listing}"
            )
    connections = [c for c in reader.connections if c.topic in (scan_topic, odom_topic)]
    scans = _Scans()
    odom_times: list[float] = []
    odom_poses: list[tuple[float, float, float]] = []
    counts = {scan_topic: 0, odom_topic: 0}
    bag_index = -1
    messages = reader.messages(connections=connections)
    while True:
        try:
            item = next(messages)
        except StopIteration:
            break
        except Exception as err:  # a corrupt chunk or record
            raise LogError(
                f"{src}: cannot read the bag after message {bag_index} ({type(err).__name__}: {err})"
            ) from None
        bag_index += 1
        connection, bag_time_ns, raw = item
        topic = connection.topic
        index = counts[topic]
        counts[topic] += 1
        where = f"{src}: {topic} message {index} (bag message {bag_index}, bag time {bag_time_ns * 1e-9:.9f} s)"
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as err:
            raise LogError(f"{where}: cannot deserialise {connection.msgtype} ({type(err).__name__}: {err})") from None
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        if stamp == 0:
            stamp = bag_time_ns * 1e-9
        where = f"{where}, stamp {stamp:.9f} s"
        if topic == scan_topic:
            if max_scans is not None and len(scans.times) >= max_scans:
                continue
            _add_scan(scans, msg, stamp, where)
        else:
            _add_odometry(odom_times, odom_poses, msg, stamp, where)
            # With max_scans, stop once the odometry brackets the last scan kept.
            if max_scans is not None and len(scans.times) >= max_scans and stamp >= scans.times[-1]:
                break
    if not scans.times:
        raise LogError(f"{src}: topic {scan_topic!r} holds no scans")
    if not odom_times:
        raise LogError(f"{src}: topic {odom_topic!r} holds no odometry messages")
    return scans, (np.asarray(odom_times), np.asarray(odom_poses, dtype=np.float64))


def _add_scan(scans: _Scans, msg, stamp: float, where: str) -> None:
    """Validate one LaserScan message and append it (its beam layout is checked at the end)."""
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    angle_min, increment = float(msg.angle_min), float(msg.angle_increment)
    range_min, range_max = float(msg.range_min), float(msg.range_max)
    num_beams = int(ranges.shape[0])
    if num_beams == 0:
        raise LogError(f"{where}: the scan has no beams")
    if scans.first is None:
        if not all(math.isfinite(v) for v in (angle_min, increment, range_min, range_max)) or increment == 0 \
                or not range_max > 0:
            raise LogError(
                f"{where}: bad beam geometry angle_min={angle_min} angle_increment={increment} "
                f"range_min={range_min} range_max={range_max}"
            )
        scans.first = (range_min, range_max)
    elif (range_min, range_max) != scans.first:
        raise LogError(
            f"{where}: range_min/range_max change from {scans.first[0]!r}/{scans.first[1]!r} "
            f"to {range_min!r}/{range_max!r}"
        )
    layout = _layout_index(scans.layouts, angle_min, increment, num_beams)
    if layout is None:
        if not (math.isfinite(angle_min) and math.isfinite(increment)) or increment == 0:
            raise LogError(f"{where}: bad beam geometry angle_min={angle_min} angle_increment={increment}")
        scans.layouts.append(BeamLayout(angle_min + increment * np.arange(num_beams, dtype=np.float64),
                                        increment, where))
        layout = len(scans.layouts) - 1
    bad = np.isnan(ranges) | (ranges < 0)
    if bad.any():
        beam = int(np.argmax(bad))
        raise LogError(f"{where}: beam {beam} has range {ranges[beam]!r} (NaN or negative)")
    if scans.times and stamp < scans.times[-1]:
        raise LogError(f"{where}: the timestamp goes backwards (previous scan at {scans.times[-1]:.9f} s)")
    range_max32 = np.float32(range_max)
    # +inf and anything at or beyond range_max mean "no return": store exactly range_max.
    scans.ranges.append(np.where(ranges >= range_max32, range_max32, ranges))
    scans.layout_of.append(layout)
    scans.times.append(stamp)


def _layout_index(layouts, angle_min: float, increment: float, num_beams: int) -> int | None:
    """The index of the known layout equal to this one (within _ANGLE_TOLERANCE), or None."""
    for k, known in enumerate(layouts):
        if (known.num_beams == num_beams and abs(known.angle_min - angle_min) <= _ANGLE_TOLERANCE
                and abs(known.increment - increment) <= _ANGLE_TOLERANCE):
            return k
    return None


def _add_odometry(times: list, poses: list, msg, stamp: float, where: str) -> None:
    """Validate one Odometry message and append its planar pose (x, y, yaw)."""
    position = msg.pose.pose.position
    q = msg.pose.pose.orientation
    values = (position.x, position.y, q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in values):
        raise LogError(f"{where}: non-finite odometry pose {values}")
    if q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w < 1e-12:
        raise LogError(f"{where}: the odometry orientation is a zero quaternion")
    if times and stamp < times[-1]:
        raise LogError(f"{where}: the odometry timestamp goes backwards (previous at {times[-1]:.9f} s)")
    # Yaw of a (not necessarily unit) quaternion: atan2 is scale-invariant.
    yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
    times.append(stamp)
    poses.append((float(position.x), float(position.y), yaw))


def _assemble(src, scan_topic, odom_topic, scans: _Scans, odometry) -> LaserLog:
    """Pair scans with interpolated odometry, drop the uncovered ones (warning), build the log."""
    odom_times, odom_poses = odometry
    times = np.asarray(scans.times, dtype=np.float64)
    paired = poses_at(times, odom_times, odom_poses)
    early = int(np.sum(times < odom_times[0]))
    late = int(np.sum(times > odom_times[-1]))
    if early or late:
        if early + late == times.size:
            raise LogError(
                f"{src}: no scan on {scan_topic!r} ({times[0]:.9f}..{times[-1]:.9f} s) lies within the "
                f"time span of the odometry on {odom_topic!r} ({odom_times[0]:.9f}..{odom_times[-1]:.9f} s)"
            )
        warnings.warn(
            f"{src}: dropped {early + late} of {times.size} scans outside the odometry's time span "
            f"({early} before the first and {late} after the last {odom_topic} message): "
            "odometry is interpolated, never extrapolated",
            stacklevel=3,
        )
    keep = paired.covered
    range_min, range_max = scans.first
    layout_of = np.asarray(scans.layout_of)
    # Every layout in the bag must fit (the error names its first scan); the kept scans'
    # layouts are then merged.
    pad_beam_layouts(src, scans.layouts, layout_of, [], max(range_min, 0.0))
    kept = np.nonzero(keep)[0]
    beam_angles, ranges, range_min, note = pad_beam_layouts(
        src, scans.layouts, layout_of[kept], [scans.ranges[i] for i in kept], max(range_min, 0.0))
    if note:
        warnings.warn(note, stacklevel=3)
    sensor = make_sensor(beam_angles, range_min=range_min, range_max=range_max)
    return LaserLog(times[keep], paired.poses[keep], ranges, sensor, None, src, (note,) if note else ())


class BeamLayout(NamedTuple):
    """The beams of the scans that share one layout (angle_min, increment, beam count)."""

    angles: np.ndarray
    """(B_i,) float64 beam angles (rad), in the scan's order."""
    increment: float
    """Angle between consecutive beams (rad), signed."""
    where: str
    """The first scan with this layout (file, index, time), for messages."""

    @property
    def num_beams(self) -> int:
        return int(self.angles.shape[0])

    @property
    def angle_min(self) -> float:
        return float(self.angles[0])

    def brief(self) -> str:
        return (f"{self.num_beams} beams from {math.degrees(self.angles[0]):.3f} deg, "
                f"{math.degrees(self.increment):.3f} deg apart")

    def describe(self) -> str:
        a, b = math.degrees(self.angles[0]), math.degrees(self.angles[-1])
        return (f"{self.num_beams} beams, angle_min {self.angles[0]:.7f} rad, increment {self.increment:.7f} rad "
                f"({a:.3f}..{b:.3f} deg)")


def pad_beam_layouts(src: str, layouts, layout_of, ranges, range_min: float):
    """Put scans of different beam layouts into one (T, B) array with one set of beam angles.

    The rule: the widest layout (most beams; the first seen among equals) is the
    reference. Every other layout's beam angles must lie on the reference's angular grid
    (``angle_min + j * increment``) or, for interleaved scans, on a grid of 1/2, 1/3 or
    1/4 of its increment (the smallest subdivision that fits every layout), each angle
    within 1e-4 rad; and within the reference's angular range, widened by less than one
    increment at either end. The common beam angles are the reference's, then the other
    layouts' beams that are not among them (layouts with more beams first, then in order
    of appearance; each in its own order, so that a beam stride still samples every
    scan evenly). A scan's beams it does not have read :data:`PAD_RANGE`, below
    ``range_min``: invalid readings, which neither clear nor mark a cell and never count
    in a likelihood. Where ``range_min`` is not above :data:`PAD_RANGE`, it becomes
    :data:`PAD_RANGE_MIN`.

    Args:
        src: the file, for the note.
        layouts: the :class:`BeamLayout` of the log, in order of first appearance.
        layout_of: (T,) int: each scan's layout (index into ``layouts``).
        ranges: T (B_i,) float32 arrays: each scan's ranges, in its layout's order
            (an empty list only validates the layouts).
        range_min: the sensor's range_min (m).

    Returns:
        ``(beam_angles (B,) float64, ranges (T, B) float32, range_min, note)``: ``note`` is
        None where every scan has the same layout (nothing is padded), else one sentence
        saying what was padded (for a ``UserWarning`` and the log's ``notes``).

    Raises:
        LogError: a layout leaves the reference's grid or range (or its beams run the other
            way); the message names the first scan with that layout and both layouts.
    """
    layout_of = np.asarray(layout_of, dtype=np.int64)
    used = [int(k) for k in np.unique(layout_of)] if ranges else list(range(len(layouts)))
    if len(used) <= 1:
        if not ranges:
            return None, None, range_min, None
        return layouts[used[0]].angles, np.stack(ranges).astype(np.float32), range_min, None
    widest = max(used, key=lambda k: (layouts[k].num_beams, -k))
    ref = layouts[widest]
    step = abs(ref.increment)
    lo, hi = float(ref.angles.min()) - step, float(ref.angles.max()) + step
    subdivisions = list(range(1, _MAX_SUBDIVISION + 1))
    for k in used:  # in order of first appearance
        layout = layouts[k]
        angles = layout.angles
        reason = None
        if layout.num_beams > 1 and ref.num_beams > 1 and (layout.increment > 0) != (ref.increment > 0):
            reason = "its beams run the other way"
        elif angles.min() <= lo + _GRID_TOLERANCE or angles.max() >= hi - _GRID_TOLERANCE:
            reason = "the angular range changes (beams beyond the widest scan's range)"
        else:
            offsets = (angles - ref.angles[0]) / step
            fits = [d for d in subdivisions
                    if np.max(np.abs(offsets * d - np.round(offsets * d))) * step / d <= _GRID_TOLERANCE]
            if not fits:
                reason = (f"its beams are not on the widest scan's angular grid, nor on one of 1/2..1/"
                          f"{_MAX_SUBDIVISION} of its increment shared with the layouts before it")
            else:
                subdivisions = fits
        if reason:
            raise LogError(
                f"{layout.where}: the beam layout changes from {ref.describe()} (the widest scan's, first at "
                f"{ref.where}) to {layout.describe()}: {reason}; scans may differ in their beam count only "
                "where every scan's beams lie on the widest scan's angular grid (or interleave with it) "
                "within its angular range"
            )
    if not ranges:
        return None, None, range_min, None
    division = subdivisions[0]
    grid_step = step / division
    # Common beams: the reference's, then the others' new ones; slot = grid index of an angle.
    order = [widest] + sorted((k for k in used if k != widest), key=lambda k: (-layouts[k].num_beams, k))
    position: dict[int, int] = {}
    beam_angles: list[float] = []
    columns: dict[int, np.ndarray] = {}
    for k in order:
        slots = np.round((layouts[k].angles - ref.angles[0]) / grid_step).astype(np.int64)
        cols = []
        for slot, angle in zip(slots.tolist(), layouts[k].angles.tolist()):
            if slot not in position:
                position[slot] = len(beam_angles)
                beam_angles.append(angle)
            cols.append(position[slot])
        columns[k] = np.asarray(cols, dtype=np.int64)
    num_beams = len(beam_angles)
    out = np.full((len(ranges), num_beams), PAD_RANGE, dtype=np.float32)
    for k in used:
        rows = np.nonzero(layout_of == k)[0]
        if rows.size:
            out[np.ix_(rows, columns[k])] = np.stack([ranges[i] for i in rows])
    new_range_min = range_min if np.float32(range_min) > np.float32(PAD_RANGE) else PAD_RANGE_MIN
    counts = Counter(layout_of.tolist())
    padded = sum(n for k, n in counts.items() if layouts[k].num_beams < num_beams)
    seen = "; ".join(f"{counts[k]} scans of {layouts[k].brief()}" for k in order)
    target = (f"the widest scan's {num_beams} beam angles" if num_beams == ref.num_beams else
              f"{num_beams} beam angles (the widest scan's {ref.num_beams} and the others' beams interleaved "
              f"1/{division} of its increment apart: {num_beams / ref.num_beams:.1f} times the beams per scan)")
    note = (f"{src}: the beam layout changes within the log ({seen}); {padded} of {len(ranges)} scans were "
            f"padded to {target}. A padded beam reads {PAD_RANGE:g} m, below range_min {new_range_min:g} m: "
            "invalid, it neither clears nor marks a cell nor counts in a likelihood")
    if new_range_min != range_min:
        note += f" (range_min raised from {range_min:g} m to {PAD_RANGE_MIN:g} m for this)"
    return np.asarray(beam_angles, dtype=np.float64), out, new_range_min, note + "."
