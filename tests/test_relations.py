"""Relations files (Kümmerle et al. 2009) and the relation error metric."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import warnings

import numpy as np
import pytest

from jaxslam.geometry import between_np, compose, compose_np
from jaxslam.io import read_log, read_relations
from jaxslam.io.relations import Relations, sideways_relations
from jaxslam.laserlog import LogError
from jaxslam.metrics import lookup_poses, relation_error

# --------------------------------------------------------------------------- relations files


def test_read_relations(tmp_path):
    path = tmp_path / "r.relations"
    path.write_text(
        "# t1 t2 x y z roll pitch yaw\n"
        "976052905.167303 976052911.885496 -0.056990 -0.128430 0.000000 0.000000 0.000000 -1.682210\n"
        "\n"
        "1134864648.67354 1134864648.46323 0.31166 0.01278 0.00000  0.00000 0.00000 0.23840\n"
    )
    rel = read_relations(path)
    assert rel.count == 2
    np.testing.assert_array_equal(rel.t1, [976052905.167303, 1134864648.67354])
    np.testing.assert_array_equal(rel.t2, [976052911.885496, 1134864648.46323])
    np.testing.assert_array_equal(rel.motion, [[-0.056990, -0.128430, -1.682210], [0.31166, 0.01278, 0.23840]])
    assert rel.t1.dtype == np.float64 and rel.motion.shape == (2, 3)


@pytest.mark.parametrize(
    "line, match",
    [
        ("1 2 0 0 0 0 0", r"expected 8 fields 't1 t2 x y z roll pitch yaw', got 7"),
        ("1 2 0 0 0 0 0 0 0", r"expected 8 fields .*got 9"),
        ("1 2 0.1 abc 0 0 0 0.2", r"field 4 is not a number: 'abc'"),
        ("1 2 0.1 nan 0 0 0 0.2", r"non-finite value"),
        ("1 2 0.1 0.2 0.5 0 0 0.2", r"z, roll, pitch must be 0"),
        ("1 2 0.1 0.2 0 0 0.1 0.2", r"z, roll, pitch must be 0"),
    ],
)
def test_relations_errors_name_the_line(tmp_path, line, match):
    path = tmp_path / "bad.relations"
    path.write_text("1 2 0.1 0.2 0 0 0 0.3\n" + line + "\n")
    with pytest.raises(LogError, match=re.escape(f"{path}:2: ") + match):
        read_relations(path)


def test_relations_empty_or_missing(tmp_path):
    path = tmp_path / "empty.relations"
    path.write_text("# nothing\n\n")
    with pytest.raises(LogError, match=r"empty\.relations: the relations file holds no relations"):
        read_relations(path)
    with pytest.raises(LogError, match="no such relations file"):
        read_relations(tmp_path / "missing.relations")


# --------------------------------------------------------------------------- relation error


def _trajectory(num=40, seed=1):
    """A wiggly path with timestamps 10.0, 10.1, ... (s)."""
    rng = np.random.default_rng(seed)
    poses = np.zeros((num, 3))
    for i in range(1, num):
        step = np.array([rng.uniform(0.1, 0.4), rng.normal(0, 0.05), rng.normal(0, 0.3)])
        poses[i] = np.asarray(compose(poses[i - 1], step))
    return 10.0 + 0.1 * np.arange(num), poses


def _relations_from(timestamps, poses, pairs):
    i, j = np.asarray(pairs).T
    motion = between_np(poses[i], poses[j])  # float64, as the metric computes
    return Relations(timestamps[i], timestamps[j], motion)


def test_relation_error_of_the_same_trajectory_is_zero():
    ts, poses = _trajectory()
    pairs = [(0, 1), (5, 30), (30, 5), (12, 39), (7, 7)]  # including t1 > t2 and t1 == t2
    result = relation_error(ts, poses, _relations_from(ts, poses, pairs))
    assert result.count == 5
    np.testing.assert_allclose(result.trans, 0.0, atol=1e-12)
    np.testing.assert_allclose(result.rot, 0.0, atol=1e-12)
    assert result.trans_max < 1e-12 and result.rot_max < 1e-12


def test_relation_error_is_invariant_to_a_rigid_motion_of_the_trajectory():
    ts, poses = _trajectory()
    rel = _relations_from(ts, poses, [(0, 10), (10, 0), (3, 25), (20, 39)])
    moved = np.asarray(compose(np.array([5.0, -3.0, 2.0]), poses), dtype=np.float64)
    result = relation_error(ts, moved, rel)
    assert result.trans_max < 1e-4 and result.rot_max < 1e-5


def test_relation_error_of_a_perturbed_trajectory():
    # A straight path along x with heading 0: between() frames equal world axes.
    ts = 10.0 + 0.1 * np.arange(6)
    poses = np.column_stack([0.5 * np.arange(6), np.zeros(6), np.zeros(6)])
    rel = _relations_from(ts, poses, [(0, 1), (1, 2), (2, 3), (3, 2), (4, 5)])
    perturbed = poses.copy()
    perturbed[2] += [0.0, 0.1, 0.05]  # 10 cm sideways and 0.05 rad at scan 2
    result = relation_error(ts, perturbed, rel)
    # (0, 1), (4, 5): untouched. (1, 2): the motion's end moves 0.1 sideways and turns 0.05.
    # (2, 3) from the turned, shifted frame: d = (0.5, -0.1) rotated by -0.05, against (0.5, 0).
    d = np.array([0.5, -0.1])
    c, s = math.cos(0.05), math.sin(0.05)
    rotated = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    e23 = float(np.hypot(*(rotated - [0.5, 0.0])))
    # (3, 2): the shifted pose seen from scan 3: (-0.5, 0.1) against (-0.5, 0).
    expected_trans = np.array([0.0, 0.1, e23, 0.1, 0.0])
    expected_rot = np.array([0.0, 0.05, 0.05, 0.05, 0.0])
    np.testing.assert_allclose(result.trans, expected_trans, atol=2e-6)
    np.testing.assert_allclose(result.rot, expected_rot, atol=2e-6)
    assert result.trans_mean == pytest.approx(expected_trans.mean(), abs=2e-6)
    assert result.trans_std == pytest.approx(expected_trans.std(), abs=2e-6)
    assert result.trans_max == pytest.approx(e23, abs=2e-6)
    assert result.rot_mean == pytest.approx(0.03, abs=2e-6)
    assert result.trans2_mean == pytest.approx(np.mean(expected_trans**2), abs=1e-6)
    assert result.trans2_std == pytest.approx(np.std(expected_trans**2), abs=1e-6)
    assert result.rot2_mean == pytest.approx(np.mean(expected_rot**2), abs=1e-7)
    assert result.rot2_std == pytest.approx(np.std(expected_rot**2), abs=1e-7)
    summary = result.to_dict()
    assert summary["count"] == 5
    assert summary["rot_mean_deg"] == pytest.approx(math.degrees(0.03), abs=1e-4)
    assert summary["rot_max_deg"] == pytest.approx(math.degrees(0.05), abs=1e-4)
    assert summary["rot2_mean_deg2"] == pytest.approx(np.mean(expected_rot**2) * (180 / math.pi) ** 2, rel=1e-4)
    assert all(isinstance(v, (int, float)) for v in summary.values())


def test_rotational_error_wraps_around_pi():
    ts = np.array([1.0, 2.0])
    poses = np.array([[0.0, 0.0, 3.1], [0.0, 0.0, -3.1]])  # turned by 2 pi - 6.2 = 0.0832 rad
    rel = Relations(np.array([1.0]), np.array([2.0]), np.array([[0.0, 0.0, 0.0]]))
    assert relation_error(ts, poses, rel).rot[0] == pytest.approx(2 * math.pi - 6.2, abs=1e-6)


def test_missing_timestamp_is_an_error():
    ts, poses = _trajectory()
    rel = Relations(np.array([10.0, 10.35]), np.array([10.1, 10.5]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"timestamp 10\.350000 \(query 1\) is not in the trajectory"):
        relation_error(ts, poses, rel)
    # Within the tolerance it matches; a looser tolerance is the caller's choice.
    near = Relations(np.array([10.00005]), np.array([10.1]), np.zeros((1, 3)))
    assert relation_error(ts, poses, near).count == 1
    with pytest.raises(ValueError, match=r"timestamp 10\.000050"):
        relation_error(ts, poses, near, time_tolerance=1e-6)


def test_lookup_poses_in_an_unsorted_trajectory():
    ts = np.array([3.0, 1.0, 2.0])
    poses = np.array([[3.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    np.testing.assert_array_equal(lookup_poses(ts, poses, [2.0, 1.0, 3.0])[:, 0], [2.0, 1.0, 3.0])


# --------------------------------------------------------------------------- sideways relations


def _drive(rng, steps: int, slip: float = 0.0) -> np.ndarray:
    """(steps + 1, 3) poses of a differential-drive robot: 0.1 m steps forward or back along arcs
    of a curvature drawn per drive (up to 0.3 rad/m) that wavers step to step, plus ``slip`` m
    sideways per step."""
    poses = [np.zeros(3)]
    direction, curve = rng.choice([-1.0, 1.0]), rng.uniform(-0.03, 0.03)
    for _ in range(steps):
        turn = curve + rng.uniform(-0.005, 0.005)
        step = np.array([direction * 0.1 * math.cos(turn / 2), direction * 0.1 * math.sin(turn / 2) + slip, turn])
        poses.append(compose_np(poses[-1], step))
    return np.asarray(poses)


def test_sideways_relations_pass_every_drive_and_catch_a_slide():
    rng = np.random.default_rng(0)
    rows = []
    for slip in (0.0, 0.0, 0.0, 0.03):  # 0.03 m sideways per 0.1 m: 17 degrees off the arc
        for _ in range(50):
            poses = _drive(rng, int(rng.integers(6, 40)), slip)  # 0.6-4 m within 12 s, up to 1.2 rad of turn
            rows.append(between_np(poses[0], poses[-1]))
    motion = np.asarray(rows)
    relations = Relations(np.zeros(len(rows)), np.full(len(rows), 10.0), motion)
    flagged = sideways_relations(relations, max_turn=1.2)
    assert not flagged[:150].any()  # a drive along arcs of any curvature, forward or back, passes
    assert flagged[150:].all()
    # The same slides checked over a longer time, a shorter chord or a sharper turn than allowed are not judged.
    assert not sideways_relations(relations._replace(t2=np.full(len(rows), 20.0)), max_turn=1.2).any()
    assert not sideways_relations(relations, min_length=5.0, max_turn=1.2).any()
    sharper = np.abs(motion[:, 2]) > 0.3
    assert sharper[150:].sum() > 10 and not sideways_relations(relations, max_turn=0.3)[sharper].any()
    # A chord 7 degrees off is kept and 9 degrees off flagged, at the default 8.
    for degrees, expected in ((7.0, False), (9.0, True), (-9.0, True), (180.0 + 9.0, True)):
        angle = math.radians(degrees)
        one = Relations(np.zeros(1), np.ones(1), np.array([[math.cos(angle), math.sin(angle), 0.0]]))
        assert bool(sideways_relations(one)[0]) is expected, degrees


@pytest.mark.parametrize("name, value", [("max_seconds", 0.0), ("min_length", -1.0), ("max_turn", float("nan")),
                                         ("max_sideways", float("inf"))])
def test_sideways_relations_refuse_bad_settings(name, value):
    relations = Relations(np.zeros(1), np.ones(1), np.array([[1.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match=name):
        sideways_relations(relations, **{name: value})


@pytest.mark.parametrize("name, count", [("intel", 0), ("aces", 1), ("mit-csail", 0), ("fr-clinic", 40),
                                         ("mit-killian", 3)])
def test_sideways_relations_of_the_real_logs(shared_data, name, count):
    assert int(sideways_relations(read_relations(shared_data / f"{name}.relations")).sum()) == count


def _corridor_log():
    """A simulated log along an L of corridors (noise-free scans), its truth, and relations between
    scans three apart taken from the truth."""
    import jax

    from jaxslam.laser import make_sensor, uniform_beams
    from jaxslam.motion import motion_params
    from jaxslam.sim import make_world, polyline_segments, simulate_log, waypoint_path

    walls = np.concatenate([polyline_segments([[-1, -1], [12, -1], [12, 10]]),
                            polyline_segments([[-1, 1], [10, 1], [10, 10]]),
                            polyline_segments([[3, -1], [3, -0.2]]), polyline_segments([[6, 1], [6, 0.4]])])
    truth = waypoint_path([[0, 0], [11, 0], [11, 9]], 0.2, 0.2)
    sensor = make_sensor(uniform_beams(181), range_max=15.0)
    log = simulate_log(jax.random.key(0), make_world(walls), truth, sensor, motion_params(0, 0, 0, 0, 0, 0), 0.0)
    first = np.arange(0, truth.shape[0] - 3, 3)
    motion = between_np(truth[first], truth[first + 3])
    return log, truth, Relations(log.timestamps[first], log.timestamps[first + 3], motion)


def test_scan_support_tells_a_wrong_relation_from_a_wrong_trajectory():
    from jaxslam.metrics import scan_support

    log, truth, relations = _corridor_log()
    # One relation slid 0.4 m sideways; and, apart, a trajectory with one pose 0.4 m off.
    wrong_relation = relations.motion.copy()
    wrong_relation[10, 1] += 0.4
    bad_relations = relations._replace(motion=wrong_relation)
    err = relation_error(log.timestamps, truth, bad_relations)
    support = scan_support(bad_relations, log.timestamps, truth, err.trans, log.timestamps, log.ranges, log.sensor)
    assert np.flatnonzero(support.checked).tolist() == [10]
    assert support.trajectory_inliers[10] > 0.9 and support.relation_inliers[10] < support.trajectory_inliers[10] - 0.3
    summary = support.summary(err.trans)
    assert (summary["favour_trajectory"], summary["favour_relation"]) == (1, 0)
    assert summary["favour_trajectory_error_share"] == pytest.approx(1.0)

    moved = truth.copy()
    moved[31:, 1] += 0.4  # every pose from the 31st on: one relation (scans 30 and 33) spans the step
    err = relation_error(log.timestamps, moved, relations)
    support = scan_support(relations, log.timestamps, moved, err.trans, log.timestamps, log.ranges, log.sensor)
    assert np.flatnonzero(support.checked).tolist() == [10]
    summary = support.summary(err.trans)
    assert (summary["favour_trajectory"], summary["favour_relation"]) == (0, 1)
    # Relations further apart in time than max_seconds are not judged.
    assert not scan_support(relations, log.timestamps, moved, err.trans, log.timestamps, log.ranges, log.sensor,
                            max_seconds=0.1).checked.any()
    with pytest.raises(ValueError, match="one error per relation"):
        scan_support(relations, log.timestamps, moved, err.trans[:-1], log.timestamps, log.ranges, log.sensor)
    with pytest.raises(ValueError, match="not"):
        scan_support(relations, log.timestamps, moved, err.trans, log.timestamps + 100.0, log.ranges, log.sensor)


def test_eval_scans_names_whose_error_it_is(tmp_path, capsys):
    from jaxslam.cli import main
    from jaxslam.io import write_carmen, write_trajectory

    log, truth, relations = _corridor_log()
    write_carmen(tmp_path / "corridor.clf", log)
    write_trajectory(tmp_path / "truth.txt", log.timestamps, truth)
    wrong = relations.motion.copy()
    wrong[10, 1] += 0.4
    (tmp_path / "rel.txt").write_text("".join(f"{a:.17g} {b:.17g} {m[0]:.17g} {m[1]:.17g} 0 0 0 {m[2]:.17g}\n"
                                              for a, b, m in zip(relations.t1, relations.t2, wrong)))
    out = tmp_path / "errors.json"
    args = ["eval", str(tmp_path / "truth.txt"), str(tmp_path / "rel.txt"), "--scans", str(tmp_path / "corridor.clf")]
    assert main(args + ["--out", str(out)]) == 0
    support = json.loads(out.read_text())["scan_support"]
    assert (support["checked"], support["favour_trajectory"], support["favour_relation"]) == (1, 1, 0)
    assert "the two scans favour the trajectory's motion in 1" in capsys.readouterr().out
    # A log that does not hold the relations' scans is named, and nothing is written.
    other = dataclasses.replace(log, timestamps=log.timestamps + 100.0)
    write_carmen(tmp_path / "other.clf", other)
    out.unlink()
    assert main(args[:-1] + [str(tmp_path / "other.clf"), "--out", str(out)]) == 2
    assert "--scans" in capsys.readouterr().err and not out.exists()


# --------------------------------------------------------------------------- real data


@pytest.mark.parametrize("name, count, backwards", [("intel", 2984, 6), ("aces", 1279, 0), ("mit-csail", 1172, 0)])
def test_real_relations_files(shared_data, name, count, backwards):
    rel = read_relations(shared_data / f"{name}.relations")
    assert rel.count == count
    assert int(np.sum(rel.t1 > rel.t2)) == backwards


def test_mit_csail_relations_match_the_log(shared_data):
    log = read_log(shared_data / "mit-csail.clf")
    rel = read_relations(shared_data / "mit-csail.relations")
    # Every relation timestamp is a FLASER ipc_timestamp (the relations carry 5 decimals).
    result = relation_error(log.timestamps, log.odometry, rel)
    assert result.count == 1172 and np.all(np.isfinite(result.trans))
    # Raw odometry drifts: far worse than the published SLAM results (0.05 m), but finite.
    assert 0.1 < result.trans_mean < 10.0


def test_aces_relations_match_the_log(shared_data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        log = read_log(shared_data / "aces.sort.bag")
    rel = read_relations(shared_data / "aces.relations")
    result = relation_error(log.timestamps, log.odometry, rel)
    assert result.count == 1279


def test_intel_relations_match_the_log(shared_data):
    with pytest.warns(UserWarning, match="dropped 1"):
        log = read_log(shared_data / "intel.sort.bag")
    rel = read_relations(shared_data / "intel.relations")
    result = relation_error(log.timestamps, log.odometry, rel)
    assert result.count == 2984


def test_absolute_trajectory_error_is_invariant_to_a_rigid_motion():
    from jaxslam.geometry import compose
    from jaxslam.metrics import absolute_trajectory_error

    rng = np.random.default_rng(0)
    truth = np.cumsum(rng.normal(0, 0.3, (50, 3)), axis=0)
    moved = np.asarray(compose(np.array([2.0, -1.0, 0.7]), truth), np.float64)
    aligned = absolute_trajectory_error(moved, truth)
    assert aligned["rmse"] < 1e-4 and aligned["rot_mean"] < 1e-5
    assert absolute_trajectory_error(moved, truth, align=False)["rmse"] > 1.0
    noisy = truth + np.column_stack([rng.normal(0, 0.1, (50, 2)), np.zeros(50)])
    # Alignment can only lower the RMSE, and here it should be close to the noise level (0.1 * sqrt 2).
    assert absolute_trajectory_error(noisy, truth)["rmse"] <= absolute_trajectory_error(noisy, truth, align=False)["rmse"] + 1e-12
    assert 0.08 < absolute_trajectory_error(noisy, truth)["rmse"] < 0.2


def test_motion_error_components_are_signed_in_the_first_poses_frame_and_wrapped():
    """A pose 0.1 m ahead and 0.05 m to the left of where the true motion ends, seen from a start
    facing +y, turned 6.2 rad where the truth turned 3.1: the heading error is 3.1 rad, not the
    unwrapped -3.18 (6.2 - 2 pi - 3.1); the norms are ``motion_errors``'."""
    from jaxslam.metrics import motion_error_components, motion_errors

    first = np.array([1.0, 2.0, math.pi / 2])
    motion = np.array([1.0, 0.0, 3.1])
    second = compose_np(first, np.array([1.1, 0.05, 6.2]))
    error = motion_error_components(first, second, motion)
    np.testing.assert_allclose(error, [0.1, 0.05, 3.1], atol=1e-12)
    trans, rot = motion_errors(first, second, motion)
    assert trans == pytest.approx(math.hypot(0.1, 0.05)) and rot == pytest.approx(3.1)
