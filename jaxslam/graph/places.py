"""Loop candidates by appearance: where the filter's estimate is further off than any window
allows, a scan that looks like an old one says where to search (after Kim and Kim's Scan
Context, 2018, for a planar laser).

Each node's scan becomes a polar occupancy signature (:func:`scan_contexts`): rings of range by
sectors of bearing, 1 where a return falls. Two signatures compared at every circular shift of
the sectors (:func:`context_similarity`) give how alike the two places look and the heading
between them. A query whose windowed search kept no loop is compared with the nodes of the
earlier submaps that search did not cover, within a bound on the drift (``place_drift_per_metre``
of the graph distance); the submaps whose best node looks most alike (:func:`appearance_pairs`)
are searched in a small window round that node's pose, turned by the heading the signatures
found, that heading kept within the pair's angular window. The match then meets the same five tests as any other,
and one more (:func:`refuse_look_alikes`): a query that matches another place as well is
refused. The bound, like the window, is what keeps a twin room out: on its first visit nothing
else matches (:func:`add_appearance_loops`; docs/design.md, "Loop closure behind the filter").
"""

from __future__ import annotations

import numpy as np

from jaxslam.geometry import between_np, compose_np, wrap_angle_np
from jaxslam.graph import acceptance
from jaxslam.graph.acceptance import Loops, Searched
from jaxslam.graph.windows import search_from


CONTEXT_POINTS = 180
"""Points of a scan its signature is drawn from (a SICK's 1-degree beams over 180 degrees)."""
RINGS = 15
"""Rings of the signature: 1 m each at the search's 15 m range."""
SECTORS = 60
"""Sectors of the signature: 6 degrees each."""


def scan_contexts(points: np.ndarray, valid: np.ndarray, max_range: float, rings: int = RINGS,
                  sectors: int = SECTORS) -> np.ndarray:
    """(S, rings, sectors) float32: 1 where a scan's points fall in the polar cell (rings of
    ``max_range / rings`` m, sectors of ``2 pi / sectors`` rad from -pi), else 0.

    Args:
        points: (S, P, 2) each scan's points in the robot frame (m).
        valid: (S, P) which points count.
    """
    radius = np.hypot(points[..., 0], points[..., 1])
    ring = np.clip((radius / max_range * rings).astype(np.int64), 0, rings - 1)
    sector = ((np.arctan2(points[..., 1], points[..., 0]) + np.pi) / (2 * np.pi) * sectors).astype(np.int64) % sectors
    ok = valid & (radius < max_range)
    contexts = np.zeros((points.shape[0], rings * sectors), np.float32)
    scan = np.broadcast_to(np.arange(points.shape[0])[:, None], ok.shape)
    contexts[scan[ok], (ring * sectors + sector)[ok]] = 1.0
    return contexts.reshape(points.shape[0], rings, sectors)


def context_similarity(query: np.ndarray, others: np.ndarray, expected: np.ndarray, max_turn: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """How alike one signature is to each of C others, at the best circular shift of the
    sectors within ``max_turn`` of the ``expected`` heading: the cosine of the two binary
    signatures, and the heading of the query in the other node's frame that the shift says (rad).

    The shifts are limited because a corridor looks alike both ways: unlimited, the best shift
    of a query turned 180 or 90 degrees from its estimate scored 0.85 at MIT Killian, and seven
    such matches passed every test. The heading is what the filter keeps best (the drift the
    window allows, 45 degrees at most); what appearance adds is where.

    Args:
        query: (R, A) signature.
        others: (C, R, A) signatures.
        expected: (C,) the query's heading in each other node's frame, by the estimate (rad).
        max_turn: (C,) how far the heading may be from ``expected`` (rad).

    Returns:
        ``(similarity (C,) in [0, 1], heading (C,) rad)``.
    """
    sectors = query.shape[-1]
    # sum_a query[a] other[a + s]: a query bearing a is the other's bearing a + s, so the query
    # is turned by s sectors in the other's frame.
    spectrum = np.conj(np.fft.rfft(query, axis=-1))[None] * np.fft.rfft(others, axis=-1)
    overlap = np.fft.irfft(spectrum, n=sectors, axis=-1).sum(axis=1)  # (C, A)
    norm = np.sqrt(query.sum() * others.sum(axis=(1, 2))) + 1e-9
    turn = np.arange(sectors) * (2 * np.pi / sectors)
    allowed = np.abs(wrap_angle_np(turn[None] - expected[:, None])) <= max_turn[:, None] + np.pi / sectors
    overlap = np.where(allowed, overlap, -1.0)
    shift = np.argmax(overlap, axis=1)
    return np.maximum(overlap[np.arange(others.shape[0]), shift], 0.0) / norm, wrap_angle_np(turn[shift])


def appearance_pairs(contexts: np.ndarray, estimate: np.ndarray, queries: np.ndarray, submaps, travelled: np.ndarray,
                     searched: np.ndarray, distance: np.ndarray, config
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (query, submap) pairs to search by appearance, and where: each query against the
    ``places_per_query`` submaps, of those that end ``min_separation`` m of path before it,
    whose most alike node is at least ``min_similarity`` alike; the guess is that node's pose in
    the submap's frame, turned by the heading the signatures found. A node counts where the drift
    could have put the query (``place_drift_per_metre`` times the graph distance, plus
    ``place_window_xy``), in a submap the windowed search did not search.

    Args:
        contexts: (S, R, A) :func:`scan_contexts`.
        estimate: (S, 3) the current node estimates.
        queries: (Q,) nodes to search from.
        submaps: the submaps.
        travelled: (S,) path along the chain (m).
        searched: (Q, M) bool: the pairs the windowed search covered. Their submaps are left to
            it: a submap the window searched and found ambiguous or poor there is not overruled
            by a better match beyond the window (MIT Killian seed 1: a query the filter had
            right to 0.2 m scored 0.50 at its true place, ambiguous, and 0.85 at a corridor's
            look-alike 7 m off, which passed every test).
        distance: (Q, M) the graph distances (m): the drift they allow bounds where the query may
            be (``place_drift_per_metre``) and how far turned (the angular window).
        config: the closure's settings.

    Returns:
        ``(query (P,), submap (P,), pose (P, 3))``: the guess in the submap's first node's frame.
    """
    first, last = submaps.first_node, submaps.last_node
    out_query, out_submap, out_pose = [], [], []
    for row, query in enumerate(queries):
        eligible = (last < query) & (travelled[query] - travelled[last] >= config.min_separation) & ~searched[row]
        if not np.any(eligible):
            continue
        owner = np.searchsorted(last, np.arange(query))  # each earlier node's submap
        nodes, owner = np.nonzero(eligible[owner])[0], owner[eligible[owner]]
        # Only where the drift could have put the query: a corridor's bays repeat (MIT Killian:
        # every 25 m), and a look-alike bay that far from a correct estimate passes every test.
        offset = np.hypot(*(estimate[nodes, :2] - estimate[query, :2]).T)
        near = offset <= config.place_drift_per_metre * distance[row, owner] + config.place_window_xy
        nodes, owner = nodes[near], owner[near]
        if nodes.size == 0:
            continue
        expected = wrap_angle_np(estimate[query, 2] - estimate[nodes, 2])
        max_turn = np.minimum(config.window_max_theta,
                              config.window_min_theta + config.window_theta_per_metre * distance[row, owner])
        similarity, heading = context_similarity(contexts[query], contexts[nodes], expected, max_turn)
        best = np.full(first.size, -1.0)
        np.maximum.at(best, owner, similarity)
        chosen = np.argsort(-best, kind="stable")[:config.places_per_query]
        chosen = chosen[best[chosen] >= config.min_similarity]
        for j in chosen:
            k = np.nonzero((owner == j) & (similarity == best[j]))[0][0]
            pose = between_np(estimate[first[j]], estimate[nodes[k]])
            pose[2] += heading[k]
            out_query.append(query), out_submap.append(j), out_pose.append(pose)
    if not out_query:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3))
    return np.array(out_query), np.array(out_submap), np.array(out_pose)


def refuse_look_alikes(loops, origins: np.ndarray, config):
    """``loops`` with each appearance loop refused as "ambiguous" where its query matched
    another place at least ``max_second_ratio`` as well: another candidate of the same query
    (found by the windowed search or by appearance) whose match puts the query more than
    ``consistency_xy`` or ``consistency_theta`` from where this one does. Two submaps of one
    place agree; twin rooms do not. A match under ``min_score`` does not count.

    Args:
        loops: a block's :class:`~jaxslam.graph.acceptance.Loops` (``appearance`` marks the rows
            found by appearance).
        origins: (M, 3) the submaps' first nodes' poses (the current estimate).
    """
    refused = loops.refused.copy()
    matched = loops.refused != "score"
    implied = compose_np(origins[loops.submap], loops.measurement)  # the query's pose through each match
    for row in np.nonzero(loops.appearance & (refused == ""))[0]:
        others = matched & (loops.query == loops.query[row])
        apart = between_np(implied[row], implied[others])
        elsewhere = ((np.hypot(apart[:, 0], apart[:, 1]) > config.consistency_xy)
                     | (np.abs(wrap_angle_np(apart[:, 2])) > config.consistency_theta))
        if np.any(elsewhere & (loops.score[others] >= config.max_second_ratio * loops.score[row])):
            refused[row] = "ambiguous"
    return loops._replace(refused=refused)


def add_appearance_loops(new: Loops, searched: Searched, distance: np.ndarray, queries: np.ndarray, estimate, travelled,
                         found: Loops, submaps, scans, ranges, sensor, likelihood, config) -> tuple[Loops, int]:
    """A block's loops (``new``, from its windowed search ``searched``), and the loops found by
    appearance from its queries that kept none, put to the five tests and
    :func:`refuse_look_alikes`; and the pairs searched by appearance.

    Args:
        distance: (Q, M) the graph distances of ``queries`` (Q,), the block's searched nodes.
        scans: ``(points, valid, contexts)`` of every node.
    """
    points, valid, contexts = scans
    unclosed = ~np.isin(queries, new.query[new.refused == ""])
    covered = np.zeros((queries.size, submaps.last_node.size), bool)
    covered[np.searchsorted(queries, searched.query), searched.submap] = True
    query, submap, pose = appearance_pairs(contexts, estimate, queries[unclosed], submaps, travelled,
                                           covered[unclosed], distance[unclosed], config)
    if query.size == 0:
        return new, 0
    alike = search_from(submaps, query, submap, pose, np.full(query.size, config.place_window_xy),
                        np.full(query.size, config.place_window_theta), points, valid, config)
    kept = Loops(*(field[new.refused == ""] for field in new))
    more = acceptance.accept(submaps, alike, ranges, sensor, likelihood, estimate, found.extend(kept), config)
    both = new.extend(more._replace(appearance=np.ones(more.query.size, bool)))
    return refuse_look_alikes(both, estimate[submaps.first_node], config), int(query.size)
