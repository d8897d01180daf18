"""Ready-made simulated datasets: worlds, true paths and logs.

* :func:`office_scenario`: the library's demo. A 20 m x 15 m office, a loop through
  the corridor and three of its six rooms, a 180-beam laser.
* :func:`~jaxslam.sim.box_world.box_world_scenario` (in :mod:`jaxslam.sim.box_world`): the box world of Grzonka, Plagemann, Grisetti and
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
from jaxslam.sim.paths import waypoint_path, waypoint_path_length
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
