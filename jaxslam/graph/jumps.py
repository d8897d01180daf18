"""A jump of the filter's heading that no loop spans: tried as the filter's.

A filter whose map parted in two at one step (a 30-degree turn the robot did not make) leaves
the places it sees again after that step where its chain puts them: a place 25 m from the step
lies 13 m off, beyond every window of the loop search and the search by appearance's bound, and
the closure keeps loops on either side of the step but none across it (our logs' runs turned by
such a jump, experiments/closure_stress.py). The step shows in the filter's heading against the
odometry's (:func:`unspanned_jumps`), but so does a wheel slip the filter corrected: the size
alone cannot say whose it is. The loops can. Where fewer loops span the step than measure a drift
(``min_drift_loops``), the closure runs again from the chain with the jump given to the filter
(:func:`undo_jump`: the odometry's turns there), and takes that closure where it keeps more loops
across the step than the first and they agree in heading with its chain, not the filter's
(:func:`loops_across`, :func:`loops_side_with`); the largest jumps first, at most
``jump_tries`` (:func:`try_jumps`). A log whose closure spans every step runs once, as before.
"""

from __future__ import annotations

import time

import numpy as np

from jaxslam.geometry import between_np, chain_np, wrap_angle_np
from jaxslam.graph.acceptance import first_kept


def unspanned_jumps(filter_headings: np.ndarray, odometry_turns: np.ndarray, spanned: np.ndarray,
                    half_width: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The largest jumps of the filter's heading against the odometry's at nodes no kept loop
    spans enough: where the filter's map may have parted in two at one step, and the places
    seen again after it lie beyond every window (a 30-degree jump puts a place 25 m away 13 m
    off).

    The jump at node ``c`` is the mean of ``d = filter heading - odometry heading`` over the
    ``half_width`` nodes from ``c`` less its mean over the ``half_width`` nodes before: the
    odometry's drift and the filter's jitter average out over either side, a step that stays
    does not. Its size is counted from the statistic's median over every node, in robust
    standard deviations (1.4826 MAD). Which of the two chains a jump is in, the statistic cannot say
    (a wheel slip the filter corrected looks the same); loops across it can
    (:func:`loops_side_with`). The jumps are taken largest first, each at least two half widths
    from a larger one (one step is seen by the nodes round it).

    Args:
        filter_headings: (S,) the filter's headings at the nodes (rad).
        odometry_turns: (S-1,) the odometry's heading change of each step (rad).
        spanned: (S,) bool: the nodes loops span enough (:func:`spanned_nodes`).
        half_width: nodes averaged on either side.
        count: jumps at most.

    Returns:
        ``(node (J,) int, jump (J,) rad, robust standard deviations (J,))``, J <= ``count``,
        largest first; none where every node is spanned or the path is shorter than two half
        widths.
    """
    headings = np.unwrap(np.asarray(filter_headings, np.float64))
    size = headings.size
    nodes = np.arange(half_width, size - half_width + 1)
    if nodes.size == 0:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    parted = headings - np.concatenate([[0.0], np.cumsum(np.asarray(odometry_turns, np.float64))])
    sums = np.concatenate([[0.0], np.cumsum(parted)])
    jump = (sums[nodes + half_width] - 2.0 * sums[nodes] + sums[nodes - half_width]) / half_width
    # Measured from the median: a filter whose heading drifts steadily from the odometry's moves
    # the statistic at every node alike (the twin rooms drifted 0.015 rad a step: 0.075 rad).
    typical = float(np.median(jump))
    spread = max(1.4826 * float(np.median(np.abs(jump - typical))), 1e-9)
    size_left = np.where(np.asarray(spanned)[nodes], -1.0, np.abs(jump - typical))
    chosen = []
    while len(chosen) < count and size_left.max() >= 0:
        best = int(np.argmax(size_left))
        chosen.append(best)
        size_left[max(best - 2 * half_width, 0):best + 2 * half_width + 1] = -1.0
    chosen = np.array(chosen, int)
    return nodes[chosen], jump[chosen], np.abs(jump[chosen] - typical) / spread


def heading_jumps(filter_headings: np.ndarray, odometry_turns: np.ndarray, half_width: int,
                  min_sds: float) -> np.ndarray:
    """(J,) int, increasing: every node where the statistic of :func:`unspanned_jumps` exceeds
    ``min_sds`` robust standard deviations, spanned by loops or not, each at least two half
    widths from a larger one. The submaps begin a new run there
    (:func:`jaxslam.graph.submaps.submap_ranges`): whichever chain the jump is in, no submap then
    holds scans placed on both sides of it.
    """
    size = np.asarray(filter_headings).size
    nodes, _, sds = unspanned_jumps(filter_headings, odometry_turns, np.zeros(size, bool), half_width, size)
    return np.sort(nodes[sds > min_sds])


def undo_jump(filter_poses: np.ndarray, odometry_turns: np.ndarray, node: int, half_width: int) -> np.ndarray:
    """(S, 3) the filter's chain with the heading changes of the steps within ``half_width`` of
    ``node`` (:func:`unspanned_jumps`) taken from the odometry: the jump given to the filter."""
    filter_poses = np.asarray(filter_poses, np.float64)
    steps = between_np(filter_poses[:-1], filter_poses[1:])
    around = slice(max(node - half_width, 0), min(node + half_width, steps.shape[0]))
    steps[around, 2] = np.asarray(odometry_turns, np.float64)[around]
    return chain_np(filter_poses[0], steps)


def loops_across(loops, first_node: np.ndarray, node: int) -> np.ndarray:
    """Indices of the kept loops (each pair once) that span ``node``: their submap ends before
    it, their query is at or after it (the step into ``node`` lies between).

    Args:
        loops: :class:`~jaxslam.graph.acceptance.Loops`.
        first_node: (M,) each submap's first node.
    """
    kept = first_kept(loops)
    after_submap = np.append(first_node[1:], np.iinfo(np.int64).max)[loops.submap[kept]]
    return kept[(after_submap <= node) & (loops.query[kept] >= node)]


def spanned_nodes(loops, first_node: np.ndarray, num_nodes: int, min_loops: int) -> np.ndarray:
    """(S,) bool: at least ``min_loops`` kept loops of the windowed search span node ``c``
    (:func:`loops_across`), or ``c`` lies in the first submap, which no loop can span.

    The loops found by appearance do not count: after a jump beyond the windows they are what
    the search finds near the wrong estimate (MIT Killian turned 30 degrees at its middle node:
    nine, all 3.5-4.4 m off, spanned the jump).

    Args:
        loops: :class:`~jaxslam.graph.acceptance.Loops`.
        first_node: (M,) each submap's first node.
        num_nodes: S.
        min_loops: loops that make a node spanned.
    """
    kept = first_kept(loops)
    kept = kept[~loops.appearance[kept]]
    after_submap = np.append(first_node[1:], num_nodes)[loops.submap[kept]]
    count = np.zeros(num_nodes + 1, np.int64)  # a difference array: +1 where a span starts, -1 after it ends
    np.add.at(count, after_submap, 1)
    np.add.at(count, loops.query[kept] + 1, -1)
    spanned = np.cumsum(count)[:-1] >= min_loops
    spanned[:first_node[1] if first_node.size > 1 else num_nodes] = True
    return spanned


def loops_side_with(loops, rows: np.ndarray, first_node: np.ndarray, chain: np.ndarray, other: np.ndarray) -> bool:
    """Whether the loops ``rows`` agree in heading with ``chain`` better than with ``other``: the
    median over them of |the measured heading less the chain's relative heading from the
    submap's first node to the query|.

    Args:
        loops: :class:`~jaxslam.graph.acceptance.Loops`.
        rows: (L,) int the loops to ask (:func:`loops_across`).
        first_node: (M,) each submap's first node.
        chain, other: (S, 3) two chains of the nodes.
    """
    origin, query = first_node[loops.submap[rows]], loops.query[rows]

    def misfit(poses):
        return np.median(np.abs(wrap_angle_np(loops.measurement[rows, 2] - (poses[query, 2] - poses[origin, 2]))))
    return bool(rows.size and misfit(chain) < misfit(other))


def try_jumps(closure, filter_poses: np.ndarray, motions: np.ndarray, close_fn, config, t0: float):
    """``closure`` (a :class:`~jaxslam.graph.closure.LoopClosure` of ``filter_poses``), or the
    closure of the chain with a jump given to the filter where the loops choose it (the module
    docstring); its ``jumps`` records every try, its ``pairs_searched`` and total seconds count
    them.

    Args:
        filter_poses: (S, 3) the filter's node poses (world frame).
        motions: (S, 3) the odometry's motions (row 0 unused).
        close_fn: ``close_fn(poses)`` -> the closure from the chain ``poses`` (S, 3).
        config: the closure's settings (``jump_tries``, ``jump_min_sds``, ``jump_half_width``,
            ``min_drift_loops``).
        t0: when the closure started (``time.perf_counter``).
    """
    spanned = spanned_nodes(closure.loops, closure.submap_first_node, filter_poses.shape[0], config.min_drift_loops)
    tried = []
    for node, jump, sds in zip(*unspanned_jumps(filter_poses[:, 2], motions[1:, 2], spanned, config.jump_half_width,
                                                config.jump_tries)):
        if sds <= config.jump_min_sds:
            break
        undone = close_fn(undo_jump(filter_poses, motions[1:, 2], node, config.jump_half_width))
        across = loops_across(undone.loops, undone.submap_first_node, node)
        given = (across.size > loops_across(closure.loops, closure.submap_first_node, node).size
                 and loops_side_with(undone.loops, across, undone.submap_first_node, undone.filter_poses, filter_poses))
        tried.append((int(node), float(jump), float(sds), given))
        closure = closure._replace(pairs_searched=closure.pairs_searched + undone.pairs_searched)
        if given:
            closure = undone._replace(filter_poses=filter_poses, pairs_searched=closure.pairs_searched)
            break
    return closure._replace(jumps=tuple(tried), timings={**closure.timings, "total": time.perf_counter() - t0})
