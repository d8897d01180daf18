"""Pad laser scans whose beam layout changes within a log to one common layout.

Shared by the ROS bag reader (:mod:`jaxslam.io.rosbag`) and the CARMEN reader
(:mod:`jaxslam.io.carmen`): each collects its scans' layouts (:class:`BeamLayout`)
while reading, then :func:`pad_beam_layouts` checks that every layout lies on the
widest scan's angular grid within its angular range and puts all scans into one
(T, B) array, a scan's missing beams reading :data:`PAD_RANGE` (an invalid reading).
"""

from __future__ import annotations

import math
from collections import Counter
from typing import NamedTuple

import numpy as np

from jaxslam.laserlog import LogError

__all__ = ["BeamLayout", "PAD_RANGE", "PAD_RANGE_MIN", "pad_beam_layouts"]

PAD_RANGE = 0.0
"""Range (m) of a padded beam (one a scan lacks): below ``range_min``, so invalid: it
neither clears nor marks a cell and never counts in a likelihood. (A no-return reading,
``>= range_max``, would not do: insertion clears free space along it.)"""
PAD_RANGE_MIN = 1e-3
"""``range_min`` (m) of a padded log whose sensor says 0, so that :data:`PAD_RANGE` lies
below it; readings under 1 mm are no real return."""
# Most a beam's angle may miss the common grid (rad): 1e-4 rad is 1 mm at 10 m, far below a
# laser beam's width; it forgives increments printed with few digits.
_GRID_TOLERANCE = 1e-4
# Finest subdivision of the widest scan's increment that interleaved scans may sit on
# (a SICK LMS interlaces 4 scans 0.25 degrees apart in its 0.25-degree mode).
_MAX_SUBDIVISION = 4


class BeamLayout(NamedTuple):
    """The beams of the scans that share one layout (angle_min, increment, beam count)."""

    angles: np.ndarray
    """(B_i,) float64 beam angles (rad), in the scan's order."""
    increment: float
    """Angle between consecutive beams (rad), signed."""
    where: str
    """The first scan with this layout (file, index, time), for messages."""

    @property
    def num_beams(self) -> int:
        return int(self.angles.shape[0])

    @property
    def angle_min(self) -> float:
        return float(self.angles[0])

    def brief(self) -> str:
        return (f"{self.num_beams} beams from {math.degrees(self.angles[0]):.3f} deg, "
                f"{math.degrees(self.increment):.3f} deg apart")

    def describe(self) -> str:
        a, b = math.degrees(self.angles[0]), math.degrees(self.angles[-1])
        return (f"{self.num_beams} beams, angle_min {self.angles[0]:.7f} rad, increment {self.increment:.7f} rad "
                f"({a:.3f}..{b:.3f} deg)")


def pad_beam_layouts(src: str, layouts, layout_of, ranges, range_min: float):
    """Put scans of different beam layouts into one (T, B) array with one set of beam angles.

    The rule: the widest layout (most beams; the first seen among equals) is the
    reference. Every other layout's beam angles must lie on the reference's angular grid
    (``angle_min + j * increment``) or, for interleaved scans, on a grid of 1/2, 1/3 or
    1/4 of its increment (the smallest subdivision that fits every layout), each angle
    within 1e-4 rad; and within the reference's angular range, widened by less than one
    increment at either end. The common beam angles are the reference's, then the other
    layouts' beams that are not among them (layouts with more beams first, then in order
    of appearance; each in its own order, so that a beam stride still samples every
    scan evenly). A scan's beams it does not have read :data:`PAD_RANGE`, below
    ``range_min``: invalid readings, which neither clear nor mark a cell and never count
    in a likelihood. Where ``range_min`` is not above :data:`PAD_RANGE`, it becomes
    :data:`PAD_RANGE_MIN`.

    Args:
        src: the file, for the note.
        layouts: the :class:`BeamLayout` of the log, in order of first appearance.
        layout_of: (T,) int: each scan's layout (index into ``layouts``).
        ranges: T (B_i,) float32 arrays: each scan's ranges, in its layout's order
            (an empty list only validates the layouts).
        range_min: the sensor's range_min (m).

    Returns:
        ``(beam_angles (B,) float64, ranges (T, B) float32, range_min, note)``: ``note`` is
        None where every scan has the same layout (nothing is padded), else one sentence
        saying what was padded (for a ``UserWarning`` and the log's ``notes``).

    Raises:
        LogError: a layout leaves the reference's grid or range (or its beams run the other
            way); the message names the first scan with that layout and both layouts.
    """
    layout_of = np.asarray(layout_of, dtype=np.int64)
    used = [int(k) for k in np.unique(layout_of)] if ranges else list(range(len(layouts)))
    if len(used) <= 1:
        if not ranges:
            return None, None, range_min, None
        return layouts[used[0]].angles, np.stack(ranges).astype(np.float32), range_min, None
    widest = max(used, key=lambda k: (layouts[k].num_beams, -k))
    ref = layouts[widest]
    # Every layout is checked, also where ``ranges`` is empty (the validate-only call).
    division = _check_layouts(layouts, used, ref)
    if not ranges:
        return None, None, range_min, None
    # Common beams: the reference's, then the others' new ones (more beams first).
    order = [widest] + sorted((k for k in used if k != widest), key=lambda k: (-layouts[k].num_beams, k))
    beam_angles, columns = _common_beams(layouts, order, ref, abs(ref.increment) / division)
    num_beams = len(beam_angles)
    out = _padded_ranges(ranges, layout_of, used, columns, num_beams)
    new_range_min = range_min if np.float32(range_min) > np.float32(PAD_RANGE) else PAD_RANGE_MIN
    note = _padding_note(src, layouts, layout_of, order, ref, division, num_beams, len(ranges),
                         range_min, new_range_min)
    return np.asarray(beam_angles, dtype=np.float64), out, new_range_min, note


def _check_layouts(layouts, used, ref: BeamLayout) -> int:
    """The subdivision of ``ref``'s increment whose grid every used layout lies on.

    Args:
        layouts: the :class:`BeamLayout` of the log, in order of first appearance.
        used: indices into ``layouts`` of the layouts to check, in order of first appearance.
        ref: the widest layout, the reference.

    Returns:
        The smallest d in 1..:data:`_MAX_SUBDIVISION` such that every layout's beam angles
        (rad) lie within :data:`_GRID_TOLERANCE` of ``ref.angles[0] + j * |ref.increment| / d``.

    Raises:
        LogError: a layout leaves the reference's grid or range (or its beams run the other
            way), naming the first scan with that layout and both layouts.
    """
    step = abs(ref.increment)
    lo, hi = float(ref.angles.min()) - step, float(ref.angles.max()) + step
    subdivisions = list(range(1, _MAX_SUBDIVISION + 1))
    for k in used:  # in order of first appearance
        layout = layouts[k]
        angles = layout.angles
        reason = None
        if layout.num_beams > 1 and ref.num_beams > 1 and (layout.increment > 0) != (ref.increment > 0):
            reason = "its beams run the other way"
        elif angles.min() <= lo + _GRID_TOLERANCE or angles.max() >= hi - _GRID_TOLERANCE:
            reason = "the angular range changes (beams beyond the widest scan's range)"
        else:
            offsets = (angles - ref.angles[0]) / step
            fits = [d for d in subdivisions
                    if np.max(np.abs(offsets * d - np.round(offsets * d))) * step / d <= _GRID_TOLERANCE]
            if not fits:
                reason = (f"its beams are not on the widest scan's angular grid, nor on one of 1/2..1/"
                          f"{_MAX_SUBDIVISION} of its increment shared with the layouts before it")
            else:
                subdivisions = fits
        if reason:
            raise LogError(
                f"{layout.where}: the beam layout changes from {ref.describe()} (the widest scan's, first at "
                f"{ref.where}) to {layout.describe()}: {reason}; scans may differ in their beam count only "
                "where every scan's beams lie on the widest scan's angular grid (or interleave with it) "
                "within its angular range"
            )
    return subdivisions[0]


def _common_beams(layouts, order, ref: BeamLayout, grid_step: float) -> tuple[list[float], dict[int, np.ndarray]]:
    """The common beam angles and where each layout's beams go among them.

    Args:
        layouts: the :class:`BeamLayout` of the log.
        order: indices into ``layouts``: the reference first, then the others in the order their
            new beams are appended.
        ref: the reference layout (``layouts[order[0]]``).
        grid_step: the common grid's spacing (rad): ``|ref.increment|`` over the subdivision.

    Returns:
        ``(beam_angles, columns)``: B common beam angles (rad, Python floats), and for each layout
        k in ``order`` a (B_k,) int64 array: the column of each of its beams among them.
    """
    # A beam's slot is its angle's index on the common grid: beams of equal slots are one beam.
    position: dict[int, int] = {}
    beam_angles: list[float] = []
    columns: dict[int, np.ndarray] = {}
    for k in order:
        slots = np.round((layouts[k].angles - ref.angles[0]) / grid_step).astype(np.int64)
        cols = []
        for slot, angle in zip(slots.tolist(), layouts[k].angles.tolist()):
            if slot not in position:
                position[slot] = len(beam_angles)
                beam_angles.append(angle)
            cols.append(position[slot])
        columns[k] = np.asarray(cols, dtype=np.int64)
    return beam_angles, columns


def _padded_ranges(ranges, layout_of: np.ndarray, used, columns, num_beams: int) -> np.ndarray:
    """(T, B) float32 ranges (m): each scan's readings in its layout's columns, :data:`PAD_RANGE` elsewhere.

    Args:
        ranges: T (B_i,) float32 arrays (m), each scan's ranges in its layout's order.
        layout_of: (T,) int64: each scan's layout.
        used: the layouts present.
        columns: per layout, (B_i,) int64 columns of its beams (:func:`_common_beams`).
        num_beams: B, the number of common beams.
    """
    out = np.full((len(ranges), num_beams), PAD_RANGE, dtype=np.float32)
    for k in used:
        rows = np.nonzero(layout_of == k)[0]
        if rows.size:
            out[np.ix_(rows, columns[k])] = np.stack([ranges[i] for i in rows])
    return out


def _padding_note(src: str, layouts, layout_of: np.ndarray, order, ref: BeamLayout, division: int,
                  num_beams: int, num_scans: int, range_min: float, new_range_min: float) -> str:
    """One sentence saying what was padded (for a ``UserWarning`` and the log's ``notes``).

    Args:
        src: the file.
        layouts, layout_of, order, ref: as in :func:`pad_beam_layouts` and :func:`_common_beams`.
        division: the subdivision of the reference's increment the beams lie on.
        num_beams: B, the number of common beams.
        num_scans: T, the number of scans.
        range_min, new_range_min: the sensor's range_min (m) before and after padding.
    """
    counts = Counter(layout_of.tolist())
    padded = sum(n for k, n in counts.items() if layouts[k].num_beams < num_beams)
    seen = "; ".join(f"{counts[k]} scans of {layouts[k].brief()}" for k in order)
    target = (f"the widest scan's {num_beams} beam angles" if num_beams == ref.num_beams else
              f"{num_beams} beam angles (the widest scan's {ref.num_beams} and the others' beams interleaved "
              f"1/{division} of its increment apart: {num_beams / ref.num_beams:.1f} times the beams per scan)")
    note = (f"{src}: the beam layout changes within the log ({seen}); {padded} of {num_scans} scans were "
            f"padded to {target}. A padded beam reads {PAD_RANGE:g} m, below range_min {new_range_min:g} m: "
            "invalid, it neither clears nor marks a cell nor counts in a likelihood")
    if new_range_min != range_min:
        note += f" (range_min raised from {range_min:g} m to {PAD_RANGE_MIN:g} m for this)"
    return note + "."
