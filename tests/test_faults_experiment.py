"""experiments/faults.py (odometry slips at the log's turns), the CARMEN writer it maps the faulted
logs through (jaxslam.io.write_carmen) and the symmetric-junction scenario of its ambiguous case.
Fast: no mapping runs (the ambiguous case's filter run is marked slow)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import faults  # noqa: E402

from jaxslam.geometry import between_np, wrap_angle_np  # noqa: E402
from jaxslam.io import read_carmen, read_log, read_relations, write_carmen  # noqa: E402
from jaxslam.laser import make_sensor, uniform_beams  # noqa: E402
from jaxslam.laserlog import LaserLog, LogError  # noqa: E402
from jaxslam.metrics import relation_error  # noqa: E402
from jaxslam.sim import simulate_scan, symmetric_junction_scenario  # noqa: E402
from jaxslam.sim.world import path_crossings  # noqa: E402

TURN_STARTS = (100, 300, 520, 700, 900)
"""Scans at which the synthetic path of :func:`turning_log` starts a 90-degree turn (10 scans long)."""


def turning_log(num_scans: int = 1000, rate_hz: float = 10.0, laser_pose=(0.0, 0.0, 0.0)) -> LaserLog:
    """Straight 0.1 m steps, with a 90-degree left turn over the 10 steps after each of
    :data:`TURN_STARTS`; timestamps far from zero (as a CARMEN log's), 7 beams."""
    turn = np.zeros(num_scans - 1)
    for start in TURN_STARTS:
        turn[start:start + 10] = math.radians(9.0)
    heading = np.concatenate([[0.3], 0.3 + np.cumsum(turn)])
    xy = np.concatenate([[[2.0, -1.0]], [2.0, -1.0] + np.cumsum(0.1 * np.stack([np.cos(heading[:-1]),
                                                                                   np.sin(heading[:-1])], 1), 0)])
    odometry = np.concatenate([xy, wrap_angle_np(heading)[:, None]], axis=1)
    rng = np.random.default_rng(0)
    ranges = rng.uniform(0.2, 12.0, (num_scans, 7)).astype(np.float32)
    ranges[::5, 3] = 10.0  # some "no return" readings (range_max)
    sensor = make_sensor(uniform_beams(7, np.pi), range_min=0.0, range_max=10.0, laser_pose=laser_pose)
    ranges = np.minimum(ranges, np.float32(10.0))
    timestamps = 1.13486e9 + np.arange(num_scans) / rate_hz
    return LaserLog(timestamps, odometry, ranges, sensor, odometry + 0.01, "turning")


def _motions(odometry):
    return between_np(odometry[:-1], odometry[1:])


# ----------------------------------------------------------------------------- inject_faults

@pytest.mark.parametrize("kind, size", [("heading", math.radians(30.0)), ("heading", -0.2),
                                        ("translation", 0.5), ("translation", 1.0)])
def test_a_slip_changes_the_relative_motion_at_its_steps_only(kind, size):
    log = turning_log()
    steps = np.array([150, 400, 800])
    faulted, returned = faults.inject_faults(log, kind, size, steps=steps)
    np.testing.assert_array_equal(returned, steps)
    before, after = _motions(log.odometry), _motions(faulted.odometry)
    changed = steps - 1  # motion i leads from scan i to scan i + 1
    others = np.setdiff1d(np.arange(before.shape[0]), changed)
    np.testing.assert_allclose(after[others], before[others], atol=1e-9)
    if kind == "translation":
        np.testing.assert_allclose(after[changed] - before[changed], np.tile([size, 0.0, 0.0], (3, 1)), atol=1e-9)
    else:
        c, s = math.cos(size), math.sin(size)
        turned = np.stack([c * before[changed, 0] - s * before[changed, 1],
                           s * before[changed, 0] + c * before[changed, 1]], 1)
        np.testing.assert_allclose(after[changed, :2], turned, atol=1e-9)
        np.testing.assert_allclose(wrap_angle_np(after[changed, 2] - before[changed, 2]), size, atol=1e-9)
    # Before the first slip the odometry is the same; timestamps, scans and truth never change.
    np.testing.assert_array_equal(faulted.odometry[:steps[0]], log.odometry[:steps[0]])
    np.testing.assert_array_equal(faulted.timestamps, log.timestamps)
    np.testing.assert_array_equal(faulted.ranges, log.ranges)
    np.testing.assert_array_equal(faulted.ground_truth, log.ground_truth)
    assert "slips" in faulted.notes[-1]


def test_a_heading_slip_rotates_the_later_poses_about_the_slip_point():
    log = turning_log()
    faulted, _ = faults.inject_faults(log, "heading", math.pi / 2, steps=[200])
    pivot = log.odometry[199, :2]
    moved = log.odometry[200:, :2] - pivot
    np.testing.assert_allclose(faulted.odometry[200:, :2] - pivot, np.stack([-moved[:, 1], moved[:, 0]], 1),
                               atol=1e-9)
    # The translation slips add up: three of 1 m at heading theta_k - 1 move the end by their sum.
    shifted, steps = faults.inject_faults(log, "translation", 1.0, steps=[100, 500, 900])
    pushes = sum(np.array([math.cos(log.odometry[k - 1, 2]), math.sin(log.odometry[k - 1, 2])]) for k in steps)
    np.testing.assert_allclose(shifted.odometry[-1, :2] - log.odometry[-1, :2], pushes, atol=1e-9)


def test_a_slip_of_size_zero_leaves_the_odometry_and_bad_input_is_refused():
    log = turning_log()
    same, _ = faults.inject_faults(log, "heading", 0.0, seed=2)
    np.testing.assert_allclose(same.odometry, log.odometry, atol=1e-12)
    with pytest.raises(ValueError, match="kind must be 'heading' or 'translation'"):
        faults.inject_faults(log, "sideways", 0.1)
    with pytest.raises(ValueError, match="size must be a finite number"):
        faults.inject_faults(log, "heading", float("nan"))
    for steps in ([0, 10], [20, 10], [10, 1000], []):
        with pytest.raises(ValueError, match=r"steps must be increasing scan indices in \[1, 999\]"):
            faults.inject_faults(log, "translation", 0.5, steps=steps)


# ----------------------------------------------------------------------------- find_turns

def test_the_turn_finder_picks_turns_one_per_part_of_the_log():
    log = turning_log()
    turns = [np.arange(start - 5, start + 16) for start in TURN_STARTS]  # a turn and its window's edges
    seen = set()
    for seed in range(12):
        steps = faults.find_turns(log.odometry, log.timestamps, 3, seed)
        assert steps.shape == (3,) and np.all(np.diff(steps) > 0)
        for k in steps:
            assert any(k in turn for turn in turns), (seed, steps)
        # One per third of scans 100..899 (margin 0.1).
        assert [int((k - 100) // (800 / 3)) for k in steps] == [0, 1, 2], steps
        np.testing.assert_array_equal(steps, faults.find_turns(log.odometry, log.timestamps, 3, seed))
        seen.add(tuple(steps))
    assert len(seen) > 1  # the seed draws among the turns
    strength = faults.turn_strength(log.odometry, log.timestamps, 2.0)
    assert math.degrees(strength[TURN_STARTS[0] + 5]) == pytest.approx(90.0)
    assert strength[50] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="too short"):
        faults.find_turns(log.odometry[:3], log.timestamps[:3], 3)
    with pytest.raises(ValueError, match="num_turns must be a positive integer"):
        faults.find_turns(log.odometry, log.timestamps, 0)


def test_real_turns_and_the_faulted_log_keep_the_relations_timestamps(shared_data, tmp_path):
    """MIT CSAIL: the turns found are turns (>= 45 degrees within 2 s), the faulted log written as
    CARMEN reads back with every relation's timestamps, and the clean round trip scores as the
    original (the relation metric matches scans by timestamp)."""
    log = read_log(shared_data / "mit-csail.clf")
    relations = read_relations(shared_data / "mit-csail.relations")
    steps = faults.find_turns(log.odometry, log.timestamps, 3, 0)
    assert np.all(faults.turn_strength(log.odometry, log.timestamps)[steps] > math.radians(45))
    faulted, _ = faults.fault_log(log, "heading-30", 0)
    write_carmen(tmp_path / "f.clf", faulted)
    back = read_log(tmp_path / "f.clf")
    np.testing.assert_array_equal(back.timestamps, log.timestamps)
    np.testing.assert_array_equal(back.odometry, faulted.odometry)
    clean = relation_error(log.timestamps, log.odometry, relations)
    slipped = relation_error(back.timestamps, back.odometry, relations)
    assert slipped.count == clean.count
    # The odometry's own error changes exactly for the relations that span a slip.
    lo, hi = np.minimum(relations.t1, relations.t2), np.maximum(relations.t1, relations.t2)
    spans = np.zeros(relations.count, dtype=bool)
    for k in steps:
        # (relation timestamps carry 5 decimals: the metric matches them within 1e-4 s)
        spans |= (lo <= log.timestamps[k - 1] + 1e-4) & (hi >= log.timestamps[k] - 1e-4)
    assert 0 < spans.sum() < relations.count
    np.testing.assert_allclose(slipped.trans[~spans], clean.trans[~spans], atol=1e-6)
    np.testing.assert_allclose(slipped.rot[~spans], clean.rot[~spans], atol=1e-6)
    assert np.all(np.abs(wrap_angle_np(slipped.rot[spans] - clean.rot[spans])) > 0) or \
        np.all(np.abs(slipped.trans[spans] - clean.trans[spans]) > 1e-3)


# ----------------------------------------------------------------------------- write_carmen

def test_write_carmen_round_trip_is_exact(tmp_path):
    log = turning_log(200, laser_pose=(0.2, -0.05, 0.1))
    path = tmp_path / "log.clf"
    write_carmen(path, log)
    back = read_carmen(path)
    np.testing.assert_array_equal(back.timestamps, log.timestamps)
    np.testing.assert_array_equal(back.odometry, log.odometry)
    np.testing.assert_array_equal(back.ranges, log.ranges)
    np.testing.assert_allclose(back.ground_truth, log.ground_truth, atol=1e-12)
    np.testing.assert_allclose(np.asarray(back.sensor.beam_angles), np.asarray(log.sensor.beam_angles), atol=1e-6)
    np.testing.assert_allclose(np.asarray(back.sensor.laser_pose), [0.2, -0.05, 0.1], atol=1e-6)
    assert float(back.sensor.range_max) == float(log.sensor.range_max)
    assert read_log(path).num_scans == 200  # read_log recognises the file as CARMEN


def test_write_carmen_refuses_what_it_cannot_write(tmp_path):
    log = turning_log(20)
    angles = np.asarray(log.sensor.beam_angles).copy()
    angles[3] += 0.01
    uneven = LaserLog(log.timestamps, log.odometry, log.ranges, log.sensor._replace(beam_angles=angles), source="u")
    with pytest.raises(LogError, match="u: beam 3 lies 0.01 rad off the even grid"):
        write_carmen(tmp_path / "u.clf", uneven)
    ranges = log.ranges.copy()
    ranges[4, 2] = 0.05
    short = LaserLog(log.timestamps, log.odometry, ranges, make_sensor(uniform_beams(7), range_min=0.1,
                                                                       range_max=10.0), source="s")
    with pytest.raises(LogError, match="s: scan 4 beam 2 reads 0.05 m, below range_min=0.1 m"):
        write_carmen(tmp_path / "s.clf", short)
    assert not (tmp_path / "u.clf").exists() and not (tmp_path / "s.clf").exists()


# ----------------------------------------------------------------------------- judging, table, figure

def _record(dataset, proposal, fault, seed, error=None):
    kind, size = faults.FAULTS[fault]
    base = {"dataset": dataset, "proposal": proposal, "fault": fault, "kind": kind, "size": size, "seed": seed}
    return {**base, "failed": "boom"} if error is None else {**base, "trans_mean": error}


def test_the_success_rule():
    clean = _record("intel", "smp", "clean", 0, 0.08)
    assert faults.judge(_record("intel", "smp", "heading-10", 0, 0.1), clean) == faults.SUCCESS  # exactly 1.25 x
    assert faults.judge(_record("intel", "smp", "heading-10", 0, 0.1001), clean) == faults.FAILURE
    assert faults.judge(_record("intel", "smp", "heading-10", 0, 0.01), clean) == faults.SUCCESS
    assert faults.judge(_record("intel", "smp", "heading-10", 0), clean) == faults.CRASHED
    assert faults.judge(_record("intel", "smp", "heading-10", 0, 0.05), None) == faults.NO_CLEAN
    assert faults.judge(_record("intel", "smp", "heading-10", 0, 0.05), _record("intel", "smp", "clean", 0)) \
        == faults.NO_CLEAN
    assert faults.judge(_record("intel", "smp", "heading-10", 0, 0.15), clean, factor=2.0) == faults.SUCCESS


def _fake_records():
    records = []
    for seed, clean in enumerate([0.05, 0.06, 0.04]):
        records.append(_record("intel", "smp", "clean", seed, clean))
        records.append(_record("intel", "smp", "heading-10", seed, clean * 1.1))  # 3 successes
        records.append(_record("intel", "smp", "heading-45", seed, clean * (1.1 if seed == 0 else 3.0)))  # 1
        records.append(_record("intel", "smp", "translation-1", seed, clean * 1.2))
    # The LP on ACES: the clean run of seed 1 crashed.
    for seed in range(2):
        records.append(_record("aces", "lp", "clean", seed, 0.05 if seed == 0 else None))
        records.append(_record("aces", "lp", "translation-0.5", seed, 0.2 if seed == 0 else 0.05))
    return records


def test_the_table_counts_successes_per_cell():
    table = faults.cells(_fake_records())
    assert table[("intel", "smp", "heading-10")]["successes"] == 3
    assert table[("intel", "smp", "heading-45")]["successes"] == 1
    assert table[("intel", "smp", "heading-45")]["judged"] == 3
    cell = table[("aces", "lp", "translation-0.5")]
    assert (cell["successes"], cell["judged"], cell["no_clean"]) == (0, 1, 1)
    assert cell["verdicts"] == {0: faults.FAILURE, 1: faults.NO_CLEAN}
    assert table[("aces", "lp", "clean")]["verdicts"] == {0: faults.SUCCESS, 1: faults.CRASHED}
    text = faults.faults_markdown(_fake_records())
    lines = text.splitlines()
    header = next(line for line in lines if line.startswith("| log"))
    assert header == "| log | proposal | clean | heading-10 | heading-45 | translation-0.5 | translation-1 |"
    intel = next(line for line in lines if line.startswith("| intel | SMP"))
    assert "| 3/3, 0.050 m |" in intel and "| 3/3, 0.055 m |" in intel and "| 1/3, " in intel
    aces = next(line for line in lines if line.startswith("| aces | LP"))
    assert "0/1, 0.125 m (1 no clean run)" in aces
    assert "| aces | LP | 1/2, 0.050 m |" in aces  # the clean column: finished runs / seeds
    assert lines.index(intel) < lines.index(aces)  # the logs in datasets.py's order


def test_the_figures_lines():
    curves = faults.success_curves(_fake_records())
    assert curves["heading"][("intel", "smp")] == ([0.0, 10.0, 45.0], [1.0, 1.0, pytest.approx(1 / 3)])
    assert curves["translation"][("intel", "smp")] == ([0.0, 1.0], [1.0, 1.0])
    assert curves["translation"][("aces", "lp")] == ([0.0, 0.5], [0.5, 0.0])
    assert ("aces", "lp") not in curves["heading"] or curves["heading"][("aces", "lp")] == ([0.0], [0.5])


def test_the_figure_and_the_store(tmp_path):
    path = faults.faults_figure(_fake_records(), tmp_path / "faults.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    store = faults.ResultStore(tmp_path / "results.json", faults.SETTINGS,
                               key=lambda r: (r["dataset"], r["proposal"], r["fault"], r["seed"]))
    store.add(*_fake_records())
    faults.write_tables(store)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["cells"]["intel/smp/heading-45"]["successes"] == 1
    assert data["cells"]["aces/lp/translation-0.5"]["verdicts"] == {"0": "failure", "1": "no clean run"}
    assert (tmp_path / "faults.md").read_text() == faults.faults_markdown(_fake_records())
    assert (tmp_path / "faults.png").is_file()


def test_bad_arguments_are_refused_before_any_work(tmp_path, capsys):
    assert faults.main(["--seeds", "0", "--out", str(tmp_path / "a")]) == 2
    assert "--seeds must be at least 1" in capsys.readouterr().err
    assert faults.main(["--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "b")]) == 2
    assert "datasets not found" in capsys.readouterr().err
    assert faults.main(["--max-scans", "1", "--out", str(tmp_path / "c")]) == 2
    assert faults.main(["--set", "num_particels=3", "--out", str(tmp_path / "d")]) == 2
    assert "--set: " in capsys.readouterr().err
    assert faults.main(["--ambiguous", "--set", "no_equals_sign", "--out", str(tmp_path / "e")]) == 2
    assert "NAME=VALUE" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        faults.main(["--faults", "heading-15"])
    assert not any((tmp_path / name).exists() for name in "abcde")


# ----------------------------------------------------------------------------- the ambiguous case

def test_the_symmetric_junction_is_ambiguous_in_the_lane_and_not_before():
    scenario = symmetric_junction_scenario(jax.random.key(0))
    world, truth, meta = scenario.world, scenario.true_poses, scenario.metadata
    assert not path_crossings(truth[:, :2], world.segments).any()
    lane = meta["ambiguous_scans"]
    assert lane.size >= 10 and np.all(truth[lane, 1] >= 0.3)
    sensor = scenario.log.sensor

    def scan(pose):
        return np.asarray(simulate_scan(jax.random.key(1), world, pose, sensor, 0.0))

    for i in lane[::3]:
        difference = np.abs(scan(truth[i]) - scan(truth[i] + meta["mirror_offset"]))
        assert difference.max() < 1e-3, (i, difference.max())
    # During the swerve, before the fork, the two poses look different: the swerve tells the lanes apart.
    swerve = [i for i in range(lane[0]) if -2.0 < truth[i, 1] < -0.3]
    assert max(np.abs(scan(truth[i]) - scan(truth[i] + meta["mirror_offset"])).max() for i in swerve) > 0.5
    # The odometry's sideways error in the lane is some tenths of a metre over a few seeds.
    sideways = [abs(symmetric_junction_scenario(jax.random.key(s)).log.odometry[lane[-1], 0] - truth[lane[-1], 0])
                for s in range(5)]
    assert max(sideways) > 0.3


@pytest.mark.slow  # a filter run (compilation included)
def test_the_ambiguous_case_reports_the_share_near_the_truth(tmp_path):
    runs = faults.ambiguous_case(tmp_path, proposals=("smp",), seeds=1, particles=8)
    run = runs[0]
    assert len(run["scans"]) == len(run["near_true"]) == len(run["near_mirror"]) > 0
    assert all(0.0 <= v <= 1.0 for v in run["near_true"] + run["near_mirror"])
    assert (tmp_path / "ambiguous.md").read_text().count("| SMP | 0 |") == 1
