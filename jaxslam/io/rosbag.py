"""Read a 2-D laser log from a ROS bag (ROS 1 ``.bag`` file or ROS 2 bag folder).

What a bag needs: ``sensor_msgs/LaserScan`` on ``/scan`` and odometry, either
``nav_msgs/Odometry`` on ``/odom`` or, where there is no such topic, the ``odom ->
base_link`` transform in ``/tf`` (a chain such as odom -> base_footprint -> base_link
works where one link moves). The laser's mounting on the robot (the transform from
the base frame to the scans' ``header.frame_id``) is read from ``/tf_static`` (from
``/tf`` where ``/tf_static`` lacks it), through intermediate frames; a laser
mounted upside down has its beam angles mirrored. Topics, frames and the mounting
can be given instead: ``scan_topic``, ``odom_topic``, ``odom_frame``, ``base_frame``
and ``laser_pose`` (``jaxslam map --scan-topic --odom-topic --odom-frame --base-frame
--laser-pose x,y,theta``). All messages go through
:class:`rosbags.highlevel.AnyReader`.

Each scan is paired with the odometry interpolated at its header timestamp
(:func:`jaxslam.laserlog.poses_at`); scans outside the odometry's time span
are dropped with a warning. Every malformed message raises
:class:`~jaxslam.laserlog.LogError` naming the bag, the topic, the message index
and its timestamp.

Scans whose beam count or beam angles change within a log are padded to one
common layout by :func:`jaxslam.io.beam_layouts.pad_beam_layouts` (shared with the CARMEN reader) when
every scan's beams lie on the widest scan's angular grid within its angular
range; any other change is a LogError.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxslam.io.beam_layouts import BeamLayout, pad_beam_layouts
from jaxslam.io.ros_tf import TF_STATIC_TOPIC, TF_TOPIC, _check_pose, _frame, _Rigid, _stamp, _TfTree
from jaxslam.laser import make_sensor
from jaxslam.laserlog import LaserLog, LogError, poses_at
from jaxslam.warn import warn

__all__ = ["read_rosbag"]

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
"""Message types of transform topics (ROS 2 and ROS 1's tf2; ROS 1's older tf, same fields)."""

# Tolerance (rad) when telling whether two scans have the same beam layout: the fields are
# float32 in the message, so identical settings compare exactly; this only forgives a
# re-serialisation through float64.
_ANGLE_TOLERANCE = 1e-7


def read_rosbag(path, scan_topic: str = "/scan", odom_topic: str = "/odom", max_scans: int | None = None,
                odom_frame: str = "odom", base_frame: str = "base_link", laser_pose=None) -> LaserLog:
    """Read laser scans and odometry from a ROS 1 ``.bag`` file or a ROS 2 bag folder.

    Odometry comes from ``odom_topic`` when the bag has it (``nav_msgs/Odometry``, or a
    ``tf2_msgs/TFMessage`` topic read as ``/tf`` is below); when it has not, from the
    ``odom_frame -> base_frame`` transform in ``/tf`` (the log's ``notes`` say so). That
    transform may be a chain of frames (odom -> base_footprint -> base_link) of which at most
    one link moves; its stamps are sorted, and the pose of ``base_frame`` in ``odom_frame``
    at each stamp, projected on the plane (x, y, yaw), is interpolated at the scans as
    ``/odom`` messages are.

    The laser's mounting, ``SensorSpec.laser_pose`` (x, y, theta of the laser in
    ``base_frame``), is the transform from ``base_frame`` to the first scan's
    ``header.frame_id`` in ``/tf_static`` (or, where ``/tf_static`` does not reach that frame,
    in ``/tf``: its first value), composed through intermediate frames and projected on the plane. A
    laser mounted upside down (its z axis pointing down: rolled 180 degrees, a quaternion
    with x=1 or y=1) sees its beams the other way round: each beam angle ``a`` becomes
    ``-a`` and the beams are reversed (angles and ranges together), so that they keep their
    order (increasing for a usual scan), with a note in ``notes``. Where the bag has no
    transform to the laser's frame, the laser is taken to sit at the base frame's origin,
    facing forward, and ``warnings`` says so. Frame names match with or without a leading
    ``/``.

    Args:
        path: a ROS 1 bag file (its name must end in ``.bag``) or a ROS 2 bag folder
            (with ``metadata.yaml``).
        scan_topic: topic of ``sensor_msgs/LaserScan`` messages.
        odom_topic: topic of ``nav_msgs/Odometry`` messages; where the bag has no such topic,
            the odometry comes from ``/tf``.
        max_scans: read only the first ``max_scans`` scans of the topic (and the odometry
            needed to bracket them); None reads all.
        odom_frame: the odometry's fixed frame in ``/tf`` (default ``"odom"``).
        base_frame: the robot's frame (default ``"base_link"``): whose pose in ``odom_frame``
            the ``/tf`` odometry is, and in which the laser's mounting is given. With an
            odometry topic it should be that topic's ``child_frame_id``.
        laser_pose: None reads the mounting from the bag's transforms; ``(x, y, theta)``
            (m, m, rad) is used instead of them, beams as the messages give them (never
            mirrored).

    Returns:
        A :class:`~jaxslam.laserlog.LaserLog` with T scans of B beams: timestamps (T,) s
        from the scan headers (bag time where a header stamp is 0); odometry (T, 3)
        [x, y, yaw] (m, m, rad) interpolated at each scan's timestamp; ranges (T, B) m,
        where +inf and readings >= ``range_max`` are exactly ``range_max`` ("no return").
        Beam angles are ``angle_min + i * angle_increment`` (rad; mirrored as above for an
        upside-down laser); range_min/range_max come from the messages. Scans before the
        first or after the last odometry message are dropped, with a ``UserWarning`` saying
        how many.

        Scans whose beam count, angle_min or angle_increment change within the log are
        padded to a common beam layout (:func:`jaxslam.io.beam_layouts.pad_beam_layouts`: B is
        then the widest scan's beam count, or more for interleaved scans; a scan's missing beams
        read :data:`jaxslam.io.beam_layouts.PAD_RANGE`, an invalid reading) with one
        ``UserWarning``, and the log's ``notes`` say so.

    Raises:
        LogError: the bag cannot be opened; the scan topic is missing or has the wrong type
            (the message lists the topics there are); there is neither the odometry topic
            nor the ``odom_frame -> base_frame`` transform in ``/tf`` (the message names both,
            the options that set them and the transforms there are); more than one link of
            that chain moves; there are no scans or no odometry; a message cannot be
            deserialised; a range is NaN or negative; a scan has no beams; a scan's beams
            leave the widest scan's angular grid or range (see
            :func:`~jaxslam.io.beam_layouts.pad_beam_layouts`); range_min or range_max change
            mid-log; header timestamps go backwards; a pose or transform is not finite or has a
            zero quaternion.
        ValueError: ``max_scans``, ``odom_frame``, ``base_frame`` or ``laser_pose`` is malformed.
    """
    src = os.fspath(path)
    if max_scans is not None and (not isinstance(max_scans, int) or max_scans < 1):
        raise ValueError(f"max_scans must be a positive int or None, got {max_scans!r}")
    frames = (_frame_option("odom_frame", odom_frame), _frame_option("base_frame", base_frame))
    mount = None if laser_pose is None else _Mount(check_laser_pose(laser_pose), False, None)
    reader = _open_bag(src)
    return _read_bag(reader, src, scan_topic, odom_topic, max_scans, frames, mount)


def _open_bag(src: str):
    """An opened :class:`rosbags.highlevel.AnyReader` on the bag at ``src`` (a ROS 1 ``.bag`` file
    or a ROS 2 bag folder); a LogError where there is none or it cannot be opened."""
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
    return reader


def _read_bag(reader, src: str, scan_topic: str, odom_topic: str, max_scans: int | None, frames: tuple[str, str],
              mount: _Mount | None) -> LaserLog:
    """Read the scans, odometry and transforms from the opened ``reader`` (closed here) and build the
    log (:func:`read_rosbag`); ``frames`` is (odom_frame, base_frame) without leading ``/``, ``mount``
    the given mounting or None to read it from the transforms."""
    try:
        plan = _plan(reader.topics, src, scan_topic, odom_topic, frames, read_mount=mount is None)
        scans, odometry, tree = _read_messages(reader, src, plan, max_scans)
        if mount is None and TF_TOPIC not in plan.tf_topics:
            _find_mount_in_tf(reader, src, plan, tree, scans.frame)
    finally:
        reader.close()
    notes, found = [], []
    if plan.tf_odometry:
        odometry = _tf_odometry(src, plan, tree)
        if plan.tf_odometry != odom_topic:
            notes.append(f"{src}: the bag has no topic {odom_topic!r}: the odometry is the {plan.odom_what} "
                         "transform")
    if mount is None:
        mount = _laser_mount(src, plan, tree, scans.frame, found)
    return _assemble(src, scan_topic, plan.odom_what, scans, odometry, mount, notes, found)


def check_laser_pose(value) -> tuple[float, float, float]:
    """``value`` as ``(x, y, theta)`` floats (m, m, rad), else ``ValueError``: a laser's mounting
    on the robot must be three finite numbers."""
    try:
        numbers = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        numbers = ()
    if isinstance(value, (str, bytes)) or len(numbers) != 3 or not all(math.isfinite(v) for v in numbers):
        raise ValueError(f"laser_pose must be three finite numbers (x, y, theta) in m, m, rad, got {value!r}")
    return numbers


def _frame_option(name: str, value) -> str:
    if not isinstance(value, str) or not _frame(value):
        raise ValueError(f"{name} must be a frame name (a non-empty string), got {value!r}")
    return _frame(value)


class _Plan(NamedTuple):
    """Which topics to read and what for."""

    scan_topic: str
    odom_topic: str | None
    """The nav_msgs/Odometry topic, or None where the odometry comes from transforms."""
    tf_odometry: str | None
    """The transform topic the odometry comes from, or None."""
    tf_topics: tuple[str, ...]
    """The transform topics to read (odometry, mounting)."""
    odom_frame: str
    base_frame: str
    listing: str
    """The bag's topics, for messages."""

    @property
    def odom_what(self) -> str:
        if self.odom_topic:
            return repr(self.odom_topic)
        return f"{self.tf_odometry} {self.odom_frame} -> {self.base_frame}"


def _plan(topics, src, scan_topic, odom_topic, frames, read_mount: bool) -> _Plan:
    """The topics to read; a LogError for a missing or mistyped scan topic and for a bag with
    neither the odometry topic nor a ``/tf`` to take it from."""
    listing = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"
    odom_frame, base_frame = frames

    def mistyped(topic, expected):
        return LogError(f"{src}: topic {topic!r} holds {topics[topic].msgtype}, expected {expected}; "
                        f"the bag's topics are: {listing}")

    if scan_topic not in topics:
        raise LogError(f"{src}: no topic {scan_topic!r} in the bag; its topics are: {listing}")
    if topics[scan_topic].msgtype != SCAN_TYPE:
        raise mistyped(scan_topic, SCAN_TYPE)
    tf_odometry = None
    if odom_topic in topics:
        if topics[odom_topic].msgtype in TF_TYPES:
            odom_topic, tf_odometry = None, odom_topic
        elif topics[odom_topic].msgtype != ODOM_TYPE:
            raise mistyped(odom_topic, ODOM_TYPE)
    elif TF_TOPIC in topics and topics[TF_TOPIC].msgtype in TF_TYPES:
        odom_topic, tf_odometry = None, TF_TOPIC
    else:
        raise LogError(f"{src}: no odometry: no topic {odom_topic!r} in the bag, and no {TF_TOPIC} topic to take "
                       f"the {odom_frame} -> {base_frame} transform from; its topics are: {listing}. "
                       f"{_ODOMETRY_OPTIONS}")
    tf_topics = [tf_odometry] if tf_odometry else []
    if read_mount:
        static = TF_STATIC_TOPIC in topics and topics[TF_STATIC_TOPIC].msgtype in TF_TYPES
        mount_topic = TF_STATIC_TOPIC if static else TF_TOPIC
        if mount_topic in topics and topics[mount_topic].msgtype in TF_TYPES and mount_topic not in tf_topics:
            tf_topics.append(mount_topic)
    return _Plan(scan_topic, odom_topic, tf_odometry, tuple(tf_topics), odom_frame, base_frame, listing)


_ODOMETRY_OPTIONS = ("Name the odometry topic (odom_topic=, jaxslam map --odom-topic) or the transform's frames "
                     "(odom_frame= and base_frame=, --odom-frame and --base-frame; defaults 'odom' and 'base_link')")


class _Scans:
    """Scan fields accumulated while reading (host lists, turned into arrays at the end)."""

    def __init__(self):
        self.times: list[float] = []
        self.ranges: list[np.ndarray] = []  # one (B_i,) array per scan
        self.layout_of: list[int] = []  # index into self.layouts, per scan
        self.layouts: list[BeamLayout] = []  # in order of first appearance
        self.first = None  # (range_min, range_max) of the first scan
        self.frame = ""  # header.frame_id of the first scan


def _read_messages(reader, src, plan: _Plan, max_scans):
    """Iterate the planned topics in bag order; returns (_Scans, (odom_times, odom_poses) or
    None, _TfTree)."""
    scan_topic, odom_topic = plan.scan_topic, plan.odom_topic
    wanted = {scan_topic, odom_topic, *plan.tf_topics} - {None}
    connections = [c for c in reader.connections if c.topic in wanted]
    scans = _Scans()
    tree = _TfTree(plan.odom_frame, plan.base_frame, series=plan.tf_odometry is not None)
    odom_times: list[float] = []
    odom_poses: list[tuple[float, float, float]] = []
    counts = dict.fromkeys(wanted, 0)
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
        if topic == scan_topic and max_scans is not None and len(scans.times) >= max_scans:
            continue
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as err:
            raise LogError(f"{where}: cannot deserialise {connection.msgtype} ({type(err).__name__}: {err})") from None
        if topic in plan.tf_topics:
            tree.add_message(msg, topic, bag_time_ns, where)
            reach = tree.series_reach() if topic == plan.tf_odometry else None
        else:
            stamp = _stamp(msg.header.stamp, bag_time_ns)
            where = f"{where}, stamp {stamp:.9f} s"
            if topic == scan_topic:
                _add_scan(scans, msg, stamp, where)
                continue
            _add_odometry(odom_times, odom_poses, msg, stamp, where)
            reach = stamp
        # With max_scans, stop once the odometry brackets the last scan kept.
        if max_scans is not None and reach is not None and len(scans.times) >= max_scans and reach >= scans.times[-1]:
            break
    if not scans.times:
        raise LogError(f"{src}: topic {scan_topic!r} holds no scans")
    if odom_topic is None:
        return scans, None, tree
    if not odom_times:
        raise LogError(f"{src}: topic {odom_topic!r} holds no odometry messages")
    return scans, (np.asarray(odom_times), np.asarray(odom_poses, dtype=np.float64)), tree


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
        scans.frame = _frame(msg.header.frame_id)
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
    _check_pose((position.x, position.y, q.x, q.y, q.z, q.w), where, "odometry")
    if times and stamp < times[-1]:
        raise LogError(f"{where}: the odometry timestamp goes backwards (previous at {times[-1]:.9f} s)")
    # Yaw of a (not necessarily unit) quaternion: atan2 is scale-invariant.
    yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
    times.append(stamp)
    poses.append((float(position.x), float(position.y), yaw))


def _tf_odometry(src: str, plan: _Plan, tree: _TfTree):
    """(times (M,), poses (M, 3)) of ``base_frame`` in ``odom_frame`` from the transforms, sorted by stamp."""
    odom, base = plan.odom_frame, plan.base_frame
    what = f"{odom} -> {base}"
    links = tree.path(odom, base)
    if not links:
        raise LogError(f"{src}: no odometry: no topic {plan.odom_topic or '/odom'!r} in the bag, and "
                       f"{plan.tf_odometry} holds no {what} transform (its transforms: {tree.listing()}). "
                       f"{_ODOMETRY_OPTIONS}")
    chain = " -> ".join([odom] + [link[0] if inverted else link[1] for link, inverted in links])
    moving = [link for link, _ in links if link in tree.moves]
    timed = [link for link in moving if link in tree.series]
    if len(moving) > 1 or (moving and not timed):
        names = ", ".join(f"{p} -> {c}" for p, c in moving)
        raise LogError(f"{src}: the {what} chain in the bag's transforms ({chain}) has moving links ({names}) "
                       f"of which jaxslam reads one, the link from {odom!r} or to {base!r}; name frames whose "
                       f"chain has one moving link (odom_frame=, base_frame=; --odom-frame, --base-frame)")
    if not timed:  # the robot stands still: the longest series gives the stamps
        timed = sorted((link for link, _ in links if link in tree.series), key=lambda k: -len(tree.series[k][0]))
    if not timed:
        raise LogError(f"{src}: no odometry: the {what} transform ({chain}) is only in {TF_STATIC_TOPIC}: "
                       f"it never changes. {_ODOMETRY_OPTIONS}")
    link = timed[0]
    k = [lk for lk, _ in links].index(link)
    stamps, values = tree.series[link]
    order = np.argsort(np.asarray(stamps), kind="stable")  # tf is a time-indexed store, not a stream
    step = _Rigid.of(np.asarray(values)[order])
    if links[k][1]:
        step = step.inverse()
    pose = tree.constant(links[:k]).then(step).then(tree.constant(links[k + 1:]))
    return np.asarray(stamps, dtype=np.float64)[order], pose.planar()


def _find_mount_in_tf(reader, src: str, plan: _Plan, tree: _TfTree, laser_frame: str) -> None:
    """Where /tf_static does not reach the laser's frame, read /tf until it does (a ROS 1 bag may
    carry fixed transforms on /tf, e.g. from tf's static_transform_publisher)."""
    base = plan.base_frame
    if not laser_frame or laser_frame == base or tree.path(base, laser_frame) is not None:
        return
    tree.collect_series = False  # the odometry's transforms are read
    connections = [c for c in reader.connections if c.topic == TF_TOPIC and c.msgtype in TF_TYPES]
    if not connections:  # (no connections would read every message)
        return
    for index, (connection, bag_time_ns, raw) in enumerate(reader.messages(connections=connections)):
        where = f"{src}: {TF_TOPIC} message {index} (bag time {bag_time_ns * 1e-9:.9f} s)"
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as err:
            raise LogError(f"{where}: cannot deserialise {connection.msgtype} ({type(err).__name__}: {err})") from None
        tree.add_message(msg, TF_TOPIC, bag_time_ns, where)
        if tree.path(base, laser_frame) is not None:
            return


class _Mount(NamedTuple):
    """The laser's mounting on the robot."""

    pose: tuple[float, float, float]
    """(x, y, theta) of the laser in the base frame (m, m, rad)."""
    upside_down: bool
    """Whether the laser's z axis points down (its beam angles are mirrored)."""
    chain: str | None
    """Where it was read (for the note), or None."""


def _laser_mount(src: str, plan: _Plan, tree: _TfTree, laser_frame: str, found: list) -> _Mount:
    """The laser's mounting from the transforms; zero (and a warning in ``found``) where they do
    not reach the laser's frame."""
    base = plan.base_frame
    if not laser_frame or laser_frame == base:
        return _Mount((0.0, 0.0, 0.0), False, None)
    links = tree.path(base, laser_frame)
    if links is None:
        detail = (f"in {' or '.join(sorted(tree.topics))} (whose transforms are: {tree.listing()})" if tree.topics
                  else f"(the bag has no {TF_STATIC_TOPIC} or {TF_TOPIC})")
        found.append(f"{src}: no transform from {base!r} to the scans' frame {laser_frame!r} {detail}: the laser is "
                     "taken to sit at the robot's origin, facing forward; give its mounting with laser_pose= "
                     "(jaxslam map --laser-pose x,y,theta), or name the robot's frame with base_frame= (--base-frame)")
        return _Mount((0.0, 0.0, 0.0), False, None)
    moving = [f"{p} -> {c}" for (p, c), _ in links if (p, c) in tree.moves]
    if moving:
        found.append(f"{src}: the laser's mounting ({base} -> {laser_frame}) moves in {TF_TOPIC} "
                     f"({', '.join(moving)}); its first value is used")
    mount = tree.constant(links)
    chain = " -> ".join([base] + [link[0] if inverted else link[1] for link, inverted in links])
    x, y, theta = (float(v) for v in mount.planar())
    return _Mount((x, y, theta), mount.upside_down(), chain)


def _assemble(src, scan_topic, odom_what, scans: _Scans, odometry, mount: _Mount, notes, found) -> LaserLog:
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
                f"time span of the odometry on {odom_what} ({odom_times[0]:.9f}..{odom_times[-1]:.9f} s)"
            )
        warn(f"{src}: dropped {early + late} of {times.size} scans outside the odometry's time span "
             f"({early} before the first and {late} after the last {odom_what.strip(chr(39))} message): "
             "odometry is interpolated, never extrapolated")
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
        warn(note)
        notes.append(note)
    if mount.upside_down:
        # Seen from above, the beams of a laser whose z axis points down sweep clockwise: angle a
        # in the laser's frame is -a in the mounting's. Reversed, they keep their order.
        beam_angles, ranges = -beam_angles[::-1], np.ascontiguousarray(ranges[:, ::-1])
        notes.append(f"{src}: the laser is mounted upside down ({mount.chain}: its z axis points down): its beam "
                     "angles are mirrored (angle a is -a, the beams reversed)")
    sensor = make_sensor(beam_angles, range_min=range_min, range_max=range_max, laser_pose=mount.pose)
    return LaserLog(times[keep], paired.poses[keep], ranges, sensor, None, src, tuple(notes), tuple(found))
