"""What happened in a run, step by step: for finding where and why a map failed.

``jaxslam map`` writes ``steps.npz`` beside the map (:func:`step_record`: the filter's per-step
diagnostics and the processed scans' odometry and best path). :func:`diagnose` turns it, with
the run's ``trajectory.txt`` and optionally a relations file, into per-step series:

* ``ess_fraction``: the effective sample size over N before resampling; ``resampled``.
* ``distinct_ancestors``: how many particles the step's resampling kept (N where it did not
  resample). A long run of small values is particle depletion.
* ``surviving_lineages``: how many of the step's particles have descendants among the final
  particles. It falls to 1 at the final set's common ancestor: the filter cannot revise its
  path before that step (``coalescence_step``). A closure that needed a hypothesis dropped
  before it has no way back. The summary's ``pair_coalescence_per_step``
  (:func:`pair_coalescence`) is the rate at which lineages merge, and ``neutral_lag_quantile``
  where the recorded lag falls among those of the same resamplings with the lucky particles
  drawn afresh (:func:`neutral_coalescence_lags`): near 0, the same lineages kept winning.
  ``lineages_back``: how many distinct histories the particles held 25, 50, 100 and 200 steps
  back, the median over the steps (:func:`lineages_at_lag`): the alternatives a loop's closure
  can still choose from, at every step rather than at the end alone.
* ``correction_trans`` (m), ``correction_rot`` (rad): how far the best path's motion between
  two processed scans differs from the odometry's (in the earlier pose's frame): the filter's
  corrections; a wrong closure shows as a large one.
* ``spread`` (m): the particles' proposed positions' standard deviation (root of the trace).
* ``fallbacks``: particles whose scan match failed (SMP) or whose localizers lost all weight
  (LP); ``slipped``: particles that drew from the odometry's slip component (the filter's slip
  search, :func:`jaxslam.slip_search.slip_log_odds`; ``slip_steps`` in the summary and ``slips`` in the
  events list the steps); ``log_evidence``: the step's log p(z_t | z_1:t-1) estimate.
* ``increment_spread`` (nats): the spread over the particles of the step's log-weight
  increments; the summary's ``weight_persistence`` says whether what accumulates between two
  resamplings lasts or is noise (:func:`weight_persistence`): a filter that resamples on noise
  loses its histories at random, however good they were.
* with relations: every relation's translational and rotational error at the time of its later
  scan, and where on the best path that was; and every final particle's own relation error
  (:func:`final_particle_errors`: its history, from the record's ancestors and proposed poses),
  and for each relation the best of the particles the filter proposed at its later scan
  (:func:`closest_then`), and their mean by that step's weights (:func:`weighted_then`). A
  relation the run gets wrong that some particle had right then was lost to the weights (the
  weighted mean far above the best) or to a later resampling (near it); one that no particle had
  right, to the proposal.

``events`` lists the largest corrections and the worst relations with their step, time and
place, ranked (no threshold): where to look in the map first.
:func:`jaxslam.plotting.plot_diagnosis` draws it all; ``jaxslam diagnose RUN_DIR [RELATIONS]`` writes ``diagnosis.json`` and ``diagnosis.png``.
For a closed run (``graph.npz``) it draws the graph over the map (``graph.png``) and, with
relations, lists the returns the closure missed and why
(:func:`jaxslam.graph.missed.missed_returns`, ``closure`` in ``diagnosis.json``).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxslam.geometry import between_np, compose_np
from jaxslam.metrics import lookup_indices, motion_errors, normalized_weights, relation_error
from jaxslam.rbpf import final_best_particle, particle_paths

STEPS_FILE = "steps.npz"
"""The per-step record ``jaxslam map`` writes into its output folder."""

NUM_EVENTS = 5
"""How many of the largest corrections and worst relations ``events`` lists."""

NEUTRAL_DRAWS = 200
"""How many relabelled copies of a run's resamplings :func:`neutral_coalescence_lags` draws."""

MIN_STRETCH = 6
"""The fewest steps between two resamplings that :func:`weight_persistence` splits in halves."""

LINEAGE_LAGS = (25, 50, 100, 200)
"""The lags (steps) at which the summary's ``lineages_back`` counts the distinct histories."""


def step_record(log, result) -> dict[str, np.ndarray]:
    """The per-step record of a run (what ``steps.npz`` holds), world frame:

    ``scan_index`` (S,) the processed scans; ``timestamp`` (S,) s; ``odometry`` (S, 3) and
    ``best_path`` (S, 3) at them; for the S - 1 steps: ``ess``, ``resampled``, ``ancestors``
    (S-1, N), ``proposed_poses`` (S-1, N, 3) and ``log_weights`` (S-1, N) float32, ``log_evidence``, ``num_fallbacks``,
    ``num_slipped``, ``best_particle``; ``num_particles`` ().
    """
    info = result.info
    index = np.asarray(result.selection.indices)
    return {
        "scan_index": index.astype(np.int64),
        "timestamp": np.asarray(log.timestamps, np.float64)[index],
        "odometry": np.asarray(log.odometry, np.float64)[index],
        "best_path": np.asarray(result.best_path, np.float64),
        "ess": np.asarray(info.ess, np.float32),
        "resampled": np.asarray(info.resampled, bool),
        "ancestors": np.asarray(info.ancestors, np.int32),
        "proposed_poses": result.to_world(info.proposed_poses).astype(np.float32),
        "log_weights": np.asarray(info.log_weights, np.float32),
        "log_evidence": np.asarray(info.log_evidence, np.float32),
        "num_fallbacks": np.asarray(info.num_fallbacks, np.int32),
        "num_slipped": np.asarray(info.num_slipped, np.int32),
        "best_particle": np.asarray(info.best_particle, np.int32),
        "num_particles": np.int64(result.config.num_particles),
    }


def write_step_record(path, record: dict[str, np.ndarray]) -> None:
    """Write a :func:`step_record` as a compressed ``.npz``."""
    with open(path, "wb") as f:
        np.savez_compressed(f, **record)


def read_step_record(run_dir) -> dict[str, np.ndarray]:
    """The ``steps.npz`` of a ``jaxslam map`` output folder; ``FileNotFoundError`` naming what to do."""
    path = Path(run_dir) / STEPS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: diagnose reads the {STEPS_FILE} that `jaxslam map` writes "
                                f"into its output folder (runs made before it did must be run again)")
    with np.load(path) as z:
        return {name: z[name] for name in z.files}


def surviving_lineages(ancestors: np.ndarray) -> np.ndarray:
    """(S-1,) int: at each step, how many of the particles it produced have descendants among
    the final particles (``ancestors`` (S-1, N): ``ancestors[t, i]`` is the index, among step
    t's proposed particles, of the particle final-of-step-t number i took its past from)."""
    steps, n = ancestors.shape
    out = np.empty(steps, np.int64)
    alive = np.ones(n, bool)  # after the last step: every final particle
    for t in range(steps - 1, -1, -1):
        kept = np.zeros(n, bool)
        kept[ancestors[t][alive]] = True
        out[t] = int(kept.sum())
        alive = kept
    return out


def coalescence_lag(ancestors: np.ndarray) -> int:
    """Steps from the end back to the final particles' common ancestor (the number of steps when
    they have none within the record)."""
    steps = np.asarray(ancestors).shape[0]
    single = np.flatnonzero(surviving_lineages(ancestors) == 1)
    return int(steps - (single[-1] + 1)) if single.size else int(steps)


def lineages_at_lag(ancestors: np.ndarray, lag: int) -> np.ndarray:
    """(S - lag + 1,) int: for each step t from ``lag`` to S (1-based), how many distinct
    histories the particles that end step t hold over their last ``lag`` steps: the number of
    step t - lag + 1's proposed particles they descend from (``ancestors`` (S, N) as in
    :func:`surviving_lineages`; empty where the record has fewer than ``lag`` steps).

    The alternatives a filter still carries ``lag`` steps back, at every step rather than only at
    the end (:func:`coalescence_lag`): 1 where every particle shares one history over that span.
    A loop closes only if some history that left the loop's start is still carried when the robot
    returns. Composed by doubling: log2(lag) gathers of the whole record."""
    ancestors = np.asarray(ancestors)
    steps = ancestors.shape[0]
    if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 1:
        raise ValueError(f"lineages_at_lag: lag must be a positive number of steps, got {lag!r}")
    if lag > steps:
        return np.zeros(0, np.int64)
    # block[j] sends the particles that end step j + span (1-based) to their ancestors among the
    # proposed particles of step j + 1: `span` steps of parents composed.
    block, span = ancestors, 1
    back, back_span = None, 0  # the same over the lowest bits of lag, done so far
    remaining = int(lag)
    while True:
        if remaining & 1:
            if back is None:
                back, back_span = block, span
            else:  # extend further into the past by the (older) block of `span` steps
                rows = steps - back_span - span + 1
                back = np.take_along_axis(block[:rows], back[span:], axis=1)
                back_span += span
        remaining >>= 1
        if not remaining:
            break
        block = np.take_along_axis(block[:steps - 2 * span + 1], block[span:], axis=1)
        span *= 2
    return (np.count_nonzero(np.diff(np.sort(back, axis=1), axis=1), axis=1) + 1).astype(np.int64)


def lineages_back(ancestors: np.ndarray, lags=LINEAGE_LAGS) -> dict[str, float | None]:
    """The median over the steps of :func:`lineages_at_lag` at each of ``lags`` (steps), keyed by
    the lag; None where the record is shorter than the lag."""
    return {str(k): float(np.median(lineages_at_lag(ancestors, k))) if k <= len(ancestors) else None for k in lags}


def neutral_coalescence_lags(ancestors: np.ndarray, draws: int = NEUTRAL_DRAWS, seed: int = 0) -> np.ndarray:
    """(draws,) int: :func:`coalescence_lag` of the same resamplings with their parents relabelled
    at random at every step: every step keeps its offspring counts (how many copies of which
    rank), but which particle had the luck is drawn afresh, so a lineage's luck at one step says
    nothing about the next (neutral drift, the coalescent's null). A recorded lag far below these
    is lineages that kept winning: lasting differences in the weights (selection), not chance."""
    ancestors = np.asarray(ancestors)
    rng = np.random.default_rng(seed)
    return np.array([coalescence_lag(relabelled_parents(ancestors, rng)) for _ in range(draws)], np.int64)


def relabelled_parents(ancestors: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(S, N) int: ``ancestors`` with each step's parents relabelled by a random permutation:
    every step keeps its offspring counts, but which particle had them is drawn afresh (neutral
    drift with the record's own resamplings; :func:`neutral_coalescence_lags`)."""
    ancestors = np.asarray(ancestors)
    relabel = rng.permuted(np.broadcast_to(np.arange(ancestors.shape[1]), ancestors.shape), axis=1)
    return np.take_along_axis(relabel, ancestors, axis=1)


def weight_increments(log_weights: np.ndarray, ancestors: np.ndarray, resampled: np.ndarray) -> np.ndarray:
    """(S-1, N) nats: each step's log-weight increment of every particle it proposed, centred on
    the particles' mean (the step's normaliser cancels). ``log_weights`` (S-1, N) are the record's
    normalised weights after each step's update; the particle a step proposes as number i carries
    the weight of the step before's particle i after its resampling (uniform where it resampled).
    A particle of weight zero (-inf) gets NaN, and the centring skips it."""
    log_weights = np.asarray(log_weights, np.float64)
    steps, n = log_weights.shape
    kept = np.take_along_axis(log_weights[:-1], np.asarray(ancestors)[:-1], axis=1)  # the identity where none resampled
    carried = np.concatenate([np.full((min(steps, 1), n), -np.log(n)),
                              np.where(np.asarray(resampled, bool)[:-1, None], -np.log(n), kept)])
    with np.errstate(invalid="ignore"):
        raw = log_weights - carried
    raw = np.where(np.isfinite(raw), raw, np.nan)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a step of NaN only: its mean is NaN, as it should be
        return raw - np.nanmean(raw, axis=1, keepdims=True)


def weight_persistence(log_weights: np.ndarray, ancestors: np.ndarray, resampled: np.ndarray,
                       min_stretch: int = MIN_STRETCH) -> dict:
    """Whether the weights that make the filter resample persist, or are noise that a few scans
    later would have reversed.

    Between two resamplings the particles keep their histories, and each one's weight is the sum
    of its increments (:func:`weight_increments`). For every such stretch of at least
    ``min_stretch`` steps, the correlation over the particles of the summed increments of its
    first half with those of its second half: near 1 where a particle's advantage lasts (a better
    map, a pose the later scans confirm), near 0 where each step's differences are independent
    draws, so that the resampling at the stretch's end picks histories by the accumulated noise
    (genetic drift). Returns ``{"increments": (S-1, N) :func:`weight_increments`,
    "increment_spread": (S-1,) each step's standard deviation of the increments over the
    particles (nats), "stretches": [{"first_step", "steps", "correlation"}],
    "median_correlation", "median_increment_spread"}`` (steps 1-based, as :func:`diagnose`'s; the
    medians None where nothing qualifies).
    """
    increments = weight_increments(log_weights, ancestors, resampled)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN step's spread is NaN
        spread = np.nanstd(increments, axis=1)
    ends = np.flatnonzero(np.asarray(resampled, bool))
    stretches = []
    for first, last in zip(np.r_[0, ends[:-1] + 1], ends):  # steps first..last, resampled at last
        length = int(last - first + 1)
        if length < min_stretch:
            continue
        half = length // 2
        early = increments[first:first + half].sum(axis=0)
        late = increments[first + half:last + 1].sum(axis=0)
        keep = np.isfinite(early) & np.isfinite(late)
        if keep.sum() < 3 or np.std(early[keep]) == 0 or np.std(late[keep]) == 0:
            continue
        stretches.append({"first_step": int(first + 1), "steps": length,
                          "correlation": float(np.corrcoef(early[keep], late[keep])[0, 1])})
    finite = spread[np.isfinite(spread)]
    return {"increments": increments, "increment_spread": spread, "stretches": stretches,
            "median_correlation": float(np.median([s["correlation"] for s in stretches])) if stretches else None,
            "median_increment_spread": float(np.median(finite)) if finite.size else None}


def pair_coalescence(ancestors: np.ndarray) -> np.ndarray:
    """(S-1,) at each step, the probability that two of its particles drawn at random (without
    replacement) took their past from the same proposed particle: sum_j c_j (c_j - 1) / (N (N - 1))
    with c_j particle j's offspring count (0 where the step kept every particle). Summed over
    steps it is how fast lineages merge. Under pure drift (weights that do not last, spread sigma
    over the particles) and systematic resampling at ESS < N/2 it is about 1.44 sigma^2 / (N - 1)
    a step, and no lower at a threshold of 0.25 or 0.75 (``experiments/lineage_loss.py``)."""
    ancestors = np.asarray(ancestors)
    steps, n = ancestors.shape
    if n < 2:
        return np.zeros(steps)
    counts = np.zeros((steps, n), np.int64)
    np.add.at(counts, (np.repeat(np.arange(steps), n), ancestors.ravel()), 1)
    return np.sum(counts * (counts - 1), axis=1) / (n * (n - 1))


class _RelationScans(NamedTuple):
    """Where the relations' scans lie in a run (see :func:`_relation_scans`)."""

    step: np.ndarray
    """(Q,) each asked scan's processed step before it (0 for the scans before the first)."""
    since: np.ndarray
    """(Q, 3) the odometry's motion from that processed scan to the asked one."""
    first: np.ndarray
    """(R,) each relation's t1 scan, an index into the asked scans."""
    second: np.ndarray
    """(R,) its t2 scan."""


def _relation_scans(record: dict[str, np.ndarray], trajectory, relations) -> _RelationScans:
    """The scans the relations read, each as a processed step and the motion since: between
    processed scans ``trajectory.txt`` composes the best path with the odometry, so any
    history's pose at an asked scan is its own pose at that step composed with the same motion
    (read from the best path and the trajectory: the log is not needed)."""
    times, per_scan = np.asarray(trajectory[0], np.float64), np.asarray(trajectory[1], np.float64)
    processed, best = np.asarray(record["scan_index"]), np.asarray(record["best_path"], np.float64)
    if per_scan.shape != (times.size, 3) or processed[-1] >= times.size:
        raise ValueError(f"diagnose: the trajectory ({per_scan.shape}) is not the record's run "
                         f"(its last processed scan is {processed[-1]})")
    asked = lookup_indices(times, np.concatenate([relations.t1, relations.t2]))
    scans, where = np.unique(asked, return_inverse=True)
    step = np.clip(np.searchsorted(processed, scans, side="right") - 1, 0, processed.size - 1)
    count = np.asarray(relations.t1).size
    return _RelationScans(step, between_np(best[step], per_scan[scans]), where[:count], where[count:])


def final_particle_errors(record: dict[str, np.ndarray], trajectory: tuple[np.ndarray, np.ndarray], relations
                          ) -> dict[str, np.ndarray]:
    """Every final particle's own relation error (Kuemmerle et al. 2009), its history rebuilt
    from the record (:func:`jaxslam.rbpf.particle_paths`). The reported particle's
    (:func:`jaxslam.rbpf.final_best_particle`) is the run's.

    Args:
      record: :func:`step_record`.
      trajectory: ``(timestamps (T,), poses (T, 3))`` the run's pose per scan (world frame).
      relations: the relations (inside the run's time span).

    Returns:
      ``{"trans_mean": (N,) m, "rot_mean": (N,) rad}``, final particle by final particle.
    """
    at = _relation_scans(record, trajectory, relations)
    best = np.asarray(record["best_path"], np.float64)
    paths = particle_paths(np.asarray(record["proposed_poses"], np.float64), record["ancestors"], best[0])
    motion = np.asarray(relations.motion, np.float64)
    trans, rot = [], []
    for path in paths:  # host-side, after the run: one particle's poses at the asked scans at a time
        poses = compose_np(path[at.step], at.since)
        errors = motion_errors(poses[at.first], poses[at.second], motion)
        trans.append(np.mean(errors[0]))
        rot.append(np.mean(errors[1]))
    return {"trans_mean": np.asarray(trans), "rot_mean": np.asarray(rot)}


def errors_then(record: dict[str, np.ndarray], trajectory: tuple[np.ndarray, np.ndarray], relations
                ) -> np.ndarray:
    """(R, N) m: for each relation, the translational error of every particle the filter proposed
    at the relation's later scan, each judged on its own history up to then (the scan's pose
    itself, and its ancestor's at the earlier scan)."""
    at = _relation_scans(record, trajectory, relations)
    proposed = np.asarray(record["proposed_poses"], np.float64)
    ancestors = np.asarray(record["ancestors"])
    n = ancestors.shape[1]
    initial = np.broadcast_to(np.asarray(record["best_path"], np.float64)[0], (n, 3))
    motion = np.asarray(relations.motion, np.float64)
    step1, step2 = at.step[at.first], at.step[at.second]
    late, early = np.maximum(step1, step2), np.minimum(step1, step2)

    def poses_at(step, index):  # (n, 3): the histories' poses at a processed step
        return proposed[step - 1, index] if step >= 1 else initial

    out = np.empty((late.size, n))
    for last in np.unique(late):
        members = np.flatnonzero(late == last)
        index, step = np.arange(n), int(last)  # step's proposed particles, followed back
        at_early = {}
        for wanted in sorted(set(early[members].tolist()), reverse=True):
            while step > wanted:
                if step >= 2:  # the parent of step s's particle j: step s - 1's proposed ancestors[s - 2, j]
                    index = ancestors[step - 2, index]
                step -= 1
            at_early[wanted] = poses_at(step, index)
        late_poses = poses_at(int(last), np.arange(n))
        for r in members:
            early_poses = at_early[int(early[r])]  # the late poses' own ancestors (themselves at the same step)
            pose1, pose2 = (late_poses, early_poses) if step1[r] == last else (early_poses, late_poses)
            out[r], _ = motion_errors(compose_np(pose1, at.since[at.first[r]]),
                                      compose_np(pose2, at.since[at.second[r]]), motion[r])
    return out


def closest_then(record: dict[str, np.ndarray], trajectory: tuple[np.ndarray, np.ndarray], relations
                 ) -> np.ndarray:
    """(R,) m: for each relation, the smallest translational error among the particles the filter
    proposed at the relation's later scan, each judged on its own history up to then
    (:func:`errors_then`).

    A relation the run gets wrong (a missed or false loop closure) with a small value here was
    right in some particle at the time, and the weights or a later resampling dropped it; with a
    large value no particle had it: the proposal or the particles' diversity failed before.
    """
    return errors_then(record, trajectory, relations).min(axis=1)


def weighted_then(record: dict[str, np.ndarray], trajectory: tuple[np.ndarray, np.ndarray], relations,
                  errors: np.ndarray | None = None) -> np.ndarray | None:
    """(R,) m: for each relation, the particles' errors at its later scan (:func:`errors_then`, or
    ``errors`` when given) averaged by that step's weights (``log_weights`` of the record, after
    the update and before resampling); None for a record written before it held them.

    Beside :func:`closest_then`: near it, the weights favoured the particles that had the relation
    right at the time (a later resampling or step lost it); far above it, they did not.
    """
    if "log_weights" not in record:
        return None
    errors = errors_then(record, trajectory, relations) if errors is None else errors
    at = _relation_scans(record, trajectory, relations)
    late = np.maximum(at.step[at.first], at.step[at.second])
    log_w = np.asarray(record["log_weights"], np.float64)
    uniform = np.full(errors.shape[1], 1.0 / errors.shape[1])  # the initial scan's: all particles alike
    weights = np.stack([normalized_weights(log_w[s - 1]) if s >= 1 else uniform for s in late]) if late.size \
        else np.zeros_like(errors)
    return np.sum(weights * errors, axis=1)


def diagnose(record: dict[str, np.ndarray], trajectory: tuple[np.ndarray, np.ndarray] | None = None,
             relations=None) -> dict:
    """Per-step series and ranked events of a run (see the module's docstring); JSON-ready.

    Args:
      record: :func:`step_record` (or :func:`read_step_record`).
      trajectory: ``(timestamps (T,), poses (T, 3))`` a pose per scan (``trajectory.txt``);
        needed with ``relations``.
      relations: a :class:`~jaxslam.io.relations.Relations`, or None.
    """
    series, persistence = _step_series(record)
    place = _placer(record)
    events = _ranked_events(series, place)
    summary = _run_summary(record, series, persistence)
    out = {"summary": summary, "series": {k: np.asarray(v).tolist() for k, v in series.items()}, "events": events}
    if relations is not None:
        _add_relation_errors(out, record, trajectory, relations, series["surviving_lineages"], place)
    return out


def relations_within(relations, times) -> tuple:
    """The relations inside a run's time span (``times``, (T,) s: its trajectory's), and how many
    lie outside it: a run of part of a log (``--max-scans``) is judged on those inside.

    Raises:
        ValueError: none lies inside (the relations are another log's).
    """
    times = np.asarray(times)
    inside = ((np.minimum(relations.t1, relations.t2) >= times[0] - 1e-4)
              & (np.maximum(relations.t1, relations.t2) <= times[-1] + 1e-4))
    if not np.any(inside):
        raise ValueError(f"diagnose: none of the {relations.count} relations lies within the run's time span "
                         f"({times[0]:.3f} to {times[-1]:.3f} s): are they the log's?")
    return type(relations)(relations.t1[inside], relations.t2[inside], relations.motion[inside]), int(np.sum(~inside))


def _step_series(record: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict]:
    """The per-step series of :func:`diagnose` (each (S,) for the record's S steps; see the
    module's docstring for their meaning and units), and :func:`weight_persistence`'s result
    (a stand-in without weights for records that have none)."""
    n = int(record["num_particles"])
    ancestors = np.asarray(record["ancestors"])
    steps = ancestors.shape[0]
    best, odo = np.asarray(record["best_path"]), np.asarray(record["odometry"])
    step_times = np.asarray(record["timestamp"])[1:]
    difference = between_np(between_np(odo[:-1], odo[1:]), between_np(best[:-1], best[1:]))
    correction_trans = np.hypot(difference[:, 0], difference[:, 1])
    correction_rot = np.abs(difference[:, 2])
    proposed = np.asarray(record["proposed_poses"], np.float64)
    spread = np.sqrt(np.var(proposed[..., 0], axis=1) + np.var(proposed[..., 1], axis=1))
    lineages = surviving_lineages(ancestors)
    distinct = (np.count_nonzero(np.diff(np.sort(ancestors, axis=1), axis=1), axis=1) + 1).astype(np.int64)
    # Records written before the weights were kept have none to judge.
    persistence = (weight_persistence(record["log_weights"], ancestors, record["resampled"]) if "log_weights" in record
                   else {"increment_spread": np.full(steps, np.nan), "stretches": [], "median_correlation": None,
                         "median_increment_spread": None})
    series = {
        "step": np.arange(1, steps + 1), "time": step_times,
        "ess_fraction": np.asarray(record["ess"], np.float64) / n,
        "resampled": np.asarray(record["resampled"]),
        "distinct_ancestors": distinct, "surviving_lineages": lineages,
        "correction_trans": correction_trans, "correction_rot": correction_rot, "spread": spread,
        "fallbacks": np.asarray(record["num_fallbacks"]), "log_evidence": np.asarray(record["log_evidence"]),
        # Records written before the slip search have no slips.
        "slipped": np.asarray(record["num_slipped"]) if "num_slipped" in record else np.zeros(steps, np.int64),
        "increment_spread": persistence["increment_spread"],
    }
    return series, persistence


def _placer(record: dict[str, np.ndarray]):
    """A function of a step's index (0-based) to where on the best path it was (x, y in m) and
    when (``elapsed_s``: seconds since the first scan), for the events."""
    best = np.asarray(record["best_path"])
    step_times = np.asarray(record["timestamp"])[1:]
    start = float(np.asarray(record["timestamp"])[0])

    def place(step_index: int) -> dict:  # where on the best path, and when (seconds since the first scan)
        return {"step": int(step_index + 1), "elapsed_s": float(step_times[step_index] - start),
                "x": float(best[step_index + 1, 0]), "y": float(best[step_index + 1, 1])}

    return place


def _ranked_events(series: dict[str, np.ndarray], place) -> dict:
    """The :data:`NUM_EVENTS` largest corrections (m, rad) and every slip, each with its place."""
    correction_trans, correction_rot = series["correction_trans"], series["correction_rot"]
    order = np.argsort(-correction_trans, kind="stable")[:NUM_EVENTS]
    return {"largest_corrections": [dict(place(i), trans=float(correction_trans[i]), rot=float(correction_rot[i]))
                                    for i in order],
            "slips": [dict(place(int(i)), particles=int(series["slipped"][i]), trans=float(correction_trans[i]),
                           rot=float(correction_rot[i])) for i in np.flatnonzero(series["slipped"])]}


def _run_summary(record: dict[str, np.ndarray], series: dict[str, np.ndarray], persistence: dict) -> dict:
    """The run's summary (see the module's docstring) from its record and per-step series."""
    n = int(record["num_particles"])
    ancestors = np.asarray(record["ancestors"])
    steps = ancestors.shape[0]
    distinct, lineages = series["distinct_ancestors"], series["surviving_lineages"]
    single = np.flatnonzero(lineages == 1)
    neutral = neutral_coalescence_lags(ancestors) if steps else None
    lag = coalescence_lag(ancestors) if steps else None
    return {
        "steps": steps, "num_particles": n,
        "resampling_steps": int(np.sum(series["resampled"])),
        "mean_ess_fraction": float(np.mean(series["ess_fraction"])) if steps else None,
        "mean_distinct_ancestors_when_resampling": (float(np.mean(distinct[series["resampled"]]))
                                                    if np.any(series["resampled"]) else None),
        "coalescence_step": int(single[-1] + 1) if single.size else None,
        "fallbacks": int(np.sum(series["fallbacks"])),
        "slip_steps": int(np.count_nonzero(series["slipped"])),
        "pair_coalescence_per_step": float(np.mean(pair_coalescence(ancestors))) if steps else None,
        "coalescence_lag_steps": lag,
        **({"neutral_lag_steps_median": float(np.median(neutral)),
            "neutral_lag_quantile": float(np.mean(neutral <= lag))} if steps else {}),
        "lineages_back": lineages_back(ancestors),
        "weight_persistence": {"median_correlation": persistence["median_correlation"],
                               "median_increment_spread": persistence["median_increment_spread"],
                               "stretches": len(persistence["stretches"])},
    }


def _add_relation_errors(out: dict, record: dict[str, np.ndarray], trajectory, relations, lineages: np.ndarray,
                         place) -> None:
    """Add to ``out`` (:func:`diagnose`'s result, in place) the relations' errors (m, rad) at their
    later scans, the closest and weighted particles' errors then, the worst relations as events and
    the final particles' own errors; ``lineages`` is the (S,) ``surviving_lineages`` series."""
    summary, events = out["summary"], out["events"]
    n, steps = summary["num_particles"], summary["steps"]
    step_times = np.asarray(record["timestamp"])[1:]
    start = float(np.asarray(record["timestamp"])[0])
    if trajectory is None:
        raise ValueError("diagnose: relations need the run's trajectory (a pose per scan)")
    relations, outside = relations_within(relations, trajectory[0])
    err = relation_error(trajectory[0], trajectory[1], relations)
    later = np.maximum(relations.t1, relations.t2)
    at_step = np.clip(np.searchsorted(step_times, later), 0, max(steps - 1, 0))
    out["relations"] = {"time": later.tolist(), "trans": err.trans.tolist(), "rot": err.rot.tolist(),
                        "step": (at_step + 1).tolist()}
    summary["relation_error"] = {"trans_mean": err.trans_mean, "rot_mean": err.rot_mean, "count": err.count,
                                 "relations_outside_the_run": outside}
    errors = errors_then(record, trajectory, relations)
    then, weighted = errors.min(axis=1), weighted_then(record, trajectory, relations, errors)
    out["relations"]["closest_then"] = then.tolist()
    summary["relation_error"]["closest_then_mean"] = float(np.mean(then))
    if weighted is not None:
        out["relations"]["weighted_then"] = weighted.tolist()
        summary["relation_error"]["weighted_then_mean"] = float(np.mean(weighted))
    worst = np.argsort(-err.trans, kind="stable")[:NUM_EVENTS]
    events["worst_relations"] = [dict(place(int(at_step[i])), relation_elapsed_s=float(later[i] - start),
                                      trans=float(err.trans[i]), rot=float(err.rot[i]),
                                      closest_then=float(then[i]),
                                      **({} if weighted is None else {"weighted_then": float(weighted[i])}))
                                 for i in worst]
    own = final_particle_errors(record, trajectory, relations)
    closest = int(np.argmin(own["trans_mean"]))
    best_final = final_best_particle(record["ancestors"], record["best_particle"])
    out["final_particles"] = {k: v.tolist() for k, v in own.items()}
    summary["final_particles"] = {
        "best_particle": best_final, "best_trans_mean": float(own["trans_mean"][best_final]),
        "closest_particle": closest, "closest_trans_mean": float(own["trans_mean"][closest]),
        "median_trans_mean": float(np.median(own["trans_mean"])),
        "distinct_histories": int(lineages[-1]) if steps else n}
