"""The returns a loop closure missed, and why: what ``jaxslam diagnose`` says of a closed run.

A relation whose two scans lie far apart along the path (``min_path``, the search's own
``min_separation``) spans a loop: the filter's chain alone cannot hold it, a loop edge must. Where
the closed trajectory still gets such relations wrong (``min_error``), the closure missed that
return. :func:`missed_returns` groups those relations into the returns they describe (their
earlier and later scans each within ``gap_nodes`` nodes of another's) and puts beside each one
the candidate loops the search found there (queries among the return's later nodes, submaps
over its earlier ones) and how the acceptance judged them (:class:`jaxslam.graph.Loops`'
``refused``), and the pairs the windowed search ran there (:class:`jaxslam.graph.acceptance.SearchRecord`).
The cause is one of (a kept loop first, then a window that missed, then a refusal):

- ``"not searched"``: no query there was searched against those submaps: the estimate put the
  query too far from them for its window (``ClosureConfig.max_node_distance`` beyond it), or
  nearer submaps took its ``submaps_per_query``;
- ``"out of the window"``: searched, but no window held the query's pose as the relations
  give it (the submap's pose composed with the relation and the closed path's short pieces at
  either end): the estimate the search started from was further off than the window had grown,
  and any candidate found there matched elsewhere (its refusal was right);
- ``"no candidate"``: a window held it, and nothing scored enough to be judged
  (``ClosureConfig.candidate_score``): the submaps do not look like the scans (a map bent
  inside a submap, a robot looking the other way);
- ``"refused: REASON"``: a window held the pose, candidates were found and all refused, the
  best-scoring one for REASON
  (``"score"``, ``"window"``, ``"ambiguous"``, ``"information"``, ``"consistency"``, ``"chi2"``);
- ``"kept, yet off"``: loops were kept there and the relations still disagree with the closed
  poses: the loops are wrong (a false loop), outweighed in the optimisation, or the relations are
  (``jaxslam eval --scans`` asks the scans).

A graph written before the search's record was kept tells the first three apart by nothing:
``"no candidate"`` there stands for them all.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from jaxslam.geometry import between_np, compose_np, wrap_angle_np
from jaxslam.metrics import lookup_indices, relation_error

MIN_ERROR = 0.3
"""Relation error (m) of the closed trajectory above which a loop's relation counts as missed:
the closure's consistency test's ``consistency_xy``."""

QUERY_MARGIN = 3
"""A return's queries are those at most this many nodes outside its later nodes (the default
``ClosureConfig.query_stride``: a shorter return may hold no query of its own)."""

CAUSES = ("not searched", "out of the window", "no candidate", "refused", "kept, yet off")
"""The causes :func:`missed_returns` gives (``refused`` with the best candidate's reason after it)."""


def _nearest_node(node_times: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(R,) the node whose scan's time is nearest each of ``times`` (node_times ascending)."""
    right = np.clip(np.searchsorted(node_times, times), 1, node_times.size - 1)
    left = right - 1
    return np.where(np.abs(node_times[right] - times) < np.abs(times - node_times[left]), right, left)


def _groups(early: np.ndarray, late: np.ndarray, gap_nodes: int) -> np.ndarray:
    """(R,) a group label per relation: single linkage of the (early, late) node pairs, two
    relations linked when both their earlier and their later nodes are at most ``gap_nodes`` apart."""
    if early.size == 0:
        return np.zeros(0, int)
    near = ((np.abs(early[:, None] - early[None]) <= gap_nodes) & (np.abs(late[:, None] - late[None]) <= gap_nodes))
    return scipy.sparse.csgraph.connected_components(scipy.sparse.csr_matrix(near), directed=False)[1]


def _submaps_over(first_node: np.ndarray, num_nodes: int, lo: int, hi: int) -> np.ndarray:
    """Indices of the submaps whose nodes meet ``[lo, hi]``, and one more on either side (the
    consistency test compares loops into adjacent submaps as one place)."""
    last_node = np.append(first_node[1:] - 1, num_nodes - 1)
    over = np.nonzero((first_node <= hi) & (last_node >= lo))[0]
    if over.size == 0:
        return over
    return np.arange(max(int(over.min()) - 1, 0), min(int(over.max()) + 2, first_node.size))


def missed_returns(graph: dict, times, closed_poses, filter_poses, relations, min_error: float = MIN_ERROR,
                   min_path: float = 10.0, gap_nodes: int = 20) -> list[dict]:
    """The returns a closed run missed, worst first (see the module's docstring).

    Args:
        graph: the closure's graph (:func:`jaxslam.graph.load_graph` of ``graph.npz``).
        times: (T,) s, the trajectories' timestamps: one per scan of the log, so that a node's
            scan index (``graph["node_scans"]``) is its row.
        closed_poses: (T, 3) the closed trajectory (``trajectory.txt``).
        filter_poses: (T, 3) the filter's (``trajectory_filter.txt``).
        relations: :class:`jaxslam.io.relations.Relations` within the run's time span.
        min_error: a relation the closed trajectory gets wrong by more than this (m) is missed.
        min_path: a relation spans a loop where its two scans' nodes are at least this far apart
            along the closed path (m); the closure searches no nearer submap.
        gap_nodes: relations whose earlier and later nodes both lie within this many nodes of
            another's describe the same return (a submap's nodes, ``ClosureConfig.nodes_per_submap``).

    Returns:
        One dict per missed return, the summed error largest first: ``later_nodes`` and
        ``earlier_nodes`` ([first, last]), ``later_elapsed_s`` ([first, last], since the first
        node), ``relations``, ``closed_error_m`` and ``filter_error_m`` (their means),
        ``path_between_m`` (median, along the closed path), ``submaps`` ([first, last] of those
        over the earlier nodes), ``candidates`` (their count by verdict: ``"kept"`` or the
        refusal), ``best`` (the best-scoring candidate: query, submap, score, second_ratio,
        refused; None without one), ``kept_elsewhere`` (loops the return's queries kept into other
        submaps), ``searched`` (the windowed search's pairs from the return's queries into those
        submaps: ``pairs``, ``best_score``, ``window_m`` [least, widest], ``guess_off_m`` [least,
        median] how far each window's centre lay from the query's pose as the relations give it,
        ``reached`` the windows that held that pose, and ``pairs_elsewhere`` into other submaps;
        None for a graph without the record) and ``cause``.

    Raises:
        ValueError: the trajectories and the graph do not belong together (named).
    """
    times = np.asarray(times, np.float64)
    node_scans = np.asarray(graph["node_scans"])
    closed_poses, filter_poses = np.asarray(closed_poses, np.float64), np.asarray(filter_poses, np.float64)
    if closed_poses.shape != (times.size, 3) or filter_poses.shape != (times.size, 3):
        raise ValueError(f"missed_returns: the trajectories' shapes {closed_poses.shape} and {filter_poses.shape} "
                         f"do not match their {times.size} timestamps")
    if node_scans.size < 2 or node_scans.max() >= times.size:
        raise ValueError(f"missed_returns: the graph's nodes (scans up to {node_scans.max()}) are not the "
                         f"trajectory's {times.size} scans: is graph.npz this run's?")
    closed_err = relation_error(times, closed_poses, relations).trans
    filter_err = relation_error(times, filter_poses, relations).trans
    node_times = times[node_scans]
    ends = _nearest_node(node_times, np.concatenate([relations.t1, relations.t2]))
    forward = ends[:relations.count] <= ends[relations.count:]  # t1 the earlier scan
    scans = lookup_indices(times, np.concatenate([relations.t1, relations.t2]))
    first, second = scans[:relations.count], scans[relations.count:]
    motion = np.asarray(relations.motion, np.float64)
    ends = _Ends(np.where(forward, ends[:relations.count], ends[relations.count:]),
                 np.where(forward, ends[relations.count:], ends[:relations.count]),
                 np.where(forward, first, second), np.where(forward, second, first),
                 np.where(forward[:, None], motion, between_np(motion, np.zeros(3))), closed_poses)
    poses = np.asarray(graph["poses"], np.float64)
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    missed = np.nonzero((along[ends.late] - along[ends.early] >= min_path) & (closed_err > min_error))[0]
    label = _groups(ends.early[missed], ends.late[missed], gap_nodes)
    out = [_describe(graph, missed[label == g], ends, along, closed_err, filter_err, node_times)
           for g in np.unique(label)]
    return sorted(out, key=lambda d: -d["relations"] * d["closed_error_m"])


class _Ends(NamedTuple):
    """Each relation's two ends, the earlier first (R,), and the closed path per scan."""

    early: np.ndarray
    """(R,) the node nearest the earlier scan."""
    late: np.ndarray
    """(R,) the node nearest the later scan."""
    early_scan: np.ndarray
    """(R,) the earlier scan's index."""
    late_scan: np.ndarray
    """(R,) the later scan's index."""
    motion: np.ndarray
    """(R, 3) the later scan's pose in the earlier's frame (the relation, turned round where t1 is the later)."""
    closed: np.ndarray
    """(T, 3) the closed trajectory."""


def _describe(graph, rows, ends: _Ends, along, closed_err, filter_err, node_times) -> dict:
    """One missed return (:func:`missed_returns`' dict) from its relations' rows."""
    early, late = ends.early, ends.late
    later_nodes = [int(late[rows].min()), int(late[rows].max())]
    earlier_nodes = [int(early[rows].min()), int(early[rows].max())]
    first_node = np.asarray(graph["submap_first_node"])
    submaps = _submaps_over(first_node, node_times.size, *earlier_nodes)
    query, submap = np.asarray(graph["loop_query"]), np.asarray(graph["loop_submap"])
    refused = np.asarray(graph["loop_refused"]).astype(str)
    at_return = (query >= later_nodes[0] - QUERY_MARGIN) & (query <= later_nodes[1] + QUERY_MARGIN)
    here = np.nonzero(at_return & np.isin(submap, submaps))[0]
    verdicts = np.where(refused[here] == "", "kept", refused[here])
    names, counts = np.unique(verdicts, return_counts=True)
    candidates = {str(n): int(c) for n, c in zip(names, counts)}
    best = None
    if here.size:
        top = here[np.argmax(np.asarray(graph["loop_score"])[here])]
        best = {"query": int(query[top]), "submap": int(submap[top]),
                "score": float(graph["loop_score"][top]), "second_ratio": float(graph["loop_second_ratio"][top]),
                "refused": str(refused[top])}
    searched = _searched_at(graph, later_nodes, submaps, ends, rows)
    if "kept" in candidates:
        cause = "kept, yet off"
    elif searched is not None and searched["pairs"] and not searched["reached"]:
        cause = "out of the window"  # any candidate there matched elsewhere: rightly refused
    elif best is not None:
        cause = "refused: " + best["refused"]
    else:
        cause = "not searched" if searched is not None and not searched["pairs"] else "no candidate"
    return {"later_nodes": later_nodes, "earlier_nodes": earlier_nodes,
            "later_elapsed_s": [float(node_times[n] - node_times[0]) for n in later_nodes],
            "relations": int(rows.size), "closed_error_m": float(np.mean(closed_err[rows])),
            "filter_error_m": float(np.mean(filter_err[rows])),
            "path_between_m": float(np.median(along[late[rows]] - along[early[rows]])),
            "submaps": [int(submaps.min()), int(submaps.max())] if submaps.size else [],
            "candidates": candidates, "best": best,
            "kept_elsewhere": int(np.sum(at_return & ~np.isin(submap, submaps) & (refused == ""))),
            "searched": searched, "cause": cause}


def _searched_at(graph, later_nodes, submaps, ends: _Ends, rows) -> dict | None:
    """The windowed search's pairs from a return's queries: into ``submaps`` (their count, best
    score, windows, and how far each window's centre lay from the relations' pose) and into
    others; None for a graph written without the record."""
    if "searched_query" not in graph:
        return None
    query, submap = np.asarray(graph["searched_query"]), np.asarray(graph["searched_submap"])
    at_return = (query >= later_nodes[0] - QUERY_MARGIN) & (query <= later_nodes[1] + QUERY_MARGIN)
    here = np.nonzero(at_return & np.isin(submap, submaps))[0]
    score, half_xy = np.asarray(graph["searched_score"])[here], np.asarray(graph["searched_half_xy"])[here]
    off = _guess_off(graph, here, ends, rows)
    reached = ((np.max(np.abs(off[:, :2]), axis=1) <= half_xy)
               & (np.abs(off[:, 2]) <= np.asarray(graph["searched_half_theta"])[here]))
    distance = np.hypot(off[:, 0], off[:, 1])
    return {"pairs": int(here.size), "best_score": float(score.max()) if score.size else None,
            "window_m": [float(half_xy.min()), float(half_xy.max())] if here.size else [],
            "guess_off_m": [float(distance.min()), float(np.median(distance))] if here.size else [],
            "reached": int(reached.sum()), "pairs_elsewhere": int(np.sum(at_return)) - int(here.size)}


def _guess_off(graph, pairs, ends: _Ends, rows) -> np.ndarray:
    """(P, 3) each searched pair's window centre (``searched_guess``) against the query's pose in
    its submap's first node's frame as the return's relations give it: through the relation whose
    later node is nearest the query and earlier node nearest the submap's first, the closed path's
    pieces from the submap's first node to the relation's earlier scan and from its later scan to
    the query. In the submap's frame (its window's axes); heading wrapped."""
    node_scans = np.asarray(graph["node_scans"])
    query, submap = np.asarray(graph["searched_query"])[pairs], np.asarray(graph["searched_submap"])[pairs]
    origin = np.asarray(graph["submap_first_node"])[submap]
    cost = np.abs(ends.late[rows][None] - query[:, None]) + np.abs(ends.early[rows][None] - origin[:, None])
    r = rows[np.argmin(cost, axis=1)] if rows.size else np.zeros(0, int)
    closed = ends.closed
    to_early = between_np(closed[node_scans[origin]], closed[ends.early_scan[r]])
    from_late = between_np(closed[ends.late_scan[r]], closed[node_scans[query]])
    given = compose_np(compose_np(to_early, ends.motion[r]), from_late)
    off = given - np.asarray(graph["searched_guess"], np.float64)[pairs]
    off[:, 2] = wrap_angle_np(off[:, 2])
    return off
