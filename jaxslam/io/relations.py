"""Ground-truth relations files of Kümmerle et al. 2009 ("On measuring the accuracy of SLAM algorithms").

One relation per line, eight numbers ``t1 t2 x y z roll pitch yaw``: the pose of
the robot at scan time ``t2`` expressed in the frame of the robot at scan time
``t1`` (m, m, m, rad, rad, rad). The logs are planar, so z, roll and pitch are 0;
a line where they are not is an error rather than a dropped dimension.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from jaxslam.laserlog import LogError

__all__ = ["Relations", "read_relations"]

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


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
