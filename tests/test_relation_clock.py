"""Relations on another clock than the log's (jaxslam.io.relation_clock): a converted log whose
scan times were rewritten, as MIT Killian's bag."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.geometry import between_np, chain_np
from jaxslam.io import write_carmen, write_trajectory
from jaxslam.io.relation_clock import align_relations_clock
from jaxslam.io.relations import Relations
from jaxslam.laser import make_sensor, scan_inliers, scan_misfit
from jaxslam.laserlog import LaserLog, LogError
from jaxslam.metrics import relation_error
from jaxslam.sim import simulate_scans
from logs import cluttered_world


def _converted_log(seed: int = 0, num_scans: int = 500):
    """A robot path, its original scan times (a 0.44 s period with jitter, one burst where two
    scans took 2.2 s), relations between a subset of them, odometry with
    drift, and the converter's clock (0.1 s apart)."""
    rng = np.random.default_rng(seed)
    speed = 0.12 + 0.08 * np.sin(np.arange(num_scans) / 17.0) + 0.02 * rng.standard_normal(num_scans)
    speed[200:230] = 0.0  # the robot stands still: no scan there can be told from its neighbour
    turn = 0.15 * np.sin(np.arange(num_scans) / 11.0) * (rng.random(num_scans) < 0.7)
    steps = np.stack([speed, np.zeros(num_scans), turn], axis=1)
    truth = chain_np(np.zeros(3), steps[1:])
    interval = 0.44 + 0.004 * rng.standard_normal(num_scans - 1)
    interval[300:302] = 1.1  # two scans that took five periods
    original = 5000.0 + np.concatenate([[0.0], np.cumsum(interval)])
    chosen = np.sort(rng.choice(np.arange(8, num_scans - 5), size=num_scans // 4, replace=False))
    pairs = [(a, b) for a, b in zip(chosen[:-1], chosen[1:])]
    pairs += [(b, a) for a, b in pairs[::9]]  # some written from the later scan
    pairs += [(chosen[i], chosen[-1 - i]) for i in range(0, 40, 4)]  # loops
    first, second = np.array(pairs).T
    relations = Relations(original[first], original[second], between_np(truth[first], truth[second]))
    noisy = steps[1:] + rng.normal(0.0, [0.005, 0.002, 0.002], size=steps[1:].shape)
    odometry = chain_np(np.zeros(3), noisy)
    converted = 1e9 + 0.1 * np.arange(num_scans)
    return truth, original, odometry, converted, relations, chosen


def test_alignment_finds_every_moving_scan_and_zero_error_for_the_truth():
    truth, original, odometry, converted, relations, chosen = _converted_log()
    aligned = align_relations_clock(relations, converted, odometry)
    np.testing.assert_array_equal(aligned.times, original[chosen])
    standing = (chosen >= 200) & (chosen <= 230)
    np.testing.assert_array_equal(aligned.scan_index[~standing], chosen[~standing])
    # Where the robot stood still a scan is not pinned, and its margin says so.
    wrong = aligned.scan_index != chosen
    assert np.all(aligned.margin[wrong] < 0.5) and np.median(aligned.margin[~standing]) > 5.0
    # The true path through the aligned relations: no error (a scan off where the robot stood
    # still is at the same pose).
    error = relation_error(converted, truth, aligned.relations)
    assert error.trans_mean < 1e-9 and error.rot_mean < 1e-9
    assert np.nanmax(aligned.residual) < 0.1 and np.isnan(aligned.residual[-10:]).all()


def test_relations_of_another_log_are_refused_before_any_work():
    truth, original, odometry, converted, relations, chosen = _converted_log()
    with pytest.raises(LogError, match=r"more than the log's 100"):
        align_relations_clock(relations, converted[:100], odometry[:100])
    with pytest.raises(LogError, match=r"longer than the log's 500 scans"):
        align_relations_clock(relations, converted, odometry, scan_period=0.05)
    with pytest.raises(LogError, match=r"must agree"):
        align_relations_clock(relations, converted, odometry[:-1])
    # Two relations that cross: each joins timestamps with the other's between them.
    loops_only = Relations(original[chosen[[0, 1]]], original[chosen[[2, 3]]], np.zeros((2, 3)))
    with pytest.raises(LogError, match=r"no relation joins two neighbouring timestamps"):
        align_relations_clock(loops_only, converted, odometry)


def test_a_window_too_narrow_is_an_error_not_a_wrong_alignment():
    truth, original, odometry, converted, relations, _ = _converted_log()
    # The burst (two scans in five periods) moves every later index three scans from its nominal.
    with pytest.raises(LogError, match=r"offset window's edge \(2 scans\)"):
        align_relations_clock(relations, converted, odometry, max_offset=2)


def test_eval_aligns_the_clock_from_the_log(tmp_path, capsys):
    """``jaxslam eval TRAJ RELATIONS --log LOG``: the converted log's scans are found, the true path
    scores no error; without --log the error says what to give."""
    truth, original, odometry, converted, relations, _ = _converted_log()
    log = LaserLog(converted, odometry, np.full((converted.size, 3), 5.0, np.float32),
                   make_sensor(np.linspace(-0.5, 0.5, 3), range_max=30.0))
    write_carmen(tmp_path / "converted.clf", log)
    write_trajectory(tmp_path / "truth.txt", converted, truth)
    (tmp_path / "original.relations").write_text("".join(
        f"{a:.6f} {b:.6f} {m[0]:.9f} {m[1]:.9f} 0 0 0 {m[2]:.9f}\n"
        for a, b, m in zip(relations.t1, relations.t2, relations.motion)))
    out = tmp_path / "errors.json"
    args = ["eval", str(tmp_path / "truth.txt"), str(tmp_path / "original.relations")]
    assert main(args + ["--log", str(tmp_path / "converted.clf"), "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert table["trans_mean"] < 1e-6 and table["clock_alignment"]["timestamps"] == np.unique(
        np.concatenate([relations.t1, relations.t2])).size
    # The log's scans are all alike: they cannot choose a shift, and the odometry's alignment stands.
    assert table["clock_alignment"]["laser_shift_scans"] == 0
    assert len(table["clock_alignment"]["shift_misfit_m2"]) == 5
    assert "relation timestamps found among the log's scans" in capsys.readouterr().out
    assert main(args) == 2
    assert "need --log LOG" in capsys.readouterr().err


def _laser_log_behind_odometry(seed: int = 0):
    """The converted log of :func:`_converted_log` with scans of a cluttered world, the odometry
    read where the laser was one scan later (as MIT Killian's bag): the laser's scan i was taken
    at ``truth[i]``, the odometry at index i reads ``truth[i + 1]`` plus drift."""
    truth, original, odometry, converted, relations, chosen = _converted_log(seed)
    world = cluttered_world(np.random.default_rng(seed + 1), truth[:, :2].min(0) - 6.0, truth[:, :2].max(0) + 6.0, 400)
    sensor = make_sensor(np.linspace(-np.pi / 2, np.pi / 2, 91), range_max=8.0)
    ranges = simulate_scans(jax.random.PRNGKey(seed), world, truth, sensor, range_noise_std=0.01)
    leading = np.concatenate([odometry[1:], odometry[-1:]])
    return truth, leading, converted, relations, chosen, ranges, sensor


def test_the_scans_find_a_laser_one_scan_behind_the_odometry():
    truth, leading, converted, relations, chosen, ranges, sensor = _laser_log_behind_odometry()
    standing = (chosen >= 200) & (chosen <= 230)
    by_odometry = align_relations_clock(relations, converted, leading)
    # The odometry alone lands a scan early wherever it pins the scan: it cannot see a lag.
    np.testing.assert_array_equal(by_odometry.scan_index[~standing], chosen[~standing] - 1)
    assert by_odometry.laser_shift == 0 and by_odometry.shift_misfit is None
    aligned = align_relations_clock(relations, converted, leading, ranges=ranges, sensor=sensor)
    assert aligned.laser_shift == 1 and int(np.argmin(aligned.shift_misfit)) == 3
    np.testing.assert_array_equal(aligned.scan_index[~standing], chosen[~standing])
    assert relation_error(converted, truth, aligned.relations).trans_mean < 0.2 * relation_error(
        converted, truth, by_odometry.relations).trans_mean
    # Scans that cannot tell the shifts apart (every one the same) leave the odometry's alignment.
    flat = np.full_like(ranges, 5.0)
    assert align_relations_clock(relations, converted, leading, ranges=flat, sensor=sensor).laser_shift == 0


def test_scan_misfit_against_brute_force_nearest_points():
    rng = np.random.default_rng(3)
    first, second = rng.uniform(-3, 3, (60, 2)), rng.uniform(-3, 3, (45, 2))
    motion = np.array([0.4, -0.2, 0.3])
    cos, sin = np.cos(motion[2]), np.sin(motion[2])
    moved = second @ np.array([[cos, -sin], [sin, cos]]).T + motion[:2]
    nearest = np.sqrt(((moved[:, None] - first[None]) ** 2).sum(-1)).min(1)
    expected = np.mean(np.minimum(nearest, 0.25) ** 2)
    assert scan_misfit(motion, first, second, 0.25) == pytest.approx(expected, rel=1e-12)
    assert scan_misfit(motion, first[:0], second, 0.25) == pytest.approx(0.0625)
    # Several motions at once share the tree and give each one's misfit.
    both = scan_misfit(np.stack([motion, np.zeros(3)]), first, second, 0.25)
    assert both.shape == (2,) and both[0] == pytest.approx(expected, rel=1e-12)
    assert both[1] == pytest.approx(scan_misfit(np.zeros(3), first, second, 0.25), rel=1e-12)


def test_scan_inliers_against_brute_force_nearest_points():
    rng = np.random.default_rng(4)
    first, second = rng.uniform(-3, 3, (60, 2)), rng.uniform(-3, 3, (45, 2))
    motions = np.array([[0.4, -0.2, 0.3], [0.0, 0.0, 0.0], [-1.0, 0.5, -2.0]])
    for motion, got in zip(motions, scan_inliers(motions, first, second, 0.3)):
        cos, sin = np.cos(motion[2]), np.sin(motion[2])
        moved = second @ np.array([[cos, -sin], [sin, cos]]).T + motion[:2]
        nearest = np.sqrt(((moved[:, None] - first[None]) ** 2).sum(-1)).min(1)
        assert got == pytest.approx(np.mean(nearest <= 0.3), abs=1e-12)
        assert scan_inliers(motion, first, second, 0.3) == pytest.approx(got, abs=1e-12)
    # A scan over itself: every point; an empty scan: none.
    assert scan_inliers(np.zeros(3), first, first, 1e-9) == 1.0
    assert scan_inliers(np.zeros(3), first[:0], second, 0.3) == 0.0


def test_scans_that_do_not_fit_the_log_are_refused_before_any_work():
    truth, leading, converted, relations, chosen, ranges, sensor = _laser_log_behind_odometry()
    with pytest.raises(LogError, match="scans and its sensor together"):
        align_relations_clock(relations, converted, leading, ranges=ranges)
    with pytest.raises(LogError, match=r"scans have shape \(499, 91\)"):
        align_relations_clock(relations, converted, leading, ranges=ranges[:-1], sensor=sensor)
    with pytest.raises(LogError, match="max_shift must be >= 0"):
        align_relations_clock(relations, converted, leading, ranges=ranges, sensor=sensor, max_shift=-1)
