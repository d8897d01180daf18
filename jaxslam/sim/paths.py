"""Ground-truth robot paths: (T, 3) poses [x, y, theta] (m, m, rad), one per scan.

The robot drives at a fixed speed (``step_length`` metres of arc per scan) and
turns at most ``max_turn_per_step`` radians per scan. Corners are rounded with
circular arcs where they fit, and turned on the spot where they do not (a
U-turn, say). Heading always follows the direction of travel. Paths are built
once, in NumPy (float64).
"""

from __future__ import annotations

import numpy as np

from jaxslam.geometry import wrap_angle_np
from jaxslam.metrics import checkpoint_passages

_TINY = 1e-9


class _Piece:
    """A line or an arc the robot drives along, parameterised by arc length."""

    def __init__(self, start, heading, length, curvature):
        self.start = np.asarray(start, np.float64)
        self.heading = float(heading)
        self.length = float(length)
        self.curvature = float(curvature)  # 1/radius, signed (> 0 turns left); 0 for a line

    def poses(self, s: np.ndarray) -> np.ndarray:
        """(S, 3) poses at arc lengths ``s`` (m) from the piece's start."""
        k = self.curvature
        theta = self.heading + k * s
        if abs(k) < _TINY:
            x = self.start[0] + s * np.cos(self.heading)
            y = self.start[1] + s * np.sin(self.heading)
        else:
            x = self.start[0] + (np.sin(theta) - np.sin(self.heading)) / k
            y = self.start[1] - (np.cos(theta) - np.cos(self.heading)) / k
        return np.stack([x, y, theta], axis=-1)


def _drive(pieces: list[_Piece], step_length: float) -> np.ndarray:
    """Poses every ``step_length`` metres of arc along consecutive pieces, excluding the start
    and including the end (the last step is shorter when the length is not a whole number of
    steps: the robot arrives and stops)."""
    lengths = np.array([p.length for p in pieces])
    total = float(lengths.sum())
    if total < _TINY:
        return np.zeros((0, 3))
    count = int(np.floor(total / step_length + 1e-9))
    s = step_length * np.arange(1, count + 1)
    if total - (s[-1] if count else 0.0) > 1e-9 * max(1.0, total):
        s = np.append(s, total)
    s = np.minimum(s, total)
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    which = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(pieces) - 1)
    out = np.empty((s.size, 3))
    for i, piece in enumerate(pieces):  # a handful of pieces; the samples are vectorised
        sel = which == i
        out[sel] = piece.poses(s[sel] - starts[i])
    return out


def _spin(position, heading_from: float, heading_to: float, max_turn_per_step: float) -> np.ndarray:
    """Poses turning on the spot in equal increments of at most ``max_turn_per_step``,
    excluding the start; the shorter way round."""
    delta = float(wrap_angle_np(heading_to - heading_from))
    count = int(np.ceil(abs(delta) / max_turn_per_step - 1e-9))
    if count == 0:
        return np.zeros((0, 3))
    theta = heading_from + delta * np.arange(1, count + 1) / count
    return np.stack([np.full(count, position[0]), np.full(count, position[1]), theta], axis=-1)


def waypoint_path(
    waypoints,
    step_length: float,
    max_turn_per_step: float,
    start_heading: float | None = None,
    turn_radius: float | None = None,
) -> np.ndarray:
    """Drive through ``waypoints`` along straight lines at constant speed.

    A corner is rounded with a circular arc of radius ``turn_radius`` (tangent to both
    lines, so the robot passes inside the corner and not over the waypoint) when the arc
    fits in the first half of the next line and the last half of the previous one (the
    whole line at the path's ends). Otherwise (a U-turn, a short leg) the robot drives to
    the waypoint, stops and turns on the spot. Heading follows the direction of travel.

    Args:
      waypoints: (P, 2) points (m), P >= 2; consecutive duplicates are dropped.
      step_length: arc length (m) driven per scan.
      max_turn_per_step: largest heading change per scan (rad), on arcs and on the spot.
      start_heading: initial heading (rad); when it differs from the first line's
        direction, the robot first turns on the spot. Default: the first line's direction.
      turn_radius: radius (m) of the corner arcs; default and minimum
        ``step_length / max_turn_per_step`` (tighter arcs would turn too fast).

    Returns:
      (T, 3) float64 poses. Every step drives exactly ``step_length`` of arc (chords on arcs
      are a little shorter), except the last step before a stop (a turn on the spot, or the
      end, which is exactly the last waypoint), which is shorter; turns on the spot keep the
      position fixed.
    """
    if step_length <= 0 or max_turn_per_step <= 0:
        raise ValueError("waypoint_path: step_length and max_turn_per_step must be positive")
    min_radius = step_length / max_turn_per_step
    radius = min_radius if turn_radius is None else float(turn_radius)
    if radius < min_radius * (1 - 1e-9):
        raise ValueError(f"waypoint_path: turn_radius {radius} is below step_length / max_turn_per_step "
                         f"= {min_radius}")
    points, legs = _plan(waypoints, radius)
    first_direction = legs[0][1][0].heading if legs[0][0] == "drive" else legs[0][2]
    heading = first_direction if start_heading is None else float(start_heading)
    poses = [np.array([[points[0, 0], points[0, 1], heading]])]
    if start_heading is not None:
        poses.append(_spin(points[0], heading, first_direction, max_turn_per_step))
    for leg in legs:
        if leg[0] == "drive":
            poses.append(_drive(leg[1], step_length))
        else:
            poses.append(_spin(*leg[1:], max_turn_per_step))
    out = np.concatenate(poses, axis=0)
    out[:, 2] = wrap_angle_np(out[:, 2])
    return out


def waypoint_path_length(waypoints, turn_radius: float) -> float:
    """Arc length (m) that :func:`waypoint_path` drives through ``waypoints`` with corner
    arcs of ``turn_radius`` (m): divide it by the number of steps for a path that ends
    exactly on a whole step."""
    _, legs = _plan(waypoints, float(turn_radius))
    return float(sum(piece.length for leg in legs if leg[0] == "drive" for piece in leg[1]))


def _plan(waypoints, radius: float):
    """The lines, corner arcs and turns on the spot through ``waypoints``.

    Returns ``(points, legs)``: the (P, 2) waypoints without consecutive duplicates, and a
    list of legs, each ``("drive", [pieces])`` or ``("spin", position, heading_from,
    heading_to)``.
    """
    points = np.asarray(waypoints, np.float64).reshape(-1, 2)
    keep = np.concatenate([[True], np.hypot(*np.diff(points, axis=0).T) > _TINY])
    points = points[keep]
    if points.shape[0] < 2:
        raise ValueError("waypoint_path: need at least 2 distinct waypoints")
    vectors = np.diff(points, axis=0)
    lengths = np.hypot(vectors[:, 0], vectors[:, 1])
    directions = np.arctan2(vectors[:, 1], vectors[:, 0])
    num_lines = lengths.size
    # Tangent length of each interior corner's arc, or None to turn on the spot.
    tangents: list[float | None] = [None] * (num_lines + 1)
    turns = np.zeros(num_lines + 1)
    for i in range(1, num_lines):
        turns[i] = float(wrap_angle_np(directions[i] - directions[i - 1]))
        tangent = radius * np.tan(0.5 * abs(turns[i]))
        # An arc may use half of a line (the other half may serve the line's other corner),
        # or the whole first or last line.
        room_before = lengths[i - 1] * (1.0 if i == 1 else 0.5)
        room_after = lengths[i] * (1.0 if i == num_lines - 1 else 0.5)
        if tangent <= min(room_before, room_after):
            tangents[i] = tangent

    legs: list[tuple] = []
    pieces: list[_Piece] = []
    for i in range(num_lines):
        unit = np.array([np.cos(directions[i]), np.sin(directions[i])])
        begin = tangents[i] if (i > 0 and tangents[i] is not None) else 0.0
        end_cut = tangents[i + 1] if (i + 1 < num_lines and tangents[i + 1] is not None) else 0.0
        pieces.append(_Piece(points[i] + begin * unit, directions[i], lengths[i] - begin - end_cut, 0.0))
        if i + 1 == num_lines:
            break
        if tangents[i + 1] is None:
            # Stop at the corner and turn on the spot.
            legs.append(("drive", pieces))
            legs.append(("spin", points[i + 1], directions[i], directions[i + 1]))
            pieces = []
        elif tangents[i + 1] > 0:
            turn = turns[i + 1]
            pieces.append(_Piece(points[i + 1] - end_cut * unit, directions[i], radius * abs(turn),
                                 np.sign(turn) / radius))
    legs.append(("drive", pieces))
    return points, legs


def circle_path(
    center,
    radius: float,
    laps: float,
    step_length: float,
    start_angle: float,
    clockwise: bool = False,
) -> np.ndarray:
    """Drive ``laps`` times around a circle, heading along the tangent.

    Args:
      center: (2,) centre (m).
      radius: radius (m).
      laps: number of laps (may be fractional).
      step_length: nominal arc length per scan (m); adjusted by at most half a step over the
        whole path so the path ends exactly after ``laps`` laps.
      start_angle: polar angle (rad) of the start point seen from the centre.
      clockwise: direction of travel (default counter-clockwise: the centre on the left).

    Returns:
      (N + 1, 3) float64 poses, first and last included; all steps have the same chord.
    """
    center = np.asarray(center, np.float64)
    sweep = 2.0 * np.pi * laps
    count = max(1, int(round(sweep * radius / step_length)))
    sign = -1.0 if clockwise else 1.0
    alpha = start_angle + sign * sweep * np.arange(count + 1) / count
    x = center[0] + radius * np.cos(alpha)
    y = center[1] + radius * np.sin(alpha)
    return np.stack([x, y, wrap_angle_np(alpha + sign * 0.5 * np.pi)], axis=-1)


def concat_paths(*paths, atol: float = 1e-6) -> np.ndarray:
    """Join paths that continue each other: each path must start where the previous one
    ended (position and heading within ``atol``); the duplicated joint pose is dropped."""
    out = [np.asarray(paths[0], np.float64).reshape(-1, 3)]
    for path in paths[1:]:
        path = np.asarray(path, np.float64).reshape(-1, 3)
        last, first = out[-1][-1], path[0]
        gap = np.hypot(*(first[:2] - last[:2]))
        turn = abs(float(wrap_angle_np(first[2] - last[2])))
        if gap > atol or turn > atol:
            raise ValueError(f"concat_paths: a path starts {gap:.3g} m and {turn:.3g} rad away from where "
                             "the previous one ended")
        out.append(path[1:])
    return np.concatenate(out, axis=0)


def passage_indices(poses, point, tolerance: float) -> np.ndarray:
    """Indices of the poses at which a path passes over ``point`` (closest pose of each run of
    poses within ``tolerance`` metres); the rule of :func:`jaxslam.metrics.checkpoint_passages`."""
    return checkpoint_passages(poses, point, tolerance)

