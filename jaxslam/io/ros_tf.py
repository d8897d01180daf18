"""The transforms of a ROS bag (``/tf``, ``/tf_static``) for :mod:`jaxslam.io.rosbag`.

:class:`_TfTree` collects a bag's transforms (each frame's parent, each link's first value, and the
odometry links' series); :class:`_Rigid` composes them. Also the message-field helpers both use:
frame names without a leading ``/`` (:func:`_frame`), header stamps (:func:`_stamp`) and the check
of a pose's fields (:func:`_check_pose`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from jaxslam.laserlog import LogError

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

# A transform whose later values differ from its first by more than this (m, or quaternion
# component) moves; a link of the odometry chain or of the laser's mounting must not, but one.
_TF_CONSTANT_TOLERANCE = 1e-6
# At most this many of a bag's transforms are listed in an error message.
_TF_LISTED = 12


def _frame(name: str) -> str:
    """A tf frame name without its leading ``/`` (ROS 1 style ``/base_link`` is ``base_link``)."""
    return name.strip().lstrip("/")


def _stamp(stamp, bag_time_ns: int) -> float:
    """A header stamp in seconds; the bag time where the stamp is 0."""
    seconds = stamp.sec + stamp.nanosec * 1e-9
    return seconds if seconds != 0 else bag_time_ns * 1e-9


def _check_pose(values: tuple, where: str, what: str) -> None:
    """A LogError for non-finite ``values`` (position fields, then quaternion x, y, z, w) or a
    zero quaternion."""
    if not all(math.isfinite(v) for v in values):
        raise LogError(f"{where}: non-finite {what} pose {values}")
    if sum(v * v for v in values[-4:]) < 1e-12:
        raise LogError(f"{where}: the {what} orientation is a zero quaternion")


def _rotation(q) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions [x, y, z, w] (normalised here)."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


class _Rigid(NamedTuple):
    """A 3-D rigid transform (the pose of a child frame in its parent), possibly a stack of them."""

    rotation: np.ndarray  # (..., 3, 3)
    translation: np.ndarray  # (..., 3)

    @staticmethod
    def identity() -> _Rigid:
        return _Rigid(np.eye(3), np.zeros(3))

    @staticmethod
    def of(values) -> _Rigid:
        """From (..., 7) [tx, ty, tz, qx, qy, qz, qw]."""
        values = np.asarray(values, dtype=np.float64)
        return _Rigid(_rotation(values[..., 3:]), values[..., :3])

    def then(self, other: _Rigid) -> _Rigid:
        """``self`` followed by ``other`` (the pose of other's child in self's parent)."""
        rotation = self.rotation @ other.rotation
        translation = (self.rotation @ other.translation[..., None])[..., 0] + self.translation
        return _Rigid(rotation, translation)

    def inverse(self) -> _Rigid:
        rotation = np.swapaxes(self.rotation, -1, -2)
        return _Rigid(rotation, -(rotation @ self.translation[..., None])[..., 0])

    def planar(self) -> np.ndarray:
        """(..., 3) [x, y, yaw]: the translation's x, y and the heading of the child's x axis."""
        yaw = np.arctan2(self.rotation[..., 1, 0], self.rotation[..., 0, 0])
        return np.stack([self.translation[..., 0], self.translation[..., 1], yaw], axis=-1)

    def upside_down(self) -> bool:
        """Whether the child's z axis points down in the parent."""
        return bool(self.rotation[..., 2, 2] < 0)


class _TfTree:
    """The transforms of a bag: each frame's parent (the first seen), each link's first value,
    and, for the odometry, every value of the links that leave ``odom_frame`` or reach
    ``base_frame``."""

    def __init__(self, odom_frame: str, base_frame: str, series: bool):
        self.odom_frame, self.base_frame, self.collect_series = odom_frame, base_frame, series
        self.parent: dict[str, str] = {}
        self.first: dict[tuple[str, str], np.ndarray] = {}  # (parent, child) -> (7,)
        self.source: dict[tuple[str, str], str] = {}  # (parent, child) -> topic of its first value
        self.moves: set[tuple[str, str]] = set()
        self.series: dict[tuple[str, str], tuple[list, list]] = {}  # (parent, child) -> (stamps, values)
        self.latest: dict[tuple[str, str], float] = {}  # (parent, child) -> latest stamp of its series
        self.topics: set[str] = set()

    def add_message(self, msg, topic: str, bag_time_ns: int, where: str) -> None:
        static = topic == TF_STATIC_TOPIC
        self.topics.add(topic)
        for j, transform in enumerate(msg.transforms):
            parent, child = _frame(transform.header.frame_id), _frame(transform.child_frame_id)
            stamp = _stamp(transform.header.stamp, bag_time_ns)
            t, q = transform.transform.translation, transform.transform.rotation
            values = (t.x, t.y, t.z, q.x, q.y, q.z, q.w)
            _check_pose(values, f"{where}, transform {j} ({parent} -> {child}), stamp {stamp:.9f} s", "transform")
            values = np.array(values, dtype=np.float64)
            link = (parent, child)
            if link not in self.first:
                self.parent.setdefault(child, parent)
                self.first[link] = values
                self.source[link] = TF_STATIC_TOPIC if static else TF_TOPIC
            elif np.max(np.abs(values - self.first[link])) > _TF_CONSTANT_TOLERANCE:
                self.moves.add(link)
            if self.collect_series and not static and (parent == self.odom_frame or child == self.base_frame):
                stamps, series = self.series.setdefault(link, ([], []))
                stamps.append(stamp)
                series.append(values)
                self.latest[link] = max(stamp, self.latest.get(link, stamp))

    def series_reach(self) -> float | None:
        """The earliest of the odometry links' latest stamps (None before any)."""
        return min(self.latest.values()) if self.latest else None

    def path(self, a: str, b: str) -> list[tuple[tuple[str, str], bool]] | None:
        """The links from frame ``a`` to frame ``b`` as ``[(link, inverted)]`` (up from ``a`` to
        their nearest common ancestor, then down to ``b``), or None where they do not connect."""
        up_a, up_b = self._ancestors(a), self._ancestors(b)
        common = next((f for f in up_a if f in up_b), None)
        if common is None:
            return None
        ups = [((self.parent[f], f), True) for f in up_a[:up_a.index(common)]]
        downs = [((self.parent[f], f), False) for f in reversed(up_b[:up_b.index(common)])]
        return ups + downs

    def _ancestors(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self.parent and self.parent[chain[-1]] not in chain:
            chain.append(self.parent[chain[-1]])
        return chain

    def constant(self, links) -> _Rigid:
        """The composition of ``links`` (``[(link, inverted)]``) at their first values."""
        total = _Rigid.identity()
        for link, inverted in links:
            step = _Rigid.of(self.first[link])
            total = total.then(step.inverse() if inverted else step)
        return total

    def listing(self) -> str:
        links = [f"{p} -> {c} ({self.source[(p, c)]})" for p, c in self.first]
        more = f", ... ({len(links)} in all)" if len(links) > _TF_LISTED else ""
        return ", ".join(links[:_TF_LISTED]) + more if links else "none"
