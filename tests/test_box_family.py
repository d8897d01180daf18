"""The box-world family (jaxslam.sim.box_family) and its experiment (experiments/box_family.py).

Fast: draws, paths and a few short simulations; one tiny filter run (1 world, OP, N = 4, one lap).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.motion import MotionParams
from jaxslam.segment_map import raycast
from jaxslam.sim import Scenario, SegmentWorld, box_world_scenario, passage_indices
from jaxslam.sim import box_family as bf
from jaxslam.sim.world import path_crossings, point_segment_distance

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import box_family as experiment  # noqa: E402  (experiments/box_family.py)
import box_world  # noqa: E402

SEEDS = [*range(bf.TUNING_FIRST_SEED, bf.TUNING_FIRST_SEED + 100), *bf.TEST_SEEDS]
"""200 seeds, half from each family."""


@pytest.fixture(scope="module")
def draws():
    return [bf.draw_world(seed) for seed in SEEDS]


def short(draw: bf.BoxWorldDraw, laps: int = 2) -> bf.BoxWorldDraw:
    """The draw with fewer laps (a shorter simulation), a visit to X after each."""
    return dataclasses.replace(draw, laps=laps, laps_per_visit=1)


# ----------------------------------------------------------------------------- the draw

def test_the_draw_is_a_pure_function_of_the_seed(draws):
    again = bf.draw_world(SEEDS[0])
    assert again == draws[0]  # after 199 other draws: no state outside the seed
    assert json.dumps(again.to_json()) == json.dumps(draws[0].to_json())
    assert bf.draw_world(np.int64(SEEDS[0])) == draws[0]
    assert draws[0] != draws[1] and len({json.dumps(d.to_json()) for d in draws}) == len(draws)
    for bad in (-1, 1.5, True, "3"):
        with pytest.raises(ValueError, match="seed"):
            bf.draw_world(bad)


def _within(value, bounds) -> bool:
    return bounds[0] <= value <= bounds[1]


def test_every_drawn_quantity_lies_in_its_range(draws):
    for d in draws:
        assert d.num_boxes in (1, 2) and len(d.box_angles) == len(d.box_centers) == d.num_boxes
        assert all(_within(s, bf.BOX_SIDE_RANGE) for s in d.box_sides)
        assert all(0.0 <= a < 0.5 * np.pi for a in d.box_angles)
        assert _within(d.circle_radius, bf.CIRCLE_RADIUS_RANGE) and _within(d.approach, bf.APPROACH_RANGE)
        assert _within(d.turnaround_distance, bf.TURNAROUND_RANGE)
        assert _within(d.laps, bf.LAPS_RANGE) and _within(d.laps_per_visit, bf.LAPS_PER_VISIT_RANGE)
        assert isinstance(d.laps, int) and isinstance(d.clockwise, bool)
        assert _within(d.range_max, bf.RANGE_MAX_RANGE) and _within(d.odometry_scale, bf.ODOMETRY_SCALE_RANGE)
        assert _within(len(d.landmarks), bf.NUM_LANDMARKS_RANGE)
        assert d.box_gap == 0.0 if d.num_boxes == 1 else _within(d.box_gap, bf.BOX_GAP_RANGE)
        np.testing.assert_allclose(d.circle_center, [d.circle_radius + d.approach, 0.0])
        world = bf.family_world(d)  # every segment inside the family's bounds (SegmentWorld checks)
        assert world.bounds == bf.FAMILY_BOUNDS
        boxes = world.segments[world.groups["box2"]].astype(np.float64)
        # The boxes fit the circle with room for the robot, and do not touch each other.
        corners = boxes[:, :2]
        assert np.hypot(*(corners - d.circle_center).T).max() <= d.circle_radius - bf.BOX_CLEARANCE + 1e-5
        if d.num_boxes == 2:
            assert point_segment_distance(corners[:4], boxes[4:]).min() >= d.box_gap - 1e-5
            assert point_segment_distance(corners[4:], boxes[:4]).min() >= d.box_gap - 1e-5
        for landmark in d.landmarks:
            segments = np.asarray(landmark.segments)
            lengths = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
            if landmark.kind == "hedge":
                assert 4 <= len(segments) <= 8 and lengths.min() >= 0.2 - 1e-9 and lengths.max() <= 0.5 + 1e-9
            elif landmark.kind == "fence":  # one broken line: each leg starts where the last ended
                assert 2 <= len(segments) <= 4 and lengths.min() >= 0.5 - 1e-9 and lengths.max() <= 1.2 + 1e-9
                np.testing.assert_allclose(segments[1:, :2], segments[:-1, 2:])
            else:  # barrels: polygons of 8-12 sides round circles of radius 0.15-0.4 m
                assert landmark.kind == "barrels"
                assert lengths.min() >= 2 * 0.15 * np.sin(np.pi / 12) - 1e-9
                assert lengths.max() <= 2 * 0.4 * np.sin(np.pi / 8) + 1e-9
            # Never in view from the circle; in part seen from X; off the path near X.
            reach = point_segment_distance(d.circle_center[None], segments).min()
            assert reach >= d.circle_radius + d.range_max + bf.VIEW_MARGIN - 1e-9
            assert bf._length_within(segments, bf.CHECKPOINT, d.range_max - bf.SEEN_MARGIN) >= bf.SEEN_LENGTH
        drift = bf.heading_drift_per_lap(d)
        assert 0.03 < drift < 0.3
    # The family holds every kind of world.
    assert {d.num_boxes for d in draws} == {1, 2} and {d.clockwise for d in draws} == {False, True}
    assert {m.kind for d in draws for m in d.landmarks} == set(bf.LANDMARK_KINDS)
    assert {d.laps for d in draws} == set(range(8, 16)) and {d.laps_per_visit for d in draws} == {3, 4, 5}


def test_the_default_robots_drift_per_lap_is_the_box_worlds():
    """The box world's robot (scale 1) on its 1.75 m circle drifts 7.6 degrees of heading a lap
    (box_world_scenario's docstring); the drift grows with the odometry scale."""
    d = dataclasses.replace(bf.draw_world(1000), circle_radius=1.75, odometry_scale=1.0, clockwise=False)
    assert np.degrees(bf.heading_drift_per_lap(d)) == pytest.approx(7.6, abs=0.05)
    assert bf.heading_drift_per_lap(dataclasses.replace(d, clockwise=True)) == pytest.approx(
        bf.heading_drift_per_lap(d), rel=1e-6)
    assert bf.heading_drift_per_lap(dataclasses.replace(d, odometry_scale=1.5)) > 1.3 * bf.heading_drift_per_lap(d)


# ----------------------------------------------------------------------------- the families

def test_the_families_are_apart_and_bad_requests_are_refused():
    assert bf.family_seeds("tuning", 5) == range(1000, 1005)
    assert bf.family_seeds("test", 100) == range(0, 100)
    assert not set(bf.family_seeds("tuning", 10_000)) & set(bf.TEST_SEEDS)
    assert bf.TUNING_FIRST_SEED >= bf.TEST_SEEDS.stop
    with pytest.raises(ValueError, match="test family has 100 worlds, 101"):
        bf.family_seeds("test", 101)
    with pytest.raises(ValueError, match="unknown family 'train'"):
        bf.family_seeds("train", 5)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="count"):
            bf.family_seeds("tuning", bad)


# ----------------------------------------------------------------------------- scenario and path

def _conventions(value):
    """What a value's convention is: its type, and for arrays their number of axes and dtype."""
    if isinstance(value, np.ndarray):
        return ("array", value.ndim, value.dtype)
    if isinstance(value, MotionParams):
        return ("motion", tuple(np.shape(v) for v in value))
    return type(value)


def test_a_worlds_scenario_has_the_box_worlds_conventions():
    reference = box_world_scenario(jax.random.key(0), laps=2, laps_per_visit=1)
    draw = short(bf.draw_world(1000))
    scenario = bf.family_scenario(draw, jax.random.key(0))
    assert type(scenario) is Scenario and isinstance(scenario.world, SegmentWorld)
    log, ref = scenario.log, reference.log
    for name in ("timestamps", "odometry", "ranges", "ground_truth"):
        got, want = np.asarray(getattr(log, name)), np.asarray(getattr(ref, name))
        assert got.dtype == want.dtype and got.ndim == want.ndim and got.shape[1:] == want.shape[1:], name
        assert got.shape[0] == scenario.true_poses.shape[0]
    np.testing.assert_array_equal(scenario.true_poses, log.ground_truth)
    assert scenario.true_poses.dtype == np.float64 and scenario.true_poses.shape[1] == 3
    assert type(log.sensor) is type(ref.sensor)
    assert float(log.sensor.range_max) == pytest.approx(draw.range_max)
    np.testing.assert_array_equal(log.sensor.beam_angles, ref.sensor.beam_angles)
    for key, value in reference.metadata.items():
        assert _conventions(scenario.metadata[key]) == _conventions(value), key
    meta = scenario.metadata
    assert meta["laps"] == 2 and len(meta["lap_end_indices"]) == 2 and meta["clockwise"] == draw.clockwise
    np.testing.assert_allclose(meta["box2_center"], draw.circle_center)
    np.testing.assert_allclose(meta["checkpoint_x"], [0.0, 0.0])
    assert meta["draw"] == draw and meta["difficulty"] == bf.difficulty(draw)
    # The robot's noise is the box world's, its proportional terms scaled by the draw.
    robot = meta["motion_params"]
    for name in bf.PROPORTIONAL_TERMS:
        assert float(getattr(robot, name)) == pytest.approx(
            float(getattr(reference.metadata["motion_params"], name)) * draw.odometry_scale, rel=1e-6)
    for name in ("min_translation_std", "min_rotation_std"):
        assert float(getattr(robot, name)) == float(getattr(reference.metadata["motion_params"], name))
    # The same key, the same data; another key, other noise.
    again = bf.family_scenario(draw, jax.random.key(0))
    np.testing.assert_array_equal(again.log.ranges, log.ranges)
    assert not np.array_equal(bf.family_scenario(draw, jax.random.key(1)).log.odometry, log.odometry)


def _winding(points: np.ndarray, center) -> float:
    """Signed turns (counter-clockwise positive) a path makes round ``center``, closed by a straight
    line from its end back to its start (from the turnaround point to X: it passes no box)."""
    points = np.concatenate([points, points[:1]])
    angles = np.unwrap(np.arctan2(points[:, 1] - center[1], points[:, 0] - center[0]))
    return float((angles[-1] - angles[0]) / (2 * np.pi))


def test_the_true_path_circles_the_boxes_the_drawn_laps_in_the_drawn_direction(draws):
    picks = {}
    for d in draws:  # a world of each kind: one box or two, either way round
        picks.setdefault((d.num_boxes, d.clockwise), d)
    assert len(picks) == 4
    for d in picks.values():
        poses, info = bf.family_path(d)
        sign = -1 if d.clockwise else 1
        visits = -(-d.laps // d.laps_per_visit)
        # Each visit goes round laps_per_visit whole laps plus the arc to the leaving tangent, and
        # the excursion over X closes that turn: laps + visits turns round every box in all.
        for center in (d.circle_center, *d.box_centers):
            assert _winding(poses[:, :2], center) == pytest.approx(sign * (d.laps + visits), abs=1e-6)
        lap_ends = info["lap_end_indices"]
        assert len(lap_ends) == d.laps
        # On the circle the heading is the tangent in the drawn direction.
        offset = poses[:, :2] - d.circle_center
        on_circle = np.abs(np.hypot(*offset.T) - d.circle_radius) < 1e-6
        assert on_circle.sum() > 0.9 * d.laps * 2 * np.pi * d.circle_radius / bf.STEP_LENGTH
        cross = offset[:, 0] * np.sin(poses[:, 2]) - offset[:, 1] * np.cos(poses[:, 2])
        assert np.all(np.sign(cross[on_circle]) == sign)
        # Every lap end is on the circle, at the visit's entry angle, a whole lap on.
        assert on_circle[lap_ends].all()
        world = bf.family_world(d)
        assert not path_crossings(poses[:, :2], world.segments).any()
        assert point_segment_distance(poses[:, :2], world.segments).min() > 0.35
        # Over X at the start, between visits and at the end.
        passages = passage_indices(poses, bf.CHECKPOINT, 0.3)
        assert passages[0] < 5 and passages[-1] > lap_ends[-1] and len(passages) >= 2 * visits


def test_landmarks_are_seen_at_x_and_never_from_the_circle():
    jit_raycast = jax.jit(raycast)
    for seed in (1000, 1003):
        scenario = bf.family_scenario(short(bf.draw_world(seed), laps=3), jax.random.key(0))
        poses = jnp.asarray(scenario.true_poses, jnp.float32)
        sensor = scenario.log.sensor
        _, hit = jit_raycast(scenario.world.segments, poses[:, None, :2], poses[:, 2:3] + sensor.beam_angles[None],
                             sensor.range_max)
        hit = np.asarray(hit)
        groups = scenario.world.groups
        sees_landmarks = np.isin(hit, groups["landmarks"]).any(axis=1)
        sees_boxes = np.isin(hit, groups["box2"]).any(axis=1)
        radius = np.hypot(*(scenario.true_poses[:, :2] - scenario.metadata["box2_center"]).T)
        on_circle = np.abs(radius - scenario.metadata["circle_radius"]) < 1e-6
        assert on_circle.sum() > 200 and sees_boxes[on_circle].all() and not sees_landmarks[on_circle].any()
        # At X facing away from the circle (the start, every return from the circle, the end: the
        # passages that RA compares), the forward laser sees the landmarks; facing back it need not.
        passages = scenario.metadata["x_passages"]
        outward = passages[np.cos(scenario.true_poses[passages, 2]) < 0]
        assert outward[0] == passages[0] and outward[-1] == passages[-1] and len(outward) == 4
        assert sees_landmarks[outward].all()


def test_the_filters_motion_follows_the_simulators_by_the_jsons_rule():
    exp = box_world.load_experiment()
    world = box_world.world_settings(exp, {})
    cell = box_world.cell_record(box_world.method_settings(exp, "OP", {"max_insert_range": 5.5}), 4, 1.0)
    setups = []
    for seed in (1000, 1001):
        draw = short(bf.draw_world(seed), laps=1)
        scenario = bf.family_scenario(draw, jax.random.key(0))
        config, settings, params = box_world.filter_setup(cell, scenario, world)
        rule = experiment.filter_motion_params(draw, world)
        for name, value in rule.items():
            assert float(getattr(params.motion, name)) == pytest.approx(value, rel=1e-6)
        robot = bf.robot_motion_params(draw)
        assert rule["srr"] == pytest.approx(float(robot.srr) * exp["motion_scale"], rel=1e-6)
        assert rule["min_rotation_std"] == pytest.approx(float(robot.min_rotation_std))
        setups.append((config, settings))
    # Every world compiles the same filter: the same static config (grid, insertion range).
    assert setups[0] == setups[1]


# ----------------------------------------------------------------------------- the experiment

def test_failure_causes():
    ok = {"ra": 0.1, "closest_then": 0.05, "weighted_then": 0.1}
    assert experiment.failure_cause(ok, 0.2) is None
    no_particle, weights, later = experiment.CAUSES
    assert experiment.failure_cause({"ra": 1.0, "closest_then": 0.5, "weighted_then": 1.0}, 0.2) == no_particle
    assert experiment.failure_cause({"ra": 1.0, "closest_then": 0.1, "weighted_then": 0.8}, 0.2) == weights
    assert experiment.failure_cause({"ra": 0.3, "closest_then": 0.1, "weighted_then": 0.15}, 0.2) == later


def test_the_cli_refuses_the_test_family_without_the_flag_before_any_work(tmp_path, capsys, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("work started")

    monkeypatch.setattr(experiment, "run_world", no_work)
    monkeypatch.setattr(experiment, "draw_worlds_figure", no_work)
    out = tmp_path / "results.json"
    assert experiment.main(["--family", "test", "--worlds", "1", "--out", str(out)]) == 2
    assert experiment.main(["--family", "test", "--draw-worlds", str(tmp_path / "w.png")]) == 2
    err = capsys.readouterr().err
    assert "--i-have-made-the-choice" in err and "tuning family" in err and "Traceback" not in err
    assert experiment.main(["--family", "test", "--i-have-made-the-choice", "--worlds", "101", "--out", str(out)]) == 2
    assert "test family has 100 worlds" in capsys.readouterr().err
    assert experiment.main(["--worlds", "1", "--methods", "nope", "--out", str(out)]) == 2
    assert experiment.main(["--worlds", "1", "--out", str(tmp_path)]) == 2  # a folder, not a file
    assert experiment.main(["--worlds", "1", "--figure", str(tmp_path / "f.png")]) == 2  # a figure of no runs
    assert not out.exists() and not (tmp_path / "w.png").exists()
    with pytest.raises(SystemExit):
        experiment.main(["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "made on the tuning family" in help_text and "measured once, after the choice is made" in help_text


def test_twelve_worlds_figure(tmp_path):
    png = tmp_path / "worlds.png"
    assert experiment.main(["--draw-worlds", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_one_tiny_cell_end_to_end_and_resumed(tmp_path, monkeypatch):
    out, png = tmp_path / "results.json", tmp_path / "difficulty.png"
    argv = ["--worlds", "1", "--methods", "OP", "--particles", "4", "--max-laps", "1", "--out", str(out),
            "--figure", str(png)]
    assert experiment.main(argv) == 0
    data = json.loads(out.read_text())
    assert data["settings"]["family"] == "tuning" and data["settings"]["max_laps"] == 1
    (run,) = data["runs"]
    assert run["seed"] == bf.TUNING_FIRST_SEED and np.isfinite(run["ra"])
    assert run["closest_then"] <= run["weighted_then"] + 1e-9
    assert run["cause"] == experiment.failure_cause(run, 0.2)
    (row,) = data["summary"]
    assert (row["method"], row["N"], row["num_runs"]) == ("OP", 4, 1)
    assert data["worlds"][str(bf.TUNING_FIRST_SEED)]["draw"]["laps"] == 1
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # Rerun with the same --out: the finished run is skipped, the file unchanged but for the rewrite.
    def no_work(*args, **kwargs):
        raise AssertionError("a finished run was run again")

    monkeypatch.setattr(experiment, "run_world", no_work)
    assert experiment.main(argv) == 0
    assert json.loads(out.read_text())["runs"] == data["runs"]
    # Other settings (no lap cut) into the same file are refused.
    uncut = argv[:6] + argv[8:]
    assert "--max-laps" not in uncut and experiment.main(uncut) == 2
