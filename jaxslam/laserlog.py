"""The one data type every reader and the simulator produce: :class:`LaserLog`.

A log lives on the host (NumPy). Update selection (GMapping's linear/angular
thresholds) happens here, before the filter: :func:`select_updates` picks the
scans the filter processes and composes the odometry between them into one
motion each. :func:`trajectory_per_scan` gives every scan a pose from the processed ones (the
relations of Kümmerle et al., and any per-scan metric, need a pose at every scan's timestamp);
:func:`poses_at` reads a time-stamped pose stream (odometry, ground truth) at other timestamps,
as the readers do to pair each scan with odometry.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from jaxslam.geometry import between, compose, interpolate, wrap_angle_np
from jaxslam.laser import SensorSpec, scan_misfit, scan_points


class LogError(ValueError):
    """A log (file or in-memory) is malformed; the message names the source and the place."""


@dataclasses.dataclass(frozen=True, eq=False)
class LaserLog:
    """A 2-D laser log: one row per scan, odometry read at each scan's timestamp."""

    timestamps: np.ndarray
    """(T,) float64 seconds, non-decreasing."""
    odometry: np.ndarray
    """(T, 3) float64 odometry poses [x, y, theta] (m, m, rad) at each scan's timestamp."""
    ranges: np.ndarray
    """(T, B) float32 ranges in metres; ``>= sensor.range_max`` means "no return"."""
    sensor: SensorSpec
    """The laser: beam angles, valid range interval, mounting pose on the robot."""
    ground_truth: np.ndarray | None = None
    """Optional (T, 3) float64 true poses, for simulated logs."""
    source: str = "<memory>"
    """Where the log came from (a path), used in error messages."""
    notes: tuple[str, ...] = ()
    """What the reader changed or assumed while reading (e.g. scans padded to a common beam
    layout), one sentence each; ``jaxslam map`` records them in ``summary.json``."""
    warnings: tuple[str, ...] = ()
    """What looks wrong with the log but does not stop it being used (scans with no valid
    return, long gaps in time, repeated timestamps dropped, a second odometry source that
    disagrees), one sentence each; ``jaxslam map`` prints them and records them in
    ``summary.json``'s ``warnings``. See :func:`check_log`."""

    def __post_init__(self):
        ts = np.asarray(self.timestamps, dtype=np.float64)
        odom = np.asarray(self.odometry, dtype=np.float64)
        ranges = np.asarray(self.ranges, dtype=np.float32)
        object.__setattr__(self, "timestamps", ts)
        object.__setattr__(self, "odometry", odom)
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))
        object.__setattr__(self, "warnings", tuple(str(n) for n in self.warnings))
        src = self.source
        if ts.ndim != 1:
            raise LogError(f"{src}: timestamps have shape {ts.shape}, expected (T,) (one per scan)")
        if ts.shape[0] == 0:
            raise LogError(f"{src}: the log is empty (no scans)")
        num_scans = ts.shape[0]
        num_beams = int(np.shape(self.sensor.beam_angles)[0])
        if ranges.shape != (num_scans, num_beams):
            raise LogError(
                f"{src}: ranges have shape {ranges.shape}, expected ({num_scans}, {num_beams}) "
                "(scans x beams of the sensor)"
            )
        if odom.shape != (num_scans, 3):
            raise LogError(f"{src}: odometry has shape {odom.shape}, expected ({num_scans}, 3)")
        _check_finite(src, "timestamp", ts)
        _check_finite(src, "odometry", odom)
        bad = ~np.isfinite(ranges) | (ranges < 0)
        if bad.any():
            scan, beam = np.argwhere(bad)[0]
            raise LogError(
                f"{src}: scan {scan} (t={ts[scan]:.6f}) beam {beam} has range {ranges[scan, beam]!r}: "
                "ranges must be finite and non-negative"
            )
        back = np.nonzero(np.diff(ts) < 0)[0]
        if back.size:
            i = int(back[0])
            raise LogError(
                f"{src}: timestamps go backwards at scan {i + 1} ({ts[i]:.6f} -> {ts[i + 1]:.6f})"
            )
        if self.ground_truth is not None:
            gt = np.asarray(self.ground_truth, dtype=np.float64)
            object.__setattr__(self, "ground_truth", gt)
            if gt.shape != (num_scans, 3):
                raise LogError(f"{src}: ground truth has shape {gt.shape}, expected ({num_scans}, 3)")
            _check_finite(src, "ground truth", gt)

    @property
    def num_scans(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def num_beams(self) -> int:
        return int(self.ranges.shape[1])

    @property
    def duration(self) -> float:
        """Seconds from the first to the last scan."""
        return float(self.timestamps[-1] - self.timestamps[0])

    def subset(self, indices) -> "LaserLog":
        """The scans at ``indices`` (sorted), as a new log."""
        idx = np.asarray(indices)
        gt = None if self.ground_truth is None else self.ground_truth[idx]
        return LaserLog(self.timestamps[idx], self.odometry[idx], self.ranges[idx], self.sensor, gt, self.source,
                        self.notes, self.warnings)


GAP_FACTOR = 10.0
"""A time step longer than this many median scan intervals is a gap (:func:`check_log` warns)."""
DEAD_SENSOR_SHARE = 0.9
"""A log where more than this share of scans have no valid return is refused (:func:`check_log`)."""


def last_of_each_timestamp(timestamps) -> np.ndarray:
    """(T,) bool: True for the last of each run of equal (non-decreasing) timestamps."""
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    keep = np.ones(ts.size, dtype=bool)
    keep[:-1] = ts[1:] != ts[:-1]
    return keep


def no_return_scans(log: LaserLog) -> np.ndarray:
    """(T,) bool: scans of which no beam reads in [range_min, range_max) and above 0 (all 0, all max, ...)."""
    r = log.ranges
    valid = (r > 0) & (r >= np.float32(float(log.sensor.range_min))) & (r < np.float32(float(log.sensor.range_max)))
    return ~np.any(valid, axis=1)


def check_log(log: LaserLog) -> LaserLog:
    """The log as ``jaxslam map`` uses it, with its oddities in ``warnings``.

    * Repeated timestamps: of the scans that share a timestamp only the last is kept (the
      rule ``jaxslam eval`` applies to trajectory files too), with a warning naming the first.
    * Scans with no valid return (every beam 0, below ``range_min`` or at/above ``range_max``):
      a warning with their count and the first; more than :data:`DEAD_SENSOR_SHARE` of the
      scans is a dead sensor and raises :class:`LogError`.
    * Gaps: time steps longer than :data:`GAP_FACTOR` median scan intervals, a warning with
      their count, the first and the longest.

    Raises:
        LogError: a dead sensor (the message names the count and the first scan).
    """
    src = log.source
    found = list(log.warnings)
    keep = last_of_each_timestamp(log.timestamps)
    if not keep.all():
        drop = np.nonzero(~keep)[0]
        i = int(drop[0])
        found.append(f"{src}: {drop.size} scans repeat the timestamp of the scan after them (first: scans {i} and "
                     f"{i + 1} at t={log.timestamps[i]:.6f}); of each repeated timestamp only the last scan is kept")
        log = LaserLog(log.timestamps[keep], log.odometry[keep], log.ranges[keep], log.sensor,
                       None if log.ground_truth is None else log.ground_truth[keep], src, log.notes, ())
    dead = no_return_scans(log)
    count = int(dead.sum())
    if count:
        i = int(np.argmax(dead))
        what = (f"{count} of {log.num_scans} scans have no valid return (every beam 0, below range_min="
                f"{float(log.sensor.range_min):g} m or at/above range_max={float(log.sensor.range_max):g} m; first: scan {i}, "
                f"t={log.timestamps[i]:.6f})")
        if count > DEAD_SENSOR_SHARE * log.num_scans:
            raise LogError(f"{src}: the laser looks dead: {what}; check the log's ranges and range_max")
        found.append(f"{src}: {what}; they add nothing to the map")
    steps = np.diff(log.timestamps)
    positive = steps[steps > 0]
    if positive.size:
        median = float(np.median(positive))
        gaps = np.nonzero(steps > GAP_FACTOR * median)[0]
        if gaps.size:
            i, j = int(gaps[0]), int(np.argmax(steps))
            found.append(f"{src}: {gaps.size} gaps in time longer than {GAP_FACTOR:g} x the median scan interval "
                         f"({median:.3g} s): first {steps[i]:.3g} s after scan {i} (t={log.timestamps[i]:.6f}), "
                         f"longest {steps[j]:.3g} s after scan {j} (t={log.timestamps[j]:.6f})")
    return dataclasses.replace(log, warnings=tuple(found))


def _check_finite(src: str, what: str, values: np.ndarray) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.argwhere(bad)[0][0])
        raise LogError(f"{src}: scan {row} has a non-finite {what} {values[row]!r}")


class UpdateSelection(NamedTuple):
    """The scans the filter processes and the motion between them."""

    indices: np.ndarray
    """(S,) int indices into the log of the processed scans; the first is scan 0."""
    motions: np.ndarray
    """(S, 3) float32 odometry motion from the previous processed scan to this one, in the
    previous scan's robot frame; row 0 is zero."""


def select_updates(log: LaserLog, linear_update: float, angular_update: float) -> UpdateSelection:
    """GMapping's update rule: process a scan once the robot has moved ``linear_update``
    metres or turned ``angular_update`` radians (odometry, accumulated along the path)
    since the last processed scan. The first scan is always processed.

    Both thresholds <= 0 process every scan.

    The motions are computed in float32 in the log's local frame (:func:`local_frame_offset`):
    a log far from the origin gives the motions of the same log near it (float32 resolves 0.5 m
    at 5,000 km), and a log already local (the filter's) gives the same bits as ever.
    """
    odom = to_local(log.odometry, frame_offset_of(log.odometry))
    steps = np.asarray(between(odom[:-1], odom[1:]), dtype=np.float64)
    step_lin = np.hypot(steps[:, 0], steps[:, 1])
    step_ang = np.abs(steps[:, 2])
    indices = [0]
    lin = ang = 0.0
    for i in range(1, log.num_scans):
        lin += step_lin[i - 1]
        ang += step_ang[i - 1]
        if lin >= linear_update or ang >= angular_update:
            indices.append(i)
            lin = ang = 0.0
    idx = np.asarray(indices, dtype=np.int64)
    motions = np.zeros((idx.size, 3), dtype=np.float64)
    motions[1:] = np.asarray(between(odom[idx[:-1]], odom[idx[1:]]))
    return UpdateSelection(idx, motions.astype(np.float32))


class PosesAt(NamedTuple):
    """Poses of a time-stamped stream read at query timestamps."""

    poses: np.ndarray
    """(Q, 3) float64 [x, y, theta] (m, m, rad) at each query time; rows outside the stream's
    time span are zero (see ``covered``)."""
    covered: np.ndarray
    """(Q,) bool: whether the query time lies within [first, last] stream timestamp."""


def poses_at(query_times, stream_times, stream_poses) -> PosesAt:
    """Interpolate a pose stream at ``query_times`` with :func:`jaxslam.geometry.interpolate`.

    Args:
        query_times: (Q,) seconds, any order.
        stream_times: (M,) seconds, non-decreasing (equal neighbours allowed), M >= 1.
        stream_poses: (M, 3) poses [x, y, theta] (m, m, rad) at ``stream_times``.

    Returns:
        :class:`PosesAt`: (Q, 3) float64 poses and a (Q,) mask of the query times inside the
        stream's span. A query equal to a stream timestamp gets that stream pose exactly;
        one strictly between two stream messages gets the pose that fraction of the way
        along the relative motion between them. Queries outside the span are not
        extrapolated: the caller decides what to do with them (the readers drop and warn).
    """
    query = np.asarray(query_times, dtype=np.float64).reshape(-1)
    times = np.asarray(stream_times, dtype=np.float64).reshape(-1)
    poses = np.asarray(stream_poses, dtype=np.float64).reshape(-1, 3)
    if times.size == 0 or poses.shape[0] != times.size:
        raise ValueError(f"poses_at needs M >= 1 times and (M, 3) poses, got {times.shape} and {poses.shape}")
    if np.any(np.diff(times) < 0):
        raise ValueError("poses_at needs non-decreasing stream timestamps")
    covered = (query >= times[0]) & (query <= times[-1])
    # Index of the last stream message at or before each query (side="right" so that with
    # equal neighbours the later one is taken; then times[j + 1] > query strictly).
    before = np.clip(np.searchsorted(times, query, side="right") - 1, 0, times.size - 1)
    after = np.minimum(before + 1, times.size - 1)
    span = times[after] - times[before]
    exact = (query == times[before]) | (span <= 0)
    fraction = np.where(exact, 0.0, (query - times[before]) / np.where(span > 0, span, 1.0))
    fraction = np.clip(fraction, 0.0, 1.0)
    # interpolate runs in float32: in the stream's local frame, so that a stream far from the
    # origin (UTM coordinates) reads as the same stream near it; exact hits keep the stream pose
    # bit for bit.
    offset = frame_offset_of(poses)
    local = to_local(poses, offset)
    result = to_world(np.asarray(interpolate(local[before], local[after], fraction), dtype=np.float64), offset)
    result = np.where(exact[:, None], poses[before], result)
    result = np.where(covered[:, None], result, 0.0)
    return PosesAt(result, covered)


def trajectory_per_scan(log: LaserLog, processed_indices, processed_poses) -> np.ndarray:
    """A pose for every scan of ``log`` from the poses of the processed scans.

    At a processed scan the result is its pose. At a skipped scan ``i`` it is the pose of
    the nearest processed scan ``k`` before it composed with the odometry motion since:
    ``compose(pose[k], between(odom[k], odom[i]))``. Scans before the first processed one
    use the first processed scan the same way (the motion is then backwards in time).

    Args:
        log: the log the filter ran on (T scans).
        processed_indices: (S,) int, strictly increasing scan indices in [0, T), S >= 1.
        processed_poses: (S, 3) poses [x, y, theta] (m, m, rad) estimated at those scans.

    Returns:
        (T, 3) float64 poses (m, m, rad), theta wrapped to (-pi, pi].
    """
    idx = np.asarray(processed_indices).reshape(-1)
    poses = np.asarray(processed_poses, dtype=np.float64)
    if idx.size == 0:
        raise ValueError("trajectory_per_scan needs at least one processed scan")
    if not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"processed_indices must be integers, got dtype {idx.dtype}")
    if poses.shape != (idx.size, 3):
        raise ValueError(f"processed_poses has shape {poses.shape}, expected ({idx.size}, 3)")
    if np.any(np.diff(idx) <= 0):
        raise ValueError("processed_indices must be strictly increasing")
    if idx[0] < 0 or idx[-1] >= log.num_scans:
        raise ValueError(f"processed_indices must lie in [0, {log.num_scans}), got {idx[0]}..{idx[-1]}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("processed_poses must be finite")
    scans = np.arange(log.num_scans)
    # The processed scan each scan hangs off: the last one at or before it, else the first.
    anchor = np.clip(np.searchsorted(idx, scans, side="right") - 1, 0, idx.size - 1)
    # compose runs in float32: in the log's local frame, so that a log far from the origin gets
    # the trajectory of the same log near it, shifted; processed scans keep their pose exactly.
    offset = frame_offset_of(log.odometry)
    odom = to_local(log.odometry, offset)
    motion = between(odom[idx[anchor]], odom)
    result = to_world(np.asarray(compose(to_local(poses, offset)[anchor], motion), dtype=np.float64), offset)
    result[idx] = poses
    result[idx, 2] = wrap_angle_np(poses[:, 2])
    return result


# ---------------------------------------------------------------------------------------------
# The filter's local frame (the one place that moves poses between it and the log's frame).


def local_frame_offset(log: LaserLog) -> np.ndarray:
    """(2,) float64: the origin of the filter's local frame in the log's frame, where the virtual
    grid is centred: :func:`frame_offset_of` the log's odometry. Subtracted on the host in float64
    before anything is cast to float32 (float32 resolves 0.5 m at 5,000 km from the origin, e.g.
    in UTM coordinates)."""
    return frame_offset_of(log.odometry)


def frame_offset_of(poses) -> np.ndarray:
    """(2,) float64: the local frame's origin for poses (N, 3) (or points (N, 2)): the first
    one's translation rounded to a multiple of 64 m (zeros for none)."""
    # Rounded to a multiple of 64 m: poses that start within 32 m of the origin stay exactly as
    # given, and shifting them by a multiple of 64 m changes no bit of the float32 arithmetic done
    # in the local frame (the local poses are equal); |local coordinates| <= 32 m + their extent.
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape[0] == 0:
        return np.zeros(2)
    return np.round(poses[0, :2] / 64.0) * 64.0 + 0.0


def to_world(poses, frame_offset) -> np.ndarray:
    """Local-frame poses (..., 3) or points (..., 2) in the log's (world) frame: float64, the
    (2,) ``frame_offset`` added."""
    out = np.array(poses, dtype=np.float64)
    out[..., :2] += frame_offset
    return out


def to_local(poses, frame_offset) -> np.ndarray:
    """World-frame poses (..., 3) or points (..., 2) in the filter's local frame: float64, the
    (2,) ``frame_offset`` subtracted."""
    out = np.array(poses, dtype=np.float64)
    out[..., :2] -= frame_offset
    return out


def grid_to_world(grid, frame_offset):
    """A grid (``GridSpec`` or ``PagedGridSpec``) of the local frame placed in the log's frame:
    its origin moved by the (2,) ``frame_offset``."""
    x0, y0 = (float(v) for v in frame_offset)
    return dataclasses.replace(grid, origin=(grid.origin[0] + x0, grid.origin[1] + y0))


def local_log(log: LaserLog, frame_offset) -> LaserLog:
    """``log`` with its odometry and ground truth in the local frame of ``frame_offset``
    (:func:`local_frame_offset`); the same object when the offset is zero."""
    if not np.any(frame_offset):
        return log
    ground_truth = None if log.ground_truth is None else to_local(log.ground_truth, frame_offset)
    return dataclasses.replace(log, odometry=to_local(log.odometry, frame_offset), ground_truth=ground_truth)


class OdometryLead(NamedTuple):
    """What :func:`estimate_odometry_lead` measured."""

    lead: float
    """Seconds by which the odometry leads the laser: the odometry read at a scan's timestamp is
    where the robot was ``lead`` s later. 0 where the scans cannot tell the leads apart."""
    leads: np.ndarray
    """(K,) float64: the leads tried (s), a quarter of the median scan interval apart."""
    misfit: np.ndarray
    """(K,) float64: the turning pairs' mean :func:`jaxslam.laser.scan_misfit` at each (m²)."""
    num_pairs: int
    """How many pairs of scans were laid over each other (0: too few turns to measure)."""


def estimate_odometry_lead(log: LaserLog, max_lead_scans: float = 2.0, gap: int = 2, min_turn: float = 0.15,
                           max_pairs: int = 800, radius: float = 0.3, z: float = 3.0) -> OdometryLead:
    """How far the log's odometry runs ahead of its laser in time, from the log's own scans.

    Pairs of scans ``gap`` apart over which the odometry turns at least ``min_turn`` are laid over
    each other under the odometry's motion read ``lead`` seconds earlier, for leads from
    ``-max_lead_scans`` to ``max_lead_scans`` median scan intervals. A turn is where a time offset
    shows: 0.1 s at 1.4 rad/s is 0.14 rad. The least mean misfit, refined by a parabola through
    its neighbours, is the lead, where it beats no lead by ``z`` standard errors of the pairs'
    paired differences; else 0. At most ``max_pairs`` pairs, drawn with a fixed seed: the same
    log gives the same lead.

    Args:
        log: the log (its timestamps, odometry, scans and sensor).
        max_lead_scans: the largest lead tried, in median scan intervals.
        gap: scans between the two of a pair.
        min_turn: the odometry's turn over a pair that makes it a witness (rad).
        max_pairs: the most pairs used.
        radius: :func:`jaxslam.laser.scan_misfit`'s cap (m).
        z: standard errors by which the best lead must beat none.

    Returns:
        :class:`OdometryLead`.

    Raises:
        ValueError: before any work, for a ``gap`` or ``max_pairs`` under 1, or a ``max_lead_scans``,
            ``radius`` or ``z`` that is not positive.
    """
    if gap < 1 or max_pairs < 1 or not (max_lead_scans > 0 and radius > 0 and z > 0):
        raise ValueError(f"estimate_odometry_lead: gap and max_pairs must be >= 1 and max_lead_scans, radius and z "
                         f"positive, got {gap}, {max_pairs}, {max_lead_scans}, {radius}, {z}")
    times = log.timestamps
    interval = float(np.median(np.diff(times))) if log.num_scans > 1 else 0.0
    steps = 4 * int(np.ceil(max_lead_scans))
    leads = interval * np.arange(-steps, steps + 1) / 4.0
    turn = np.abs(wrap_angle_np(log.odometry[gap:, 2] - log.odometry[:-gap, 2]))
    witnesses = np.nonzero(turn >= min_turn)[0]
    if interval <= 0 or witnesses.size < 20:
        return OdometryLead(0.0, leads, np.full(leads.size, np.nan), 0)
    rng = np.random.default_rng(0)
    first = np.sort(rng.choice(witnesses, size=min(max_pairs, witnesses.size), replace=False))
    second = first + gap
    used = np.unique(np.concatenate([first, second]))
    points, valid = scan_points(log.ranges[used], log.sensor, float(log.sensor.range_max), log.num_beams)
    scans = [points[k][valid[k]] for k in range(used.size)]
    row_first, row_second = np.searchsorted(used, first), np.searchsorted(used, second)
    motions = np.empty((leads.size, first.size, 3))  # each pair's motion at each lead
    local_odometry = to_local(log.odometry, frame_offset_of(log.odometry))  # float32 below: local
    for k, lead in enumerate(leads):
        odometry = poses_at(np.clip(times - lead, times[0], times[-1]), times, local_odometry).poses
        motions[k] = np.asarray(between(odometry[first], odometry[second]), np.float64)
    misfit = np.stack([scan_misfit(motions[:, n], scans[i], scans[j], radius)
                       for n, (i, j) in enumerate(zip(row_first, row_second))], axis=1)  # (K, pairs)
    return OdometryLead(_best_lead(leads, misfit, z), leads, misfit.mean(axis=1), int(first.size))


def least_misfit_over_none(misfit, none: int, z: float) -> int:
    """The row of ``misfit`` (K, N) (K candidates, each scored on the same N witnesses) with the
    least mean, where it beats row ``none`` (no correction) by ``z`` standard errors of the
    witnesses' paired differences; else ``none``: witnesses that cannot tell the candidates apart
    leave things as they were. Rows of inf (a candidate that cannot be scored) never win."""
    best = int(np.argmin(np.mean(misfit, axis=1)))
    gain = misfit[none] - misfit[best]
    if best == none or gain.size < 2:
        return none
    return best if gain.mean() > z * gain.std(ddof=1) / np.sqrt(gain.size) else none


def _best_lead(leads, misfit, z: float) -> float:
    """The lead of :func:`least_misfit_over_none`, refined by a parabola through its two
    neighbours; 0 where no lead wins."""
    mean = misfit.mean(axis=1)
    zero = leads.size // 2
    best = least_misfit_over_none(misfit, zero, z)
    if best == zero:
        return 0.0
    if 0 < best < leads.size - 1:
        left, centre, right = mean[best - 1:best + 2]
        curvature = left - 2.0 * centre + right
        step = leads[1] - leads[0]
        return float(leads[best] + (0.5 * step * (left - right) / curvature if curvature > 0 else 0.0))
    return float(leads[best])


def with_odometry_lead(log: LaserLog, lead: float) -> LaserLog:
    """The log with its odometry read ``lead`` seconds earlier at every scan (:func:`poses_at`; a
    scan whose read time falls before the log's first scan or after its last takes that end's
    pose); ``lead == 0`` returns the log itself, bit for bit."""
    if lead == 0:
        return log
    times = log.timestamps
    odometry = poses_at(np.clip(times - lead, times[0], times[-1]), times, log.odometry).poses
    note = f"the odometry read {lead:.3f} s earlier at every scan: it leads the laser by that much"
    return dataclasses.replace(log, odometry=odometry, notes=log.notes + (note,))
