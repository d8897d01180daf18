"""A family of box worlds, one per integer seed: the paper's claim over worlds, not one world.

:func:`~jaxslam.sim.box_world.box_world_scenario` is one world, and the library's defaults were
tuned on it. This module draws worlds of the same plan (Grzonka et al., Figs. 1 and 4): a robot
starts at a checkpoint X whose surroundings it maps, drives to a box, circles it for laps with
nothing else in view, drives back over X now and then, and at the end comes back to X: a loop
to close. What varies, drawn by :func:`draw_world` from ``np.random.default_rng(seed)``:

* one or two boxes of side 0.5-1.5 m, each at any angle, inside the circle (two boxes side by
  side, a gap between them, the pair centred on the circle's centre);
* the landmarks round X, 1 to 3 of them, each of a random kind: a *hedge* (short line segments
  in a ragged row), a *fence* (a broken line) or *barrels* (a few small polygons approximating
  circles);
* the circle's radius (1.5-2.5 m), the laps (8-15), the direction (clockwise or
  counter-clockwise), the laps between visits to X (3-5), how far X lies from the circle
  (2.5-3.5 m) and how far beyond X the robot turns back (1.5-2.5 m);
* the laser's range (3-5 m) and the odometry's noise (0.5 to 1.5 times the default robot's
  proportional terms, :data:`~jaxslam.sim.box_world.BOX_WORLD_MOTION`; the floors stay).

Every world keeps the box world's two properties that make the test: the landmarks are seen
from X (at least 0.75 m of each within the laser's range less 0.3 m, on the side the robot faces
when it arrives) and never from the circle (every landmark point at least the range plus 0.35 m
from every point of the circle), and the path keeps 0.4 m off every box and 0.5 m off every
landmark. All worlds share one frame and one rectangle (:data:`FAMILY_BOUNDS`): X at the
origin, the circle's centre east of it on the x axis, the turnaround point west; so a filter's
virtual grid, sized from the bounds, is the same for every world and compiles once.

:func:`family_scenario` builds a world's :class:`~jaxslam.sim.scenarios.Scenario` with
:func:`~jaxslam.sim.box_world.box_world_scenario` itself (its path, laser and simulation), so a
family world is the box world with other numbers.

The two families are kept apart: seeds from :data:`TUNING_FIRST_SEED` on are the *tuning*
family, on which every default and mechanism is chosen; :data:`TEST_SEEDS` (0-99) are the
*test* family, measured once after the choice is made (:func:`family_seeds`; docs/design.md,
"The box-world family").
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from jaxtyping import PRNGKeyArray

from jaxslam.geometry import between_np
from jaxslam.motion import MotionParams, motion_params, noise_std
from jaxslam.sim.paths import circle_path
from jaxslam.sim.box_world import BOX_WORLD_MOTION, box_world_path, box_world_scenario
from jaxslam.sim.scenarios import Scenario
from jaxslam.sim.world import (
    SegmentWorld,
    box_segments,
    concat_worlds,
    make_world,
    path_crossings,
    point_segment_distance,
    polyline_segments,
)

FAMILY_VERSION = 1
"""Bumped whenever :func:`draw_world` draws other worlds for the same seeds: results stores
name it, so runs of two versions are never mixed."""

TUNING_FIRST_SEED = 1000
"""The tuning family: seeds from this one on (1000, 1001, ...)."""
TEST_SEEDS = range(0, 100)
"""The test family: seeds 0-99, measured once, after every choice was made on the tuning family."""
FAMILIES = ("tuning", "test")
"""The families' names, as :func:`family_seeds` takes them."""

BOX_SIDE_RANGE = (0.5, 1.5)
"""Side (m) of each box, uniform."""
CIRCLE_RADIUS_RANGE = (1.5, 2.5)
"""Radius (m) of the circle the robot drives round the box(es), uniform."""
LAPS_RANGE = (8, 15)
"""Laps round the box(es), inclusive, uniform."""
LAPS_PER_VISIT_RANGE = (3, 5)
"""Laps between two visits to X, inclusive, uniform."""
RANGE_MAX_RANGE = (3.0, 5.0)
"""The laser's range (m), uniform."""
ODOMETRY_SCALE_RANGE = (0.5, 1.5)
"""The simulated robot's proportional odometry-noise terms, times :data:`BOX_WORLD_MOTION`'s, uniform."""
APPROACH_RANGE = (2.5, 3.5)
"""Distance (m) from X to the circle, uniform (the box world's: 2.25 m): room between the circle's
view and X's for landmarks that X sees and the circle does not."""
TURNAROUND_RANGE = (1.5, 2.5)
"""Distance (m) beyond X, away from the circle, at which the robot turns back, uniform (the box world's: 2.5 m)."""
BOX_GAP_RANGE = (0.1, 0.5)
"""Gap (m) between two boxes, uniform."""
NUM_LANDMARKS_RANGE = (1, 3)
"""Landmark objects round X, inclusive, uniform."""
LANDMARK_KINDS = ("hedge", "fence", "barrels")
"""The landmarks' kinds, each equally likely."""

BOX_CLEARANCE = 0.4
"""Least distance (m) from the circle to a box corner: the robot's radius and a margin."""
LANDMARK_CLEARANCE = 0.5
"""Least distance (m) from the path between X and the turnaround point to a landmark."""
LANDMARK_SEPARATION = 0.3
"""Least distance (m) between two landmark objects."""
VIEW_MARGIN = 0.35
"""Landmarks lie at least the laser's range plus this from every point of the circle: out of
view while the robot circles."""
SEEN_MARGIN = 0.3
"""At least :data:`SEEN_LENGTH` of every landmark lies within the laser's range less this from X."""
SEEN_LENGTH = 0.75
"""Least length (m) of every landmark that X sees (within the range less :data:`SEEN_MARGIN`): the box
world's hedge has 1.4 m within 3.7 m of X (its 4 m range less the margin)."""
LANDMARK_BEARING = 1.0
"""Largest angle (rad) between a landmark's place, seen from X, and the direction away from the
circle (the way the robot faces at X): in the forward laser's view on arrival."""
FAMILY_BOUNDS = (-7.0, -6.0, 9.0, 6.0)
"""(xmin, ymin, xmax, ymax) m: the rectangle every world of the family lies in (every world's
:class:`SegmentWorld` has these bounds), so a filter's grid sized from it is the same for all."""
CHECKPOINT = np.zeros(2)
"""X: the origin of every world's frame."""

_MAX_TRIES = 2000  # rejection sampling: far more than any seed needs (tests draw 200 seeds)


class Landmark(NamedTuple):
    """One landmark object near X: its kind and its segments."""

    kind: str
    """"hedge", "fence" or "barrels" (:data:`LANDMARK_KINDS`)."""
    segments: tuple[tuple[float, float, float, float], ...]
    """Its (K,) segments ``(x1, y1, x2, y2)`` (m), as tuples so that a draw compares with ``==``."""


@dataclasses.dataclass(frozen=True)
class BoxWorldDraw:
    """Every quantity drawn for one world of the family (:func:`draw_world`): what it takes to
    build the world, its path and its simulation, given a key for the noise."""

    seed: int
    """The seed it was drawn from (:func:`draw_world`)."""
    box_sides: tuple[float, ...]
    """(B,) side (m) of each box, B = 1 or 2, in :data:`BOX_SIDE_RANGE`."""
    box_angles: tuple[float, ...]
    """(B,) rotation (rad) of each box, in [0, pi/2) (a square's every angle)."""
    box_centers: tuple[tuple[float, float], ...]
    """(B, 2) centre (m) of each box: the circle's centre for one box; for two, either side of it
    along a random axis, ``box_gap`` apart."""
    box_gap: float
    """Least gap (m) between the two boxes, in :data:`BOX_GAP_RANGE` (0 for one box)."""
    circle_radius: float
    """Radius (m) of the circle round the box(es), in :data:`CIRCLE_RADIUS_RANGE`."""
    approach: float
    """Distance (m) from X to the circle, in :data:`APPROACH_RANGE`; the circle's centre is at
    ``(circle_radius + approach, 0)``."""
    turnaround_distance: float
    """Distance (m) beyond X at which the robot turns back, in :data:`TURNAROUND_RANGE`: the
    turnaround point is ``(-turnaround_distance, 0)``."""
    laps: int
    """Laps round the box(es), in :data:`LAPS_RANGE`."""
    laps_per_visit: int
    """Laps between visits to X, in :data:`LAPS_PER_VISIT_RANGE`."""
    clockwise: bool
    """The direction round the circle (False: counter-clockwise, the box world's)."""
    range_max: float
    """The laser's range (m), in :data:`RANGE_MAX_RANGE`."""
    odometry_scale: float
    """The robot's proportional odometry-noise terms over the box world's, in :data:`ODOMETRY_SCALE_RANGE`."""
    landmarks: tuple[Landmark, ...]
    """The landmark objects near X, 1 to 3 (:data:`NUM_LANDMARKS_RANGE`)."""

    @property
    def circle_center(self) -> np.ndarray:
        """(2,) m: the centre of the circle the robot drives round."""
        return np.array([self.circle_radius + self.approach, 0.0])

    @property
    def turnaround(self) -> np.ndarray:
        """(2,) m: where the excursions from the circle turn back."""
        return np.array([-self.turnaround_distance, 0.0])

    @property
    def num_boxes(self) -> int:
        """B: how many boxes the robot circles (1 or 2)."""
        return len(self.box_sides)

    def to_json(self) -> dict:
        """The draw as plain JSON data (lists and numbers)."""
        out = dataclasses.asdict(self)
        out["landmarks"] = [{"kind": m.kind, "segments": [list(s) for s in m.segments]} for m in self.landmarks]
        return out


# ----------------------------------------------------------------------------- the families

def family_seeds(family: str, count: int) -> range:
    """The first ``count`` seeds of a family: "tuning" (from :data:`TUNING_FIRST_SEED` on) or
    "test" (:data:`TEST_SEEDS`, at most 100).

    Raises:
      ValueError: an unknown family, a count below 1, or more than the test family's 100 worlds.
    """
    if family not in FAMILIES:
        raise ValueError(f"family_seeds: unknown family {family!r}; the families are {FAMILIES}")
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"family_seeds: count must be a whole number >= 1, got {count!r}")
    if family == "test":
        if count > len(TEST_SEEDS):
            raise ValueError(f"family_seeds: the test family has {len(TEST_SEEDS)} worlds, {count} were asked for")
        return TEST_SEEDS[:count]
    return range(TUNING_FIRST_SEED, TUNING_FIRST_SEED + int(count))


# ----------------------------------------------------------------------------- drawing a world

def _box_corners(center, side: float, angle: float) -> np.ndarray:
    """(4, 2) corners (m) of a square of ``side`` (m) at ``center`` turned by ``angle`` (rad)."""
    return box_segments(center[0], center[1], side, side, angle)[:, :2].astype(np.float64)


def _draw_boxes(rng: np.random.Generator, num_boxes: int, center: np.ndarray, radius: float):
    """Sides, angles, centres and gap of ``num_boxes`` boxes that fit inside the circle with
    :data:`BOX_CLEARANCE` to spare: drawn until they do (the sides stay uniform where they fit)."""
    for _ in range(_MAX_TRIES):
        sides = rng.uniform(*BOX_SIDE_RANGE, size=num_boxes)
        angles = rng.uniform(0.0, 0.5 * np.pi, size=num_boxes)
        if num_boxes == 1:
            centers, gap = center[None, :], 0.0
        else:
            # Side by side along a random axis u: each box's half-extent along u (its support),
            # so a slab ``gap`` wide perpendicular to u separates them.
            axis = rng.uniform(0.0, np.pi)
            gap = float(rng.uniform(*BOX_GAP_RANGE))
            u = np.array([np.cos(axis), np.sin(axis)])
            reach = 0.5 * sides * (np.abs(np.cos(angles - axis)) + np.abs(np.sin(angles - axis)))
            centers = np.stack([center - (reach[0] + 0.5 * gap) * u, center + (reach[1] + 0.5 * gap) * u])
        corners = np.concatenate([_box_corners(c, s, a) for c, s, a in zip(centers, sides, angles)])
        if np.hypot(*(corners - center).T).max() <= radius - BOX_CLEARANCE:
            return sides, angles, centers, gap
    raise RuntimeError("box_family: no boxes fit the circle")  # unreachable: small boxes always fit


def _hedge(rng: np.random.Generator) -> np.ndarray:
    """A ragged row of 4-8 short segments (0.2-0.5 m, gaps of 0.1-0.3 m), centred on the origin."""
    count = int(rng.integers(4, 9))
    lengths = rng.uniform(0.2, 0.5, count)
    gaps = rng.uniform(0.1, 0.3, count - 1)
    starts = np.concatenate([[0.0], np.cumsum(lengths[:-1] + gaps)])
    mids = starts + 0.5 * lengths - 0.5 * (starts[-1] + lengths[-1])  # along the row, centred
    offsets = rng.uniform(-0.1, 0.1, count)  # across the row
    tilt = rng.uniform(-0.4, 0.4, count)  # each segment off the row's direction
    direction = rng.uniform(0.0, np.pi)
    local = np.stack([mids, offsets], axis=-1)
    half = 0.5 * lengths[:, None] * np.stack([np.cos(tilt), np.sin(tilt)], axis=-1)
    segments = np.concatenate([local - half, local + half], axis=-1)
    return _turned(segments, direction)


def _fence(rng: np.random.Generator) -> np.ndarray:
    """A broken line of 2-4 legs (0.5-1.2 m), turning by up to 0.7 rad at each joint (so it never
    crosses itself: less than pi turned in all), centred on the origin."""
    legs = int(rng.integers(2, 5))
    lengths = rng.uniform(0.5, 1.2, legs)
    headings = rng.uniform(0.0, 2 * np.pi) + np.concatenate([[0.0], np.cumsum(rng.uniform(-0.7, 0.7, legs - 1))])
    points = np.concatenate([np.zeros((1, 2)), np.cumsum(lengths[:, None] * np.stack(
        [np.cos(headings), np.sin(headings)], axis=-1), axis=0)])
    return polyline_segments(points - points.mean(axis=0)).astype(np.float64)


def _barrels(rng: np.random.Generator) -> np.ndarray:
    """2-5 barrels: polygons of 8-12 sides round circles of radius 0.15-0.4 m, within 1.2 m of
    the origin, at least 0.25 m apart."""
    count = int(rng.integers(2, 6))
    radii = rng.uniform(0.15, 0.4, count)
    centers: list[np.ndarray] = []
    for r in radii:
        for _ in range(_MAX_TRIES):
            c = rng.uniform(-1.2, 1.2, 2)
            if all(np.hypot(*(c - o)) >= r + ro + 0.25 for o, ro in zip(centers, radii)):
                centers.append(c)
                break
    parts = []
    for c, r in zip(centers, radii):
        sides = int(rng.integers(8, 13))
        angles = rng.uniform(0.0, 2 * np.pi / sides) + 2 * np.pi * np.arange(sides) / sides
        parts.append(polyline_segments(c + r * np.stack([np.cos(angles), np.sin(angles)], axis=-1), closed=True))
    return np.concatenate(parts).astype(np.float64)


_SHAPES = {"hedge": _hedge, "fence": _fence, "barrels": _barrels}


def _turned(segments: np.ndarray, angle: float) -> np.ndarray:
    """(K, 4) segments turned by ``angle`` (rad) about the origin."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, s], [-s, c]])
    return np.concatenate([segments[:, :2] @ rot, segments[:, 2:] @ rot], axis=-1)


def _segment_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Least distance (m) between two sets of segments ((K, 4) and (M, 4)): 0 where they cross,
    else the least of their ends' distances to the other set's segments."""
    if any(path_crossings(seg.reshape(2, 2), b).any() for seg in a):
        return 0.0
    ends_a, ends_b = a.reshape(-1, 2), b.reshape(-1, 2)
    return float(min(point_segment_distance(ends_a, b).min(), point_segment_distance(ends_b, a).min()))


def _length_within(segments: np.ndarray, point, radius: float, spacing: float = 0.02) -> float:
    """Length (m) of ``segments`` ((K, 4), m) within ``radius`` (m) of ``point`` ((2,) m), to
    within ``spacing`` per segment (midpoint samples)."""
    total = 0.0
    for x1, y1, x2, y2 in segments:  # a handful of segments; the samples are vectorised
        length = float(np.hypot(x2 - x1, y2 - y1))
        count = max(1, int(np.ceil(length / spacing)))
        t = (np.arange(count) + 0.5) / count
        samples = np.stack([x1 + t * (x2 - x1), y1 + t * (y2 - y1)], axis=-1)
        total += length / count * int(np.sum(np.hypot(*(samples - point).T) <= radius))
    return total


def _landmark_fits(segments: np.ndarray, placed: list[np.ndarray], draw: dict) -> bool:
    """Whether a landmark at its place keeps the family's rules (the module's doc)."""
    center, radius, range_max = draw["circle_center"], draw["circle_radius"], draw["range_max"]
    points = segments.reshape(-1, 2)
    xmin, ymin, xmax, ymax = FAMILY_BOUNDS
    inside = (points[:, 0] > xmin + 0.2) & (points[:, 0] < xmax - 0.2) & (points[:, 1] > ymin + 0.2) \
        & (points[:, 1] < ymax - 0.2)
    # Out of view from the circle: every point of it (not only the ends) at least radius +
    # range + margin from the circle's centre.
    unseen = point_segment_distance(center[None], segments).min() >= radius + range_max + VIEW_MARGIN
    # Off the path: the line from X to the turnaround point is all of the path on this side.
    path = np.array([[0.0, 0.0, -draw["turnaround_distance"], 0.0]])
    if not (inside.all() and unseen and _segment_distance(segments, path) >= LANDMARK_CLEARANCE):
        return False
    seen = _length_within(segments, CHECKPOINT, range_max - SEEN_MARGIN) >= SEEN_LENGTH
    return bool(seen and all(_segment_distance(segments, other) >= LANDMARK_SEPARATION for other in placed))


def draw_world(seed: int) -> BoxWorldDraw:
    """The family's world number ``seed``: a pure function of the seed (``np.random.default_rng(seed)``).

    Every quantity is drawn uniformly in its range (the module's doc and the ``*_RANGE``
    constants); the boxes are drawn again until they fit the circle, and each landmark's shape
    and place until it keeps the family's rules (seen from X, never from the circle, off the
    path, apart from the others, inside :data:`FAMILY_BOUNDS`).

    Args:
      seed: an integer >= 0 (:func:`family_seeds` gives the families' seeds).

    Returns:
      The :class:`BoxWorldDraw`; lengths in metres, angles in radians.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"draw_world: seed must be a whole number >= 0, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    num_boxes = int(rng.integers(1, 3))
    radius = float(rng.uniform(*CIRCLE_RADIUS_RANGE))
    approach = float(rng.uniform(*APPROACH_RANGE))
    center = np.array([radius + approach, 0.0])
    sides, angles, centers, gap = _draw_boxes(rng, num_boxes, center, radius)
    laps = int(rng.integers(LAPS_RANGE[0], LAPS_RANGE[1] + 1))
    laps_per_visit = int(rng.integers(LAPS_PER_VISIT_RANGE[0], LAPS_PER_VISIT_RANGE[1] + 1))
    clockwise = bool(rng.random() < 0.5)
    range_max = float(rng.uniform(*RANGE_MAX_RANGE))
    odometry_scale = float(rng.uniform(*ODOMETRY_SCALE_RANGE))
    turnaround_distance = float(rng.uniform(*TURNAROUND_RANGE))
    known = dict(circle_center=center, circle_radius=radius, range_max=range_max,
                 turnaround_distance=turnaround_distance)
    placed: list[np.ndarray] = []
    kinds: list[str] = []
    for _ in range(int(rng.integers(NUM_LANDMARKS_RANGE[0], NUM_LANDMARKS_RANGE[1] + 1))):
        kind = str(LANDMARK_KINDS[int(rng.integers(len(LANDMARK_KINDS)))])
        for _ in range(_MAX_TRIES):
            # Placed round X on the side away from the circle, near enough to be seen in part.
            bearing = np.pi + rng.uniform(-LANDMARK_BEARING, LANDMARK_BEARING)
            distance = rng.uniform(1.0, range_max + 1.0)
            segments = _SHAPES[kind](rng) + distance * np.array([np.cos(bearing), np.sin(bearing)] * 2)
            if _landmark_fits(segments, placed, known):
                placed.append(segments)
                kinds.append(kind)
                break
        else:
            raise RuntimeError(f"draw_world: seed {seed}: no place for a {kind}")  # not met on seeds 0-99 and 1000-2999
    return BoxWorldDraw(
        seed=int(seed), box_sides=tuple(map(float, sides)), box_angles=tuple(map(float, angles)),
        box_centers=tuple((float(x), float(y)) for x, y in centers), box_gap=float(gap), circle_radius=radius,
        approach=approach, turnaround_distance=turnaround_distance, laps=laps, laps_per_visit=laps_per_visit,
        clockwise=clockwise, range_max=range_max, odometry_scale=odometry_scale,
        landmarks=tuple(Landmark(k, tuple(tuple(map(float, s)) for s in seg)) for k, seg in zip(kinds, placed)),
    )


# ----------------------------------------------------------------------------- the world and its scenario

def family_world(draw: BoxWorldDraw) -> SegmentWorld:
    """The draw's segments, in :data:`FAMILY_BOUNDS`.

    Groups: "box2" (the circled box or boxes: box 2's part in the box world), "landmarks" (every
    landmark near X: the part of box 1 and the hedge), and each landmark kind present ("hedge",
    "fence", "barrels").
    """
    boxes = np.concatenate([box_segments(c[0], c[1], s, s, a)
                            for c, s, a in zip(draw.box_centers, draw.box_sides, draw.box_angles)])
    worlds = [make_world(boxes, FAMILY_BOUNDS, groups={"box2": np.arange(boxes.shape[0])})]
    for landmark in draw.landmarks:
        segments = np.asarray(landmark.segments, np.float64).reshape(-1, 4)
        every = np.arange(segments.shape[0])
        worlds.append(make_world(segments, FAMILY_BOUNDS, groups={"landmarks": every, landmark.kind: every}))
    return concat_worlds(*worlds)


PROPORTIONAL_TERMS = ("srr", "srt", "str", "stt")
"""The odometry model's terms that grow with the motion (the floors do not), as :class:`MotionParams` names."""


def robot_motion_params(draw: BoxWorldDraw) -> MotionParams:
    """The simulated robot's odometry noise: :data:`BOX_WORLD_MOTION` with its proportional terms
    (srr m/m, srt m/rad, str rad/m, stt rad/rad) times ``draw.odometry_scale``, the floors
    (minimum stds, m and rad) as they are; per 0.1 m step, as the box world's."""
    terms = {name: float(getattr(BOX_WORLD_MOTION, name)) for name in BOX_WORLD_MOTION._fields}
    for name in PROPORTIONAL_TERMS:
        terms[name] *= draw.odometry_scale
    return motion_params(terms["srr"], terms["srt"], terms["str"], terms["stt"], terms["min_translation_std"],
                         terms["min_rotation_std"])


STEP_LENGTH = 0.1
"""Metres driven between two scans (the box world's: 1 m/s at 10 Hz)."""


def heading_drift_per_lap(draw: BoxWorldDraw) -> float:
    """Std (rad) of the odometry's heading error accumulated over one lap of the circle: the
    per-step heading stds of :func:`jaxslam.motion.noise_std` at the circle's true motion (the
    simulator draws each step's noise independently), added in variance over the lap's steps.
    The box world's default robot: 0.133 rad (7.6 degrees) a lap."""
    lap = circle_path(np.zeros(2), draw.circle_radius, 1.0, STEP_LENGTH, 0.0, clockwise=draw.clockwise)
    # Every step of a circle is the same motion (equal chords): one std, sqrt(steps) of them.
    step_heading_std = float(noise_std(between_np(lap[0], lap[1]), robot_motion_params(draw))[2])
    return float(np.sqrt(lap.shape[0] - 1) * step_heading_std)


def difficulty(draw: BoxWorldDraw) -> dict[str, float]:
    """The world's difficulty figures: ``heading_drift_per_lap`` (rad, :func:`heading_drift_per_lap`),
    ``box_size`` (m, the largest box's side: how much the circling robot sees), ``range_max``
    (m, the laser's range), ``laps``, ``odometry_scale``."""
    return {"heading_drift_per_lap": heading_drift_per_lap(draw), "box_size": float(max(draw.box_sides)),
            "range_max": draw.range_max, "laps": draw.laps, "odometry_scale": draw.odometry_scale}


def family_path(draw: BoxWorldDraw) -> tuple[np.ndarray, dict]:
    """The draw's true path without its simulation (for figures): :func:`box_world_path` on the
    draw's circle, laps, direction, checkpoint and turnaround point.

    Returns:
      ``(poses, info)``: (T, 3) float64 poses (m, m, rad), one per scan, and ``box_world_path``'s
      info (``lap_end_indices``, ``turn_radius``); the same poses as :func:`family_scenario`'s.
    """
    return box_world_path(draw.laps, draw.laps_per_visit, draw.circle_radius, STEP_LENGTH, clockwise=draw.clockwise,
                          circle_center=draw.circle_center, checkpoint=CHECKPOINT, turnaround=draw.turnaround)


def family_scenario(draw: BoxWorldDraw, key: PRNGKeyArray) -> Scenario:
    """The draw's dataset: :func:`~jaxslam.sim.box_world.box_world_scenario` on the draw's world,
    circle, checkpoint, turnaround point, laps, direction, laser range and odometry noise; the
    rest as the box world's (0.1 m steps at 10 Hz, 180 beams over 180 degrees, 0.02 m range noise).

    Args:
      draw: a :func:`draw_world` draw.
      key: a JAX PRNG key for the range and odometry noise.

    Returns:
      A :class:`~jaxslam.sim.scenarios.Scenario` like ``box_world_scenario``'s: log (T scans of
      180 beams), world, (T, 3) float64 true poses (m, m, rad) and its metadata, where
      ``box2_center`` is the circle's centre and ``box1_center`` ((2,) m) the centre of the
      landmarks' points (what box 1 and the hedge are in the box world), with ``draw`` (the
      :class:`BoxWorldDraw`), ``box_centers`` ((B, 2) m) and ``difficulty`` (:func:`difficulty`) added.
    """
    world = family_world(draw)
    scenario = box_world_scenario(
        key, laps=draw.laps, laps_per_visit=draw.laps_per_visit, circle_radius=draw.circle_radius,
        step_length=STEP_LENGTH, range_max=draw.range_max, motion=robot_motion_params(draw), world=world,
        clockwise=draw.clockwise, circle_center=draw.circle_center, checkpoint=CHECKPOINT,
        turnaround=draw.turnaround)
    landmark_points = world.segments[world.groups["landmarks"]].reshape(-1, 2).astype(np.float64)
    metadata = {**scenario.metadata, "box1_center": landmark_points.mean(axis=0), "draw": draw,
                "box_centers": np.asarray(draw.box_centers, np.float64), "difficulty": difficulty(draw)}
    return scenario._replace(metadata=metadata)
