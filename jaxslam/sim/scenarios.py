"""Ready-made simulated datasets: worlds, true paths and logs.

* :func:`office_scenario`: the library's demo. A 20 m x 15 m office, a loop through
  the corridor and three of its six rooms, a 180-beam laser.
* :func:`box_world_scenario`: the box world of Grzonka, Plagemann, Grisetti and
  Burgard, "Look-ahead Proposals for Robust Grid-based SLAM with Rao-Blackwellized
  Particle Filters" (Figs. 1 and 4): 15 laps around a lone box with a 4 m laser,
  then back to a checkpoint X whose surroundings were mapped at the start.
* :func:`hall_scenario`: an open hall with two rows of pillars, a figure-of-eight tour: a
  second world for checks that should not be the office's doing (learning's fit tables).
* :func:`symmetric_junction_scenario`: a corridor that forks into two identical lanes; from
  inside a lane the scan cannot tell which lane the robot is in.

All are deterministic given the key: the world and the true path are fixed, the key
draws the range and odometry noise.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from jaxtyping import PRNGKeyArray

from jaxslam.laserlog import LaserLog
from jaxslam.motion import MotionParams, motion_params
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.sim.paths import circle_path, concat_paths, passage_indices, waypoint_path, waypoint_path_length
from jaxslam.sim.simulate import simulate_log
from jaxslam.sim.world import (
    SegmentWorld,
    box_segments,
    concat_worlds,
    make_world,
    polyline_segments,
    wall_segments,
)


class Scenario(NamedTuple):
    """A simulated dataset with everything needed to score a filter on it."""

    log: LaserLog
    """Simulated scans and odometry, with ``ground_truth`` set."""
    world: SegmentWorld
    """The segments the scans were cast against."""
    true_poses: np.ndarray
    """(T, 3) float64 true robot poses (m, m, rad), the same as ``log.ground_truth``."""
    metadata: dict[str, Any]
    """Scenario facts: the parameters it was simulated with (``motion_params``,
    ``range_noise_std``, ``step_length``, ...) and landmarks such as checkpoints."""


# ----------------------------------------------------------------------------- office

OFFICE_SIZE = (20.0, 15.0)
"""Outer dimensions (m) of the office."""
_CORRIDOR_Y = (6.5, 8.5)  # the corridor's south and north walls
_DOOR_WIDTH = 1.2
_UPPER_DOORS = (3.5, 10.25, 16.75)  # door centres (x, m) in the corridor's north wall
_LOWER_DOORS = (3.0, 9.0, 16.0)  # door centres (x, m) in the corridor's south wall


def office_world() -> SegmentWorld:
    """A small office: 20 m x 15 m outer walls, an east-west corridor 2 m wide
    (y from 6.5 to 8.5 m), three rooms north of it and three south, each with a 1.2 m
    door onto the corridor, and furniture (desks, tables, cabinets, a pillar).

    Groups: "outer", "walls" (corridor walls and room dividers), "furniture".
    """
    width, height = OFFICE_SIZE
    south, north = _CORRIDOR_Y
    outer = polyline_segments([[0, 0], [width, 0], [width, height], [0, height]], closed=True)
    walls = np.concatenate([
        wall_segments([0, north], [width, north], [(x, _DOOR_WIDTH) for x in _UPPER_DOORS]),
        wall_segments([0, south], [width, south], [(x, _DOOR_WIDTH) for x in _LOWER_DOORS]),
        # Room dividers: north rooms x in [0, 7], [7, 13.5], [13.5, 20];
        # south rooms x in [0, 6], [6, 12], [12, 20].
        polyline_segments([[7.0, north], [7.0, height]]),
        polyline_segments([[13.5, north], [13.5, height]]),
        polyline_segments([[6.0, 0.0], [6.0, south]]),
        polyline_segments([[12.0, 0.0], [12.0, south]]),
    ])
    pillar = np.array([[18.8 + 0.25 * np.cos(a), 7.9 + 0.25 * np.sin(a)]
                       for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
    furniture = np.concatenate([
        # North-west room: two desks along the back wall, a cabinet.
        box_segments(2.0, 14.1, 1.6, 0.8),
        box_segments(4.6, 14.1, 1.6, 0.8),
        box_segments(6.55, 11.0, 0.5, 1.4),
        # North-middle room: a meeting table in the middle, a cabinet in a corner.
        box_segments(10.25, 11.9, 2.2, 1.2),
        box_segments(13.0, 14.3, 0.8, 0.6),
        # North-east room: a desk at an angle.
        box_segments(17.0, 12.5, 1.6, 0.8, angle=0.4),
        # South-west room: a table, a shelf on the west wall.
        box_segments(3.0, 3.2, 1.4, 1.0),
        box_segments(0.3, 2.0, 0.4, 1.6),
        # South-middle room: two desks.
        box_segments(7.5, 1.0, 1.6, 0.8),
        box_segments(10.5, 3.5, 0.8, 1.6),
        # South-east room: an island of two tables, a cabinet.
        box_segments(15.0, 3.2, 1.6, 1.2),
        box_segments(17.3, 3.0, 1.2, 1.6, angle=-0.3),
        box_segments(19.6, 0.6, 0.6, 0.9),
        # A pillar in the corridor's east end (8-sided).
        polyline_segments(pillar, closed=True),
    ])
    world = make_world(outer, bounds=(-1.0, -1.0, width + 1.0, height + 1.0), groups={"outer": np.arange(4)})
    return concat_worlds(
        world,
        make_world(walls, world.bounds, groups={"walls": np.arange(walls.shape[0])}),
        make_world(furniture, world.bounds, groups={"furniture": np.arange(furniture.shape[0])}),
    )


def office_waypoints() -> np.ndarray:
    """(P, 2) waypoints (m) of the office tour: from the corridor's west end east into the
    north-middle room (round its table), on into the south-east room (round its tables),
    back west along the corridor into the south-west room (round its table), and back to
    the start, so the corridor and the start are revisited."""
    mid = 0.5 * sum(_CORRIDOR_Y)  # the corridor's centre line
    return np.array([
        [1.2, mid],
        # North-middle room, counter-clockwise round the meeting table.
        [10.25, mid], [10.25, 10.0], [12.6, 10.0], [12.6, 13.6], [8.0, 13.6], [8.0, 10.0],
        [10.25, 10.0], [10.25, mid],
        # South-east room, clockwise round the two tables.
        [16.0, mid], [16.0, 5.2], [18.9, 5.2], [18.9, 1.2], [13.0, 1.2], [13.0, 5.2], [16.0, 5.2],
        [16.0, mid],
        # Back west; south-west room, round its table.
        [3.0, mid], [3.0, 5.2], [4.9, 5.2], [4.9, 1.4], [1.4, 1.4], [1.4, 5.2], [3.0, 5.2],
        [3.0, mid], [1.2, mid],
    ])


OFFICE_TURN_RADIUS = 0.6
"""Radius (m) of the office path's rounded corners: tight enough to turn through a
1.2 m door from the corridor's centre line without touching the door frame."""


def office_scenario(
    key: PRNGKeyArray,
    num_scans: int = 500,
    num_beams: int = 180,
    range_max: float = 10.0,
    range_noise_std: float = 0.02,
    speed: float = 1.0,
    motion: MotionParams | None = None,
) -> Scenario:
    """The library's demo dataset: a loop through :func:`office_world`.

    The path (:func:`office_waypoints`, 88 m long) is sampled at ``num_scans`` poses of
    equal arc length (0.18 m apart at the default 500; corners are arcs of radius
    :data:`OFFICE_TURN_RADIUS`), and scans are ``step / speed`` seconds apart. The laser
    has ``num_beams`` beams over 180 degrees, range_max 10 m, and Gaussian range noise
    of 0.02 m (a SICK LMS-like scanner).

    Odometry noise (default ``motion``): srr = 0.05 m/m (5 % of each step's length),
    srt = 0.02 m/rad, str = 0.05 rad/m (about 3 degrees of heading per metre, as a
    single-step std), stt = 0.05 rad/rad (about 18 degrees per revolution turned in one
    step), minimum stds 1 mm and 0.001 rad. Accumulated over the 500 independent steps
    (the per-step stds grow with the step, so these figures hold for ~0.2 m steps) this is
    a heading std of about 17 degrees at the end, and odometry that ends 2.7 m from the
    truth (median over 100 seeds; 0.9 m to 5 m from the 10th to the 90th percentile): a
    map built from odometry alone is visibly wrong, and the loop back to the start must be
    closed by the filter.

    Returns:
      A :class:`Scenario`; metadata holds ``motion_params``, ``range_noise_std``,
      ``step_length``, ``dt``, ``turn_radius``, ``start`` ((2,) m) and ``path_length`` (m).
    """
    if motion is None:
        motion = motion_params(0.05, 0.02, 0.05, 0.05, 0.001, 0.001)
    return _waypoint_scenario(key, "office", office_world(), office_waypoints(), OFFICE_TURN_RADIUS, num_scans,
                              num_beams, range_max, range_noise_std, speed, motion)


def _waypoint_scenario(key, name: str, world: SegmentWorld, waypoints: np.ndarray, turn_radius: float,
                       num_scans: int, num_beams: int, range_max: float, range_noise_std: float, speed: float,
                       motion: MotionParams) -> Scenario:
    """A tour through ``waypoints`` in ``world`` sampled at ``num_scans`` poses of equal arc length
    (corners arcs of ``turn_radius``), scanned by a 180-degree laser of ``num_beams`` beams:
    the one builder of :func:`office_scenario` and :func:`hall_scenario`."""
    if num_scans < 2:
        raise ValueError(f"{name}_scenario: num_scans must be at least 2, got {num_scans}")
    # The step that puts exactly num_scans poses on the path, the last one on its end.
    length = waypoint_path_length(waypoints, turn_radius)
    step = length / (num_scans - 1)
    true_poses = waypoint_path(waypoints, step, step / turn_radius, turn_radius=turn_radius)
    if true_poses.shape[0] != num_scans:  # a guard: these tours have no turns on the spot
        raise AssertionError(f"{name} path has {true_poses.shape[0]} poses, expected {num_scans}")
    sensor = make_sensor(uniform_beams(num_beams, np.pi), range_min=0.05, range_max=range_max)
    dt = step / speed
    log = simulate_log(key, world, true_poses, sensor, motion, range_noise_std, dt=dt, source=f"<{name} scenario>")
    metadata = dict(
        motion_params=motion,
        range_noise_std=float(range_noise_std),
        step_length=step,
        dt=dt,
        turn_radius=turn_radius,
        start=waypoints[0].copy(),
        path_length=length,
    )
    return Scenario(log, world, log.ground_truth, metadata)


# ------------------------------------------------------------------------------- hall

HALL_SIZE = (24.0, 16.0)
"""Outer dimensions (m) of the hall."""
HALL_TURN_RADIUS = 1.0
"""Radius (m) of the hall tour's rounded corners."""


def hall_world() -> SegmentWorld:
    """An open hall, unlike the office's corridors: 24 m x 16 m outer walls, two rows of
    round and square pillars, shelving along the north and south walls with gaps, and an
    alcove in the east wall. Most of a scan is long beams to distant walls and short ones to
    isolated pillars; there is no corridor to constrain the heading.

    Groups: "outer", "pillars", "shelves".
    """
    width, height = HALL_SIZE
    outer = polyline_segments([[0, 0], [width, 0], [width, 6.5], [width + 2.0, 6.5], [width + 2.0, 9.5],
                               [width, 9.5], [width, height], [0, height]], closed=True)
    pillars = []
    for i, x in enumerate((4.0, 9.0, 14.0, 19.0)):
        for y in (5.0, 11.0):
            if (i + (y > 8)) % 2:  # round and square pillars alternate
                ring = [[x + 0.3 * np.cos(a), y + 0.3 * np.sin(a)] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
                pillars.append(polyline_segments(ring, closed=True))
            else:
                pillars.append(box_segments(x, y, 0.6, 0.6))
    pillars = np.concatenate(pillars)
    shelves = np.concatenate([
        box_segments(3.0, 15.4, 4.0, 0.6), box_segments(10.5, 15.4, 5.0, 0.6), box_segments(19.0, 15.4, 3.0, 0.6),
        box_segments(5.5, 0.6, 5.0, 0.6), box_segments(15.0, 0.6, 3.0, 0.6, angle=0.0),
        box_segments(21.0, 2.5, 1.0, 2.0, angle=0.3),
    ])
    world = make_world(outer, bounds=(-1.0, -1.0, width + 3.0, height + 1.0), groups={"outer": np.arange(outer.shape[0])})
    return concat_worlds(
        world,
        make_world(pillars, world.bounds, groups={"pillars": np.arange(pillars.shape[0])}),
        make_world(shelves, world.bounds, groups={"shelves": np.arange(shelves.shape[0])}),
    )


def hall_waypoints() -> np.ndarray:
    """(P, 2) waypoints (m) of the hall tour: a figure of eight between the pillar rows, through
    the middle twice, round the east pillars and the west pillars, back to the start."""
    return np.array([
        [2.0, 8.0], [11.5, 8.0], [11.5, 13.2], [21.5, 13.2], [21.5, 8.0], [16.5, 8.0], [16.5, 2.8],
        [6.5, 2.8], [6.5, 8.0], [11.5, 8.0], [11.5, 2.8], [2.0, 2.8], [2.0, 8.0],
    ])


def hall_scenario(
    key: PRNGKeyArray,
    num_scans: int = 500,
    num_beams: int = 180,
    range_max: float = 10.0,
    range_noise_std: float = 0.02,
    speed: float = 1.0,
    motion: MotionParams | None = None,
) -> Scenario:
    """A second simulated dataset beside the office (:func:`office_scenario`), for checking that
    what holds there is not the office's doing: a figure-of-eight tour of :func:`hall_world`
    (:func:`hall_waypoints`, corners of radius :data:`HALL_TURN_RADIUS`) sampled at
    ``num_scans`` poses of equal arc length, the same laser and, by default, odometry noise of
    the same form with other terms: srr = 0.08 m/m, srt = 0.01 m/rad, str = 0.03 rad/m,
    stt = 0.08 rad/rad, minimum stds 1 mm and 0.001 rad.

    Returns:
      A :class:`Scenario`; metadata as :func:`office_scenario`'s.
    """
    if motion is None:
        motion = motion_params(0.08, 0.01, 0.03, 0.08, 0.001, 0.001)
    return _waypoint_scenario(key, "hall", hall_world(), hall_waypoints(), HALL_TURN_RADIUS, num_scans, num_beams,
                              range_max, range_noise_std, speed, motion)


# -------------------------------------------------------------------------- box world

BOX_SIZE = 1.0
"""Side (m) of both box landmarks."""
BOX1_CENTER = np.array([-6.0, 0.0])
BOX2_CENTER = np.array([4.0, 0.0])
CHECKPOINT_X = np.array([0.0, 0.0])
"""Checkpoint X: 4 m from box 2's centre (3.5 m from its near face), 3.1 m from the hedge."""
TURNAROUND = np.array([-2.5, 0.0])
"""Where excursions from the circle turn back: 3 m from box 1, so box 1 and the hedge are seen."""
_HEDGE_POINTS = np.array([
    # A hedge north-east of box 1: a ragged row of short segments, 3.7 m long.
    [-5.9, 1.45], [-5.4, 1.62], [-4.9, 1.5], [-4.4, 1.7], [-3.9, 1.55], [-3.4, 1.72],
    [-2.9, 1.58], [-2.5, 1.9], [-2.25, 2.3],
])


def box_world() -> SegmentWorld:
    """Open flat ground with two 1 m x 1 m boxes 10 m apart and a hedge near box 1.

    Box 1 is centred at (-6, 0) and turned by 0.3 rad; box 2 is centred at (4, 0). Box 1's
    nearest corner is 8.9 m from box 2, more than twice the 4 m laser range plus a margin,
    so no scan sees both. The hedge (a ragged
    polyline from (-5.9, 1.45) to (-2.25, 2.3)) is visible from checkpoint X (0, 0), but not
    from anywhere within 2.1 m of box 2, so it is out of view while the robot circles box 2.
    No enclosing walls: beams into the open return nothing.

    Groups: "box1", "box2", "hedge".
    """
    box1 = box_segments(*BOX1_CENTER, BOX_SIZE, BOX_SIZE, angle=0.3)
    box2 = box_segments(*BOX2_CENTER, BOX_SIZE, BOX_SIZE)
    hedge = polyline_segments(_HEDGE_POINTS)
    bounds = (-8.0, -4.0, 7.0, 4.0)
    return concat_worlds(
        make_world(box1, bounds, groups={"box1": np.arange(4)}),
        make_world(box2, bounds, groups={"box2": np.arange(4)}),
        make_world(hedge, bounds, groups={"hedge": np.arange(hedge.shape[0])}),
    )


def box_world_path(
    laps: int = 15,
    laps_per_visit: int = 5,
    circle_radius: float = 1.75,
    step_length: float = 0.1,
    max_turn_per_step: float = 0.1,
    clockwise: bool = False,
    circle_center=None,
    checkpoint=None,
    turnaround=None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """The true path of :func:`box_world_scenario` and facts about it.

    The robot starts at X facing box 1 and the hedge, drives to the turnaround point, turns
    on the spot (counter-clockwise), drives back over X and on a line tangent
    to the circle round box 2, circles
    it counter-clockwise ``laps_per_visit`` times, leaves on the tangent through X, turns at
    the turnaround point, comes back over X to the circle, and so on; after the last lap it
    drives over X and stops at the turnaround point facing the hedge.

    ``clockwise`` circles the other way (entering north of the X-circle line, leaving south of
    it); ``circle_center``, ``checkpoint`` and ``turnaround`` ((2,) m; default
    :data:`BOX2_CENTER`, :data:`CHECKPOINT_X`, :data:`TURNAROUND`) move the circle, X and the
    turnaround point (X must lie outside the circle): the box-world family's worlds
    (:mod:`jaxslam.sim.box_family`). The defaults give the box world's path.

    Returns:
      ``(poses, info)``: (T, 3) float64 poses and a dict with ``lap_end_indices`` (index of
      the pose that completes each lap) and ``turn_radius``.
    """
    center = BOX2_CENTER if circle_center is None else np.asarray(circle_center, np.float64)
    checkpoint = CHECKPOINT_X if checkpoint is None else np.asarray(checkpoint, np.float64)
    turnaround = TURNAROUND if turnaround is None else np.asarray(turnaround, np.float64)
    radius = circle_radius
    # Tangent points on the circle for lines through X: with cos(beta) = r / d, the robot
    # enters at polar angle pi + beta (south of the X-box line) heading counter-clockwise
    # along the tangent, and leaves at pi - beta (north of it) on the tangent back to X;
    # clockwise, the mirror image (sign -1).
    sign = -1.0 if clockwise else 1.0
    distance = float(np.hypot(*(center - checkpoint)))
    if not distance > radius:
        raise ValueError(f"box_world_path: the checkpoint lies {distance:.3g} m from the circle's centre, "
                         f"inside the circle of radius {radius:.3g} m")
    toward_x = float(np.arctan2(*(checkpoint - center)[::-1]))
    beta = float(np.arccos(radius / distance))
    enter_angle, leave_angle = toward_x + sign * beta, toward_x - sign * beta
    enter = center + radius * np.array([np.cos(enter_angle), np.sin(enter_angle)])
    leave = center + radius * np.array([np.cos(leave_angle), np.sin(leave_angle)])
    # From entering to leaving, in the direction of travel: whole laps plus the arc between them.
    leave_sweep = float(np.mod(sign * (leave_angle - enter_angle), 2.0 * np.pi))
    turn_radius = step_length / max_turn_per_step

    def line(points, start_heading=None):
        return waypoint_path(points, step_length, max_turn_per_step, start_heading=start_heading,
                             turn_radius=turn_radius)

    def circle(num_laps):
        return circle_path(center, radius, num_laps + leave_sweep / (2 * np.pi), step_length, enter_angle,
                           clockwise=clockwise)

    heading_to_box1 = float(np.arctan2(*(turnaround - checkpoint)[::-1]))
    parts = [line([checkpoint, turnaround, checkpoint, enter], start_heading=heading_to_box1)]
    lap_ends = []
    visits = [laps_per_visit] * (laps // laps_per_visit) + ([laps % laps_per_visit] if laps % laps_per_visit else [])
    for v, num_laps in enumerate(visits):
        offset = sum(len(p) - 1 for p in parts)  # index of the circle's first pose in the joined path
        loop = circle(num_laps)
        per_lap = (loop.shape[0] - 1) * 2 * np.pi / (2 * np.pi * num_laps + leave_sweep)
        lap_ends += [offset + int(round(per_lap * (k + 1))) for k in range(num_laps)]
        parts.append(loop)
        last = v + 1 == len(visits)
        out = [leave, checkpoint, turnaround] + ([] if last else [checkpoint, enter])
        parts.append(line(out, start_heading=loop[-1, 2]))
    poses = concat_paths(*parts, atol=1e-5)
    return poses, dict(lap_end_indices=np.array(lap_ends, dtype=np.int64), turn_radius=turn_radius)


X_TOLERANCE = 0.3
"""Radius (m) round checkpoint X within which the path counts as passing over it."""


BOX_WORLD_MOTION = motion_params(0.05, 0.02, 0.05, 0.1, 0.001, 0.002)
"""The box world's odometry noise per 0.1 m step (see :func:`box_world_scenario` for why)."""


def box_world_scenario(
    key: PRNGKeyArray,
    laps: int = 15,
    laps_per_visit: int = 5,
    circle_radius: float = 1.75,
    step_length: float = 0.1,
    max_turn_per_step: float = 0.1,
    num_beams: int = 180,
    range_max: float = 4.0,
    range_noise_std: float = 0.02,
    dt: float = 0.1,
    motion: MotionParams | None = None,
    field_of_view: float = np.pi,
    world: SegmentWorld | None = None,
    clockwise: bool = False,
    circle_center=None,
    checkpoint=None,
    turnaround=None,
) -> Scenario:
    """The box world of Grzonka et al. (Figs. 1 and 4), the test case for look-ahead proposals.

    The robot starts at checkpoint X, 4 m from box 2, looks at box 1 and the hedge, drives
    to box 2 and circles it ``laps`` times at ``circle_radius`` (1.75 m: 1.25 m off the
    box's faces), counter-clockwise. After every ``laps_per_visit`` laps it drives out over
    X to the turnaround point 2.5 m beyond, and back to the circle; after the last lap it
    drives over X again and stops at the turnaround point. While circling, only box 2 is in
    view, and a 1 m square seen from one side is a weak constraint: the filter's pose error
    grows, and at X the robot sees the hedge again, mapped at the start: a loop to close.
    With the defaults: 2,351 scans (0.1 m steps, 1 m/s at 10 Hz; U-turns on the spot in
    0.1 rad steps), 229 m.

    The turns at the turnaround point go counter-clockwise, through south: for part of each
    turn, and on the drive back until box 2 is in range, the laser sees nothing, so the
    odometry's heading error of the first U-turn is in box 2's map.

    Laser: ``num_beams`` = 180 beams over ``field_of_view`` = 180 degrees (forward-facing), range_max 4 m,
    Gaussian range noise 0.02 m. We keep the 180-degree field of view of the SICK LMS on
    the paper's Pioneer-class robots: the robot sees the hedge only when it drives toward
    X from the box, which is what makes the return to X a loop closure. Circling box 2
    counter-clockwise keeps it on the robot's left, in view at bearings of 70 to 90 degrees.

    Odometry noise (default ``motion``, per 0.1 m step, independent between steps):
    srr = 0.05 m/m (5 % translation error), srt = 0.02 m/rad, str = 0.05 rad/m (rotation
    drift per metre driven), stt = 0.1 rad/rad, minimum stds 1 mm and 0.002 rad. The
    per-step heading stds add up (GMapping's model sums the terms), so per lap (11 m and
    2 pi turned in 110 steps) odometry accumulates a heading std of about 7.6 degrees and a
    position std of about 0.3 m: the noisy end of a wheeled robot's odometry on flat ground.
    (Half the proportional terms give 4.4 degrees a lap; how the LP's success rate depends on
    the scale: ``experiments/box_world.py --table noise`` and docs/results.md.) Over the
    whole run (measured on 100 seeds) the heading std reaches about 40 degrees, and at the
    last passage over X odometry is off by 2 m (median; 0.65 m to 4.5 m from the 10th to the
    90th percentile). So the filter must close the loop at X:
    the point of the paper is that the odometry (OP) and scan-matching (SMP) proposals
    lose the right hypothesis during the laps, and the look-ahead proposal (LP) keeps it.
    These stds scale with the step: with longer steps (fewer, larger independent errors)
    the same coefficients give more drift.

    ``world`` (a :class:`SegmentWorld`; default :func:`box_world`), ``clockwise``,
    ``circle_center``, ``checkpoint`` and ``turnaround`` (as :func:`box_world_path`'s) give
    another world of the same plan: the box-world family (:mod:`jaxslam.sim.box_family`).

    Returns:
      A :class:`Scenario`. metadata: ``checkpoint_x`` ((2,) m), ``x_passages`` (indices of
      the scans at which the true path passes over X, within ``x_tolerance`` = 0.3 m: the
      start, out and back after every visit but the last, and the end), ``x_tolerance``,
      ``turnaround`` ((2,) m), ``box1_center`` (the default world's only), ``box2_center``
      (the circle's centre), ``circle_radius``, ``clockwise``,
      ``lap_end_indices`` (the scan completing each lap), ``laps``, ``turn_radius``,
      ``motion_params``, ``range_noise_std``, ``step_length``, ``dt``.
    """
    if motion is None:
        motion = BOX_WORLD_MOTION
    default_world = world is None
    world = box_world() if default_world else world
    center = BOX2_CENTER if circle_center is None else np.asarray(circle_center, np.float64)
    checkpoint = CHECKPOINT_X if checkpoint is None else np.asarray(checkpoint, np.float64)
    turnaround = TURNAROUND if turnaround is None else np.asarray(turnaround, np.float64)
    true_poses, info = box_world_path(laps, laps_per_visit, circle_radius, step_length, max_turn_per_step,
                                      clockwise, center, checkpoint, turnaround)
    sensor = make_sensor(uniform_beams(num_beams, field_of_view), range_min=0.05, range_max=range_max)
    log = simulate_log(key, world, true_poses, sensor, motion, range_noise_std, dt=dt, source="<box world scenario>")
    metadata = dict(
        checkpoint_x=checkpoint.copy(),
        turnaround=turnaround.copy(),
        x_passages=passage_indices(true_poses, checkpoint, X_TOLERANCE),
        x_tolerance=X_TOLERANCE,
        **({"box1_center": BOX1_CENTER.copy()} if default_world else {}),
        box2_center=center.copy(),
        clockwise=bool(clockwise),
        circle_radius=circle_radius,
        lap_end_indices=info["lap_end_indices"],
        laps=laps,
        turn_radius=info["turn_radius"],
        motion_params=motion,
        range_noise_std=float(range_noise_std),
        step_length=step_length,
        dt=dt,
    )
    return Scenario(log, world, log.ground_truth, metadata)


# ------------------------------------------------------------------ symmetric junction

JUNCTION_LANE_WIDTH = 1.6
"""Width (m) of each of the two lanes the corridor forks into (the corridor is twice as wide)."""
JUNCTION_STEM = (-5.0, 0.0)
"""South end and fork (y, m) of the corridor's undivided stem."""
JUNCTION_LANE_END = 4.0
"""North end (y, m) of both lanes: one end wall across the corridor."""
JUNCTION_MOTION = motion_params(0.1, 0.05, 0.3, 0.1, 0.002, 0.002)
"""Odometry noise of :func:`symmetric_junction_scenario`: srr = 0.1 m/m, srt = 0.05 m/rad,
str = 0.3 rad/m (a heading std of about 8 degrees per metre driven at 0.1 m steps), stt = 0.1
rad/rad, minimum stds 2 mm and 0.002 rad: by the lanes the odometry's sideways error is some
tenths of a metre, comparable with the 1.6 m between the two lanes' centre lines."""


def symmetric_junction_world(lane_width: float = JUNCTION_LANE_WIDTH) -> SegmentWorld:
    """A corridor ``2 * lane_width`` wide running north from y = -5 m, split at y = 0 by a
    thin wall along its centre line (x = 0) into two identical lanes that end at one wall at
    y = 4 m: a fork whose two branches look the same to a forward-facing laser.

    Seen from inside a lane (y > 0, heading north), the laser's 180 degrees hit only that
    lane's two walls and the end wall, so the scan at ``(x, y, theta)`` in the east lane equals
    the scan at ``(x - lane_width, y, theta)`` in the west lane: the two poses cannot be told
    apart by the scan alone.

    Groups: "walls" (the corridor's outer walls and end walls), "divider" (the centre wall).
    """
    w = float(lane_width)
    if not w > 0:
        raise ValueError(f"symmetric_junction_world: lane_width must be positive, got {lane_width!r}")
    south, fork = JUNCTION_STEM
    north = JUNCTION_LANE_END
    walls = polyline_segments([[-w, south], [w, south], [w, north], [-w, north]], closed=True)
    divider = polyline_segments([[0.0, fork], [0.0, north]])
    bounds = (-w - 1.0, south - 1.0, w + 1.0, north + 1.0)
    return concat_worlds(
        make_world(walls, bounds, groups={"walls": np.arange(walls.shape[0])}),
        make_world(divider, bounds, groups={"divider": np.arange(divider.shape[0])}),
    )


def symmetric_junction_scenario(
    key: PRNGKeyArray,
    step_length: float = 0.1,
    num_beams: int = 181,
    range_max: float = 10.0,
    range_noise_std: float = 0.02,
    dt: float = 0.1,
    motion: MotionParams | None = None,
    lane_width: float = JUNCTION_LANE_WIDTH,
) -> Scenario:
    """A drive through a symmetric junction (:func:`symmetric_junction_world`): up the
    corridor's centre line from y = -4.5 m, a swerve to the east lane's centre line before the
    fork (y = -2 .. -0.5 m, corners rounded at 0.5 m), and north in the east lane to y = 3 m,
    1 m short of the end wall (78 scans at the default 0.1 m steps).

    Only the swerve, seen against the tip of the dividing wall, tells the lanes apart: from
    inside a lane the scan at the true pose equals the scan at the *mirror pose* one lane
    width west (``metadata["mirror_offset"]``), and the odometry (default
    :data:`JUNCTION_MOTION`) is too noisy to tell them apart either. A filter must keep the
    true mode from the swerve on; the fraction of its particles near the true pose at the
    scans in the lane (``metadata["ambiguous_scans"]``) measures whether it does
    (``experiments/faults.py --ambiguous``).

    Laser: ``num_beams`` beams over 180 degrees, range_max 10 m (the end wall is in view from
    the start, so the position along the corridor is observed), Gaussian range noise.

    Returns:
      A :class:`Scenario`. metadata: ``lane_width``, ``mirror_offset`` ((3,) [dx, dy, dtheta]
      added to a pose in the east lane to get the pose in the west lane that sees the same
      scan), ``ambiguous_scans`` (indices of the scans whose true pose lies 0.3 m or more
      into the east lane, heading north), ``motion_params``, ``range_noise_std``,
      ``step_length``, ``dt``.
    """
    if motion is None:
        motion = JUNCTION_MOTION
    w = float(lane_width)
    world = symmetric_junction_world(w)
    waypoints = np.array([[0.0, -4.5], [0.0, -2.0], [0.5 * w, -0.5], [0.5 * w, 3.0]])
    true_poses = waypoint_path(waypoints, step_length, step_length / 0.5, turn_radius=0.5)
    sensor = make_sensor(uniform_beams(num_beams, np.pi), range_min=0.05, range_max=range_max)
    log = simulate_log(key, world, true_poses, sensor, motion, range_noise_std, dt=dt,
                       source="<symmetric junction scenario>")
    in_lane = (true_poses[:, 1] >= JUNCTION_STEM[1] + 0.3) & (np.abs(true_poses[:, 0] - 0.5 * w) < 1e-6)
    metadata = dict(
        lane_width=w,
        mirror_offset=np.array([-w, 0.0, 0.0]),
        ambiguous_scans=np.nonzero(in_lane)[0],
        motion_params=motion,
        range_noise_std=float(range_noise_std),
        step_length=float(step_length),
        dt=float(dt),
    )
    return Scenario(log, world, log.ground_truth, metadata)
