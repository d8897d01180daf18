"""Read a 2-D laser log from a ROS bag (ROS 1 ``.bag`` file or ROS 2 bag folder).

Scans come from a ``sensor_msgs/LaserScan`` topic, odometry from a
``nav_msgs/Odometry`` topic, both through :class:`rosbags.highlevel.AnyReader`.
Each scan is paired with the odometry interpolated at its header timestamp
(:func:`jaxslam.io.trajectory.poses_at`); scans outside the odometry's time span
are dropped with a warning. Every malformed message raises
:class:`~jaxslam.laserlog.LogError` naming the bag, the topic, the message index
and its timestamp.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np

from jaxslam.io.trajectory import poses_at
from jaxslam.laserlog import LaserLog, LogError
from jaxslam.laser import make_sensor

__all__ = ["read_rosbag"]

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"

# Tolerance (rad) when checking that the beam geometry stays the same from scan to scan:
# the fields are float32 in the message, so identical settings compare exactly; this only
# forgives a re-serialisation through float64.
_ANGLE_TOLERANCE = 1e-7


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

    Raises:
        LogError: the bag cannot be opened; a topic is missing or has the wrong type
            (the message lists the topics there are); there are no scans or no odometry;
            a message cannot be deserialised; a range is NaN or negative; the beam count,
            angle_min, angle_increment, range_min or range_max change mid-log; header
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
        self.ranges: list[np.ndarray] = []
        self.first = None  # (angle_min, angle_increment, range_min, range_max, num_beams)


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
    """Validate one LaserScan message against the first one and append it."""
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    geometry = (
        float(msg.angle_min),
        float(msg.angle_increment),
        float(msg.range_min),
        float(msg.range_max),
        int(ranges.shape[0]),
    )
    if scans.first is None:
        angle_min, increment, range_min, range_max, num_beams = geometry
        if num_beams == 0:
            raise LogError(f"{where}: the scan has no beams")
        if not all(math.isfinite(v) for v in geometry[:4]) or increment == 0 or not range_max > 0:
            raise LogError(
                f"{where}: bad beam geometry angle_min={angle_min} angle_increment={increment} "
                f"range_min={range_min} range_max={range_max}"
            )
        scans.first = geometry
    else:
        angle_min, increment, range_min, range_max, num_beams = scans.first
        if geometry[4] != num_beams:
            raise LogError(f"{where}: the beam count changes from {num_beams} to {geometry[4]}")
        if abs(geometry[0] - angle_min) > _ANGLE_TOLERANCE or abs(geometry[1] - increment) > _ANGLE_TOLERANCE:
            raise LogError(
                f"{where}: angle_min/angle_increment change from {angle_min!r}/{increment!r} "
                f"to {geometry[0]!r}/{geometry[1]!r}"
            )
        if geometry[2] != range_min or geometry[3] != range_max:
            raise LogError(
                f"{where}: range_min/range_max change from {range_min!r}/{range_max!r} "
                f"to {geometry[2]!r}/{geometry[3]!r}"
            )
    bad = np.isnan(ranges) | (ranges < 0)
    if bad.any():
        beam = int(np.argmax(bad))
        raise LogError(f"{where}: beam {beam} has range {ranges[beam]!r} (NaN or negative)")
    if scans.times and stamp < scans.times[-1]:
        raise LogError(f"{where}: the timestamp goes backwards (previous scan at {scans.times[-1]:.9f} s)")
    range_max = np.float32(scans.first[3])
    # +inf and anything at or beyond range_max mean "no return": store exactly range_max.
    scans.ranges.append(np.where(ranges >= range_max, range_max, ranges))
    scans.times.append(stamp)


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
    ranges = np.stack(scans.ranges)
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
    angle_min, increment, range_min, range_max, num_beams = scans.first
    beam_angles = angle_min + increment * np.arange(num_beams, dtype=np.float64)
    sensor = make_sensor(beam_angles, range_min=max(range_min, 0.0), range_max=range_max)
    return LaserLog(times[keep], paired.poses[keep], ranges[keep], sensor, None, src)
