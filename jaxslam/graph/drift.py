"""How fast the filter's heading and the odometry's drift, as the loops measure them, and the
chain whose headings weigh the two by it (:func:`heading_drift_rates`, :func:`smoothed_headings`,
:func:`fused_chain`, :func:`weighed_chain`), and whether the two part after the last loop beyond
what they allow (:func:`parting`, :func:`parted`); and the graph's edges along a chain, whose
heading noise is that rate (:func:`sequential_edges`).

The pose graph's chain between loops is the filter's steps. Where the filter's heading drifts
faster than the robot's odometry (on FR-clinic 34 degrees after 1.4 km against the odometry's
1.3), the chain carries the filter's drift to every loop that no window reaches. Which of the two
drifts slower differs from robot to robot, and no single step says it: a step's difference
between them is mostly the filter's white jitter about its map, which the map cancels over the
next steps (the particles' spread at a step measures that jitter, not the drift: weighing each
step by it took Intel from 0.051 to 2.04 m; docs/design.md, "Measured and rejected").
Drift shows over long spans, and a kept loop is a long span measured: its heading against each
chain's relative heading over it is one sample of each chain's drift over that many steps.

Modelling each chain's heading error as a random walk, the loops give each one's variance per
step (:func:`heading_drift_rates`), the loop's ends taken where the submap's scans and the
query's neighbours put them, not where one jittered node does. The step disagreements give the
filter's white jitter (:func:`step_noise`). A robust smoother then takes the headings most
probable under both (:func:`smoothed_headings`): who is at fault at a large disagreement is
decided by whether it stays, not by its size (on FR-clinic 88-94 % of the steps beyond 4 robust
stds were the filter's jumps, which a rule on the size took for wheel slips and kept; the
chains it made ended 19-24 m off; docs/design.md, "Measured and rejected"). The chain turns each submap
rigidly by its nodes' mean correction (:func:`fused_chain`). The loop closure searches again
from that chain, and measures the rates again from its loops, until the odometry's share
``w = v_filter / (v_filter + v_odometry)`` settles
(:func:`jaxslam.graph.closure.close_trajectory_loops`). On Intel and ACES the odometry's heading
drifts 10-30 times faster than the filter's (std per square-root step; w under 0.01): one pass,
nothing changes (MIT CSAIL: w 0.061-0.065, two passes). On FR-clinic the filter's drifts 3-14
times faster in nine seeds of ten (w 0.89-1.0).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxslam.geometry import between_np, chain_np, compose_np, wrap_angle_np
from jaxslam.graph.acceptance import first_kept
from jaxslam.graph.pose_graph import SEQUENTIAL, Edges
from jaxslam.graph.windows import path_distances
from jaxslam.motion import noise_std


def heading_drift_rates(first: np.ndarray, last: np.ndarray, second: np.ndarray, measured_heading: np.ndarray,
                        filter_headings: np.ndarray, odometry_headings: np.ndarray) -> tuple[float, float]:
    """Each chain's heading variance per step (rad^2), from loops: loop ``l`` measures the
    heading of node ``second[l]`` in the frame of a submap of nodes ``first[l]..last[l]``
    (inclusive), the frame of its first node, as ``measured_heading[l]``; a chain's error over
    the loop is its own relative heading minus that, and under a random walk its variance is the
    rate times the steps spanned: the maximum-likelihood rate is the sum of squared errors over
    the sum of the spans.

    A submap's scans sit where the filter put all of them, so its frame is off its first
    node's heading by that node's jitter against the rest (on FR-clinic one first node's
    3.5 degrees put that error into eight loops); the loop's ends are therefore taken as
    the means over the submap's nodes and over as many nodes round the query, where the
    filter's heading is its odometry-relative mean: the white jitter of either end cancels and
    the drift stays.

    Args:
        first, last: (L,) int the loop's submap's first and last node.
        second: (L,) int the query node, after ``last``.
        measured_heading: (L,) rad.
        filter_headings: (S,) the filter's heading at each node (rad).
        odometry_headings: (S,) the odometry's heading at each node, in any frame (rad).

    Returns:
        ``(filter_rate, odometry_rate)`` in rad^2 per step; nan for no loops.
    """
    first, last, second = np.asarray(first), np.asarray(last), np.asarray(second)
    if not first.shape == last.shape == second.shape == np.shape(measured_heading):
        raise ValueError(f"heading_drift_rates: first, last, second and measured_heading must have one shape, got "
                         f"{first.shape}, {last.shape}, {second.shape} and {np.shape(measured_heading)}")
    if np.any(last < first) or np.any(second <= last):
        raise ValueError("heading_drift_rates: every loop's submap must end (last >= first) before its query node")
    spans = np.sum(second - first)
    if spans == 0:
        return float("nan"), float("nan")
    odometry = np.unwrap(np.asarray(odometry_headings, np.float64))
    disagreement = np.unwrap(np.asarray(filter_headings, np.float64)) - odometry  # the filter's, less the odometry's
    total = np.concatenate([[0.0], np.cumsum(disagreement)])

    def mean_disagreement(start, stop):  # over nodes start..stop inclusive, clipped to the path
        start, stop = np.maximum(start, 0), np.minimum(stop, disagreement.size - 1)
        return (total[stop + 1] - total[start]) / (stop - start + 1)

    half = (last - first) // 2
    anchor, query = mean_disagreement(first, last), mean_disagreement(second - half, second + half)
    # the measurement in the submap's own frame: where its scans, not its first node, put it
    measured = np.asarray(measured_heading, np.float64) + disagreement[first] - anchor
    odometry_error = wrap_angle_np(odometry[second] - odometry[first] - measured)
    filter_error = wrap_angle_np(odometry_error + query - anchor)
    return float(np.sum(filter_error ** 2) / spans), float(np.sum(odometry_error ** 2) / spans)


# Huber's constant: 95 % efficiency under Gaussian errors; a residual beyond it counts linearly
# (the textbook choice, not tuned on any log).
HUBER_K = 1.345


def parting(filter_headings: np.ndarray, odometry_headings: np.ndarray, since: int, rates, jitter: float) -> float:
    """How far the filter's and the odometry's headings part from node ``since`` to the last, in
    standard deviations of what the drift rates allow: the random walks' ``(filter_rate +
    odometry_rate)`` per step over the steps, plus the filter's jitter ``r`` at both ends.

    The rates are measured by the loops, so they speak for the stretches the loops span. After
    the last loop nothing measured them: a filter that drifted little up to its last loop and
    then turned away from the odometry (FR-clinic seed 5: 16 degrees over the 745 nodes after its
    last loop, 7 standard deviations) refutes its rate there, and a chain weighed by it carries
    the turn to every return that comes later.

    Args:
        filter_headings, odometry_headings: (S,) headings at the nodes (rad; the odometry's in
            any frame).
        since: the node the parting is counted from.
        rates: ``(filter_rate, odometry_rate)`` rad^2 per step (:func:`heading_drift_rates`).
        jitter: the filter's white jitter variance ``r`` (rad^2; :func:`step_noise`).

    Returns:
        |the filter's heading change less the odometry's| over the standard deviation.
    """
    filter_headings = np.unwrap(np.asarray(filter_headings, np.float64))
    odometry_headings = np.unwrap(np.asarray(odometry_headings, np.float64))
    steps = filter_headings.size - 1 - int(since)
    parted = (filter_headings[-1] - filter_headings[since]) - (odometry_headings[-1] - odometry_headings[since])
    return float(abs(parted) / np.sqrt((rates[0] + rates[1]) * steps + 2.0 * jitter))


def step_noise(filter_steps: np.ndarray, odometry_steps: np.ndarray) -> tuple[float, float]:
    """The per-step variances of the step disagreement's two parts (rad^2): the random walk
    ``q`` (both chains' drift) and the filter's white jitter ``r`` about its map.

    The disagreement ``d_t`` between the odometry's and the filter's heading change of step ``t``
    is the two random walks' increments plus the jitter's difference ``j_{t+1} - j_t``. One step
    has variance ``q + 2r``; two steps' sum has ``2q + 2r``, the jitter telescoping. Both are the
    robust variances (1.4826 MAD, squared) of the disagreements, so a slip of either does not
    inflate them. On FR-clinic the jitter is 0.28-0.34 degrees and the walk 0.24-0.32 per step.

    Args:
        filter_steps, odometry_steps: (S-1, 3) relative steps.

    Returns:
        ``(q, r)``, each at least 1e-4 of the one-step variance.
    """
    diff = wrap_angle_np(np.asarray(odometry_steps, np.float64)[:, 2] - np.asarray(filter_steps, np.float64)[:, 2])

    def robust_var(x):
        return (1.4826 * np.median(np.abs(x - np.median(x)))) ** 2

    one, two = robust_var(diff), robust_var(diff[1:] + diff[:-1])
    floor = 1e-4 * max(one, 1e-12)
    return max(two - one, floor), max(one - two / 2, floor)


def smoothed_headings(filter_headings: np.ndarray, odometry_turns: np.ndarray, filter_rate: float,
                      odometry_rate: float, jitter: float, iterations: int = 10) -> np.ndarray:
    """(S,) the headings (rad, unwrapped) most probable under both chains: a robust smoother.

    The model: the true heading ``x`` turns by the odometry's turn plus a random walk of
    ``odometry_rate`` per step; the filter's heading is ``x`` plus its own drift ``b`` (a random
    walk of ``filter_rate``, ``b_0 = 0``) plus white jitter of variance ``jitter``. The odometry's
    turns and the filter's headings have Huber's heavy tails, so which of the two is at fault at a
    large disagreement is decided by what follows it, not by its size: a filter jump that its
    map takes back is the filter's jitter; a step that stays (a wheel slip) is the odometry's.
    On FR-clinic 88-94 % of the steps the two disagree on beyond 4 robust stds are the filter's
    (against the relations they span), which a rule on the size alone took for wheel slips.

    The least squares over ``(x, b)`` is banded (two superdiagonals, interleaved): Cholesky by
    ``scipy.linalg.solveh_banded``, iteratively reweighted.

    Args:
        filter_headings: (S,) rad.
        odometry_turns: (S-1,) the odometry's heading change of each step (rad).
        filter_rate, odometry_rate: random-walk variances per step (rad^2; floored at 1e-12).
        jitter: the filter's white-jitter variance (rad^2).
        iterations: reweighting rounds.
    """
    headings = np.unwrap(np.asarray(filter_headings, np.float64))
    turns = np.asarray(odometry_turns, np.float64)
    size = headings.size
    if turns.shape != (size - 1,):
        raise ValueError(f"smoothed_headings: odometry_turns must have shape ({size - 1},), got {turns.shape}")
    filter_rate, odometry_rate, jitter = (max(float(v), 1e-12) for v in (filter_rate, odometry_rate, jitter))
    odometry_weight, filter_weight = np.ones(size - 1), np.ones(size)
    for _ in range(iterations):
        # unknowns (x_0, b_0, x_1, b_1, ...); the upper band: diagonal, first, second superdiagonal
        band = np.zeros((3, 2 * size))
        rhs = np.zeros(2 * size)
        turn_info = odometry_weight / odometry_rate  # x_{t+1} - x_t = turn_t
        band[2, 0:-2:2] += turn_info
        band[2, 2::2] += turn_info
        band[0, 2::2] -= turn_info
        rhs[0:-2:2] -= turn_info * turns
        rhs[2::2] += turn_info * turns
        band[2, 1:-2:2] += 1.0 / filter_rate  # b_{t+1} - b_t = 0
        band[2, 3::2] += 1.0 / filter_rate
        band[0, 3::2] -= 1.0 / filter_rate
        heading_info = filter_weight / jitter  # x_t + b_t = the filter's heading
        band[2, 0::2] += heading_info
        band[2, 1::2] += heading_info
        band[1, 1::2] += heading_info
        rhs[0::2] += heading_info * headings
        rhs[1::2] += heading_info * headings
        band[2, 1] += 1.0 / jitter  # b_0 = 0: the filter's frame
        solution = scipy.linalg.solveh_banded(band, rhs)
        x, b = solution[0::2], solution[1::2]
        odometry_weight = _huber_weight((np.diff(x) - turns) / np.sqrt(odometry_rate))
        filter_weight = _huber_weight((headings - x - b) / np.sqrt(jitter))
    return x


def _huber_weight(standardized: np.ndarray) -> np.ndarray:
    return HUBER_K / np.maximum(np.abs(standardized), HUBER_K)


def fused_chain(filter_poses: np.ndarray, headings: np.ndarray, first_node: np.ndarray,
                last_node: np.ndarray) -> np.ndarray:
    """(S, 3) the filter's submaps, each turned by its nodes' mean of ``headings`` less the
    filter's and joined by the filter's steps between them: the chain the smoothed headings
    give, with every submap rigid.

    Inside a submap the chain keeps the filter's relative poses: a loop measures its query in
    the frame the submap's scans make, which is the filter's, and a chain that moved the
    submap's first node alone (its jitter removed) would disagree with every loop into that
    submap by that jitter.

    Args:
        filter_poses: (S, 3) the filter's node poses (m, m, rad).
        headings: (S,) rad, unwrapped (:func:`smoothed_headings`).
        first_node, last_node: (M,) int the submaps' node runs (inclusive), covering 0..S-1 in
            order.
    """
    filter_poses = np.asarray(filter_poses, np.float64)
    correction = np.asarray(headings, np.float64) - np.unwrap(filter_poses[:, 2])
    sizes = np.asarray(last_node) - np.asarray(first_node) + 1
    if sizes.sum() != filter_poses.shape[0] or np.any(sizes < 1):
        raise ValueError(f"fused_chain: the submaps' node runs must cover the {filter_poses.shape[0]} nodes in order")
    turn = np.repeat(np.add.reduceat(correction, np.asarray(first_node)) / sizes, sizes)
    steps = between_np(filter_poses[:-1], filter_poses[1:])
    steps[:, 2] += np.diff(turn)
    return chain_np(compose_np(filter_poses[0], np.array([0.0, 0.0, turn[0]])), steps)


def measured_share(everything, submaps, local: np.ndarray, odometry_headings: np.ndarray, share: float,
                   config) -> tuple[float, tuple[float, float]]:
    """The odometry's share of the heading that the kept loops of ``everything`` (every pass's
    :class:`~jaxslam.graph.acceptance.Loops` so far) measure (the filter's
    drift rate over both: the minimum-variance weighing), and the rates; ``share`` unchanged
    with fewer than ``min_drift_loops`` loops.

    Every loop any pass kept measures both chains' drift, whether or not the last pass's chain
    found it again (a loop's measurement is the query's scan against a filter submap: no chain
    enters it), so the rates come from all of them, and so does the final graph."""
    kept = first_kept(everything)
    rates = (np.nan, np.nan)
    if kept.size >= config.min_drift_loops:
        rates = heading_drift_rates(submaps.first_node[everything.submap[kept]],
                                    submaps.last_node[everything.submap[kept]], everything.query[kept],
                                    everything.measurement[kept, 2], local[:, 2], odometry_headings)
    if np.all(np.isfinite(rates)) and sum(rates) > 0:
        return rates[0] / (rates[0] + rates[1]), rates
    return share, rates


def parted(everything, local, odometry_headings, rates, jitter, config) -> bool:
    """Whether the filter's and the odometry's headings part after the last kept loop of
    ``everything`` (every pass's loops) by more than ``max_parting`` standard deviations
    (:func:`parting`), over a path long enough (``min_separation``) to hold a loop no window
    reached.

    Args:
        local: (S, 3) the filter's chain; ``odometry_headings`` (S,) rad.
        rates: ``(filter, odometry)`` rad^2 per step; ``jitter``: rad^2 (:func:`step_noise`).
        config: the closure's settings.
    """
    kept = first_kept(everything)
    since = int(everything.query[kept].max()) if kept.size else local.shape[0] - 1
    return bool(np.all(np.isfinite(rates)) and path_distances(local[since:])[-1] >= config.min_separation
                and parting(local[:, 2], odometry_headings, since, rates, jitter) > config.max_parting)


def weighed_chain(local: np.ndarray, motions: np.ndarray, rates, jitter: float,
                  submaps) -> tuple[np.ndarray, float | None]:
    """The chain a pass searches from, and its sequential edges' heading variance per step.

    With the drift rates ``(filter, odometry)``: the headings of both weighed by them and the
    filter's jitter (:func:`smoothed_headings`), each submap rigid (:func:`fused_chain`), at the
    rate the fused chain drifts. Without (``None``): the odometry's headings, every node turned,
    not every submap (a filter that drifted out of every window has drifted inside its submaps
    too), the motion model's variance.

    Args:
        local: (S, 3) the filter's chain (m, m, rad); ``motions``: (S, 3) the odometry's (row 0
            unused); ``jitter``: rad^2; ``submaps``: their node runs.
    """
    if rates is None:
        every_node = np.arange(local.shape[0])
        odometry = local[0, 2] + np.concatenate([[0.0], np.cumsum(motions[1:, 2])])
        return fused_chain(local, odometry, every_node, every_node), None
    headings = smoothed_headings(local[:, 2], motions[1:, 2], rates[0], rates[1], jitter)
    fused_rate = rates[0] * rates[1] / (rates[0] + rates[1])
    return fused_chain(local, headings, submaps.first_node, submaps.last_node), fused_rate


def sequential_edges(poses: np.ndarray, motions: np.ndarray, motion_params, heading_rate: float | None = None) -> Edges:
    """Edges between consecutive nodes: the chain's relative poses, with the motion model's
    covariance of the odometry motion between them ((S, 3) poses, (S, 3) motions, row 0 unused).

    ``heading_rate`` (rad^2 per step), where the loops measured it, is each step's heading
    variance instead, plus the motion model's share of the step's turn (``stt`` times it): the
    model's whole (about 3 degrees a step) would let the graph bend a chain whose heading the
    loops found good to 0.04-0.06 degrees a root step, and close a loop's translation by turning
    it (FR-clinic: 12 degrees); the rate alone held a turn's error too, which a random walk does
    not model (FR-clinic's last corner, 2.8 degrees: the loops after it were outvoted)."""
    first = np.arange(poses.shape[0] - 1)
    measurement = between_np(poses[:-1], poses[1:])
    std = np.asarray(noise_std(jnp.asarray(motions[1:], jnp.float32), motion_params), np.float64)
    if heading_rate is not None:
        std[:, 2] = np.sqrt(heading_rate + (float(motion_params.stt) * motions[1:, 2]) ** 2)
    information = np.zeros((first.size, 3, 3))
    information[:, [0, 1, 2], [0, 1, 2]] = 1.0 / np.maximum(std, 1e-6) ** 2
    return Edges(first, first + 1, measurement, information, np.full(first.size, SEQUENTIAL))
