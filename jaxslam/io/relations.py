"""Ground-truth relations files of Kümmerle et al. 2009 ("On measuring the accuracy of SLAM algorithms").

One relation per line, eight numbers ``t1 t2 x y z roll pitch yaw``: the pose of
the robot at scan time ``t2`` expressed in the frame of the robot at scan time
``t1`` (m, m, m, rad, rad, rad). The logs are planar, so z, roll and pitch are 0;
a line where they are not is an error rather than a dropped dimension.
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple

import numpy as np

from jaxslam.laserlog import LogError

__all__ = ["Relations", "read_relations", "sideways_relations"]

# z, roll and pitch are written as 0.000000; anything larger is not a planar relation.
_PLANAR_TOLERANCE = 1e-6


class Relations(NamedTuple):
    """R relative-motion constraints between pairs of scan timestamps."""

    t1: np.ndarray
    """(R,) float64 seconds: the scan whose robot frame the motion is expressed in."""
    t2: np.ndarray
    """(R,) float64 seconds: the scan the motion leads to (may be earlier than t1)."""
    motion: np.ndarray
    """(R, 3) float64 [x, y, yaw] (m, m, rad): the pose at t2 in the frame of the pose at t1."""

    @property
    def count(self) -> int:
        """Number of relations R."""
        return int(self.t1.shape[0])


def read_relations(path) -> Relations:
    """Read a relations file (Kümmerle et al. 2009 format).

    Blank lines and ``#`` comments are skipped; every other line must hold exactly eight
    finite numbers ``t1 t2 x y z roll pitch yaw`` with z = roll = pitch = 0.

    Returns:
        :class:`Relations` with t1, t2 (R,) s and motion (R, 3) [x, y, yaw] (m, m, rad).

    Raises:
        LogError: naming the file and line, for a line with another field count, a
            non-numeric or non-finite field, a non-zero z/roll/pitch; or for a file with
            no relations.
    """
    src = os.fspath(path)
    try:
        with open(src, encoding="utf-8") as f:
            lines = f.read().splitlines()
    except FileNotFoundError:
        raise LogError(f"{src}: no such relations file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise LogError(f"{src}: cannot read the relations file ({err})") from None
    rows: list[list[float]] = []
    for line_no, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.split()
        where = f"{src}:{line_no}"
        if len(fields) != 8:
            raise LogError(f"{where}: expected 8 fields 't1 t2 x y z roll pitch yaw', got {len(fields)}")
        try:
            values = [float(v) for v in fields]
        except ValueError:
            bad = next(v for v in fields if not _is_number(v))
            raise LogError(f"{where}: field {fields.index(bad) + 1} is not a number: {bad!r}") from None
        if not all(np.isfinite(values)):
            raise LogError(f"{where}: non-finite value in {stripped!r}")
        if max(abs(values[4]), abs(values[5]), abs(values[6])) > _PLANAR_TOLERANCE:
            raise LogError(f"{where}: z, roll, pitch must be 0 for a planar relation, got {values[4:7]}")
        rows.append(values)
    if not rows:
        raise LogError(f"{src}: the relations file holds no relations")
    table = np.asarray(rows, dtype=np.float64)
    return Relations(table[:, 0].copy(), table[:, 1].copy(), table[:, [2, 3, 7]].copy())


def sideways_relations(relations: Relations, max_seconds: float = 12.0, min_length: float = 0.5,
                       max_turn: float = math.radians(10.0), max_sideways: float = math.radians(8.0)) -> np.ndarray:
    """(R,) bool: the relations a differential-drive robot cannot make: a short, nearly straight
    motion whose chord leaves the robot's heading sideways.

    A differential-drive robot moves along its heading. Over an arc that turns it by ``yaw``,
    the chord from start to end points ``yaw / 2`` off its first heading (forward or backward),
    whatever the arc's radius. A relation whose two scans are at most ``max_seconds`` apart,
    at least ``min_length`` apart in space, and turn at most ``max_turn``, but whose chord
    points more than ``max_sideways`` off that direction, says the robot slid sideways.

    FR-clinic's relations hold 40 such (of 2,820), most of them in one minute of the log where
    they say 0.34 m sideways for every metre ahead. The odometry, the filter and the loop
    closure all say straight ahead there. For 37 of the 40, the two scans lay over each other
    better under the closure's motion than under the relation's, and for one the other way
    (:func:`jaxslam.metrics.scan_support`). The other four logs hold 0-3 each
    (docs/design.md, "Relations a differential-drive robot cannot make"). They are part of every method's
    mean on that log: :func:`jaxslam.metrics.relation_error` keeps them, as the benchmark does,
    and ``jaxslam eval`` reports the mean without them beside it.

    Args:
        relations: R relations (:func:`read_relations`).
        max_seconds: longest time between the two scans checked (s): a longer relation may
            hold any path.
        min_length: shortest chord checked (m): a short one's direction is noise.
        max_turn: largest heading change checked (rad): over a sharper turn the path need not be
            one arc.
        max_sideways: largest angle between the chord and the arc's direction (rad).
    """
    for name, value in (("max_seconds", max_seconds), ("min_length", min_length), ("max_turn", max_turn),
                        ("max_sideways", max_sideways)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"sideways_relations: {name} must be a finite number > 0, got {value!r}")
    motion = np.asarray(relations.motion, np.float64)
    seconds = np.abs(np.asarray(relations.t2, np.float64) - np.asarray(relations.t1, np.float64))
    length = np.hypot(motion[:, 0], motion[:, 1])
    # The chord's angle off the arc's direction, forward or backward: folded into [-pi/2, pi/2).
    off = (np.arctan2(motion[:, 1], motion[:, 0]) - motion[:, 2] / 2 + np.pi / 2) % np.pi - np.pi / 2
    checked = (seconds <= max_seconds) & (length >= min_length) & (np.abs(motion[:, 2]) <= max_turn)
    return checked & (np.abs(off) > max_sideways)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
