"""ROS bag reader: round trips through small ROS 1 and ROS 2 bags written here, every
malformed-input error, and the real Intel / ACES bags when ../shared/data is present."""

from __future__ import annotations

import math
import re
import time
import warnings

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

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
    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
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
    return get_typestore(Stores.ROS2_HUMBLE if kind == "ros2" else Stores.ROS1_NOETIC)


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
    from jaxslam.io.rosbag import BeamLayout, pad_beam_layouts
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
