"""Which of the loop search's matches become loop edges: the five tests of
:mod:`jaxslam.graph.closure` (score, window, uniqueness, information, consistency), each match
refined below the search's cell first, and the record of every candidate (:class:`Loops`); and
a match on its window's edge searched again wider (:func:`widen_edge_peaks`).
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.geometry import between_np, compose_np, wrap_angle_np
from jaxslam.grid import GridSpec
from jaxslam.graph.loop_search import SearchResult, search_pairs
from jaxslam.graph.pose_graph import LOOP, Edges
from jaxslam.graph.submaps import Submaps
from jaxslam.laser import within_usable_range
from jaxslam.map_view import MapView
from jaxslam.scan_matching import match
from jaxslam.sensor_model import ENDPOINT


class Loops(NamedTuple):
    """Candidate loops (host arrays, one row each)."""

    query: np.ndarray
    """(C,) int: the node searched."""
    submap: np.ndarray
    """(C,) int: the submap it matched."""
    measurement: np.ndarray
    """(C, 3): the query's pose in the submap's first node's frame."""
    information: np.ndarray
    """(C, 3, 3): the match's information (the Laplace fit's inverse covariance)."""
    score: np.ndarray
    """(C,) the refined match's mean fit."""
    second_ratio: np.ndarray
    """(C,) the second mode's score over the best's."""
    certified: np.ndarray
    """(C,) bool: the search's best is the exact optimum of its window."""
    refused: np.ndarray
    """(C,) str: why the loop was refused ("" for a kept one): "score", "window", "ambiguous",
    "information", "consistency" or "chi2"."""
    chi2: np.ndarray
    """(C,) the loop's chi2 in the final graph (nan for one refused before the optimisation)."""
    appearance: np.ndarray
    """(C,) bool: found by the search by appearance (:mod:`jaxslam.graph.places`), not by the
    windowed search."""

    @classmethod
    def empty(cls) -> "Loops":
        """No loops (``refused`` of dtype object while the closure collects them)."""
        return cls(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0),
                   np.zeros(0), np.zeros(0, bool), np.zeros(0, object), np.zeros(0), np.zeros(0, bool))

    def extend(self, other: "Loops") -> "Loops":
        """These loops, then ``other``'s."""
        return Loops(*(np.concatenate([a, b]) for a, b in zip(self, other)))


class Searched(NamedTuple):
    """One block's searched pairs (host arrays, one row a pair)."""

    query: np.ndarray
    submap: np.ndarray
    guess: np.ndarray
    half_xy: np.ndarray
    half_theta: np.ndarray
    result: SearchResult


class SearchRecord(NamedTuple):
    """Every pair the windowed search ran, whatever it scored (host arrays, one row a pair): where
    the graph holds no candidate, whether the search looked there (:mod:`jaxslam.graph.missed`).
    The pairs searched again wider or by appearance are not in it."""

    query: np.ndarray
    """(P,) int: the node searched."""
    submap: np.ndarray
    """(P,) int: the submap it was searched against."""
    guess: np.ndarray
    """(P, 3): the query's pose in the submap's first node's frame that the window was centred on
    (m, m, rad)."""
    score: np.ndarray
    """(P,) the search's best score (a candidate from ``ClosureConfig.candidate_score`` on)."""
    half_xy: np.ndarray
    """(P,) m: the translation window, either side."""
    half_theta: np.ndarray
    """(P,) rad: the angular window, either side."""
    chain_pass: np.ndarray
    """(P,) int: the pass whose chain it was searched from (1 the filter's; :mod:`jaxslam.graph.drift`)."""

    @classmethod
    def of(cls, searched: Searched, submaps: Submaps) -> "SearchRecord":
        """A block's searched pairs (``searched.guess`` is in its submap's grid: its corner added
        back); ``chain_pass`` 1 until the closure's passes number them."""
        guess = np.asarray(searched.guess, np.float64).copy()
        guess[:, :2] += submaps.corner[searched.submap]
        return cls(searched.query, searched.submap, guess, np.asarray(searched.result.score, np.float64),
                   searched.half_xy, searched.half_theta, np.ones(searched.query.size, int))

    @classmethod
    def empty(cls) -> "SearchRecord":
        """No pairs."""
        return cls(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0),
                   np.zeros(0, int))

    def extend(self, other: "SearchRecord") -> "SearchRecord":
        """These pairs, then ``other``'s."""
        return SearchRecord(*(np.concatenate([a, b]) for a, b in zip(self, other)))


@partial(jax.jit, static_argnames=("grid", "iterations"))
def _refine_one(field, grid: GridSpec, pose, scan, sensor, likelihood, iterations: int):
    """One match refined below the search's cell on its submap's field (bilinear hill climb),
    its mean fit there, and its information: minus the Hessian of the tempered log-likelihood
    (central differences at one cell and 0.01 rad), clamped positive semi-definite."""
    steps = jnp.array([grid.resolution, grid.resolution, 0.01], jnp.float32)
    result = match(grid, field, pose, scan, sensor, likelihood, jnp.float32(grid.resolution), jnp.float32(0.005),
                   iterations, lookup="bilinear")
    view = MapView(grid, field)
    eye = jnp.eye(3) * steps
    corners = [result.pose + sa * eye[:, None, :] + sb * eye[None, :, :] for sa, sb in ((1, 1), (-1, -1), (1, -1), (-1, 1))]
    stencil = jnp.concatenate([c.reshape(-1, 3) for c in corners])
    ll = ENDPOINT.log_likelihoods_fn(view, stencil, scan, sensor, likelihood, "bilinear").reshape(4, 3, 3)
    hess = (ll[0] + ll[1] - ll[2] - ll[3]) / (4.0 * steps[:, None] * steps[None, :])
    info = -0.5 * (hess + hess.T)
    w, v = jnp.linalg.eigh(info)
    info = (v * jnp.maximum(w, 1e-6)) @ v.T
    return result.pose, info, ENDPOINT.match_score_fn(view, result.pose, scan, sensor, likelihood)


def _refine_and_fit(submaps: Submaps, submap, grid_pose, ranges, sensor, likelihood, iterations: int):
    """:func:`_refine_one` for every match (host arrays), 32 at a time."""
    fn = jax.vmap(lambda j, p, r: _refine_one(submaps.field[j], submaps.grid, p, r, sensor, likelihood, iterations))
    poses, infos, scores = [], [], []
    for start in range(0, len(submap), 32):
        take = np.arange(start, start + 32).clip(max=len(submap) - 1)
        p, i, s = fn(jnp.asarray(submap[take]), jnp.asarray(grid_pose[take], jnp.float32), jnp.asarray(ranges[take]))
        n = min(32, len(submap) - start)
        poses.append(np.asarray(p)[:n]), infos.append(np.asarray(i)[:n]), scores.append(np.asarray(s)[:n])
    if not poses:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
    return np.concatenate(poses), np.concatenate(infos).astype(np.float64), np.concatenate(scores)


def consistency_votes(query: np.ndarray, submap: np.ndarray, measurement: np.ndarray, poses: np.ndarray,
                      origins: np.ndarray, config) -> tuple[np.ndarray, np.ndarray]:
    """For each loop, how many other loops agree with it and how many disagree: loops whose
    queries lie within ``consistency_nodes`` nodes and whose submaps are the same or adjacent
    are compared through the filter's relative poses (a loop's query pose is its submap's
    origin composed with its measurement); they agree when they predict the relative pose of
    the two queries within ``consistency_xy`` and ``consistency_theta`` of the filter's.

    Returns:
        ``(agree (C,), disagree (C,))`` counts.
    """
    a, _, agree, _ = _pair_agreement(query, submap, measurement, poses, origins, config)
    return np.bincount(a[agree], minlength=query.size), np.bincount(a[~agree], minlength=query.size)


def _pair_agreement(query, submap, measurement, poses, origins, config):
    """The vote's pairs (both orders) and whether each agrees: :func:`consistency_votes`' rule.

    Returns:
        ``(a (P,), b (P,), agree (P,) bool, turn (P,))``: row indices of each pair's two loops,
        and the heading by which the loops' relative pose turns from the chain's (rad).
    """
    implied = compose_np(origins[submap], measurement)  # each query's pose through its loop
    near = ((np.abs(query[:, None] - query[None]) <= config.consistency_nodes)
            & (np.abs(submap[:, None] - submap[None]) <= 1) & ~np.eye(query.size, dtype=bool))
    a, b = np.nonzero(near)
    through_loops = between_np(implied[a], implied[b])
    through_filter = between_np(poses[query[a]], poses[query[b]])
    diff = between_np(through_filter, through_loops)
    agree = (np.hypot(diff[:, 0], diff[:, 1]) <= config.consistency_xy) & (np.abs(diff[:, 2]) <= config.consistency_theta)
    return a, b, agree, diff[:, 2]


def pairwise_consistent(query_a, origin_a, implied_a, query_b, origin_b, implied_b, poses: np.ndarray,
                        travelled: np.ndarray, config) -> np.ndarray:
    """Whether loops a and b agree (broadcast over their shapes): the cycle query a -> its submap
    -> the chain -> b's submap -> query b -> the chain -> query a closes within a tolerance that
    grows with the chain it runs along.

    Through the loops, the two queries' relative pose is ``implied_a^-1 (+) implied_b`` (each
    query's pose through its loop, its submap's first node at its ``poses`` estimate); through the
    chain it is ``poses[query_a]^-1 (+) poses[query_b]``. They agree when the two differ by at most
    ``consistency_theta`` plus ``consistency_theta_per_metre`` for each metre of chain the cycle
    runs along (between the queries and between the submaps' first nodes) in heading, and in
    position by ``consistency_xy`` plus ``consistency_xy_per_metre`` a metre plus the heading miss
    times the lever it turns (the larger distance between the two queries or the two first nodes):
    the drift the chain may hold between two loops. A heading error far back in the chain moves
    the far end by much more than its metres' share (MIT Killian seed 1: 4-17 degrees over
    180-590 m of chain, 6-19 m); a loop that aliases (a twin room 10 m away) moves it by the
    alias' offset without the turn.

    Args:
        query_a, origin_a: int arrays: each loop's query node and its submap's first node.
        implied_a: (..., 3) each query's pose through its loop (local frame).
        query_b, origin_b, implied_b: the same for the loops compared with.
        poses: (S, 3) the current estimate (local frame).
        travelled: (S,) metres along ``poses`` from the first node.
        config: the closure's :class:`~jaxslam.graph.closure.ClosureConfig`.
    """
    through_loops = between_np(implied_a, implied_b)
    through_chain = between_np(poses[query_a], poses[query_b])
    diff = between_np(through_chain, through_loops)
    chain = np.abs(travelled[query_a] - travelled[query_b]) + np.abs(travelled[origin_a] - travelled[origin_b])
    # A heading error in the chain turns one end about a node between: the cycle misses by the turn
    # times that lever, taken as the larger span of the two queries or of the two submaps' first nodes.
    lever = np.maximum(np.linalg.norm(poses[query_a][..., :2] - poses[query_b][..., :2], axis=-1),
                       np.linalg.norm(poses[origin_a][..., :2] - poses[origin_b][..., :2], axis=-1))
    turn_ok = np.abs(diff[..., 2]) <= config.consistency_theta + config.consistency_theta_per_metre * chain
    return ((np.hypot(diff[..., 0], diff[..., 1])
             <= config.consistency_xy + config.consistency_xy_per_metre * chain + np.abs(diff[..., 2]) * lever)
            & turn_ok)


def consistent_group(query: np.ndarray, submap: np.ndarray, measurement: np.ndarray, kept_query: np.ndarray,
                     kept_submap: np.ndarray, kept_measurement: np.ndarray, poses: np.ndarray,
                     first_node: np.ndarray, config) -> np.ndarray:
    """Which of a block's loops join the kept ones as one consistent group (pairwise consistency,
    after Mangelson et al. 2018's PCM, with the kept loops fixed): a loop that disagrees with more
    kept loops than it agrees with is out; of the rest, the largest set whose every pair agrees
    (:func:`pairwise_consistent`) is taken greedily, the loops that agree with most first; and a
    loop of it needs ``min_support`` agreeing loops (of the group or kept) whose queries lie within
    ``consistency_nodes`` nodes: one match alone says nothing about itself.

    Args:
        query, submap, measurement: (N,), (N,), (N, 3) the block's loops that passed the other tests.
        kept_query, kept_submap, kept_measurement: (K,), (K,), (K, 3) the loops kept before.
        poses: (S, 3) the estimate the block was searched from (local frame).
        first_node: (M,) each submap's first node.
        config: the closure's :class:`~jaxslam.graph.closure.ClosureConfig`.

    Returns:
        (N,) bool: kept.
    """
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    origin, kept_origin = first_node[submap], first_node[kept_submap]
    implied = compose_np(poses[origin], measurement)
    kept_implied = compose_np(poses[kept_origin], kept_measurement)
    with_kept = pairwise_consistent(query[:, None], origin[:, None], implied[:, None], kept_query[None],
                                    kept_origin[None], kept_implied[None], poses, travelled, config)
    among = pairwise_consistent(query[:, None], origin[:, None], implied[:, None], query[None], origin[None],
                                implied[None], poses, travelled, config)
    # Far kept loops agree with anything (their chain allows any drift): only the comparisons whose
    # chain allows no more than the base tolerance count for a loop; every disagreement counts.
    kept_chain = (np.abs(travelled[query][:, None] - travelled[kept_query][None])
                  + np.abs(travelled[origin][:, None] - travelled[kept_origin][None]))
    telling = kept_chain * config.consistency_xy_per_metre <= config.consistency_xy
    disagree = (~with_kept).sum(axis=1)
    admissible = (disagree == 0) | ((with_kept & telling).sum(axis=1) > disagree)
    among &= admissible[:, None] & admissible[None]
    chosen = np.zeros(query.size, bool)
    candidates = admissible.copy()
    while np.any(candidates):
        degree = np.where(candidates, (among & candidates[None]).sum(axis=1), -1)
        best = int(np.argmax(degree))
        chosen[best] = True
        candidates &= among[best]
        candidates[best] = False
    near = np.abs(query[:, None] - query[None]) <= config.consistency_nodes
    support = ((among & chosen[None] & near & ~np.eye(query.size, dtype=bool)).sum(axis=1)
               + (with_kept & (np.abs(query[:, None] - kept_query[None]) <= config.consistency_nodes)).sum(axis=1))
    return chosen & (support >= config.min_support)


def accept(submaps: Submaps, searched: Searched, ranges, sensor, likelihood, estimate, kept_before: Loops,
            config) -> Loops:
    """The searched pairs whose score is near the threshold, refined, fitted and put to the
    score, window, uniqueness, information and consistency tests (``refused`` says which failed);
    ``config`` is the closure's :class:`~jaxslam.graph.closure.ClosureConfig`."""
    result = searched.result
    promising = np.nonzero(result.score >= config.candidate_score)[0]
    query, submap = searched.query[promising], searched.submap[promising]
    guess, half_xy, half_theta = (searched.guess[promising], searched.half_xy[promising],
                                  searched.half_theta[promising])
    # The beams the search scored: a beam past the search's range ends where the submaps hold
    # nothing (they register endpoints to the same range), and counted it scores 0. At FR-clinic's
    # return to its start 29-52 % of the beams are longer; counted, they took true matches of
    # 0.6 down to 0.4, under min_score.
    usable = np.asarray(within_usable_range(jnp.asarray(ranges[query]), config.search_range))
    refined, information, score = _refine_and_fit(submaps, submap, result.pose[promising], usable, sensor,
                                                  likelihood, config.match_iterations)
    measurement = refined.astype(np.float64)
    measurement[:, :2] += submaps.corner[submap]
    measurement[:, 2] = wrap_angle_np(measurement[:, 2])
    second_ratio = result.second_score[promising] / np.maximum(result.score[promising], 1e-9)
    cov = np.linalg.inv(information) if promising.size else np.zeros((0, 3, 3))
    std_xy = np.sqrt(np.clip(np.linalg.eigvalsh(cov[:, :2, :2])[:, -1], 0, None)) if promising.size else np.zeros(0)
    std_theta = np.sqrt(np.clip(cov[:, 2, 2], 0, None))
    # A peak on the window's edge is no mode of the score: the best match may lie outside, where
    # the search did not look (along a corridor, a shifted doorway).
    offset = refined - guess
    margin_xy = 2 * submaps.grid.resolution
    at_edge = ((np.max(np.abs(offset[:, :2]), axis=1) > half_xy - margin_xy)
               | (np.abs(wrap_angle_np(offset[:, 2])) > half_theta - 2 * config.angular_step))
    refused = np.full(promising.size, "", dtype=object)
    refused[score < config.min_score] = "score"
    refused[(refused == "") & at_edge] = "window"
    refused[(refused == "") & (second_ratio >= config.max_second_ratio)] = "ambiguous"
    refused[(refused == "") & ((std_xy > config.max_std_xy) | (std_theta > config.max_std_theta))] = "information"
    # Consistency: the block's loops that passed, and the loops kept before (which vote but are
    # not judged again): a loop needs min_support agreeing and more agreeing than disagreeing.
    passed = np.nonzero(refused == "")[0]
    earlier = np.nonzero(kept_before.refused == "")[0]
    if config.consistency in ("vote", "both"):
        agree, disagree = consistency_votes(np.concatenate([query[passed], kept_before.query[earlier]]),
                                            np.concatenate([submap[passed], kept_before.submap[earlier]]),
                                            np.concatenate([measurement[passed], kept_before.measurement[earlier]]),
                                            estimate, estimate[submaps.first_node], config)
        voted = (agree[:passed.size] >= config.min_support) & (disagree[:passed.size] < agree[:passed.size])
        refused[passed[~voted]] = "consistency"
        passed = passed[voted]
    if config.consistency in ("group", "both"):  # "both": the group test on what the vote kept
        group_config = dataclasses.replace(config, min_support=0) if config.consistency == "both" else config
        ok = consistent_group(query[passed], submap[passed], measurement[passed], kept_before.query[earlier],
                              kept_before.submap[earlier], kept_before.measurement[earlier], estimate,
                              submaps.first_node, group_config)
        refused[passed[~ok]] = "consistency"
    return Loops(query, submap, measurement, information, score, second_ratio,
                 (result.score >= result.dropped_bound)[promising], refused, np.full(promising.size, np.nan),
                 np.zeros(promising.size, bool))


def widen_edge_peaks(new: Loops, searched: Searched, submaps: Submaps, ranges, points, valid, sensor, likelihood,
                     estimate, found: Loops, config) -> tuple[Loops, int]:
    """The block's loops, those refused for a peak on the window's edge searched again in a window
    twice as wide (up to the maximum), until the peak lies inside or the window can grow no more;
    and the pairs searched again. Each pair's row is its last search's.

    A peak on the edge says the estimate is further off than the window's prior growth allowed
    (MIT Killian seed 3's return to its start: matches up to 0.89 on the edge, none kept, 0.69 m).
    The wider window keeps the first one inside it, so a twin that the wider window reaches is
    judged against the first peak by the uniqueness test."""
    retried, latest = 0, 0  # rows from ``latest`` on are the last search's
    for _ in range(config.max_widenings):
        edge = latest + np.nonzero((new.refused[latest:] == "window") & (new.score[latest:] >= config.min_score))[0]
        row = {(int(q), int(j)): i for i, (q, j) in enumerate(zip(searched.query, searched.submap))}
        take = np.array([row[(int(new.query[i]), int(new.submap[i]))] for i in edge], int)
        half_xy = np.minimum(2.0 * searched.half_xy[take], config.window_max_xy)
        half_theta = np.minimum(2.0 * searched.half_theta[take], config.window_max_theta)
        grows = (half_xy > searched.half_xy[take]) | (half_theta > searched.half_theta[take])
        edge, take, half_xy, half_theta = edge[grows], take[grows], half_xy[grows], half_theta[grows]
        if edge.size == 0:
            break
        resolution = submaps.grid.resolution
        query, submap, guess = searched.query[take], searched.submap[take], searched.guess[take]
        result = search_pairs(submaps, submap, points[query], valid[query], guess,
                              np.ceil(half_xy / resolution).astype(np.int32), half_theta, config.window(resolution),
                              batch=config.batch)
        searched = Searched(query, submap, guess, half_xy, half_theta, result)
        retried += int(query.size)
        kept = Loops(*(field[new.refused == ""] for field in new))
        again = accept(submaps, searched, ranges, sensor, likelihood, estimate, found.extend(kept), config)
        stays = np.ones(new.query.size, bool)
        stays[edge] = False
        new = Loops(*(field[stays] for field in new))
        latest = new.query.size
        new = new.extend(again)
    return new, retried


def one_jump_explains_refused_group(new: Loops, found: Loops, submaps: Submaps, estimate: np.ndarray,
                                    config) -> Loops:
    """The block's loops, with those the vote refused kept after all where one jump of the
    chain's heading explains every disagreement.

    The vote compares loops through the chain's relative poses, rigidly. Where the filter's
    heading jumped between two queries (MIT Killian seed 1: 4-6 degrees at nodes 3,435-3,438, a
    turn of 15-20 degrees a step), the loops after the jump disagree with the loops kept before
    it, which outnumber them, and they were refused until the return was out of every window.
    A jump is one turn ``delta`` at one node ``c``: every later pose, the later submaps with them,
    turns rigidly about node ``c``. For each node ``c`` over the span of the block's loops (and the
    kept loops they are compared with), ``delta`` is the median heading disagreement of the pairs
    that straddle it, and the vote is taken again through the chain so turned. The best such
    chain (most of the block's loops kept) replaces the vote's verdict when:

    - ``|delta| <= consistency_jump``;
    - it keeps more of the block's loops, and every loop the rigid vote kept;
    - every kept loop of the blocks before that it compares agrees with more loops than it
      disagrees with;
    - every pair of loops it keeps that straddles ``c`` agrees in heading through the turned
      chain (within ``consistency_theta``).

    The last test tells a jump from a drift: a jump turns every later pose by the same angle, a
    heading that drifts (a bent chain, a bent submap) turns a pair by the nodes between its
    queries. The caller applies the rule only where the chain carries the submaps rigidly.

    Args:
        new: the block's candidates (``refused`` as :func:`accept` left it).
        found: the loops of the blocks before (their kept ones take part).
        submaps: the submaps.
        estimate: (S, 3) the estimate the block was searched from (local frame).
        config: the closure's :class:`~jaxslam.graph.closure.ClosureConfig`.
    """
    if config.consistency_jump <= 0 or not np.any(new.refused == "consistency"):
        return new
    passed = np.nonzero((new.refused == "") | (new.refused == "consistency"))[0]
    earlier = np.nonzero(found.refused == "")[0]
    query = np.concatenate([new.query[passed], found.query[earlier]])
    submap = np.concatenate([new.submap[passed], found.submap[earlier]])
    measurement = np.concatenate([new.measurement[passed], found.measurement[earlier]])
    # The earlier loops that take part: near some loop of the block.
    near = ((np.abs(query[:, None] - query[None, :passed.size]) <= config.consistency_nodes)
            & (np.abs(submap[:, None] - submap[None, :passed.size]) <= 1)).any(axis=1)
    query, submap, measurement = query[near], submap[near], measurement[near]
    block = np.arange(query.size) < passed.size  # the block's rows come first, all near themselves
    rigid_kept = new.refused[passed] == ""

    # The vote's pairs, each once (earlier query first), and their heading disagreement: through
    # the loops against through the chain. A centre's straddling pairs are a subset.
    a, b = np.nonzero((query[:, None] < query[None]) & (query[None] - query[:, None] <= config.consistency_nodes)
                      & (np.abs(submap[:, None] - submap[None]) <= 1))
    implied = compose_np(estimate[submaps.first_node][submap], measurement)
    turn = wrap_angle_np(between_np(implied[a], implied[b])[:, 2]
                         - between_np(estimate[query[a]], estimate[query[b]])[:, 2])
    best, best_kept = None, int(rigid_kept.sum())
    for centre in range(int(query.min()), int(query.max())):
        straddling = (query[a] <= centre) & (query[b] > centre)
        if not np.any(straddling):
            continue
        delta = float(np.median(turn[straddling]))
        if abs(delta) > config.consistency_jump:
            continue
        turned = estimate.copy()  # every pose after the centre turned about it, rigidly
        turned[centre + 1:] = compose_np(compose_np(estimate[centre], [0.0, 0.0, delta]),
                                         between_np(estimate[centre], estimate[centre + 1:]))
        ok, explained = _vote_across(query, submap, measurement, turned, submaps.first_node, centre, config)
        kept = int(ok[block].sum())
        # Every earlier loop here is near a block's loop, so it has a vote to keep.
        if explained and kept > best_kept and np.all(ok[block][rigid_kept]) and np.all(ok[~block]):
            best, best_kept = ok[block], kept
    if best is None:
        return new
    refused = new.refused.copy()
    refused[passed] = np.where(best, "", "consistency")
    return new._replace(refused=refused)


def _vote_across(query, submap, measurement, poses, first_node, centre: int, config):
    """The vote (:func:`consistency_votes`' rule) through ``poses``, a chain turned at node
    ``centre``: each loop's verdict, and whether every kept pair that straddles the centre
    agrees in heading."""
    a, b, agree, turn = _pair_agreement(query, submap, measurement, poses, poses[first_node], config)
    agreeing, disagreeing = np.bincount(a[agree], minlength=query.size), np.bincount(a[~agree], minlength=query.size)
    ok = (agreeing >= config.min_support) & (disagreeing < agreeing)
    # One jump turns every later pose by the same angle: through the turned chain, every pair of
    # loops it keeps that straddles the jump agrees in heading (their positions by the vote's
    # majority, as anywhere).
    straddles = (query[a] <= centre) != (query[b] <= centre)
    explained = not np.any(straddles & ok[a] & ok[b] & (np.abs(turn) > config.consistency_theta))
    return ok, explained


def loop_edges(loops: Loops, submaps: Submaps) -> Edges:
    """The graph's edges of the kept loops: from each one's submap's first node to its query."""
    kept = loops.refused == ""
    return Edges(submaps.first_node[loops.submap[kept]], loops.query[kept], loops.measurement[kept],
                 loops.information[kept], np.full(int(kept.sum()), LOOP))


def first_kept(loops: Loops) -> np.ndarray:
    """Indices of the kept loops, each (query, submap) pair once (its first kept row)."""
    kept = np.nonzero(loops.refused == "")[0]
    if kept.size == 0:
        return kept
    _, first = np.unique(np.stack([loops.query[kept], loops.submap[kept]]), axis=1, return_index=True)
    return kept[np.sort(first)]


def merged(loops: Loops) -> Loops:
    """Every pass's candidates as one set: each (query, submap) pair once, its first kept row
    where a pass kept it, else its last refused one; ``chi2`` reset for the final solve."""
    kept = first_kept(loops)
    refused = np.nonzero(loops.refused != "")[0][::-1]  # the last refusal first
    pairs = np.stack([loops.query, loops.submap])
    if pairs.shape[1] == 0:
        return loops
    _, first = np.unique(pairs[:, np.concatenate([kept, refused])], axis=1, return_index=True)
    rows = np.sort(np.concatenate([kept, refused])[first])
    merged = Loops(*(field[rows] for field in loops))
    return merged._replace(refused=merged.refused.copy(), chi2=np.full(rows.size, np.nan))
