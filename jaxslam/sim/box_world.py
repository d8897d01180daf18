"""The box world of Grzonka, Plagemann, Grisetti and Burgard, "Look-ahead Proposals for Robust
Grid-based SLAM with Rao-Blackwellized Particle Filters" (Figs. 1 and 4): 15 laps around a lone
box with a 4 m laser, then back to a checkpoint X whose surroundings were mapped at the start.

:func:`box_world` is the world, :func:`box_world_path` the true path and
:func:`box_world_scenario` the simulated dataset (a :class:`~jaxslam.sim.scenarios.Scenario`);
the box-world family (:mod:`jaxslam.sim.box_family`) varies them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from jaxtyping import PRNGKeyArray

from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.motion import MotionParams, motion_params
from jaxslam.sim.paths import circle_path, concat_paths, passage_indices, waypoint_path
from jaxslam.sim.scenarios import Scenario
from jaxslam.sim.simulate import simulate_log
from jaxslam.sim.world import SegmentWorld, box_segments, concat_worlds, make_world, polyline_segments


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
    center, checkpoint, turnaround = _plan_points(circle_center, checkpoint, turnaround)
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
    motion = BOX_WORLD_MOTION if motion is None else motion
    center, checkpoint, turnaround = _plan_points(circle_center, checkpoint, turnaround)
    true_poses, info = box_world_path(laps, laps_per_visit, circle_radius, step_length, max_turn_per_step,
                                      clockwise, center, checkpoint, turnaround)
    metadata = _box_world_metadata(true_poses, info, center, checkpoint, turnaround, world is None, clockwise,
                                   circle_radius, laps, motion, range_noise_std, step_length, dt)
    world = box_world() if world is None else world
    sensor = make_sensor(uniform_beams(num_beams, field_of_view), range_min=0.05, range_max=range_max)
    log = simulate_log(key, world, true_poses, sensor, motion, range_noise_std, dt=dt, source="<box world scenario>")
    return Scenario(log, world, log.ground_truth, metadata)


def _plan_points(circle_center, checkpoint, turnaround) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The circle's centre, checkpoint X and the turnaround point, (2,) float64 m each: as given,
    or the box world's (:data:`BOX2_CENTER`, :data:`CHECKPOINT_X`, :data:`TURNAROUND`) for None."""
    center = BOX2_CENTER if circle_center is None else np.asarray(circle_center, np.float64)
    checkpoint = CHECKPOINT_X if checkpoint is None else np.asarray(checkpoint, np.float64)
    turnaround = TURNAROUND if turnaround is None else np.asarray(turnaround, np.float64)
    return center, checkpoint, turnaround


def _box_world_metadata(true_poses: np.ndarray, info: dict, center: np.ndarray, checkpoint: np.ndarray,
                        turnaround: np.ndarray, default_world: bool, clockwise: bool, circle_radius: float,
                        laps: int, motion: MotionParams, range_noise_std: float, step_length: float,
                        dt: float) -> dict[str, Any]:
    """:func:`box_world_scenario`'s metadata (see its Returns) from its (T, 3) true poses (m, m, rad),
    :func:`box_world_path`'s ``info``, the (2,) m plan points and the simulation's settings;
    ``default_world``: whether the world is :func:`box_world` (box 1 is that world's only)."""
    return dict(
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
