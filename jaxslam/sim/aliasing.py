"""A world built to alias, for the loop closure (:mod:`jaxslam.graph`): two identical rooms.

:func:`twin_rooms_world`: a corridor 2 m wide running east, and north of it two rooms that are
the same to the centimetre (6 m x 5 m, a 1.2 m door in the same place, the same furniture in the
same places), 10 m apart. The corridor's walls have no feature between the doors, so a scan
taken inside room B is the scan taken at the same place in room A, shifted by
:data:`TWIN_OFFSET`: a loop search that matches B's scans against A's submaps (or A's against
B's) finds a perfect match at the wrong place. :func:`twin_rooms_scenario` tours room A, then
room B, then room A again (the true loop), and back to the start.

:func:`twin_corridors_world`: three parallel corridors 36 m long joined at both ends, of which
the south and the north one are the same to the centimetre (niches at the same irregular
places), :data:`CORRIDOR_OFFSET` apart. Inside either twin a scan is the other's, moved by the
offset; along one corridor the niches' spacing never repeats, so a match is unique within it.
:func:`twin_corridors_scenario` drives both twins eastward (back west along the middle one), twice:
every true loop of the second lap has its twin in the other corridor.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import PRNGKeyArray

from jaxslam.motion import MotionParams, motion_params
from jaxslam.sim.scenarios import Scenario, _waypoint_scenario
from jaxslam.sim.world import SegmentWorld, box_segments, concat_worlds, make_world, polyline_segments, wall_segments

TWIN_OFFSET = np.array([10.0, 0.0, 0.0])
"""Room B is room A moved by this (m, m, rad)."""
ROOM_A_X = 2.0
"""West wall of room A (m); its east wall is 6 m further."""
CORRIDOR_Y = (0.0, 2.0)
"""The corridor's south and north walls (m); the rooms lie north of it, up to y = 7 m."""
_DOOR_X = 3.0  # a door's centre, from its room's west wall
_DOOR_WIDTH = 1.2


def _room_furniture(x0: float) -> np.ndarray:
    """A room's furniture, the room's west wall at ``x0``: a table, a cabinet, a desk at an angle."""
    return np.concatenate([
        box_segments(x0 + 1.3, 5.9, 1.4, 0.8),
        box_segments(x0 + 5.5, 6.4, 0.6, 0.8),
        box_segments(x0 + 3.8, 5.7, 1.2, 0.6, angle=0.5),
    ])


def twin_rooms_world() -> SegmentWorld:
    """The corridor and the two identical rooms (see the module docstring).

    Groups: "walls", "furniture"."""
    south, north = CORRIDOR_Y
    xa, xb = ROOM_A_X, ROOM_A_X + TWIN_OFFSET[0]
    west, east = -2.0, xb + 10.0
    walls = [polyline_segments([[west, north], [west, south], [east, south], [east, north]]),
             wall_segments([west, north], [east, north], [(x + _DOOR_X, _DOOR_WIDTH) for x in (xa, xb)])]
    furniture = []
    for x0 in (xa, xb):
        walls.append(polyline_segments([[x0, north], [x0, north + 5.0], [x0 + 6.0, north + 5.0], [x0 + 6.0, north]]))
        furniture.append(_room_furniture(x0))
    walls, furniture = np.concatenate(walls), np.concatenate(furniture)
    bounds = (west - 1.0, south - 1.0, east + 1.0, north + 6.0)
    return concat_worlds(make_world(walls, bounds, groups={"walls": np.arange(walls.shape[0])}),
                         make_world(furniture, bounds, groups={"furniture": np.arange(furniture.shape[0])}))


def _room_tour(x0: float) -> list[list[float]]:
    """Waypoints into a room through its door, once round its table and desk, and out."""
    door, mid = x0 + _DOOR_X, 0.5 * sum(CORRIDOR_Y)
    return [[door, mid], [door, 3.0], [x0 + 5.2, 3.0], [x0 + 5.2, 4.5], [x0 + 0.8, 4.5], [x0 + 0.8, 3.0],
            [door, 3.0], [door, mid]]


def twin_rooms_waypoints() -> np.ndarray:
    """(P, 2) waypoints (m): from the corridor's west end into room A and round it, along the
    corridor into room B and round it, back into room A and round it again, back to the start."""
    mid = 0.5 * sum(CORRIDOR_Y)
    xa, xb = ROOM_A_X, ROOM_A_X + TWIN_OFFSET[0]
    points = [[-1.0, mid]] + _room_tour(xa) + _room_tour(xb) + _room_tour(xa) + [[-1.0, mid]]
    keep = [points[0]] + [p for prev, p in zip(points, points[1:]) if p != prev]  # no repeated waypoint
    return np.array(keep)


def twin_rooms_scenario(key: PRNGKeyArray, num_scans: int = 600, num_beams: int = 180, range_max: float = 10.0,
                        range_noise_std: float = 0.02, speed: float = 1.0,
                        motion: MotionParams | None = None) -> Scenario:
    """The tour of :func:`twin_rooms_waypoints` in :func:`twin_rooms_world`, sampled at
    ``num_scans`` poses of equal arc length (corners of radius 0.5 m), a 180-degree laser,
    and the office's odometry noise unless ``motion`` is given.

    Returns:
      A :class:`~jaxslam.sim.scenarios.Scenario`; metadata as the office's plus
      ``twin_offset`` ((3,) :data:`TWIN_OFFSET`).
    """
    if motion is None:
        motion = motion_params(0.05, 0.02, 0.05, 0.05, 0.001, 0.001)
    scenario = _waypoint_scenario(key, "twin_rooms", twin_rooms_world(), twin_rooms_waypoints(), 0.5, num_scans,
                                  num_beams, range_max, range_noise_std, speed, motion)
    scenario.metadata["twin_offset"] = TWIN_OFFSET.copy()
    return scenario


CORRIDOR_OFFSET = np.array([0.0, 10.0, 0.0])
"""The north corridor is the south one moved by this (m, m, rad)."""
CORRIDOR_LENGTH = 36.0
"""Length of each corridor (m), from x = 0; the end connectors lie beyond."""
_CORRIDOR_WIDTH = 2.4
_TWIN_NICHES = (3.0, 7.5, 10.0, 16.0, 21.5, 24.0, 30.0, 33.5)  # niche centres along a twin (m): no spacing repeats
_MIDDLE_NICHES = (5.0, 12.5, 14.5, 19.0, 27.0, 31.5)  # the middle corridor's, on its south wall
_NICHE_WIDTH, _NICHE_DEPTH = 1.0, 0.6


def _corridor(y0: float, niches, north: bool) -> list[np.ndarray]:
    """One corridor, its south wall at ``y0``, with a niche at each of ``niches`` (m along it) in
    its north wall (``north``) or its south wall; its ends open onto the connectors."""
    walls = {False: y0, True: y0 + _CORRIDOR_WIDTH}
    depth = _NICHE_DEPTH if north else -_NICHE_DEPTH
    parts = [wall_segments([0.0, walls[not north]], [CORRIDOR_LENGTH, walls[not north]]),
             wall_segments([0.0, walls[north]], [CORRIDOR_LENGTH, walls[north]], [(x, _NICHE_WIDTH) for x in niches])]
    for x in niches:
        left, right, y = x - 0.5 * _NICHE_WIDTH, x + 0.5 * _NICHE_WIDTH, walls[north]
        parts.append(polyline_segments([[left, y], [left, y + depth], [right, y + depth], [right, y]]))
    return parts


def twin_corridors_world() -> SegmentWorld:
    """The three corridors and the two connectors that join their ends (see the module
    docstring). The south twin's ends open north only, the north twin's south only, so the
    junctions tell the twins apart.

    Groups: "walls"."""
    w, step = _CORRIDOR_WIDTH, float(CORRIDOR_OFFSET[1]) / 2
    middle, north = step, 2 * step
    parts = _corridor(0.0, _TWIN_NICHES, True) + _corridor(middle, _MIDDLE_NICHES, False)
    parts += _corridor(north, _TWIN_NICHES, True)
    for x_inner, x_outer in ((0.0, -w), (CORRIDOR_LENGTH, CORRIDOR_LENGTH + w)):
        parts.append(polyline_segments([[x_inner, 0.0], [x_outer, 0.0], [x_outer, north + w], [x_inner, north + w]]))
        parts.append(polyline_segments([[x_inner, w], [x_inner, middle]]))
        parts.append(polyline_segments([[x_inner, middle + w], [x_inner, north]]))
    walls = np.concatenate(parts)
    bounds = (-w - 1.0, -_NICHE_DEPTH - 1.0, CORRIDOR_LENGTH + w + 1.0, north + w + _NICHE_DEPTH + 1.0)
    return make_world(walls, bounds, groups={"walls": np.arange(walls.shape[0])})


def twin_corridors_waypoints(laps: int = 2) -> np.ndarray:
    """(P, 2) waypoints (m): ``laps`` times east along the south twin, west along the middle
    corridor, east along the north twin, west along the middle again, then back to the start."""
    w, step = _CORRIDOR_WIDTH, float(CORRIDOR_OFFSET[1]) / 2
    south, middle, north = 0.5 * w, step + 0.5 * w, 2 * step + 0.5 * w
    west, east = -0.5 * w, CORRIDOR_LENGTH + 0.5 * w
    lap = [[east, south], [east, middle], [west, middle], [west, north], [east, north], [east, middle],
           [west, middle], [west, south]]
    return np.array([[1.0, south]] + lap * laps + [[1.0, south]])


def twin_corridors_scenario(key: PRNGKeyArray, num_scans: int = 1000, num_beams: int = 180, range_max: float = 10.0,
                            range_noise_std: float = 0.02, speed: float = 1.0,
                            motion: MotionParams | None = None) -> Scenario:
    """Two laps of :func:`twin_corridors_waypoints` in :func:`twin_corridors_world` (about 340 m),
    sampled as :func:`twin_rooms_scenario` samples its tour (corners of radius 0.5 m).

    Returns:
      A :class:`~jaxslam.sim.scenarios.Scenario`; metadata as the office's plus
      ``twin_offset`` ((3,) :data:`CORRIDOR_OFFSET`).
    """
    if motion is None:
        motion = motion_params(0.05, 0.02, 0.05, 0.05, 0.001, 0.001)
    scenario = _waypoint_scenario(key, "twin_corridors", twin_corridors_world(), twin_corridors_waypoints(), 0.5,
                                  num_scans, num_beams, range_max, range_noise_std, speed, motion)
    scenario.metadata["twin_offset"] = CORRIDOR_OFFSET.copy()
    return scenario
