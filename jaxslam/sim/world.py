"""Planar worlds made of line segments, and helpers to build and check them.

A :class:`SegmentWorld` is host-side data (NumPy): an (M, 4) float32 array of
segments ``[x1, y1, x2, y2]`` in metres, the rectangle it lives in, and named
groups of segment indices ("box2", "walls", ...) so that tests and experiments
can ask which object a ray hit (see :func:`jaxslam.segment_map.raycast`). Worlds are
built once, with NumPy; only the ray casting runs in JAX.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from types import MappingProxyType

import numpy as np

Bounds = tuple[float, float, float, float]


@dataclasses.dataclass(frozen=True, eq=False)
class SegmentWorld:
    """A static 2-D world of line segments."""

    segments: np.ndarray
    """(M, 4) float32 rows [x1, y1, x2, y2] in metres."""
    bounds: Bounds
    """(xmin, ymin, xmax, ymax) in metres: the region the world describes (for plots and
    default map extents); every segment lies inside it."""
    groups: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    """Name -> (K,) int64 indices into ``segments`` of a named object (read-only)."""

    def __post_init__(self):
        segments = np.asarray(self.segments, dtype=np.float32).reshape(-1, 4)
        if not np.all(np.isfinite(segments)):
            raise ValueError("SegmentWorld: segments must be finite")
        bounds = tuple(float(b) for b in self.bounds)
        if len(bounds) != 4 or bounds[0] >= bounds[2] or bounds[1] >= bounds[3]:
            raise ValueError(f"SegmentWorld: bounds {bounds} are not (xmin, ymin, xmax, ymax)")
        if segments.size:
            xs, ys = segments[:, 0::2], segments[:, 1::2]
            # A small slack for float32 rounding of coordinates that sit on the bounds.
            slack = 1e-4
            if (xs.min() < bounds[0] - slack or xs.max() > bounds[2] + slack
                    or ys.min() < bounds[1] - slack or ys.max() > bounds[3] + slack):
                raise ValueError(f"SegmentWorld: a segment lies outside the bounds {bounds}")
        groups = {}
        for name, idx in dict(self.groups).items():
            idx = np.asarray(idx, dtype=np.int64).reshape(-1)
            if idx.size and (idx.min() < 0 or idx.max() >= segments.shape[0]):
                raise ValueError(f"SegmentWorld: group {name!r} indexes a segment that does not exist")
            idx.setflags(write=False)
            groups[name] = idx
        segments.setflags(write=False)
        object.__setattr__(self, "segments", segments)
        object.__setattr__(self, "bounds", bounds)
        object.__setattr__(self, "groups", MappingProxyType(groups))

    @property
    def num_segments(self) -> int:
        return int(self.segments.shape[0])

    def group_mask(self, name: str) -> np.ndarray:
        """(M,) bool: which segments belong to the group ``name``."""
        mask = np.zeros(self.num_segments, dtype=bool)
        mask[self.groups[name]] = True
        return mask


def make_world(segments, bounds: Bounds | None = None, margin: float = 1.0,
               groups: Mapping[str, Sequence[int]] | None = None) -> SegmentWorld:
    """A :class:`SegmentWorld` from (M, 4) segments (m).

    ``bounds`` defaults to the segments' bounding box grown by ``margin`` metres.
    """
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if bounds is None:
        if segments.size == 0:
            raise ValueError("make_world: give bounds for a world without segments")
        xs, ys = segments[:, 0::2], segments[:, 1::2]
        bounds = (xs.min() - margin, ys.min() - margin, xs.max() + margin, ys.max() + margin)
    return SegmentWorld(segments, bounds, groups or {})


def box_segments(cx: float, cy: float, width: float, height: float, angle: float = 0.0) -> np.ndarray:
    """The 4 sides of a rectangle, as (4, 4) float32 segments.

    Args:
      cx, cy: centre (m).
      width, height: side lengths (m) along the box's own x and y axes.
      angle: rotation of the box (rad, counter-clockwise).
    """
    hw, hh = 0.5 * width, 0.5 * height
    corners = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]])
    c, s = np.cos(angle), np.sin(angle)
    corners = corners @ np.array([[c, s], [-s, c]]) + np.array([cx, cy])
    return polyline_segments(corners, closed=True)


def polyline_segments(points, closed: bool = False) -> np.ndarray:
    """Segments joining consecutive ``points`` ((P, 2), m): (P-1, 4), or (P, 4) when ``closed``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if points.shape[0] < 2:
        raise ValueError("polyline_segments: need at least 2 points")
    ends = np.roll(points, -1, axis=0) if closed else points[1:]
    starts = points if closed else points[:-1]
    return np.concatenate([starts, ends], axis=1).astype(np.float32)


def wall_segments(start, end, gaps: Sequence[tuple[float, float]] = ()) -> np.ndarray:
    """A straight wall from ``start`` to ``end`` ((2,) m) with door gaps, as (K, 4) float32.

    Each gap is ``(centre, width)``: the distance (m) of the gap's centre from ``start``
    along the wall, and the gap's width (m). Gaps must lie inside the wall and not overlap.
    """
    start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
    length = float(np.hypot(*(end - start)))
    direction = (end - start) / length
    cuts = [0.0]
    for centre, width in sorted(gaps):
        a, b = centre - 0.5 * width, centre + 0.5 * width
        if a < cuts[-1] or b > length:
            raise ValueError(f"wall_segments: gap ({centre}, {width}) overlaps another or leaves the wall")
        cuts += [a, b]
    cuts.append(length)
    pieces = [(a, b) for a, b in zip(cuts[0::2], cuts[1::2]) if b - a > 1e-9]
    if not pieces:
        return np.zeros((0, 4), np.float32)
    return np.array(
        [np.concatenate([start + a * direction, start + b * direction]) for a, b in pieces],
        dtype=np.float32,
    )


def concat_worlds(*worlds: SegmentWorld, bounds: Bounds | None = None) -> SegmentWorld:
    """One world holding the segments of all ``worlds``, in order.

    Groups are merged (indices shifted; groups of the same name are joined). ``bounds``
    defaults to the union of the worlds' bounds.
    """
    if not worlds:
        raise ValueError("concat_worlds: no worlds given")
    segments, groups, offset = [], {}, 0
    for world in worlds:
        segments.append(world.segments)
        for name, idx in world.groups.items():
            groups[name] = np.concatenate([groups.get(name, np.zeros(0, np.int64)), idx + offset])
        offset += world.num_segments
    if bounds is None:
        b = np.array([w.bounds for w in worlds])
        bounds = (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max())
    return SegmentWorld(np.concatenate(segments, axis=0), bounds, groups)


def point_segment_distance(points, segments) -> np.ndarray:
    """(P, M) float64 distances (m) from each point ((P, 2), m) to each segment ((M, 4), m)."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    segments = np.asarray(segments, np.float64).reshape(-1, 4)
    a, e = segments[:, :2], segments[:, 2:] - segments[:, :2]
    ap = points[:, None, :] - a[None]  # (P, M, 2)
    length2 = np.maximum(np.sum(e * e, axis=-1), 1e-18)
    u = np.clip(np.sum(ap * e, axis=-1) / length2, 0.0, 1.0)
    closest = a[None] + u[..., None] * e[None]
    return np.hypot(*(points[:, None, :] - closest).transpose(2, 0, 1))


def path_crossings(points, segments) -> np.ndarray:
    """(T-1, M) bool: whether the straight step from ``points[i]`` to ``points[i+1]`` ((T, 2), m)
    touches segment m ((M, 4), m). Zero-length steps (turns on the spot) cross nothing.

    Float64, with touching counted as crossing, so a path that grazes a wall end fails too.
    """
    points = np.asarray(points, np.float64).reshape(-1, 2)
    segments = np.asarray(segments, np.float64).reshape(-1, 4)
    p, r = points[:-1, None, :], (points[1:] - points[:-1])[:, None, :]  # (T-1, 1, 2)
    q, s = segments[None, :, :2], (segments[:, 2:] - segments[:, :2])[None]  # (1, M, 2)
    qp = q - p
    denom = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    t_num = qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]
    u_num = qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]
    ok = np.abs(denom) > 1e-12
    safe = np.where(ok, denom, 1.0)
    t, u = t_num / safe, u_num / safe
    proper = ok & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    # A parallel step crosses a segment only when both lie on one line and overlap.
    step_len2 = r[..., 0] ** 2 + r[..., 1] ** 2
    safe_len2 = np.where(step_len2 > 0, step_len2, 1.0)
    collinear = ~ok & (np.abs(u_num) <= 1e-12 * np.sqrt(safe_len2))
    t0 = (qp[..., 0] * r[..., 0] + qp[..., 1] * r[..., 1]) / safe_len2
    t1 = t0 + (s[..., 0] * r[..., 0] + s[..., 1] * r[..., 1]) / safe_len2
    collinear &= (np.maximum(np.minimum(t0, t1), 0.0) <= np.minimum(np.maximum(t0, t1), 1.0))
    step_len = np.sqrt(step_len2)
    moving = (step_len > 0)
    return (proper | collinear) & moving
