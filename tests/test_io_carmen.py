"""CARMEN log reader: round trips through small logs written here, every malformed line,
format detection by read_log, and the real MIT CSAIL log when ../shared/data is present."""

from __future__ import annotations

import math
import re
import time

import numpy as np
import pytest

from jaxslam.geometry import compose
from jaxslam.io import read_carmen, read_log
from jaxslam.laserlog import LogError

HEADER = (
    "# CARMEN Logfile\n"
    "# message formats defined: PARAM SYNC ODOM FLASER ROBOTLASER1\n"
    "PARAM robot_front_laser_max 81.9 nohost 0.0\n"
    "SYNC 123.0 nohost 0.0\n"
)


def flaser_line(ranges, odom=(1.0, 2.0, 0.5), pose=(9.0, 9.0, 0.0), stamp=100.0, host="host"):
    values = " ".join(f"{r:.2f}" if isinstance(r, float) else str(r) for r in ranges)
    x, y, th = pose
    ox, oy, oth = odom
    return f"FLASER {len(ranges)} {values} {x} {y} {th} {ox} {oy} {oth} {stamp:.6f} {host} {stamp + 0.01:.6f}"


def robotlaser_line(ranges, robot=(1.0, 2.0, 0.5), offset=(0.1, 0.0, 0.0), stamp=100.0, remissions=(),
                    start=-1.5, res=0.01, max_range=30.0):
    values = " ".join(str(r) for r in ranges)
    laser = np.asarray(compose(np.asarray(robot), np.asarray(offset)), dtype=np.float64)
    rems = " ".join(str(r) for r in remissions)
    return (
        f"ROBOTLASER1 0 {start} {res * (len(ranges) - 1)} {res} {max_range} 0.01 0 {len(ranges)} {values} "
        f"{len(remissions)} {rems} {laser[0]:.9f} {laser[1]:.9f} {laser[2]:.9f} {robot[0]} {robot[1]} {robot[2]} "
        f"0.0 0.0 0.5 0.2 0.0 {stamp:.6f} host {stamp + 0.01:.6f}"
    ).replace("  ", " ")


def odom_line(x, y, theta, stamp):
    return f"ODOM {x} {y} {theta} 0.1 0.0 0.0 {stamp:.6f} host {stamp + 0.01:.6f}"


def write_log(tmp_path, lines, name="test.clf"):
    path = tmp_path / name
    path.write_text(HEADER + "\n".join(lines) + "\n")
    return path


def line_of(path, k):
    """The file line number of the k-th (0-based) body line: after the 4 header lines."""
    return k + 5


def where(path, line_no):
    return re.escape(f"{path}:{line_no}") + ":"


# --------------------------------------------------------------------------- round trips


def test_flaser_round_trip(tmp_path):
    ranges0 = [1.0, 2.5, 81.91, 3.25, 0.0]
    ranges1 = [1.5, 90.0, 2.0, 3.0, 4.0]
    path = write_log(tmp_path, [
        flaser_line(ranges0, odom=(1.0, 2.0, 0.5), stamp=1134864629.895182),
        "TRUEPOS 1 2 3 1 2 3 1134864630.0 host 1.0",  # one TRUEPOS does not cover the scans
        flaser_line(ranges1, odom=(1.5, 2.0, -3.0), stamp=1134864630.105179),
    ])
    with pytest.warns(UserWarning, match="TRUEPOS lines do not cover every laser timestamp"):
        log = read_carmen(path)
    assert log.num_scans == 2 and log.num_beams == 5
    np.testing.assert_array_equal(log.timestamps, [1134864629.895182, 1134864630.105179])
    np.testing.assert_allclose(log.odometry, [[1.0, 2.0, 0.5], [1.5, 2.0, -3.0]])
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles), np.linspace(-math.pi / 2, math.pi / 2, 5), atol=1e-6)
    assert float(log.sensor.range_max) == pytest.approx(81.91)
    expected = np.array([ranges0, ranges1], dtype=np.float32)
    expected[1, 1] = np.float32(81.91)  # beyond the no-return value: no return
    np.testing.assert_array_equal(log.ranges, expected)
    assert log.ground_truth is None


def test_flaser_range_max_argument(tmp_path):
    path = write_log(tmp_path, [flaser_line([1.0, 6.0, 81.91], stamp=1.0)])
    log = read_carmen(path, range_max=5.0)
    np.testing.assert_array_equal(log.ranges[0], [1.0, 5.0, 5.0])
    assert float(log.sensor.range_max) == 5.0


def test_robotlaser_round_trip(tmp_path):
    path = write_log(tmp_path, [
        robotlaser_line([1.0, 2.0, 31.0, 30.0], robot=(1.0, 2.0, 0.5), stamp=10.0, remissions=(0.5, 0.5, 0.1, 0.2)),
        "RAWLASER1 0 -1.5 3.14 0.01 30 0.01 0 2 1 1 0 10.05 host 1.0",
        robotlaser_line([1.5, 2.5, 3.5, 4.5], robot=(1.2, 2.0, 0.6), stamp=10.1),
    ])
    log = read_carmen(path)
    assert log.num_scans == 2 and log.num_beams == 4
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles), -1.5 + 0.01 * np.arange(4), atol=1e-6)
    assert float(log.sensor.range_max) == 30.0
    np.testing.assert_array_equal(log.ranges[0], [1.0, 2.0, 30.0, 30.0])
    np.testing.assert_allclose(log.odometry, [[1.0, 2.0, 0.5], [1.2, 2.0, 0.6]])
    np.testing.assert_allclose(np.asarray(log.sensor.laser_pose), [0.1, 0.0, 0.0], atol=1e-5)


def test_odometry_from_odom_lines(tmp_path):
    lines = [
        odom_line(0.0, 0.0, 0.0, 9.9),  # before every laser line
        flaser_line([1.0, 2.0], stamp=9.8),  # before the first ODOM: dropped
        odom_line(1.0, 0.0, 0.0, 10.0),
        flaser_line([1.0, 2.0], stamp=10.0),  # exactly at an ODOM line
        odom_line(2.0, 0.0, 0.0, 11.0),
        flaser_line([1.0, 2.0], stamp=10.25),  # a quarter of the way
        flaser_line([1.0, 2.0], stamp=11.5),  # after the last ODOM: dropped
    ]
    path = write_log(tmp_path, lines)
    with pytest.warns(UserWarning, match=r"dropped 2 of 4 laser lines .*1 before the first, 1 after the last"):
        log = read_carmen(path, odometry_source="odom")
    np.testing.assert_array_equal(log.timestamps, [10.0, 10.25])
    np.testing.assert_allclose(log.odometry, [[1.0, 0.0, 0.0], [1.25, 0.0, 0.0]], atol=1e-6)
    # The laser's own odometry is the default.
    np.testing.assert_allclose(read_carmen(path).odometry[:, :2], [[1.0, 2.0]] * 4)


def test_truepos_fills_ground_truth(tmp_path):
    lines = [
        "TRUEPOS 5.0 6.0 0.1 1 2 0.5 9.0 host 9.0",
        flaser_line([1.0, 2.0], stamp=10.0),
        "TRUEPOS 7.0 6.0 0.1 1 2 0.5 11.0 host 11.0",
    ]
    log = read_carmen(write_log(tmp_path, lines))
    np.testing.assert_allclose(log.ground_truth, [[6.0, 6.0, 0.1]], atol=1e-6)


def test_read_log_detects_carmen(tmp_path):
    path = write_log(tmp_path, [flaser_line([1.0, 2.0], stamp=1.0)], name="log.txt")
    assert read_log(path).num_scans == 1
    assert float(read_log(path, range_max=1.5).sensor.range_max) == 1.5
    odom_first = tmp_path / "odom_first.log"
    odom_first.write_text(odom_line(0, 0, 0, 0.5) + "\n" + flaser_line([1.0], stamp=1.0) + "\n")
    assert read_log(odom_first).num_scans == 1


def test_read_log_rejects_other_files(tmp_path):
    other = tmp_path / "notes.txt"
    other.write_text("# a comment\nhello world\nFLASER 1 1.0\n")
    with pytest.raises(LogError, match=re.escape(str(other)) + r": unrecognised log format; expected a ROS 1"):
        read_log(other)
    binary = tmp_path / "data.bin"
    binary.write_bytes(b"\x00\x01FLASER")
    with pytest.raises(LogError, match="unrecognised log format"):
        read_log(binary)
    only_params = tmp_path / "params.clf"
    only_params.write_text("PARAM a 1 host 0\n")
    with pytest.raises(LogError, match="unrecognised log format"):
        read_log(only_params)
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(LogError, match=re.escape(str(folder)) + r": a folder without metadata\.yaml"):
        read_log(folder)
    with pytest.raises(LogError, match=r"no such file or folder"):
        read_log(tmp_path / "missing.clf")


# --------------------------------------------------------------------------- errors


def _error(tmp_path, body_lines, bad_index, match, **kwargs):
    path = write_log(tmp_path, body_lines)
    with pytest.raises(LogError, match=where(path, line_of(path, bad_index)) + " " + match):
        read_carmen(path, **kwargs)


def test_truncated_flaser(tmp_path):
    good = flaser_line([1.0, 2.0, 3.0], stamp=1.0)
    truncated = " ".join(flaser_line([1.0, 2.0, 3.0], stamp=2.0).split()[:-4])
    _error(tmp_path, [good, truncated], 1, r"truncated FLASER \(n=3\) line: 10 fields, expected 14")


def test_flaser_with_too_many_fields(tmp_path):
    _error(tmp_path, [flaser_line([1.0, 2.0], stamp=1.0) + " 7"], 0, r"FLASER \(n=2\) line has 14 fields, expected 13")


def test_flaser_count_not_an_integer(tmp_path):
    _error(tmp_path, ["FLASER two 1.0 2.0"], 0, r"field 2 \(number of readings\) is not a non-negative integer")
    _error(tmp_path, ["FLASER"], 0, r"truncated line")


def test_non_numeric_range(tmp_path):
    line = flaser_line([1.0, 2.0, 3.0], stamp=1.0).split()
    line[3] = "2.x"
    _error(tmp_path, [" ".join(line)], 0, r"field 4 \(range\) is not a number: '2\.x'")


def test_non_numeric_pose_and_timestamp(tmp_path):
    line = flaser_line([1.0, 2.0], stamp=1.0).split()
    bad_odom = list(line)
    bad_odom[7] = "y"
    _error(tmp_path, [" ".join(bad_odom)], 0, r"field 8 \(pose or ipc_timestamp\) is not a number")
    bad_stamp = list(line)
    bad_stamp[10] = "noon"
    _error(tmp_path, [" ".join(bad_stamp)], 0, r"field 11 \(pose or ipc_timestamp\) is not a number")
    bad_logger = list(line)
    bad_logger[12] = "later"
    _error(tmp_path, [" ".join(bad_logger)], 0, r"field 13 \(logger_timestamp\) is not a number")


@pytest.mark.parametrize("bad", ["nan", "-1.0", "-inf"])
def test_nan_or_negative_range(tmp_path, bad):
    line = flaser_line([1.0, 2.0, 3.0], stamp=1.0).split()
    line[4] = bad
    _error(tmp_path, [flaser_line([1.0, 2.0, 3.0], stamp=0.5), " ".join(line)], 1,
           r"beam 2 has range .* \(NaN or negative\)")


def test_non_finite_odometry(tmp_path):
    _error(tmp_path, [flaser_line([1.0, 2.0], odom=(1.0, "nan", 0.0), stamp=1.0)], 0, r"non-finite odometry pose")


def test_flaser_180_and_181_readings_are_an_error(tmp_path):
    # FLASER lines of n readings span -90..+90 degrees: 180 and 181 readings lie on different grids.
    _error(tmp_path, [flaser_line([1.0] * 181, stamp=1.0), flaser_line([1.0] * 180, stamp=2.0)], 1,
           r"the beam layout changes from 181 beams, angle_min -1\.570796\d rad, increment 0\.0174533 rad "
           r"\(-90\.000\.\.90\.000 deg\) \(the widest scan's, first at .*:5\) to 180 beams, "
           r".*increment 0\.0175508 rad.*: "
           r"its beams are not on the widest scan's angular grid")


# --------------------------------------------------------------------------- changing beam layouts


def _read_counting_warnings(path, **kwargs):
    import warnings

    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        log = read_carmen(path, **kwargs)
    return log, [w for w in record if "beam layout changes" in str(w.message)]


def test_robotlaser_180_and_181_beams_are_padded(tmp_path):
    from jaxslam.laser import valid_returns

    start, res = -math.pi / 2, math.pi / 180
    counts = [181, 180, 180, 181]
    lines = [robotlaser_line(list(1.0 + k + np.arange(n) / 100), offset=(0.0, 0.0, 0.0), stamp=10.0 + k,
                             start=start, res=res) for k, n in enumerate(counts)]
    path = write_log(tmp_path, lines)
    log, warned = _read_counting_warnings(path)
    assert len(warned) == 1 and log.notes == (str(warned[0].message),)
    assert "2 of 4 scans were padded to the widest scan's 181 beam angles" in log.notes[0]
    assert "range_min raised from 0 m to 0.001 m" in log.notes[0]
    assert log.ranges.shape == (4, 181)
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles), start + res * np.arange(181), atol=1e-6)
    for k, n in enumerate(counts):
        np.testing.assert_allclose(log.ranges[k, :n], 1.0 + k + np.arange(n) / 100, rtol=1e-6)
    assert np.all(log.ranges[[1, 2], 180] == 0.0)
    # range_min 0 would make a 0 m reading a return: it is raised to 1 mm so that padding is invalid.
    assert float(log.sensor.range_min) == pytest.approx(1e-3)
    valid = np.asarray(valid_returns(log.ranges, log.sensor))
    assert not valid[[1, 2], 180].any() and valid[[0, 3]].all()


def test_flaser_lines_that_interleave_are_merged(tmp_path):
    # 181 readings (1 degree apart) lie on every other beam of 361 (0.5 degrees apart).
    path = write_log(tmp_path, [flaser_line([2.0] * 181, stamp=1.0), flaser_line([3.0] * 361, stamp=2.0)])
    log, warned = _read_counting_warnings(path)
    assert len(warned) == 1 and log.num_beams == 361
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles), np.linspace(-math.pi / 2, math.pi / 2, 361),
                               atol=1e-6)
    assert np.all(log.ranges[0, ::2] == 2.0) and np.all(log.ranges[0, 1::2] == 0.0)
    assert np.all(log.ranges[1] == 3.0)
    # 3 readings (-90, 0, 90 degrees) and 2 (-90, 90): the 2 are the 3's first and last.
    path = write_log(tmp_path, [flaser_line([1.0, 2.0, 3.0], stamp=1.0), flaser_line([4.0, 5.0], stamp=2.0)],
                     name="small.clf")
    log, warned = _read_counting_warnings(path)
    assert len(warned) == 1
    np.testing.assert_array_equal(log.ranges, [[1.0, 2.0, 3.0], [4.0, 0.0, 5.0]])


def test_robotlaser_lines_changing_their_angular_range_are_an_error(tmp_path):
    start, res = -math.pi / 2, math.pi / 180
    lines = [robotlaser_line([1.0] * 181, stamp=1.0, start=start, res=res),
             robotlaser_line([1.0] * 180, stamp=2.0, start=start, res=res),
             robotlaser_line([1.0] * 180, stamp=3.0, start=start + 5 * res, res=res)]
    _error(tmp_path, lines, 2, r"the beam layout changes from 181 beams, angle_min -1\.570796\d rad, .* to "
           r"180 beams, angle_min -1\.48352\d+ rad, .*: the angular range changes")
    lines[2] = robotlaser_line([1.0] * 180, stamp=3.0, start=start + 0.37 * res, res=res)
    _error(tmp_path, lines, 2, r"the beam layout changes .*: its beams are not on the widest scan's angular grid")


def test_a_log_of_180_and_181_beam_lines_maps(tmp_path):
    """The office simulation as ROBOTLASER1 lines, every other one without its last beam:
    it reads, maps, and summary.json records the padding."""
    import json

    import jax

    from jaxslam.cli import main
    from jaxslam.sim import office_scenario

    sim = office_scenario(jax.random.key(0), num_scans=150, num_beams=181).log.subset(np.arange(40))
    lines = []
    for k in range(sim.num_scans):
        ranges = sim.ranges[k] if k % 2 == 0 else sim.ranges[k, :180]
        lines.append(robotlaser_line([float(f"{r:.3f}") for r in ranges], robot=tuple(map(float, sim.odometry[k])),
                                     offset=(0.0, 0.0, 0.0), stamp=1000.0 + float(sim.timestamps[k]),
                                     start=-math.pi / 2, res=math.pi / 180, max_range=float(sim.sensor.range_max)))
    path = write_log(tmp_path, lines)
    log, warned = _read_counting_warnings(path)
    assert len(warned) == 1 and log.num_beams == 181 and np.all(log.ranges[1::2, 180] == 0.0)
    out = tmp_path / "out"
    assert main(["map", str(path), "--particles", "2", "--proposal", "smp", "--no-progress", "--set",
                 "linear_update=0.3", "--set", "max_insert_range=8", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["log_notes"]) == 1 and "20 of 40 scans were padded" in summary["log_notes"][0]
    traj = np.loadtxt(out / "trajectory.txt")
    err = np.hypot(*(traj[:, 1:3] - sim.ground_truth[:, :2]).T)
    assert traj.shape == (40, 4) and err.max() < 0.3, err.max()


def test_timestamps_going_backwards(tmp_path):
    _error(tmp_path, [flaser_line([1.0], stamp=2.0), flaser_line([1.0], stamp=3.0), flaser_line([1.0], stamp=2.5)], 2,
           r"timestamp goes backwards \(3\.000000 -> 2\.500000\)")


def test_odom_timestamps_going_backwards(tmp_path):
    _error(tmp_path, [odom_line(0, 0, 0, 2.0), odom_line(0, 0, 0, 1.0)], 1, r"ODOM timestamp goes backwards")


def test_truncated_odom(tmp_path):
    _error(tmp_path, ["ODOM 1 2 3 0 0 0 5.0 host"], 0, r"truncated ODOM line: 9 fields, expected 10")


def test_mixed_laser_messages(tmp_path):
    _error(tmp_path, [flaser_line([1.0, 2.0], stamp=1.0), robotlaser_line([1.0, 2.0], stamp=2.0)], 1,
           r"ROBOTLASER1 line in a log of FLASER lines \(first at .*:5\)")


def test_robotlaser_errors(tmp_path):
    line = robotlaser_line([1.0, 2.0, 3.0], stamp=1.0, remissions=(0.1, 0.2, 0.3)).split()
    _error(tmp_path, [" ".join(line[:-5])], 0, r"truncated ROBOTLASER1 \(n=3, n_remissions=3\) line")
    _error(tmp_path, [" ".join(line[:11])], 0, r"truncated line: 11 fields, no field 13 \(number of remissions\)")
    geometry_change = robotlaser_line([1.0, 2.0, 3.0], stamp=2.0, start=-1.0)
    _error(tmp_path, [" ".join(line), geometry_change], 1,
           r"the beam layout changes from 3 beams, angle_min -1\.5000000 rad, .* to 3 beams, angle_min -1\.0000000 "
           r"rad, .*: the angular range changes")
    range_change = robotlaser_line([1.0, 2.0, 3.0], stamp=2.0, max_range=50.0)
    _error(tmp_path, [" ".join(line), range_change], 1, r"max_range changes from 30\.0 to 50\.0")


def test_no_laser_lines(tmp_path):
    path = write_log(tmp_path, [odom_line(0, 0, 0, 1.0)])
    with pytest.raises(LogError, match=re.escape(str(path)) + r": no laser lines \(expected FLASER or ROBOTLASER1\)"):
        read_carmen(path)
    empty = tmp_path / "empty.clf"
    empty.write_text("")
    with pytest.raises(LogError, match=r"empty\.clf: is empty"):
        read_carmen(empty)


def test_odometry_source_odom_without_odom_lines(tmp_path):
    path = write_log(tmp_path, [flaser_line([1.0], stamp=1.0)])
    with pytest.raises(LogError, match=r"odometry_source='odom' but the log has no ODOM lines"):
        read_carmen(path, odometry_source="odom")
    with pytest.raises(ValueError, match="odometry_source"):
        read_carmen(path, odometry_source="wheels")


def test_missing_or_binary_file(tmp_path):
    with pytest.raises(LogError, match=r"no such CARMEN log"):
        read_carmen(tmp_path / "missing.clf")
    binary = tmp_path / "binary.clf"
    binary.write_bytes(b"\x80\x81\x00FLASER")
    with pytest.raises(LogError, match=r"binary\.clf: not a text file"):
        read_carmen(binary)
    binary.write_bytes(b"\xff\xfe\x00FLASER")  # a UTF-16 byte-order mark
    with pytest.raises(LogError, match=r"binary\.clf: looks like UTF-16 text; save it as UTF-8"):
        read_carmen(binary)


# --------------------------------------------------------------------------- real data


def test_mit_csail_log(shared_data):
    start = time.perf_counter()
    log = read_log(shared_data / "mit-csail.clf")
    elapsed = time.perf_counter() - start
    assert log.num_scans == 1988 and log.num_beams == 361
    assert elapsed < 10.0
    assert float(log.sensor.range_max) == pytest.approx(81.91)
    assert log.ranges.max() == np.float32(81.91)
    np.testing.assert_allclose(np.asarray(log.sensor.beam_angles)[[0, 180, 360]], [-math.pi / 2, 0.0, math.pi / 2],
                               atol=1e-6)
    # The first FLASER line: odom (576.536523, 0.106594, -2.255213) at ipc_timestamp 1134864629.895182.
    np.testing.assert_allclose(log.odometry[0], [576.536523, 0.106594, -2.255213])
    assert log.timestamps[0] == 1134864629.895182
    assert np.all(np.diff(log.timestamps) >= 0)
