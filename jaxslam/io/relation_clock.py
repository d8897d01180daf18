"""Relations written on another clock than the log's: :func:`align_relations_clock`.

A relations file names its scans by the original log's timestamps. A converter that rewrote the
timestamps (MIT Killian's bag: 1,000,000,000 s onward, 0.1 s apart) keeps the scans and their
order but loses that key, so :func:`jaxslam.metrics.relation_error` cannot find a relation's two
scans. Every distinct relation timestamp is still one scan of the log, and the indices increase
with the time. Two things say which:

- **the time gaps**: the original scans came at a nearly steady period, so the number of scans
  between two relation timestamps is close to their time apart over the period (exactly, where
  the gap is short; within a few scans over a long one);
- **the odometry**: a relation between two neighbouring relation timestamps (most of them: a
  short step of the robot) must match the log's odometry between the two scans, to the
  odometry's error over a second or two.

:func:`align_relations_clock` finds the indices that best satisfy both: each timestamp's index is
its nominal one (its time from the first over the period) plus an offset, and a Viterbi pass over
the timestamps in order picks the offsets, with a cost per scan that an offset changes by between
neighbours and a robust chi-square of each neighbour relation against the odometry.

What it cannot pin: where the robot stood still or moved evenly, shifting a run of timestamps by
one scan leaves every neighbour relation's odometry the same. ``margin`` says where: the cost of
the best alignment that moves that timestamp by one scan, above the best. A relation that spans a
loop and ends at such a timestamp is off by that scan's motion (the robot's speed over one scan
period), so a relation error measured through this alignment carries it; measure its spread over
``gap_cost`` before trusting the last centimetre.

**The laser pins what the odometry cannot.** A relation is the motion that lays its second scan
over its first. Where the odometry and the laser were stamped on clocks a scan apart (MIT
Killian: the odometry read at a scan's stamp is where the laser was one scan later), the
odometry's alignment is off by that scan everywhere, and a shift of every index by the same
amount changes no neighbour relation's odometry. Given the log's scans, every relation's two
scans are laid over each other under its motion at each shift of every index by ``-max_shift``
to ``max_shift`` scans. The shift with the smallest mean misfit is taken (``laser_shift``) where
it beats no shift by three standard errors of the relations' paired differences. It is one
shift for the whole log, measured over all its relations: a single relation's scans are too
noisy a witness to move one timestamp.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxslam.geometry import between_np, wrap_angle_np
from jaxslam.io.relations import Relations
from jaxslam.laser import SensorSpec, scan_misfit, scan_points
from jaxslam.laserlog import LogError, least_misfit_over_none

__all__ = ["ClockAlignment", "align_relations_clock"]


class ClockAlignment(NamedTuple):
    """What :func:`align_relations_clock` returns."""

    relations: Relations
    """The relations with ``t1`` and ``t2`` replaced by their scans' timestamps in the log."""
    times: np.ndarray
    """(K,) float64: the relations' distinct timestamps on their own clock, increasing (s)."""
    scan_index: np.ndarray
    """(K,) int: the log scan of each of ``times`` (``laser_shift`` included)."""
    margin: np.ndarray
    """(K,) float64: the cost of the best alignment that moves this timestamp by one scan, above
    the best (chi-square units): small where the robot stood still or moved evenly."""
    residual: np.ndarray
    """(R,) float64: each relation's translation error against the odometry at the scans the
    odometry aligned, before ``laser_shift`` (m); nan for a relation between timestamps that are
    not neighbours (a loop's)."""
    scan_period: float
    """The original log's scan period the nominal indices used (s)."""
    laser_shift: int = 0
    """Scans added to every index the odometry aligned, chosen by the scans (0 without them)."""
    shift_misfit: np.ndarray | None = None
    """(2 * max_shift + 1,) float64: the relations' mean scan misfit (m²,
    :func:`jaxslam.laser.scan_misfit`) at each shift from ``-max_shift``, inf where a shift leaves
    the log; None without scans."""


def align_relations_clock(relations: Relations, timestamps, odometry, scan_period: float | None = None,
                          max_offset: int = 40, gap_cost: float = 5.0, long_gap: float = 10.0,
                          sigma_xy: float = 0.05, sigma_theta: float = 0.03, max_cost: float = 50.0,
                          ranges=None, sensor: SensorSpec | None = None, max_shift: int = 2,
                          misfit_radius: float = 0.3) -> ClockAlignment:
    """Find the log scan of every relation timestamp (see the module docstring).

    Args:
        relations: the relations on their own clock (R relations, K distinct timestamps).
        timestamps: (T,) the log's scan timestamps (s), increasing: what the aligned relations use.
        odometry: (T, 3) the log's odometry poses at its scans (m, m, rad).
        scan_period: the original log's scan period (s); default: the relations' time span over
            T - 1, right when the relations run from the log's first scans to its last.
        max_offset: largest difference, in scans, between a timestamp's index and its nominal
            one (its time from the first relation timestamp over ``scan_period``).
        gap_cost: cost (chi-square units) per scan by which the offset changes between two
            neighbouring timestamps at most ``long_gap`` apart; a longer gap costs less in
            proportion (its scan count is less certain).
        long_gap: see ``gap_cost`` (s).
        sigma_xy: the odometry's translation error over a neighbour relation (m).
        sigma_theta: ... and its heading error (rad).
        max_cost: largest chi-square one relation adds (a robust cap: odometry slips).
        ranges: optional (T, B) the log's scans (m); with ``sensor``, the laser chooses one shift
            of every index (see the module docstring). Without them the odometry's alignment
            is returned as it is.
        sensor: the log's laser (beam angles, mounting, valid ranges).
        max_shift: largest shift the scans may choose (scans).
        misfit_radius: a point's misfit is its squared distance to the nearest point of the
            other scan, capped at this radius (m): the parts of a scan the other did not see.

    Returns:
        :class:`ClockAlignment`.

    Raises:
        LogError: before any work, for a log whose arrays disagree, relations with more distinct
            timestamps than the log has scans or a time span longer than the log at
            ``scan_period``, scans that are not one per log scan or given without their sensor;
            after the pass, for a best alignment that reaches ``max_offset``
            (the window was too narrow: its true offset may lie beyond).
    """
    times_log = np.asarray(timestamps, np.float64)
    odometry = np.asarray(odometry, np.float64)
    times, period = _checked_times(relations, times_log, odometry, scan_period, ranges, sensor, max_shift,
                                   misfit_radius)
    first = np.searchsorted(times, relations.t1)
    second = np.searchsorted(times, relations.t2)
    neighbours = np.abs(first - second) == 1
    if not np.any(neighbours):
        raise LogError("align_relations_clock: no relation joins two neighbouring timestamps: the odometry has "
                       "nothing to align")
    nominal = np.round((times - times[0]) / period).astype(np.int64)
    offsets = np.arange(-max_offset, max_offset + 1)
    gap_costs = gap_cost * np.minimum(1.0, long_gap / np.maximum(np.diff(times), 1e-9))
    by_step = _neighbour_relations(first, second, neighbours, times.size)
    step_cost = _StepCost(relations.motion, first, nominal, offsets, odometry, by_step,
                          (sigma_xy, sigma_theta, max_cost))
    marginal = _min_marginals(step_cost, gap_costs, offsets, times.size)
    best = np.argmin(marginal, axis=1)
    rows = np.arange(times.size)
    neighbour_best = np.minimum(marginal[rows, np.maximum(best - 1, 0)], marginal[rows, np.minimum(best + 1, offsets.size - 1)])
    margin = neighbour_best - marginal[rows, best]
    if np.any(np.abs(offsets[best]) == max_offset):
        raise LogError(f"align_relations_clock: the best alignment reaches the offset window's edge ({max_offset} "
                       f"scans): raise max_offset or give the scan period")
    scan_index = nominal + offsets[best]
    if np.any(np.diff(scan_index) <= 0):  # only where the window forbade nothing: a tie
        raise LogError("align_relations_clock: two relation timestamps came to the same scan (the odometry "
                       "could not tell them apart); give the scan period")
    moved = between_np(odometry[scan_index[first]], odometry[scan_index[second]])
    residual = np.where(neighbours, np.hypot(*(moved[:, :2] - relations.motion[:, :2]).T), np.nan)
    laser_shift, shift_misfit = 0, None
    if ranges is not None:
        per_relation = _shift_misfits(relations.motion, scan_index[first], scan_index[second], ranges, sensor,
                                      max_shift, misfit_radius)
        shift_misfit = per_relation.mean(axis=1)
        laser_shift = least_misfit_over_none(per_relation, max_shift, z=3.0) - max_shift
        scan_index = scan_index + laser_shift
    aligned = relations._replace(t1=times_log[scan_index[first]], t2=times_log[scan_index[second]])
    return ClockAlignment(aligned, times, scan_index, margin, residual, period, laser_shift, shift_misfit)


def _shift_misfits(motion, first_index, second_index, ranges, sensor, max_shift, radius) -> np.ndarray:
    """(2 * max_shift + 1, R) each relation's :func:`scan_misfit` with every index shifted by
    -max_shift..max_shift scans; inf rows for a shift that moves an index out of the log."""
    num_scans, num_beams = np.shape(ranges)
    shifts = np.arange(-max_shift, max_shift + 1)
    ends = np.concatenate([first_index, second_index])
    needed = np.unique((ends[None] + shifts[:, None]).ravel())
    needed = needed[(needed >= 0) & (needed < num_scans)]
    points, valid = scan_points(np.asarray(ranges)[needed], sensor, float(sensor.range_max), num_beams)
    row = {int(i): k for k, i in enumerate(needed)}
    misfit = np.full((shifts.size, len(motion)), np.inf)
    for j, shift in enumerate(shifts):
        a, b = first_index + shift, second_index + shift
        if min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= num_scans:
            continue
        misfit[j] = [scan_misfit(m, points[row[i]][valid[row[i]]], points[row[k]][valid[row[k]]], radius)
                     for m, i, k in zip(motion, a, b)]
    return misfit


def _checked_times(relations, times_log, odometry, scan_period, ranges, sensor, max_shift, misfit_radius):
    """The relations' distinct timestamps and the scan period, after every check that can be made
    before any work (see :func:`align_relations_clock`'s Raises)."""
    num_scans = times_log.size
    if times_log.ndim != 1 or odometry.shape != (num_scans, 3):
        raise LogError(f"align_relations_clock: timestamps (T,) and odometry (T, 3) must agree, got "
                       f"{times_log.shape} and {odometry.shape}")
    if not (np.all(np.isfinite(odometry)) and np.all(np.diff(times_log) > 0)):
        raise LogError("align_relations_clock: the log's timestamps must increase and its odometry be finite")
    if (ranges is None) != (sensor is None):
        raise LogError("align_relations_clock: give the log's scans and its sensor together")
    if ranges is not None and np.shape(ranges) != (num_scans, np.shape(sensor.beam_angles)[0]):
        raise LogError(f"align_relations_clock: the scans have shape {np.shape(ranges)}, expected "
                       f"({num_scans}, {np.shape(sensor.beam_angles)[0]}): one per log scan, one range per beam")
    if not (max_shift >= 0 and misfit_radius > 0):
        raise LogError(f"align_relations_clock: max_shift must be >= 0 and misfit_radius > 0, got {max_shift} "
                       f"and {misfit_radius}")
    times = np.unique(np.concatenate([relations.t1, relations.t2]))
    if times.size > num_scans:
        raise LogError(f"align_relations_clock: the relations name {times.size} distinct scans, more than the "
                       f"log's {num_scans}: they are not this log's")
    span = float(times[-1] - times[0])
    period = span / max(num_scans - 1, 1) if scan_period is None else float(scan_period)
    if not period > 0 or round(span / period) > num_scans - 1:
        raise LogError(f"align_relations_clock: the relations span {span:.1f} s, {span / period:.0f} scans at a "
                       f"{period:.4f} s period, longer than the log's {num_scans} scans")
    return times, period


def _min_marginals(step_cost, gap_costs, offsets, num_times) -> np.ndarray:
    """(K, O) each timestamp's min-marginal cost per offset: the forward and the backward pass of
    min-sum over the chain of timestamps, added (the outside costs, 0 or inf, counted twice)."""
    change = np.abs(offsets[:, None] - offsets[None])
    forward = np.zeros((num_times, offsets.size))
    backward = np.zeros((num_times, offsets.size))
    forward[0] = step_cost.outside(0)
    for k in range(num_times - 1):
        forward[k + 1] = np.min(forward[k][:, None] + step_cost(k) + gap_costs[k] * change, axis=0)
    backward[-1] = step_cost.outside(num_times - 1)
    for k in range(num_times - 2, -1, -1):
        backward[k] = np.min(step_cost(k) + gap_costs[k] * change + backward[k + 1][None], axis=1) + step_cost.outside(k)
    return forward + backward


def _neighbour_relations(first, second, neighbours, num_times) -> list:
    """For each step k -> k + 1 between neighbouring timestamps, its relations' indices."""
    step = np.minimum(first, second)
    chosen = np.nonzero(neighbours)[0]
    order = chosen[np.argsort(step[chosen], kind="stable")]
    bounds = np.searchsorted(step[order], np.arange(num_times + 1))
    return [order[bounds[k]:bounds[k + 1]] for k in range(num_times)]


class _StepCost:
    """The cost of each pair of offsets (k's, k + 1's): the neighbour relations' robust chi-square
    against the odometry, and an infinite cost for an index outside the log or not after k's."""

    def __init__(self, motion, first, nominal, offsets, odometry, by_step, noise):
        self.motion, self.first, self.nominal, self.offsets = motion, first, nominal, offsets
        self.odometry, self.by_step, self.noise = odometry, by_step, noise

    def outside(self, k) -> np.ndarray:
        """(O,) inf where timestamp k's index would fall outside the log."""
        index = self.nominal[k] + self.offsets
        return np.where((index < 0) | (index >= self.odometry.shape[0]), np.inf, 0.0)

    def __call__(self, k) -> np.ndarray:
        sigma_xy, sigma_theta, max_cost = self.noise
        here = self.nominal[k] + self.offsets
        there = self.nominal[k + 1] + self.offsets
        cost = np.where(there[None] > here[:, None], 0.0, np.inf) + self.outside(k + 1)[None]
        last = self.odometry.shape[0] - 1
        here_pose = self.odometry[np.clip(here, 0, last)][:, None]
        there_pose = self.odometry[np.clip(there, 0, last)][None]
        for s in self.by_step[k]:
            # The relation's own direction: from t1's scan to t2's.
            moved = between_np(here_pose, there_pose) if self.first[s] == k else between_np(there_pose, here_pose)
            wanted = self.motion[s]
            chi2 = (np.sum((moved[..., :2] - wanted[:2]) ** 2, axis=-1) / sigma_xy ** 2
                    + wrap_angle_np(moved[..., 2] - wanted[2]) ** 2 / sigma_theta ** 2)
            cost = cost + np.minimum(chi2, max_cost)
        return cost
