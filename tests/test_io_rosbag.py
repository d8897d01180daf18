"""ROS bag reader: round trips through small ROS 1 and ROS 2 bags written here, every
malformed-input error, odometry from /tf and the laser's mounting from /tf_static (a
simulated office mapped through a bag with the laser mounted off-centre), and the real
Intel / ACES bags when ../shared/data is present."""

from __future__ import annotations

import math
import os
import re
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from jaxslam.io import read_log, read_rosbag
from jaxslam.laserlog import LogError

ANGLE_MIN = -math.pi / 2
INCREMENT = math.pi / 179
NUM_BEAMS = 180
RANGE_MAX = 80.0
T0 = 1000.0  # seconds: the first odometry stamp of the synthetic bags


def _time(ts, stamp: float):
    sec = int(math.floor(stamp))
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp - sec) * 1e9)))


def _header(ts, stamp: float, frame: str):
    Header = ts.types["std_msgs/msg/Header"]
    if "seq" in [f[0] for f in ts.fielddefs["std_msgs/msg/Header"][1]]:
        return Header(seq=0, stamp=_time(ts, stamp), frame_id=frame)
    return Header(stamp=_time(ts, stamp), frame_id=frame)


def scan_msg(ts, stamp, ranges, angle_min=ANGLE_MIN, increment=INCREMENT, range_max=RANGE_MAX):
    ranges = np.asarray(ranges, dtype=np.float32)
    return ts.types["sensor_msgs/msg/LaserScan"](
        header=_header(ts, stamp, "laser"),
        angle_min=angle_min,
        angle_max=angle_min + increment * (ranges.size - 1),
        angle_increment=increment,
        time_increment=0.0,
        scan_time=0.0,
        range_min=0.1,
        range_max=range_max,
        ranges=ranges,
        intensities=np.zeros(0, dtype=np.float32),
    )


def odom_msg(ts, stamp, x, y, yaw):
    T = ts.types
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
    )
    twist = T["geometry_msgs/msg/Twist"](
        linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return T["nav_msgs/msg/Odometry"](
        header=_header(ts, stamp, "odom"),
        child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def odom_pose(t):
    """The synthetic robot: constant forward and angular speed (x, y, yaw at time t)."""
    s = t - T0
    return 0.5 * s, 0.1 * s * s, 0.3 * s


def write_bag(path, messages, ros2=False, raw=(), empty_topics=()):
    """Write ``messages``: a list of (topic, bag_time_s, message). ``raw``: (topic, msgtype,
    bag_time_s, bytes) written as given (to corrupt a bag). ``empty_topics``: (topic,
    msgtype) connections without messages."""
    ts = _store("ros2" if ros2 else "ros1")
    writer = Writer2(path, version=9) if ros2 else Writer1(path)
    serialize = ts.serialize_cdr if ros2 else ts.serialize_ros1
    records = [(t, topic, msg.__msgtype__, bytes(serialize(msg, msg.__msgtype__))) for topic, t, msg in messages]
    records += [(t, topic, msgtype, data) for topic, msgtype, t, data in raw]
    records.sort(key=lambda r: r[0])
    with writer:
        connections = {}
        for topic, msgtype in empty_topics:
            connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for _, topic, msgtype, _ in records:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for t, topic, _, data in records:
            writer.write(connections[topic], int(round(t * 1e9)), data)
    return path


def standard_messages(ts, num_scans=5, odom_from=T0, odom_to=T0 + 3.0):
    """Odometry every 0.5 s over [odom_from, odom_to]; scans every 0.5 s from T0 + 0.25."""
    messages = []
    for t in np.arange(odom_from, odom_to + 1e-9, 0.5):
        messages.append(("/odom", t, odom_msg(ts, t, *odom_pose(t))))
    for k in range(num_scans):
        t = T0 + 0.25 + 0.5 * k
        ranges = np.linspace(1.0, 5.0, NUM_BEAMS) + k
        messages.append(("/scan", t, scan_msg(ts, t, ranges)))
    return messages


@pytest.fixture(params=["ros1", "ros2"])
def bag_kind(request):
    return request.param


def _bag_path(tmp_path, kind, name="test"):
    return tmp_path / (f"{name}.bag" if kind == "ros1" else name)


def _write(tmp_path, kind, messages, name="test", raw=(), empty_topics=()):
    return write_bag(_bag_path(tmp_path, kind, name), messages, ros2=(kind == "ros2"), raw=raw,
                     empty_topics=empty_topics)


def _store(kind):
    """The message types of a ROS 2 ('ros2') or ROS 1 bag; ROS 1's gets tf2_msgs/TFMessage, which
    rosbags' Noetic store lacks."""
    if kind == "ros2":
        return get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


# --------------------------------------------------------------------------- round trips


def test_round_trip(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = standard_messages(ts)
    # Scan 1: a +inf (no return), a reading beyond range_max and one exactly at it.
    special = np.linspace(1.0, 5.0, NUM_BEAMS) + 1
    special[[3, 4, 5]] = [np.inf, 95.0, RANGE_MAX]
    messages[[i for i, m in enumerate(messages) if m[0] == "/scan"][1]] = (
        "/scan", T0 + 0.75, scan_msg(ts, T0 + 0.75, special))
    path = _write(tmp_path, bag_kind, messages)
    log = read_rosbag(path)

    assert log.num_scans == 5 and log.num_beams == NUM_BEAMS
    np.testing.assert_allclose(log.timestamps, T0 + 0.25 + 0.5 * np.arange(5), atol=1e-9)
    expected_angles = np.float32(ANGLE_MIN) + np.float32(INCREMENT) * np.arange(NUM_BEAMS, dtype=np.float64)
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles), expected_angles, atol=1e-6)
    assert float(log.sensor.range_max) == RANGE_MAX
    assert float(log.sensor.range_min) == pytest.approx(0.1)
    assert log.ranges.dtype == np.float32
    assert np.all(log.ranges[1, 3:6] == np.float32(RANGE_MAX))
    np.testing.assert_allclose(log.ranges[0], np.linspace(1.0, 5.0, NUM_BEAMS), rtol=1e-6)
    assert np.all(np.isfinite(log.ranges))
    assert log.source == str(path)

    # Odometry: between two messages 0.5 s apart the pose is interpolated along the relative
    # motion; here at the midpoint, compare with geometry.interpolate's own numbers.
    from jaxslam.geometry import interpolate

    for k, t in enumerate(log.timestamps):
        a = np.array(odom_pose(t - 0.25))
        b = np.array(odom_pose(t + 0.25))
        np.testing.assert_allclose(log.odometry[k], np.asarray(interpolate(a, b, 0.5)), atol=1e-5)


def test_ros1_and_ros2_give_the_same_log(tmp_path):
    logs = []
    for kind in ("ros1", "ros2"):
        path = _write(tmp_path, kind, standard_messages(_store(kind)))
        logs.append(read_rosbag(path))
    np.testing.assert_array_equal(logs[0].timestamps, logs[1].timestamps)
    np.testing.assert_array_equal(logs[0].ranges, logs[1].ranges)
    np.testing.assert_allclose(logs[0].odometry, logs[1].odometry, atol=1e-12)


def test_scan_at_an_odometry_stamp_gets_that_pose(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = [("/odom", T0 + k, odom_msg(ts, T0 + k, *odom_pose(T0 + k))) for k in range(3)]
    messages.append(("/scan", T0 + 1.0, scan_msg(ts, T0 + 1.0, np.ones(NUM_BEAMS))))
    log = read_rosbag(_write(tmp_path, bag_kind, messages))
    np.testing.assert_allclose(log.odometry[0], odom_pose(T0 + 1.0), atol=1e-12)


def test_scans_outside_the_odometry_are_dropped_with_a_warning(tmp_path, bag_kind):
    ts = _store(bag_kind)
    # Odometry covers only [T0 + 0.5, T0 + 1.5]: scans at 0.25 (before) and 1.75, 2.25 (after).
    path = _write(tmp_path, bag_kind, standard_messages(ts, odom_from=T0 + 0.5, odom_to=T0 + 1.5))
    with pytest.warns(UserWarning, match=r"dropped 3 of 5 scans .*1 before the first and 2 after the last"):
        log = read_rosbag(path)
    np.testing.assert_allclose(log.timestamps, [T0 + 0.75, T0 + 1.25], atol=1e-9)


def test_no_scan_within_the_odometry_is_an_error(tmp_path, bag_kind):
    ts = _store(bag_kind)
    path = _write(tmp_path, bag_kind, standard_messages(ts, num_scans=2, odom_from=T0 + 5, odom_to=T0 + 6))
    with pytest.raises(LogError, match=r"no scan .* lies within the time span of the odometry"):
        read_rosbag(path)


def test_zero_header_stamp_falls_back_to_bag_time(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = [("/odom", T0 + k, odom_msg(ts, T0 + k, *odom_pose(T0 + k))) for k in range(3)]
    zero_stamp = scan_msg(ts, 0.0, np.ones(NUM_BEAMS))
    messages.append(("/scan", T0 + 1.5, zero_stamp))
    log = read_rosbag(_write(tmp_path, bag_kind, messages))
    np.testing.assert_allclose(log.timestamps, [T0 + 1.5], atol=1e-9)


def test_max_scans(tmp_path, bag_kind):
    path = _write(tmp_path, bag_kind, standard_messages(_store(bag_kind)))
    log = read_rosbag(path, max_scans=2)
    assert log.num_scans == 2
    np.testing.assert_array_equal(log.timestamps, read_rosbag(path).timestamps[:2])
    with pytest.raises(ValueError, match="max_scans"):
        read_rosbag(path, max_scans=0)


def test_other_topic_names(tmp_path, bag_kind):
    ts = _store(bag_kind)
    renamed = [({"/scan": "/base_scan", "/odom": "/wheel_odom"}[topic], t, msg)
               for topic, t, msg in standard_messages(ts)]
    path = _write(tmp_path, bag_kind, renamed)
    log = read_rosbag(path, scan_topic="/base_scan", odom_topic="/wheel_odom")
    assert log.num_scans == 5


def test_read_log_dispatches_bags(tmp_path, bag_kind):
    path = _write(tmp_path, bag_kind, standard_messages(_store(bag_kind)))
    assert read_log(path).num_scans == 5
    assert read_log(path, max_scans=3).num_scans == 3


# --------------------------------------------------------------------------- errors


def _where(path):
    return re.escape(str(path))


def test_unknown_topic_lists_the_topics(tmp_path, bag_kind):
    path = _write(tmp_path, bag_kind, standard_messages(_store(bag_kind)))
    with pytest.raises(LogError, match=_where(path) + r".*no topic '/laser'.*topics are: /odom \(nav_msgs/msg/Odometry\), "
                       r"/scan \(sensor_msgs/msg/LaserScan\)"):
        read_rosbag(path, scan_topic="/laser")
    with pytest.raises(LogError, match=r"no topic '/wheels'"):
        read_rosbag(path, odom_topic="/wheels")


def test_topic_of_the_wrong_type(tmp_path, bag_kind):
    path = _write(tmp_path, bag_kind, standard_messages(_store(bag_kind)))
    with pytest.raises(LogError, match=r"topic '/odom' holds nav_msgs/msg/Odometry, expected sensor_msgs/msg/LaserScan"):
        read_rosbag(path, scan_topic="/odom")


def test_no_scans(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = [m for m in standard_messages(ts) if m[0] == "/odom"]
    path = _write(tmp_path, bag_kind, messages)
    with pytest.raises(LogError, match=_where(path) + r".*no topic '/scan'"):
        read_rosbag(path)
    path = _write(tmp_path, bag_kind, messages, name="empty_scan",
                  empty_topics=[("/scan", "sensor_msgs/msg/LaserScan")])
    with pytest.raises(LogError, match=_where(path) + r": topic '/scan' holds no scans"):
        read_rosbag(path)


def test_no_odometry(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = [m for m in standard_messages(ts) if m[0] == "/scan"]
    messages.append(("/odom_other", T0, odom_msg(ts, T0, 0.0, 0.0, 0.0)))
    path = _write(tmp_path, bag_kind, messages)
    with pytest.raises(LogError, match=r"no topic '/odom'"):
        read_rosbag(path)
    path = _write(tmp_path, bag_kind, messages, name="empty_odom",
                  empty_topics=[("/odom", "nav_msgs/msg/Odometry")])
    with pytest.raises(LogError, match=_where(path) + r": topic '/odom' holds no odometry messages"):
        read_rosbag(path)


def _replace_scan(messages, index, new_msg):
    """Replace the ``index``-th /scan message (keeping its bag time)."""
    positions = [i for i, m in enumerate(messages) if m[0] == "/scan"]
    topic, t, _ = messages[positions[index]]
    messages[positions[index]] = (topic, t, new_msg)
    return messages


def _scan_error(tmp_path, kind, index, make, match):
    ts = _store(kind)
    t = T0 + 0.25 + 0.5 * index
    messages = _replace_scan(standard_messages(ts), index, make(ts, t))
    path = _write(tmp_path, kind, messages)
    pattern = _where(path) + rf".*/scan message {index} \(bag message \d+, bag time {t:.9f} s\), stamp .*" + match
    with pytest.raises(LogError, match=pattern):
        read_rosbag(path)


def test_angle_min_changing(tmp_path, bag_kind):
    _scan_error(tmp_path, bag_kind, 3, lambda ts, t: scan_msg(ts, t, np.ones(NUM_BEAMS), angle_min=-1.0),
                r"the beam layout changes from 180 beams, angle_min -1\.5707964 rad, .*\(the widest scan's, first "
                r"at .*/scan message 0 .*\) to 180 beams, angle_min -1\.0000000 rad.*: the angular range changes")


def test_angle_increment_changing(tmp_path, bag_kind):
    _scan_error(tmp_path, bag_kind, 1, lambda ts, t: scan_msg(ts, t, np.ones(NUM_BEAMS), increment=0.01),
                r"the beam layout changes .* to 180 beams, angle_min -1\.5707964 rad, increment 0\.0100000 rad.*: "
                r"its beams are not on the widest scan's angular grid")


# --------------------------------------------------------------------------- changing beam layouts


def _layout_warnings(record):
    return [w for w in record if issubclass(w.category, UserWarning) and "beam layout changes" in str(w.message)]


def _read_counting_warnings(path, **kwargs):
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        log = read_rosbag(path, **kwargs)
    return log, _layout_warnings(record)


def _mixed_messages(ts, layouts):
    """standard_messages whose k-th scan has layouts[k] = (num_beams, angle_min); ranges 1 + k + beam/100."""
    messages = standard_messages(ts, num_scans=len(layouts))
    for k, (num_beams, angle_min) in enumerate(layouts):
        t = T0 + 0.25 + 0.5 * k
        _replace_scan(messages, k, scan_msg(ts, t, 1.0 + k + np.arange(num_beams) / 100, angle_min=angle_min))
    return messages


def test_180_and_181_beam_scans_are_padded(tmp_path, bag_kind):
    from jaxslam.laser import valid_returns

    layouts = [(180, ANGLE_MIN), (181, ANGLE_MIN), (180, ANGLE_MIN), (181, ANGLE_MIN), (180, ANGLE_MIN)]
    path = _write(tmp_path, bag_kind, _mixed_messages(_store(bag_kind), layouts))
    log, warned = _read_counting_warnings(path)
    assert len(warned) == 1  # once per log, not once per scan
    message = str(warned[0].message)
    assert message.startswith(f"{path}: the beam layout changes within the log (2 scans of 181 beams from -90.000 "
                              "deg, 1.006 deg apart; 3 scans of 180 beams from -90.000 deg, 1.006 deg apart)")
    assert "3 of 5 scans were padded to the widest scan's 181 beam angles" in message
    assert log.notes == (message,)
    assert log.ranges.shape == (5, 181)
    # The widest scan's angles; the 180-beam scans are its first 180 beams, the 181st is padding.
    expected_angles = np.float32(ANGLE_MIN) + np.float32(INCREMENT) * np.arange(181, dtype=np.float64)
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles), expected_angles, atol=1e-6)
    for k, (num_beams, _) in enumerate(layouts):
        np.testing.assert_allclose(log.ranges[k, :num_beams], 1.0 + k + np.arange(num_beams) / 100, rtol=1e-6)
    assert np.all(log.ranges[[0, 2, 4], 180] == 0.0)
    valid = np.asarray(valid_returns(log.ranges, log.sensor))
    assert not valid[[0, 2, 4], 180].any() and valid[[1, 3], 180].all()
    # A padded beam is no "no return" either (that would clear free space).
    assert np.all(log.ranges[[0, 2, 4], 180] < float(log.sensor.range_min))
    # Reading only scans of one layout pads nothing and says nothing.
    log2, warned2 = _read_counting_warnings(path, max_scans=1)
    assert log2.num_beams == 180 and not warned2 and log2.notes == ()


def test_padded_beams_neither_clear_nor_mark_cells():
    """Inserting a padded scan changes exactly what inserting the unpadded one changes."""
    import jax
    import jax.numpy as jnp

    from jaxslam import grid as G
    from jaxslam import occupancy as O
    from jaxslam.io.beam_layouts import BeamLayout, pad_beam_layouts
    from jaxslam.laser import make_sensor

    angles = ANGLE_MIN + INCREMENT * np.arange(181)
    layouts = [BeamLayout(angles[:180], INCREMENT, "a"), BeamLayout(angles, INCREMENT, "b")]
    rng = np.random.default_rng(0)
    scans = [rng.uniform(0.5, 3.0, 180).astype(np.float32), rng.uniform(0.5, 3.0, 181).astype(np.float32)]
    beam_angles, ranges, range_min, note = pad_beam_layouts("x", layouts, [0, 1], scans, 0.0)
    assert note and range_min == pytest.approx(1e-3)  # range_min 0 is raised so that 0 m is invalid
    spec = G.GridSpec((40, 40), 0.2, (-4.0, -4.0))
    params = O.InsertionParams(*(jnp.float32(v) for v in (0.9, -0.4, -2.0, 3.5, 5.0)))
    insert = jax.jit(O.insert_scan, static_argnums=(0, 6, 7))
    pose = jnp.asarray([0.1, -0.2, 0.3], jnp.float32)
    padded = insert(spec, O.empty_map(spec), pose, jnp.asarray(ranges[0]),
                    make_sensor(beam_angles, range_min, 3.5), params, 3.5, 3)[0]
    plain = insert(spec, O.empty_map(spec), pose, jnp.asarray(scans[0]),
                   make_sensor(angles[:180], range_min, 3.5), params, 3.5, 3)[0]
    np.testing.assert_array_equal(np.asarray(padded.logodds), np.asarray(plain.logodds))
    np.testing.assert_array_equal(np.asarray(padded.hit_dist2), np.asarray(plain.hit_dist2))


def test_interleaved_scans_are_merged(tmp_path, bag_kind):
    """Scans on the widest scan's grid shifted by a quarter increment (a SICK LMS's interlaced
    mode, as in FR-clinic) are kept at their own angles, each beam stride sampling all scans."""
    from jaxslam.laser import subsample_beams, valid_returns

    quarter = ANGLE_MIN + INCREMENT / 4
    layouts = [(180, quarter), (181, ANGLE_MIN), (180, quarter)]
    path = _write(tmp_path, bag_kind, _mixed_messages(_store(bag_kind), layouts))
    log, warned = _read_counting_warnings(path)
    assert len(warned) == 1 and "interleaved 1/4 of its increment apart" in str(warned[0].message)
    assert log.num_beams == 361
    angles = np.asarray(log.sensor.beam_angles, dtype=np.float64)
    np.testing.assert_allclose(angles[:181], np.float32(ANGLE_MIN) + np.float32(INCREMENT) * np.arange(181),
                               atol=1e-6)
    np.testing.assert_allclose(angles[181:], np.float32(quarter) + np.float32(INCREMENT) * np.arange(180),
                               atol=1e-6)
    np.testing.assert_allclose(log.ranges[0, 181:], 1.0 + np.arange(180) / 100, rtol=1e-6)
    assert np.all(log.ranges[0, :181] == 0.0) and np.all(log.ranges[1, 181:] == 0.0)
    for stride in (2, 3):
        sensor, ranges = subsample_beams(log.sensor, log.ranges, stride)
        valid = np.asarray(valid_returns(ranges, sensor)).sum(axis=1)
        assert np.all(valid >= 180 // stride), (stride, valid)


def test_scans_changing_their_angular_range_are_an_error(tmp_path, bag_kind):
    ts = _store(bag_kind)
    shifted = ANGLE_MIN + 10 * INCREMENT  # on the grid, but 10 beams beyond the widest scan's range
    path = _write(tmp_path, bag_kind, _mixed_messages(ts, [(181, ANGLE_MIN), (180, ANGLE_MIN), (180, shifted)]))
    pattern = (_where(path) + r": /scan message 2 \(bag message \d+, bag time 1001\.250000000 s\), stamp "
               r"1001\.250000000 s: the beam layout changes from 181 beams, angle_min -1\.5707964 rad, increment "
               r"0\.0175508 rad \(-90\.000\.\.91\.006 deg\) \(the widest scan's, first at .*/scan message 0 .*\) to "
               r"180 beams, angle_min -1\.39528\d+ rad, .*: the angular range changes")
    with pytest.raises(LogError, match=pattern):
        read_rosbag(path)
    # Off the grid by 0.37 of an increment: not interleaved either.
    path = _write(tmp_path, bag_kind, _mixed_messages(ts, [(181, ANGLE_MIN), (180, ANGLE_MIN + 0.37 * INCREMENT)]),
                  name="offgrid")
    with pytest.raises(LogError, match=r"/scan message 1 .*its beams are not on the widest scan's angular grid"):
        read_rosbag(path)


def _office_log():
    import jax

    from jaxslam.sim import office_scenario

    return office_scenario(jax.random.key(0), num_scans=150, num_beams=181).log.subset(np.arange(40))


def test_a_bag_of_180_and_181_beam_scans_maps(tmp_path):
    """The office simulation written as a bag whose odd scans lack their last beam: it reads,
    maps, and summary.json records the padding."""
    import json

    from jaxslam.cli import main

    sim = _office_log()
    ts = _store("ros1")
    increment = math.pi / 180
    messages = []
    for k in range(sim.num_scans):
        t = T0 + float(sim.timestamps[k])
        messages.append(("/odom", t, odom_msg(ts, t, *map(float, sim.odometry[k]))))
        ranges = sim.ranges[k] if k % 2 == 0 else sim.ranges[k, :180]
        messages.append(("/scan", t, scan_msg(ts, t, ranges, increment=increment,
                                              range_max=float(sim.sensor.range_max))))
    path = write_bag(tmp_path / "office.bag", messages)
    log, warned = _read_counting_warnings(path)
    assert len(warned) == 1 and log.num_beams == 181
    np.testing.assert_array_equal(log.ranges[::2], sim.ranges[::2])
    assert np.all(log.ranges[1::2, 180] == 0.0)

    out = tmp_path / "out"
    assert main(["map", str(path), "--particles", "2", "--proposal", "smp", "--no-progress", "--set",
                 "linear_update=0.3", "--set", "max_insert_range=8", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans_in_log"] == 40
    assert len(summary["log_notes"]) == 1 and "20 of 40 scans were padded" in summary["log_notes"][0]
    traj = np.loadtxt(out / "trajectory.txt")
    # The path follows the simulated one (odometry drift over 40 scans is corrected, not added).
    err = np.hypot(*(traj[:, 1:3] - sim.ground_truth[:, :2]).T)
    assert traj.shape == (40, 4) and err.max() < 0.3, err.max()


def test_range_max_changing(tmp_path, bag_kind):
    _scan_error(tmp_path, bag_kind, 1, lambda ts, t: scan_msg(ts, t, np.ones(NUM_BEAMS), range_max=30.0),
                "range_min/range_max change")


@pytest.mark.parametrize("bad", [np.nan, -0.5, -np.inf])
def test_nan_or_negative_range(tmp_path, bag_kind, bad):
    def make(ts, t):
        ranges = np.ones(NUM_BEAMS)
        ranges[17] = bad
        return scan_msg(ts, t, ranges)

    _scan_error(tmp_path, bag_kind, 2, make, r"beam 17 has range .*NaN or negative")


def test_scan_timestamps_going_backwards(tmp_path, bag_kind):
    _scan_error(tmp_path, bag_kind, 2, lambda ts, t: scan_msg(ts, t - 0.6, np.ones(NUM_BEAMS)),
                "timestamp goes backwards")


def test_odometry_timestamps_going_backwards(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = standard_messages(ts)
    messages.append(("/odom", T0 + 3.2, odom_msg(ts, T0 + 1.0, 0.0, 0.0, 0.0)))
    path = _write(tmp_path, bag_kind, messages)
    with pytest.raises(LogError, match=r"/odom message 7 .*odometry timestamp goes backwards"):
        read_rosbag(path)


@pytest.mark.parametrize("pose, match", [((0.0, math.nan), "non-finite odometry pose"),
                                         ((0.0, 0.0), "the odometry orientation is a zero quaternion")])
def test_bad_odometry_pose(tmp_path, bag_kind, pose, match):
    ts = _store(bag_kind)
    messages = standard_messages(ts)
    bad = odom_msg(ts, T0 + 3.5, 0.0, pose[1], 0.0)
    if pose[1] == 0.0:
        bad.pose.pose.orientation.w = 0.0
    messages.append(("/odom", T0 + 3.5, bad))
    path = _write(tmp_path, bag_kind, messages)
    with pytest.raises(LogError, match=_where(path) + r".*/odom message 7 .*stamp 1003\.500000000 s: " + match):
        read_rosbag(path)


def test_message_that_cannot_be_deserialised(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = standard_messages(ts)
    raw = [("/scan", "sensor_msgs/msg/LaserScan", T0 + 2.6, b"\x00\x01\x02")]
    path = _write(tmp_path, bag_kind, messages, raw=raw)
    with pytest.raises(LogError, match=_where(path) + r".*/scan message 5 .*bag time 1002\.600000000 s.*cannot deserialise"):
        read_rosbag(path)


def test_bad_paths(tmp_path):
    with pytest.raises(LogError, match=r"no such bag"):
        read_rosbag(tmp_path / "missing.bag")
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(LogError, match=re.escape(str(folder)) + r".*metadata\.yaml"):
        read_rosbag(folder)
    text = tmp_path / "log.txt"
    text.write_text("hello\n")
    with pytest.raises(LogError, match=r"expected a ROS 1 '\.bag' file"):
        read_rosbag(text)
    broken = tmp_path / "broken.bag"
    broken.write_bytes(b"#ROSBAG V2.0\nthis is not a bag")
    with pytest.raises(LogError, match=re.escape(str(broken)) + r": cannot open the bag"):
        read_rosbag(broken)


# --------------------------------------------------------------------------- odometry from /tf


def quaternion(roll=0.0, pitch=0.0, yaw=0.0):
    """(x, y, z, w) of the rotation yaw about z, after pitch about y, after roll about x."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def transform(ts, stamp, parent, child, xyz=(0.0, 0.0, 0.0), quat=(0.0, 0.0, 0.0, 1.0)):
    """A geometry_msgs/TransformStamped: the pose of ``child`` in ``parent``."""
    T = ts.types
    return T["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, stamp, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2], w=quat[3])))


def tf_msg(ts, *transforms):
    return ts.types["tf2_msgs/msg/TFMessage"](transforms=list(transforms))


def odometry_as_tf(ts, messages, parent="odom", child="base_link", extra=()):
    """``messages`` with every /odom message replaced by the same pose as a /tf transform
    ``parent -> child`` (with ``extra(stamp)`` transforms in the same message)."""
    out = []
    for topic, t, msg in messages:
        if topic == "/odom":
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            msg = tf_msg(ts, *[f(stamp) for f in extra],
                         transform(ts, stamp, parent, child, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)))
            topic = "/tf"
        out.append((topic, t, msg))
    return out


@pytest.mark.parametrize("frames, options", [
    (("odom", "base_link"), {}),
    (("/odom", "/base_link"), {}),  # ROS 1 style names
    (("odom_combined", "base_footprint"), {"odom_frame": "/odom_combined", "base_frame": "base_footprint"}),
])
def test_odometry_from_tf_equals_odom(tmp_path, bag_kind, frames, options):
    ts = _store(bag_kind)
    messages = standard_messages(ts)
    with_odom = read_rosbag(_write(tmp_path, bag_kind, messages, name="odom"))
    # Other transforms in the same /tf messages (map -> odom, a wheel) must not matter.
    extra = (lambda t: transform(ts, t, "map", frames[0], (5.0, -3.0, 0.0), quaternion(yaw=1.0)),
             lambda t: transform(ts, t, frames[1], "wheel", (0.0, 0.2, 0.0), quaternion(pitch=t)))
    path = _write(tmp_path, bag_kind, odometry_as_tf(ts, messages, *frames, extra=extra), name="tf")
    with_tf = read_rosbag(path, **options)
    np.testing.assert_array_equal(with_tf.timestamps, with_odom.timestamps)
    np.testing.assert_array_equal(with_tf.ranges, with_odom.ranges)
    np.testing.assert_allclose(with_tf.odometry, with_odom.odometry, atol=1e-12, rtol=0)
    assert any("no topic '/odom': the odometry is the /tf" in note for note in with_tf.notes), with_tf.notes
    # The /tf topic named as the odometry topic: the same, without the note.
    named = read_rosbag(path, odom_topic="/tf", **options)
    np.testing.assert_array_equal(named.odometry, with_tf.odometry)
    assert named.notes == ()
    assert read_log(path, **options).num_scans == 5  # read_log passes the frames on


def test_odometry_from_a_tf_chain(tmp_path, bag_kind):
    """odom -> base_footprint moving in /tf, base_footprint -> base_link fixed in /tf_static
    (5 cm ahead, 10 cm up): the odometry is base_link's pose."""
    from jaxslam.geometry import compose

    ts = _store(bag_kind)
    messages = standard_messages(ts)
    fixed = ("/tf_static", T0 - 1.0, tf_msg(ts, transform(ts, T0 - 1.0, "base_footprint", "base_link",
                                                            (0.05, 0.0, 0.1))))
    path = _write(tmp_path, bag_kind, odometry_as_tf(ts, messages, "odom", "base_footprint") + [fixed])
    log = read_rosbag(path)
    # The same as /odom messages of base_link's pose (composed before the interpolation).
    ahead = [(topic, t, odom_msg(ts, t, *map(float, compose(np.array(odom_pose(t)), np.array([0.05, 0.0, 0.0])))))
             if topic == "/odom" else (topic, t, msg) for topic, t, msg in messages]
    np.testing.assert_allclose(log.odometry, read_rosbag(_write(tmp_path, bag_kind, ahead, name="ahead")).odometry,
                               atol=1e-6)
    # Read up to base_footprint instead, it is the /odom odometry.
    plain = read_rosbag(_write(tmp_path, bag_kind, messages, name="odom"))
    np.testing.assert_allclose(read_rosbag(path, base_frame="base_footprint").odometry, plain.odometry, atol=1e-12)


def test_tf_stamps_out_of_order_are_sorted(tmp_path, bag_kind):
    ts = _store(bag_kind)
    messages = odometry_as_tf(ts, standard_messages(ts))
    tf_positions = [i for i, m in enumerate(messages) if m[0] == "/tf"]
    a, b = tf_positions[2], tf_positions[3]
    messages[a], messages[b] = (messages[a][0], messages[a][1], messages[b][2]), (messages[b][0], messages[b][1],
                                                                                 messages[a][2])
    log = read_rosbag(_write(tmp_path, bag_kind, messages))
    np.testing.assert_allclose(log.odometry, read_rosbag(_write(tmp_path, bag_kind, standard_messages(ts),
                                                                name="odom")).odometry, atol=1e-12)


def test_no_odometry_names_the_topic_and_the_frames(tmp_path, bag_kind):
    ts = _store(bag_kind)
    scans_only = [m for m in standard_messages(ts) if m[0] == "/scan"]
    path = _write(tmp_path, bag_kind, scans_only)
    with pytest.raises(LogError, match=_where(path) + r": no odometry: no topic '/odom' in the bag, and no /tf topic "
                       r"to take the odom -> base_link transform from; its topics are: /scan .*--odom-topic.*"
                       r"--odom-frame and --base-frame"):
        read_rosbag(path)
    # /tf without the odom -> base_link transform: the message lists the transforms there are.
    messages = odometry_as_tf(ts, standard_messages(ts), "odom", "base_footprint")
    path = _write(tmp_path, bag_kind, messages, name="other_frames")
    with pytest.raises(LogError, match=r"no odometry: no topic '/odom' in the bag, and /tf holds no odom -> base_link "
                       r"transform \(its transforms: odom -> base_footprint \(/tf\)\)\. .*--odom-frame"):
        read_rosbag(path)
    assert read_rosbag(path, base_frame="base_footprint").num_scans == 5
    with pytest.raises(LogError, match=r"holds no wheel_odom -> base_footprint transform"):
        read_rosbag(path, odom_frame="wheel_odom", base_frame="base_footprint")


def test_two_moving_links_are_an_error(tmp_path, bag_kind):
    ts = _store(bag_kind)
    wobble = (lambda t: transform(ts, t, "base_footprint", "base_link", (0.01 * t, 0.0, 0.0)),)
    messages = odometry_as_tf(ts, standard_messages(ts), "odom", "base_footprint", extra=wobble)
    with pytest.raises(LogError, match=r"the odom -> base_link chain .*\(odom -> base_footprint -> base_link\) has "
                       r"moving links \(.*\)"):
        read_rosbag(_write(tmp_path, bag_kind, messages))


def test_bad_frame_options(tmp_path):
    path = _write(tmp_path, "ros1", standard_messages(_store("ros1")))
    for kwargs in ({"odom_frame": ""}, {"base_frame": "/"}, {"base_frame": 3}):
        with pytest.raises(ValueError, match=r"must be a frame name"):
            read_rosbag(path, **kwargs)
    for pose in ((1.0, 2.0), (0.0, 0.0, math.nan), "0,0,0", 5.0):
        with pytest.raises(ValueError, match=r"laser_pose must be three finite numbers"):
            read_rosbag(path, laser_pose=pose)


# --------------------------------------------------------------------------- the laser's mounting


def _with_static(ts, messages, *transforms, topic="/tf_static"):
    return messages + [(topic, T0 - 1.0, tf_msg(ts, *transforms))]


def test_laser_mount_from_tf_static(tmp_path, bag_kind):
    ts = _store(bag_kind)
    mount = transform(ts, T0, "base_link", "laser", (0.25, 0.0, 0.3), quaternion(yaw=0.1))
    log = read_rosbag(_write(tmp_path, bag_kind, _with_static(ts, standard_messages(ts), mount)))
    np.testing.assert_allclose(np.asarray(log.sensor.laser_pose), [0.25, 0.0, 0.1], atol=1e-6)
    assert log.warnings == () and log.notes == ()
    plain = read_rosbag(_write(tmp_path, bag_kind, standard_messages(ts), name="plain"))
    np.testing.assert_array_equal(log.ranges, plain.ranges)
    np.testing.assert_array_equal(np.asarray(log.sensor.beam_angles), np.asarray(plain.sensor.beam_angles))
    # laser_pose given: used instead of the bag's.
    given = read_rosbag(_write(tmp_path, bag_kind, _with_static(ts, standard_messages(ts), mount), name="given"),
                        laser_pose=(0.0, 0.0, 0.0))
    np.testing.assert_array_equal(np.asarray(given.sensor.laser_pose), [0.0, 0.0, 0.0])


def test_laser_mount_through_intermediate_frames(tmp_path, bag_kind):
    """base_link -> mast (0.25 m ahead) -> laser (0.2 m up, yawed 0.1 rad), the laser hung off
    the mast and the mast off base_footprint, a sibling of base_link in the odometry's tree;
    frame names with a leading '/' in the scans."""
    ts = _store(bag_kind)
    messages = odometry_as_tf(ts, standard_messages(ts), "odom", "base_footprint",
                              extra=(lambda t: transform(ts, t, "base_footprint", "base_link", (0.0, 0.0, 0.1)),))
    for topic, _, msg in messages:
        if topic == "/scan":
            msg.header.frame_id = "/laser"
    messages = _with_static(ts, messages, transform(ts, T0, "/base_footprint", "mast", (0.25, 0.0, 0.5)),
                            transform(ts, T0, "mast", "/laser", (0.0, 0.0, 0.2), quaternion(yaw=0.1)))
    log = read_rosbag(_write(tmp_path, bag_kind, messages))
    np.testing.assert_allclose(np.asarray(log.sensor.laser_pose), [0.25, 0.0, 0.1], atol=1e-6)
    assert log.warnings == ()


def test_laser_mount_from_tf_when_there_is_no_tf_static(tmp_path, bag_kind):
    ts = _store(bag_kind)
    mount = transform(ts, T0, "base_link", "laser", (-0.1, 0.05, 0.0), quaternion(yaw=-0.2))
    messages = standard_messages(ts)
    messages += [("/tf", T0 + 0.1 * k, tf_msg(ts, mount)) for k in range(3)]  # tf's static_transform_publisher
    log = read_rosbag(_write(tmp_path, bag_kind, messages))
    np.testing.assert_allclose(np.asarray(log.sensor.laser_pose), [-0.1, 0.05, -0.2], atol=1e-6)


def test_a_laser_frame_without_transform_is_warned_of(tmp_path, bag_kind):
    ts = _store(bag_kind)
    other = transform(ts, T0, "base_link", "camera", (0.1, 0.0, 0.0))
    log = read_rosbag(_write(tmp_path, bag_kind, _with_static(ts, standard_messages(ts), other)))
    np.testing.assert_array_equal(np.asarray(log.sensor.laser_pose), [0.0, 0.0, 0.0])
    assert len(log.warnings) == 1
    assert re.search(r"no transform from 'base_link' to the scans' frame 'laser' in /tf_static \(whose transforms "
                     r"are: base_link -> camera \(/tf_static\)\): the laser is taken to sit at the robot's origin.*"
                     r"--laser-pose x,y,theta", log.warnings[0]), log.warnings[0]
    # No transforms at all: the same, saying so.
    bare = read_rosbag(_write(tmp_path, bag_kind, standard_messages(ts), name="bare"))
    assert len(bare.warnings) == 1 and "(the bag has no /tf_static or /tf)" in bare.warnings[0]


UPSIDE_DOWN = [  # (quaternion, the laser's heading on the robot)
    ((1.0, 0.0, 0.0, 0.0), 0.0),  # rolled 180 degrees
    ((0.0, 1.0, 0.0, 0.0), math.pi),  # pitched 180 degrees: facing backwards
    (quaternion(roll=math.pi, yaw=0.1), 0.1),
]


@pytest.mark.parametrize("quat, heading", UPSIDE_DOWN)
def test_upside_down_laser_has_mirrored_beams(tmp_path, bag_kind, quat, heading):
    """Beams -2..1 rad in the laser's frame are 1..-2 rad seen from above; read as -1..2 rad
    increasing, each range with its beam."""
    ts = _store(bag_kind)
    num_beams, angle_min, increment = 301, -2.0, 0.01
    messages = [m for m in standard_messages(ts) if m[0] == "/odom"]
    raw = [1.0 + k + np.arange(num_beams) / 100 for k in range(3)]
    messages += [("/scan", T0 + 0.5 + k, scan_msg(ts, T0 + 0.5 + k, raw[k], angle_min=angle_min,
                                                   increment=increment)) for k in range(3)]
    messages = _with_static(ts, messages, transform(ts, T0, "base_link", "laser", (0.2, 0.0, 0.3), quat))
    log = read_rosbag(_write(tmp_path, bag_kind, messages))
    angles = np.asarray(log.sensor.beam_angles, dtype=np.float64)
    laser_angles = np.float32(angle_min) + np.float32(increment) * np.arange(num_beams, dtype=np.float64)
    np.testing.assert_allclose(angles, -laser_angles[::-1], atol=1e-6)
    assert np.all(np.diff(angles) > 0)
    for k in range(3):
        np.testing.assert_allclose(log.ranges[k], raw[k][::-1], rtol=1e-6)  # beam j: angle -a, range r(a)
    pose = np.asarray(log.sensor.laser_pose, dtype=np.float64)
    np.testing.assert_allclose(pose[:2], [0.2, 0.0], atol=1e-6)
    assert abs(np.angle(np.exp(1j * (pose[2] - heading)))) < 1e-6
    assert any("mounted upside down" in note and "mirrored" in note for note in log.notes), log.notes
    # The beams' world directions: a beam at laser angle a points along heading - a.
    from jaxslam.laser import laser_rays

    _, world = laser_rays(np.zeros(3, np.float32), log.sensor)
    np.testing.assert_allclose(np.angle(np.exp(1j * (np.asarray(world) - (heading - laser_angles[::-1])))), 0.0,
                               atol=1e-5)


# --------------------------------------------------------------------------- a mounted laser, mapped


MOUNT = (0.25, 0.0, 0.1)  # the laser 0.25 m ahead of base_link, yawed 0.1 rad


@pytest.fixture(scope="module")
def mounted_office():
    """The simulated office's first 40 scans (23 m of path) as a laser mounted at MOUNT sees
    them, and as one at the robot's origin sees them (the same noise draws, the same poses)."""
    import jax
    import jax.numpy as jnp

    from jaxslam.sim import office_scenario
    from jaxslam.sim.simulate import simulate_scans

    scenario = office_scenario(jax.random.key(0), num_scans=150, num_beams=181)
    sim = scenario.log.subset(np.arange(40))
    key = jax.random.key(7)
    mounted = simulate_scans(key, scenario.world, sim.ground_truth,
                             sim.sensor._replace(laser_pose=jnp.asarray(MOUNT, jnp.float32)), 0.02)
    plain = simulate_scans(key, scenario.world, sim.ground_truth, sim.sensor, 0.02)
    return sim, np.asarray(mounted), np.asarray(plain)


def _office_bag(path, sim, ranges, mount_quat=None, mount_xyz=(0.0, 0.0, 0.0), upside_down=False,
                odometry_in_tf=False):
    """The office log as a ROS 1 bag: /odom (or, ``odometry_in_tf``, only /tf odom -> base_link)
    and /scan at the scan times, /tf_static base_link -> laser (``mount_quat``; none when None).
    An upside-down laser's beams run the other way: its message holds the ranges reversed (the
    office's beams are symmetric about 0)."""
    ts = _store("ros1")
    messages = []
    range_max = float(sim.sensor.range_max)
    for k in range(sim.num_scans):
        t = T0 + float(sim.timestamps[k])
        messages.append(("/odom", t, odom_msg(ts, t, *map(float, sim.odometry[k]))))
        scan = np.ascontiguousarray(ranges[k][::-1]) if upside_down else ranges[k]
        messages.append(("/scan", t, scan_msg(ts, t, scan, increment=math.pi / 180, range_max=range_max)))
    if odometry_in_tf:
        messages = odometry_as_tf(ts, messages)
    if mount_quat is not None:
        messages = _with_static(ts, messages, transform(ts, T0, "base_link", "laser", mount_xyz, mount_quat))
    return write_bag(path, messages)


def _map_errors(log, truth, key=0, figure=None):
    """Position errors (m) of the best path against the truth at the processed scans, and the
    per-scan trajectory: jaxslam.slam.run with 4 particles, a scan every 0.3 m."""
    import jax

    from jaxslam import slam
    from jaxslam.config import RunSettings, SlamConfig, default_params

    config = SlamConfig(num_particles=4, proposal="smp", max_insert_range=8.0, beam_stride=1, map_extent=128.0)
    result = slam.run(jax.random.key(key), log, config, default_params(),
                      RunSettings(linear_update=0.3, angular_update=0.25), progress=False)
    idx = result.selection.indices
    errors = np.hypot(*(result.best_path[:, :2] - truth[idx, :2]).T)
    return (errors, result.trajectory, result) if figure else (errors, result.trajectory)


@pytest.fixture(scope="module")
def mounted_maps(mounted_office, tmp_path_factory):
    """Read and mapped: the mounted laser's bag (mount in /tf_static), the plain laser's bag,
    and the mounted laser's bag read with laser_pose=(0, 0, 0) (the mount ignored)."""
    sim, mounted, plain = mounted_office
    folder = tmp_path_factory.mktemp("mounted")
    # As many robots record it: no /odom topic, the odometry only in /tf, the mount in /tf_static.
    mounted_bag = _office_bag(folder / "mounted.bag", sim, mounted, quaternion(yaw=MOUNT[2]), (MOUNT[0], MOUNT[1], 0.3),
                              odometry_in_tf=True)
    logs = {"mounted": read_rosbag(mounted_bag),
            "plain": read_rosbag(_office_bag(folder / "plain.bag", sim, plain, quaternion())),
            "ignored": read_rosbag(mounted_bag, laser_pose=(0.0, 0.0, 0.0))}
    maps = {name: _map_errors(log, sim.ground_truth, figure=name) for name, log in logs.items()}
    figures = os.environ.get("JAXSLAM_TEST_FIGURES")
    if figures:  # the maps side by side, for the docs: JAXSLAM_TEST_FIGURES=FOLDER pytest -k mounted
        _plot_mounted_maps(Path(figures) / "mounted_laser_bag.png", maps, sim)
    return logs, {name: (errors, trajectory) for name, (errors, trajectory, _) in maps.items()}


def _plot_mounted_maps(path, maps, sim):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxslam.plotting import plot_map

    titles = {"mounted": "odometry in /tf, laser mount in /tf_static", "plain": "the laser at the robot's origin",
              "ignored": "the mount ignored (--laser-pose 0,0,0)"}
    fig, axes = plt.subplots(1, 3, figsize=(15, 5))
    for ax, (name, (errors, trajectory, result)) in zip(axes, maps.items()):
        logodds, _, grid = result.dense_map()
        plot_map(ax, logodds, grid)
        ax.plot(sim.ground_truth[:, 0], sim.ground_truth[:, 1], "g-", lw=1, label="truth")
        ax.plot(trajectory[:, 0], trajectory[:, 1], "r-", lw=1, label="best path")
        ax.set_title(f"{titles[name]}\nmean error {errors.mean():.3f} m")
    axes[0].legend(loc="lower right")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def test_a_mounted_laser_maps_as_one_at_the_origin(mounted_office, mounted_maps):
    """The key check: the same robot path seen by a laser 0.25 m ahead and yawed 0.1 rad, its
    mount in /tf_static, maps as well as the laser at the robot's origin does, and the best
    paths agree; ignoring the mount (laser_pose 0) is several times worse."""
    sim = mounted_office[0]
    logs, maps = mounted_maps
    np.testing.assert_allclose(np.asarray(logs["mounted"].sensor.laser_pose), MOUNT, atol=1e-6)
    np.testing.assert_allclose(logs["mounted"].odometry, sim.odometry, atol=1e-9)
    (mounted, mounted_path), (plain, plain_path), (ignored, _) = maps["mounted"], maps["plain"], maps["ignored"]
    summary = {name: (round(float(err.mean()), 3), round(float(err.max()), 3)) for name, (err, _) in maps.items()}
    # Measured (mean, max) m: mounted (0.047, 0.077), plain (0.064, 0.125), ignored (0.728, 1.104);
    # the two paths 0.10 m apart on average; odometry alone drifts 0.8 m.
    assert mounted.mean() < 0.15 and mounted.max() < 0.3, summary
    assert plain.mean() < 0.15 and plain.max() < 0.3, summary
    assert np.hypot(*(mounted_path[:, :2] - plain_path[:, :2]).T).mean() < 0.2, summary
    assert ignored.mean() > 0.4 and ignored.mean() > 3 * max(mounted.mean(), plain.mean()), summary


def test_an_upside_down_mounted_laser_maps_the_same(tmp_path, mounted_office, mounted_maps):
    """The mounted laser rolled 180 degrees (its messages' beams run the other way): read with
    mirrored angles, it is the upright mounted laser's log, and maps as it does."""
    sim, mounted, _ = mounted_office
    logs, maps = mounted_maps
    upright = logs["mounted"]
    path = _office_bag(tmp_path / "upside_down.bag", sim, mounted, quaternion(roll=math.pi, yaw=MOUNT[2]),
                       (MOUNT[0], MOUNT[1], 0.3), upside_down=True)
    log = read_rosbag(path)
    np.testing.assert_array_equal(log.ranges, upright.ranges)
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles), np.asarray(upright.sensor.beam_angles), atol=1e-6)
    np.testing.assert_allclose(np.asarray(log.sensor.laser_pose), MOUNT, atol=1e-6)
    errors, trajectory = _map_errors(log, sim.ground_truth)
    assert errors.mean() < 0.15 and errors.max() < 0.3, (errors.mean(), errors.max())
    # Measured: (0.041, 0.076) m, 0.012 m from the upright laser's path (the angles differ in float32 rounding).
    assert np.hypot(*(trajectory[:, :2] - maps["mounted"][1][:, :2]).T).mean() < 0.1
    # Read upright (the mirror ignored: the mount read without its roll) it maps badly (1.8 m).
    flipped = read_rosbag(path, laser_pose=MOUNT)
    assert not np.array_equal(flipped.ranges, upright.ranges)
    errors_flipped, _ = _map_errors(flipped, sim.ground_truth)
    assert errors_flipped.mean() > 3 * errors.mean(), (errors_flipped.mean(), errors.mean())


# --------------------------------------------------------------------------- the command line


def _refused(argv, capsys, monkeypatch, *words):
    """``jaxslam map`` refuses on one line naming ``words``, exit code 2, before the filter runs."""
    import jaxslam.cli.map
    from jaxslam.cli import main

    def trap(*args, **kwargs):
        raise AssertionError("the filter ran")

    monkeypatch.setattr(jaxslam.pipeline, "run", trap)  # the filter jaxslam map calls (jaxslam.pipeline.map_log)
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2 and len(lines) == 1, captured.err
    assert lines[0].startswith("jaxslam map: error: ") and "Traceback" not in captured.err + captured.out
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


@pytest.mark.parametrize("value", ["0.25,0", "0.25,0,0.1,0", "a,b,c", "0.25,0,nan", "0.25;0;0.1", "", "1,,2"])
def test_malformed_laser_pose_is_refused_before_reading(tmp_path, capsys, monkeypatch, value):
    import jaxslam.cli.map

    def trap(*args, **kwargs):
        raise AssertionError("the log was read")

    monkeypatch.setattr(jaxslam.cli.map, "read_log", trap)  # the name jaxslam map calls
    path = _write(tmp_path, "ros1", standard_messages(_store("ros1")))
    out = tmp_path / "out"
    line = _refused(["map", str(path), "--no-progress", "--out", str(out), f"--laser-pose={value}"], capsys,
                    monkeypatch, "--laser-pose expects x,y,theta", repr(value))
    assert "e.g. 0.25,0,0.1" in line and not out.exists()


def test_missing_odometry_is_refused_naming_the_options(tmp_path, capsys, monkeypatch):
    ts = _store("ros1")
    path = _write(tmp_path, "ros1", [m for m in standard_messages(ts) if m[0] == "/scan"])
    _refused(["map", str(path), "--no-progress", "--out", str(tmp_path / "out")], capsys, monkeypatch,
             "no topic '/odom' in the bag", "odom -> base_link", "--odom-topic", "--odom-frame", "--base-frame")
    path = _write(tmp_path, "ros1", odometry_as_tf(ts, standard_messages(ts), "odom", "base_footprint"),
                  name="footprint")
    _refused(["map", str(path), "--no-progress", "--out", str(tmp_path / "out"), "--odom-frame", "/odom"], capsys,
             monkeypatch, "/tf holds no odom -> base_link transform", "odom -> base_footprint", "--base-frame")
    assert not (tmp_path / "out").exists()


def test_frame_options_on_a_carmen_log_are_refused(tmp_path, capsys, monkeypatch, mounted_office):
    from logs import write_flaser_log

    write_flaser_log(tmp_path / "office.clf", mounted_office[0], stop=12)
    _refused(["map", str(tmp_path / "office.clf"), "--no-progress", "--out", str(tmp_path / "out"),
              "--base-frame", "base_footprint"], capsys, monkeypatch, "--base-frame does not apply to a CARMEN log")


def test_the_new_options_reach_the_readers(tmp_path, monkeypatch, mounted_office):
    """--odom-frame, --base-frame and --laser-pose reach read_rosbag; --laser-pose also
    overrides a CARMEN log's mounting."""
    import jaxslam.io
    from jaxslam.cli import main
    from jaxslam.io import read_carmen
    from logs import write_flaser_log

    write_flaser_log(tmp_path / "office.clf", mounted_office[0], stop=12)
    log = read_log(tmp_path / "office.clf", laser_pose=(0.1, -0.2, 0.3))
    np.testing.assert_allclose(np.asarray(log.sensor.laser_pose), [0.1, -0.2, 0.3], atol=1e-7)
    np.testing.assert_array_equal(np.asarray(read_carmen(tmp_path / "office.clf").sensor.laser_pose), 0.0)

    seen = {}

    def spy(path, **kwargs):
        seen.update(kwargs)
        raise LogError("stop here")

    monkeypatch.setattr(jaxslam.io, "read_rosbag", spy)
    path = _write(tmp_path, "ros1", standard_messages(_store("ros1")))
    assert main(["map", str(path), "--no-progress", "--out", str(tmp_path / "out"), "--odom-frame", "odom_combined",
                 "--base-frame", "base_footprint", "--laser-pose=-0.25,0,3.1416", "--odom-topic", "/tf"]) == 2
    assert seen == {"odom_frame": "odom_combined", "base_frame": "base_footprint", "laser_pose": (-0.25, 0.0, 3.1416),
                    "odom_topic": "/tf"}


# --------------------------------------------------------------------------- real data


def test_intel_bag(shared_data):
    start = time.perf_counter()
    with pytest.warns(UserWarning, match=r"dropped 1 of 13631 scans .*0 before the first and 1 after the last"):
        log = read_rosbag(shared_data / "intel.sort.bag")
    elapsed = time.perf_counter() - start
    # 13,631 scans in the bag; the last one is 8.8 ms after the last odometry message.
    assert log.num_scans == 13630 and log.num_beams == 180
    assert elapsed < 30.0
    assert float(log.sensor.range_max) == 80.0
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles)[[0, -1]], [-math.pi / 2, math.pi / 2], atol=1e-6)
    assert np.all(np.diff(log.timestamps) > 0)
    assert log.duration == pytest.approx(2691, abs=1.0)
    assert log.ranges.max() == np.float32(80.0)


def test_aces_bag(shared_data):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every ACES scan lies within the odometry
        log = read_log(shared_data / "aces.sort.bag")
    assert log.num_scans == 7374 and log.num_beams == 180
    assert float(log.sensor.range_max) == 50.0
    assert log.timestamps[0] == pytest.approx(70.2899, abs=1e-6)
    assert log.duration == pytest.approx(1366, abs=1.0)


def test_fr_clinic_bag(shared_data):
    """FR-clinic's scans: 181 beams from -90 degrees and 180 from -89.75, -89.5 or -89.25
    degrees, 1 degree apart (a SICK LMS's interlaced 0.25-degree mode)."""
    log, warned = _read_counting_warnings(shared_data / "fr-clinic.bag")
    assert len(warned) == 1
    assert log.num_scans == 6917 and log.num_beams == 721
    assert "1748 scans of 181 beams from -90.000 deg" in str(warned[0].message)
    assert float(log.sensor.range_min) == pytest.approx(0.1)
    padded = np.sum(log.ranges == 0.0, axis=1)
    assert np.sum(padded == 540) == 1748 and np.sum(padded == 541) == 5169
    np.testing.assert_allclose(np.degrees(np.sort(np.asarray(log.sensor.beam_angles)))[[0, -1]], [-90.0, 90.0],
                               atol=0.01)


def test_intel_max_scans(shared_data):
    log = read_rosbag(shared_data / "intel.sort.bag", max_scans=50)
    assert log.num_scans == 50
