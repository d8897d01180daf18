"""Loop closure behind the particle filter: :func:`close_loops`.

From a finished run (:class:`jaxslam.slam.SlamResult`): the nodes are its processed scans at
the best particle's poses, the edges between neighbours are its relative poses with the motion
model's covariance, the submaps are runs of consecutive scans (:mod:`jaxslam.graph.submaps`).
Every ``query_stride``-th scan is searched against every submap it is not a neighbour of in time
and could be near (:mod:`jaxslam.graph.loop_search`), in a window that grows with the distance
travelled since the submap. A match becomes a loop edge when it passes five tests, each of which
a false loop on an aliasing world fails for its own reason (docs/design.md, "Loop closure behind
the filter"):

1. **score**: its mean fit is at least ``min_score``;
2. **window**: the refined match lies inside the search window, two cells (two angular steps)
   from its edge: a best match on the edge is no peak, the true one may lie beyond;
3. **unique**: no other mode in the window comes within ``max_second_ratio`` of it;
4. **information**: the match pins the pose: the Laplace covariance of the tempered
   log-likelihood at the refined pose has its widest translation axis under ``max_std_xy`` and
   heading under ``max_std_theta`` (a corridor's matches slide along it and fail here);
5. **consistency**: the loops that close near it (queries within ``consistency_nodes`` nodes,
   submaps within one; earlier kept loops vote too) are compared with it through the filter's
   local relative poses: at least ``min_support`` agree, and more agree than disagree (a slide
   along a corridor agrees with its own kind, but the loops before it disagree). Where the chain
   carries the submaps rigidly, a block's refused loops are voted again through the chain turned
   at one node by one angle, and kept where that one jump explains every disagreement
   (:func:`jaxslam.graph.acceptance.one_jump_explains_refused_group`).

A pair whose best match lies on its window's edge is searched again in a wider window
(:func:`jaxslam.graph.acceptance.widen_edge_peaks`). A query that keeps no loop is also searched
by appearance (:mod:`jaxslam.graph.places`): against the submaps whose scans look most like it,
beyond its window but within a bound that grows twice as fast, round their most alike node.

The queries are taken in time order, ``query_block`` nodes at a time, each block searched from
the graph as solved so far; after a block that kept loops the graph is solved
(:func:`jaxslam.graph.pose_graph.optimize`): plain least squares, the loops still in conflict
(chi2 above ``max_chi2``) refused and the graph solved again, then Dynamic Covariance Scaling on
the loops from that solution. :mod:`jaxslam.graph.acceptance` holds the five tests.

The chain between loops is the filter's steps, until the loops say otherwise. The kept loops
measure how fast the filter's heading and the odometry's drift (:mod:`jaxslam.graph.drift`);
where the filter's drifts faster, the closure runs again from the chain that takes the
odometry's share of every heading change, which reaches loops the filter's chain left out of
every window, and measures the rates again from every loop kept so far, until the share moves by
less than ``min_share_change`` (at most ``max_passes``). Where the filter's and the odometry's
headings then part after the last kept loop by more than the rates allow (``max_parting``), one
more pass searches from the odometry's chain. The final graph holds every pass's kept loops on
the last chain, with each step's length weighed between what its scan pins and the odometry's
(:mod:`jaxslam.graph.lengths`). The submaps stay the filter's. Where too few loops span a jump of
the filter's heading against the odometry's, the closure runs again with the jump given to the
filter, and the loops across it choose (:mod:`jaxslam.graph.jumps`). :mod:`jaxslam.graph.output`
draws the map again at the optimised poses and writes the graph."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxslam.geometry import between_np, compose_np
from jaxslam.laser import scan_points
from jaxslam.laserlog import to_local, to_world, trajectory_per_scan
from jaxslam.graph import acceptance, drift, lengths, places, pose_graph
from jaxslam.graph.acceptance import Loops, SearchRecord, loop_edges
from jaxslam.graph.jumps import heading_jumps, try_jumps
from jaxslam.graph.loop_search import SearchWindow, class_shape
from jaxslam.graph.pose_graph import Edges, PoseGraph
from jaxslam.graph.submaps import Submaps, build_submaps
from jaxslam.graph.windows import path_distances, search_block


@dataclasses.dataclass(frozen=True)
class ClosureConfig:
    """Settings of the loop closure. Hashable; the fields marked static set array shapes."""

    nodes_per_submap: int = 20
    """Consecutive processed scans per submap (static); a jump of the heading at least
    ``jump_min_sds`` begins one (:func:`jaxslam.graph.submaps.submap_ranges`)."""
    query_stride: int = 3
    """Every this many processed scans is searched for loops."""
    submaps_per_query: int = 2
    """A scan is searched against at most this many submaps, the nearest to its estimated
    position (their scans overlap: a third adds little), where its window is at most
    ``near_window_xy``; a wider window searches this many per ``near_window_xy`` square of its
    area: its estimate no longer says which of the submaps it reaches it is at (FR-clinic's
    hour-long loop, 20 m: the eighth nearest; Intel's windows stay under it, and eight nearest
    there took its closure from 0.053 to 0.058 m)."""
    near_window_xy: float = 8.0
    """See ``submaps_per_query`` (m either side)."""
    num_points: int = 90
    """Points of a scan the search matches, spread evenly over its valid returns (static)."""
    search_range: float = 15.0
    """Longest return the search and the acceptance's score use (m); the submaps register
    endpoints to the filter's ``max_insert_range``."""
    sigma: float = 0.05
    """Width of the per-point fit exp(-d^2 / (2 sigma^2)) the search scores (m)."""
    min_separation: float = 10.0
    """A submap is searched only from scans at least this far along the path after its last
    scan (m): nearer ones are the filter's neighbours."""
    max_node_distance: float = 5.0
    """A submap is searched from a scan whose estimated position lies within the window plus
    this of one of the submap's scans (m)."""
    window_min_xy: float = 1.0
    """Translation window (m either side) right after the submap."""
    window_xy_per_metre: float = 0.03
    """Growth of the translation window per metre travelled since the submap (m/m)."""
    window_max_xy: float = 20.0
    """Largest translation window (m either side; static): the growth reaches it after 630 m
    of path without a loop (FR-clinic's hour-long loop is 10-14 m off on every chain)."""
    window_min_theta: float = math.radians(30.0)
    """Angular window (rad either side) right after the submap."""
    window_theta_per_metre: float = math.radians(0.05)
    """Growth of the angular window per metre travelled (rad/m)."""
    window_max_theta: float = math.radians(45.0)
    """Largest angular window (rad either side; static)."""
    angular_step: float = 0.01
    """Angle between candidate headings (rad): a cell's side at 5 m; the hill climb refines
    the heading below it (static)."""
    levels: int = 5
    """Levels of the search's bound (static), the least: see ``top_squares``."""
    top_squares: int = 9
    """A window wider than this many top squares a side is screened at more levels (``search_pairs``;
    static; 0: never): 9 leaves those up to 6.4 m as they were (20 m took 9/10 of FR-clinic's search)."""
    keep: int = 128
    """Nodes the search keeps per level (static)."""
    batch: int = 16
    """Pairs searched at once (static; memory)."""
    min_score: float = 0.45
    """Least mean fit of a loop."""
    max_second_ratio: float = 0.9
    """A match whose second mode (0.5 m or 3 degrees away) scores at least this fraction of it is
    ambiguous."""
    max_std_xy: float = 0.10
    """Widest translation std a loop may have (m)."""
    max_std_theta: float = 0.02
    """Widest heading std a loop may have (rad)."""
    consistency_nodes: int = 40
    """Loops whose queries are at most this many nodes apart check each other."""
    consistency_xy: float = 0.3
    """Loops agree when they predict each other's query within this (m) ..."""
    consistency_theta: float = 0.05
    """... and this (rad)."""
    consistency_xy_per_metre: float = 0.03
    """Growth of ``consistency_xy`` per metre of chain between two loops (m/m;
    :func:`jaxslam.graph.acceptance.pairwise_consistent`): the drift the chain may hold."""
    consistency_theta_per_metre: float = math.radians(0.05)
    """Growth of ``consistency_theta`` per metre of chain between two loops (rad/m)."""
    consistency_jump: float = math.radians(45.0)
    """Largest jump of the chain's heading (rad) that may explain why a block's loops disagree with
    the loops kept before them (:func:`jaxslam.graph.acceptance.one_jump_explains_refused_group`;
    0: never). The widest angular window's: a larger turn leaves no loop to explain."""
    consistency: str = "vote"
    """How the consistency test judges a block's loops: "vote" (:func:`jaxslam.graph.acceptance.consistency_votes`),
    "group" (:func:`jaxslam.graph.acceptance.consistent_group`, pairwise consistency with the kept loops) or "both"
    (the vote, then the group test on what it kept; docs/results.md, "Loops accepted as a group")."""
    min_support: int = 1
    """Other loops a loop must agree with."""
    loop_phi: float = 5.0
    """Dynamic Covariance Scaling's phi for loop edges (chi2 units)."""
    max_chi2: float = 25.0
    """A loop whose chi2 after the least-squares solve exceeds this is refused."""
    max_rounds: int = 5
    """Solve-and-refuse rounds at most."""
    query_block: int = 100
    """Nodes whose queries are searched before the graph is solved again (time order)."""
    match_iterations: int = 12
    """Hill-climbing rounds that refine each match below the search's cell (static)."""
    max_passes: int = 4
    """Closures at most: each after the first searches from the chain whose heading weighs the
    filter's and the odometry's by the drift rates the last one's loops measured
    (:mod:`jaxslam.graph.drift`)."""
    min_share_change: float = 0.05
    """The passes stop when the odometry's share of the heading changes by less than this."""
    min_drift_loops: int = 3
    """Kept loops needed to measure the drift rates (fewer: one pass)."""
    max_widenings: int = 2
    """Times a pair whose best match lies on its window's edge is searched again in a window twice
    as wide (:func:`jaxslam.graph.acceptance.widen_edge_peaks`; up to ``window_max_xy`` and
    ``window_max_theta``)."""
    places_per_query: int = 3
    """Submaps a query whose windowed search kept no loop is also searched against by appearance:
    those whose scans look most like it, beyond its window (:mod:`jaxslam.graph.places`; 0: never)."""
    min_similarity: float = 0.6
    """Least similarity (the cosine of the scans' polar signatures, in [0, 1]) for a search by
    appearance."""
    place_window_xy: float = 3.0
    """Translation window of a search by appearance (m either side of the alike node)."""
    place_drift_per_metre: float = 0.06
    """How far from its estimate a search by appearance may put a query, per metre of graph
    distance to the submap (m/m): twice the window's growth."""
    place_window_theta: float = 0.2
    """Angular window of a search by appearance (rad either side of the signatures' heading)."""
    max_parting: float = 3.0
    """Standard deviations by which the filter's and the odometry's headings may part after the
    last kept loop (:func:`jaxslam.graph.drift.parting`); beyond, one pass searches from the
    odometry's chain, whatever the share."""
    jump_tries: int = 2
    """Jumps of the filter's heading against the odometry's that fewer than ``min_drift_loops``
    loops span, tried largest first: each given to the filter and the closure run again from that
    chain, taken where the loops across it choose it (:mod:`jaxslam.graph.jumps`;
    0: never)."""
    jump_min_sds: float = 4.0
    """Least size of a jump tried, and of one that begins a submap (robust standard deviations
    of the jump statistic, :func:`jaxslam.graph.jumps.heading_jumps`)."""
    jump_half_width: int = 5
    """Nodes averaged on either side of a jump (:mod:`jaxslam.graph.jumps`)."""

    def __post_init__(self):
        counts = ("nodes_per_submap", "query_stride", "submaps_per_query", "num_points", "levels", "keep", "batch",
                  "consistency_nodes", "max_rounds", "query_block", "match_iterations", "max_passes",
                  "min_drift_loops", "jump_half_width")
        lengths = ("search_range", "sigma", "window_min_xy", "window_max_xy", "window_min_theta", "window_max_theta",
                   "angular_step", "near_window_xy", "max_std_xy", "max_std_theta", "consistency_xy",
                   "consistency_theta", "loop_phi", "max_chi2", "max_parting", "place_window_xy", "place_window_theta")
        for name in counts:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ClosureConfig: {name} must be a positive integer, got {value!r}")
        for name in ("max_widenings", "top_squares", "places_per_query", "jump_tries"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"ClosureConfig: {name} must be an integer >= 0, got {value!r}")
        for name in lengths + ("min_separation", "max_node_distance", "window_xy_per_metre",
                               "window_theta_per_metre", "consistency_xy_per_metre",
                               "consistency_theta_per_metre", "min_score", "max_second_ratio", "min_share_change",
                               "min_similarity", "place_drift_per_metre", "jump_min_sds"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or value < 0:
                raise ValueError(f"ClosureConfig: {name} must be a finite number >= 0, got {value!r}")
        for name in lengths:
            if not getattr(self, name) > 0:
                raise ValueError(f"ClosureConfig: {name} must be > 0, got {getattr(self, name)!r}")
        if self.consistency not in ("vote", "group", "both"):
            raise ValueError(f"ClosureConfig: consistency must be 'vote', 'group' or 'both', got {self.consistency!r}")
        if not self.consistency_jump >= 0:
            raise ValueError(f"ClosureConfig: consistency_jump must be >= 0, got {self.consistency_jump!r}")
        if self.window_min_xy > self.window_max_xy or self.window_min_theta > self.window_max_theta:
            raise ValueError("ClosureConfig: a window's minimum exceeds its maximum (window_min_xy > window_max_xy "
                             "or window_min_theta > window_max_theta)")
        if not (0 < self.min_score <= 1 and 0 < self.max_second_ratio <= 1):
            raise ValueError(f"ClosureConfig: min_score and max_second_ratio must lie in (0, 1], got "
                             f"{self.min_score!r} and {self.max_second_ratio!r}")

    def window(self, resolution: float, half_cells: int | None = None) -> SearchWindow:
        """The search's static shape at a map resolution (m), for translation windows up to
        ``half_cells`` (default: ``window_max_xy``)."""
        if half_cells is None:
            half_cells = int(math.ceil(self.window_max_xy / resolution))
        return SearchWindow(
            half_cells=int(half_cells),
            half_angles=int(math.ceil(self.window_max_theta / self.angular_step)),
            angular_step=float(self.angular_step), levels=int(self.levels), keep=int(self.keep),
            ambiguity_cells=int(math.ceil(0.5 / resolution)),
            ambiguity_angles=int(math.ceil(math.radians(3.0) / self.angular_step)), top_squares=int(self.top_squares),
            recheck_score=self.candidate_score)

    candidate_score = property(lambda self: 0.8 * float(self.min_score),
                               doc="Least search score of a pair the acceptance refines and judges.")


class LoopClosure(NamedTuple):
    """What :func:`close_loops` returns (host arrays, world frame)."""

    node_scans: np.ndarray
    """(S,) int: the log index of each node's scan."""
    filter_poses: np.ndarray
    """(S, 3): the filter's poses at the nodes."""
    poses: np.ndarray
    """(S, 3): the optimised poses."""
    trajectory: np.ndarray
    """(T, 3): an optimised pose for every scan of the log."""
    edges: Edges
    """The final graph's edges (node indices): the chain's, the odometry's (:mod:`jaxslam.graph.lengths`), the kept loops."""
    loops: Loops
    """Every candidate loop the search found with a score, kept or refused."""
    submap_first_node: np.ndarray
    """(M,) each submap's first node."""
    pairs_searched: int
    """Scan-submap pairs the search ran."""
    timings: dict
    """Seconds: ``submaps``, ``search``, ``accept``, ``optimize`` (summed over the passes), ``total``."""
    chain_poses: np.ndarray
    """(S, 3): the chain the last pass searched from (world frame): the filter's steps, their
    heading changes moved by ``odometry_share`` toward the odometry's."""
    odometry_share: float
    """The odometry's share of each step's heading change in ``chain_poses`` (0: the filter's)."""
    drift_rates: tuple
    """``(filter, odometry)`` heading variance per step (rad^2) that the last pass's kept loops
    measured (:func:`jaxslam.graph.drift.heading_drift_rates`; nan with too few loops)."""
    passes: int
    """Closures run (:attr:`ClosureConfig.max_passes`)."""
    jumps: tuple = ()
    """The jumps of the filter's heading that too few loops spanned, tried in turn
    (:attr:`ClosureConfig.jump_tries`): ``(node, rad, robust stds, given to the filter)`` each;
    where the last was given, the closure is its chain's and ``filter_poses`` the filter's."""
    searched: SearchRecord = SearchRecord.empty()
    """Every pair the windowed search of its passes ran, with its score and window."""

    @property
    def num_loops(self) -> int:
        """Loop edges kept in the graph."""
        return int(np.sum(self.loops.refused == ""))

    def summary(self) -> dict:
        """Counts for ``summary.json``'s ``closure`` (its seconds go under ``timings``): pairs
        searched, loops kept (and those of them the search by appearance found), refused by
        reason, the share of searches whose best was certified exact, and the largest correction
        (m)."""
        refused = self.loops.refused[self.loops.refused != ""]
        reasons, counts = np.unique(refused, return_counts=True)
        shift = np.hypot(*(self.poses - self.filter_poses)[:, :2].T) if self.poses.size else np.zeros(1)
        return {"nodes": int(self.node_scans.size), "submaps": int(self.submap_first_node.size),
                "pairs_searched": int(self.pairs_searched), "candidates": int(self.loops.query.size),
                "loops_kept": self.num_loops,
                "loops_kept_by_appearance": int(np.sum(self.loops.appearance & (self.loops.refused == ""))),
                "refused": {str(r): int(c) for r, c in zip(reasons, counts)},
                "certified_share": float(np.mean(self.loops.certified)) if self.loops.query.size else None,
                "largest_correction_m": float(shift.max()), "passes": int(self.passes),
                "odometry_heading_share": float(self.odometry_share),
                "jumps_tried": [{"node": node, "deg": float(np.degrees(jump)), "robust_stds": sds,
                                 "given_to_filter": given} for node, jump, sds, given in self.jumps],
                "heading_drift_deg_per_sqrt_step": {
                    name: (float(np.degrees(np.sqrt(rate))) if np.isfinite(rate) else None)
                    for name, rate in zip(("filter", "odometry"), self.drift_rates)}}


def _solve(found: Loops, submaps: Submaps, sequential: Edges, local: np.ndarray, estimate: np.ndarray,
           solved_until: int, config: ClosureConfig) -> np.ndarray:
    """The graph optimised with the kept loops (their ``chi2`` written into ``found``; loops in
    conflict refused as "chi2"). Nodes from ``solved_until`` on follow the last solved node by
    the filter's steps. Plain least squares first: a true loop after a long drift has a chi2 of
    thousands at the filter's poses, where a robust kernel would switch it off; loops still in
    conflict after the solve are refused and the graph solved again; the kernel then polishes."""
    # Only the searched nodes are solved: the later ones hang off them by sequential edges
    # alone, which any solution satisfies exactly, so they change nothing but the solve's size.
    initial = estimate[:solved_until].copy()
    searched = sequential.second < solved_until
    sequential = Edges(*(field[searched] for field in sequential))

    def solve(loop_phi, start):
        kept = np.nonzero(found.refused == "")[0]
        solved = pose_graph.optimize(PoseGraph(start, pose_graph.concat_edges(sequential, loop_edges(found, submaps))),
                                     loop_phi=loop_phi)
        found.chi2[kept] = solved.chi2[sequential.count:]
        return kept, solved.poses

    poses = initial
    for _ in range(config.max_rounds):
        kept, poses = solve(None, initial)
        conflict = kept[found.chi2[kept] > config.max_chi2]
        if conflict.size == 0:
            break
        found.refused[conflict] = "chi2"
    _, solved = solve(config.loop_phi, poses)
    # The nodes not yet searched follow the last searched one rigidly (their filter steps).
    poses = estimate.copy()
    poses[:solved_until] = solved
    if solved_until < poses.shape[0]:
        anchor = solved_until - 1
        poses[solved_until:] = compose_np(poses[anchor], between_np(local[anchor], local[solved_until:]))
    return poses


def close_loops(log, result, params, config: ClosureConfig = ClosureConfig(), progress: bool = False) -> LoopClosure:
    """Close the loops of a finished filter run (see the module docstring).

    Args:
        log: the log the filter ran on.
        result: its :class:`jaxslam.slam.SlamResult`.
        params: the filter's :class:`jaxslam.config.SlamParams` (motion noise, insertion,
            likelihood).
        config: the closure's settings.
        progress: show a tqdm bar over the search's pairs.

    Returns:
        :class:`LoopClosure` (world frame).
    """
    return close_trajectory_loops(log, result.selection.indices, result.best_path, result.selection.motions, params,
                                  result.config, result.frame_offset, config, progress)


def close_trajectory_loops(log, node_scans, node_poses, motions, params, slam_config, frame_offset,
                           config: ClosureConfig = ClosureConfig(), progress: bool = False) -> LoopClosure:
    """:func:`close_loops` from a trajectory rather than a run: a finished run's
    ``trajectory_filter.txt`` at its processed scans, or any path to test the closure on.

    Args:
        log: the log (T scans).
        node_scans: (S,) int increasing log indices of the nodes (the processed scans).
        node_poses: (S, 3) their poses in the log's frame (m, m, rad).
        motions: (S, 3) odometry motion from the previous node, in its frame (row 0 unused).
        params: :class:`jaxslam.config.SlamParams`.
        slam_config: the filter's :class:`jaxslam.config.SlamConfig` (resolution, insertion range).
        frame_offset: (2,) the translation subtracted from world poses for float32 work (m).
        config: the closure's settings.
        progress: show a tqdm bar over the search's pairs.
    """
    t0 = time.perf_counter()
    node_scans = np.asarray(node_scans)
    filter_poses = np.asarray(node_poses, np.float64)
    if node_scans.ndim != 1 or filter_poses.shape != (node_scans.size, 3) or np.shape(motions) != filter_poses.shape:
        raise ValueError(f"close_loops: node_scans (S,), node_poses (S, 3) and motions (S, 3) must agree, got "
                         f"{node_scans.shape}, {filter_poses.shape} and {np.shape(motions)}")
    motions = np.asarray(motions, np.float64)
    closure = _close_chain(log, node_scans, filter_poses, motions, params, slam_config, frame_offset, config, progress,
                           t0)
    if closure.passes == 0:
        return closure
    return try_jumps(closure, filter_poses, motions, lambda poses: _close_chain(
        log, node_scans, poses, motions, params, slam_config, frame_offset, config, progress, time.perf_counter()),
        config, t0)


def _close_chain(log, node_scans, filter_poses, motions, params, slam_config, frame_offset, config: ClosureConfig,
                 progress: bool, t0: float) -> LoopClosure:
    """:func:`close_trajectory_loops` from one chain of the nodes (world frame), without the jump's
    second try."""
    local = to_local(filter_poses, frame_offset)
    if path_distances(local)[-1] < config.min_separation:  # no submap can be searched: nothing to build
        return _unclosed(log, node_scans, filter_poses, drift.sequential_edges(local, motions, params.motion), t0)
    ranges = np.asarray(log.ranges[node_scans], np.float32)
    points, valid = scan_points(ranges, log.sensor, config.search_range, config.num_points)
    contexts = places.scan_contexts(*scan_points(ranges, log.sensor, config.search_range, places.CONTEXT_POINTS),
                                    config.search_range)
    # The submaps are the filter's, whatever chain a pass searches from: a submap's 20 scans are
    # placed by the filter's own steps, which its map held together; a chain that takes part of
    # its heading from the odometry takes the odometry's step-to-step noise too (the simulated
    # worlds' loops came out 3 degrees off against submaps drawn on it).
    widest = config.window(slam_config.resolution)  # the bounds the deepest search reads
    cuts = heading_jumps(local[:, 2], motions[1:, 2], config.jump_half_width, config.jump_min_sds)
    submaps = build_submaps(local, ranges, log.sensor, params.insertion, slam_config.resolution, slam_config.max_insert_range,
                            config.nodes_per_submap, config.sigma, class_shape(widest.half_cells, widest).levels, cuts=cuts)
    seconds = {"submaps": time.perf_counter() - t0, "search": 0.0, "accept": 0.0, "appearance": 0.0, "optimize": 0.0}
    run = _passes(local, motions, submaps, ranges, (points, valid, contexts), log.sensor, params, config, seconds,
                  progress)
    closed, everything, share, chain, rates, done = run.closed, run.everything, run.share, run.chain, run.rates, run.done
    if not np.all(np.isfinite(rates)):  # no pass kept enough loops: nothing says the odometry is better
        closed, share, chain = run.first_pass, 0.0, local
    found, estimate, sequential = closed.loops, closed.poses, closed.sequential
    if run.searched_parting:  # the final chain is not the one the last pass searched from
        sequential = drift.sequential_edges(chain, motions, params.motion, run.heading_rate)
    if done > 1 and share > 0:  # the loops of every pass in one graph on the last chain
        found = acceptance.merged(everything)
    t_solve = time.perf_counter()
    sequential = lengths.weighed_steps(sequential, lengths.scan_structure(ranges, log.sensor, config.search_range),
                                       motions, params.motion, slam_config.resolution)
    estimate = _solve(found, submaps, sequential, chain, estimate, chain.shape[0], config)
    seconds["optimize"] += time.perf_counter() - t_solve
    poses = to_world(estimate, frame_offset)
    return LoopClosure(node_scans, filter_poses, poses, trajectory_per_scan(log, node_scans, poses),
                       pose_graph.concat_edges(sequential, loop_edges(found, submaps)),
                       found._replace(refused=found.refused.astype(str)), submaps.first_node, run.pairs,
                       {**seconds, "total": time.perf_counter() - t0}, to_world(chain, frame_offset), float(share),
                       tuple(float(r) for r in rates), done, searched=run.searched)


class _Passes(NamedTuple):
    """What :func:`_passes` leaves: the last pass and the first, every pass's candidates, the final
    chain, its share and heading rate, the rates measured, whether the last pass was the parting's
    (:func:`jaxslam.graph.drift.parted`), the passes run and the pairs searched (counted, and the
    windowed search's recorded)."""

    closed: _Pass
    first_pass: _Pass
    everything: Loops
    share: float
    chain: np.ndarray
    heading_rate: float | None
    rates: tuple
    searched_parting: bool
    done: int
    pairs: int
    searched: SearchRecord


def _passes(local, motions, submaps: Submaps, ranges, scans, sensor, params, config: ClosureConfig,
            seconds: dict, progress: bool) -> _Passes:
    """The closure's passes (:func:`close_trajectory_loops`), each from the chain the loops so far
    weigh; ``seconds`` gains each stage's time."""
    odometry_headings = np.concatenate([[0.0], np.cumsum(motions[1:, 2])])
    _, jitter = drift.step_noise(between_np(local[:-1], local[1:]), motions[1:])
    pairs, searched = 0, SearchRecord.empty()
    share, chain, heading_rate = 0.0, local, None
    everything = Loops.empty()  # every pass's candidates, in pass order
    parting_pass = searched_parting = False  # the next pass, the pass just run: the parting's (at most one)
    bar = None
    for done in range(1, config.max_passes + 1):
        if progress:
            bar = tqdm(total=int(local.shape[0]), desc=f"loop closure, pass {done}", unit="node")
        # The odometry's chain turns every node, not every submap: the filter's submaps are bent
        # against it, and one jump of its heading no longer carries them rigidly.
        closed = _close_pass(chain, heading_rate, motions, submaps, ranges, scans, sensor, params, config,
                             bar, jumps=chain is local or heading_rate is not None)
        if bar is not None:
            bar.close()
        pairs += closed.pairs
        searched = searched.extend(closed.searched._replace(chain_pass=np.full(closed.searched.query.size, done)))
        for stage, taken in closed.seconds.items():
            seconds[stage] += taken
        everything = everything.extend(closed.loops)
        new_share, rates = drift.measured_share(everything, submaps, local, odometry_headings, share, config)
        if done == 1:
            first_pass = closed
        if done == 1 and not np.all(np.isfinite(rates)) and done < config.max_passes:
            # No loop to measure the drift with: the filter's chain may have drifted past every
            # window before the first revisit. The odometry's chain is the other estimate of where
            # the robot was; search once from it, and let its loops (if any) measure the rates.
            share = 1.0
            chain, heading_rate = drift.weighed_chain(local, motions, None, jitter, submaps)
            continue
        searched_parting = parting_pass  # the parting's pass settles the passes
        settled = abs(new_share - share) < config.min_share_change or searched_parting
        # share < 1: the parting's pass searches the odometry's chain (share 1), so it runs once.
        parting_pass = (settled and done < config.max_passes and share < 1.0
                        and drift.parted(everything, local, odometry_headings, rates, jitter, config))
        if (settled or done == config.max_passes) and not parting_pass:
            break
        # The rates did not settle, or the chains part after the last loop beyond what they allow:
        # nothing measured the filter there, and the odometry's chain is the other estimate.
        share = 1.0 if parting_pass else new_share
        chain, heading_rate = drift.weighed_chain(local, motions, None if parting_pass else rates, jitter, submaps)
    if searched_parting:
        # The last pass searched from the odometry's chain: the final graph weighs the headings by
        # the rates every pass's loops measure.
        share = new_share
        chain, heading_rate = drift.weighed_chain(local, motions, rates, jitter, submaps)
    return _Passes(closed, first_pass, everything, share, chain, heading_rate, rates, searched_parting, done, pairs,
                   searched)


def _unclosed(log, node_scans, filter_poses, sequential: Edges, t0: float) -> LoopClosure:
    """The closure of a path too short for any search: the filter's poses, no loop."""
    return LoopClosure(node_scans, filter_poses, filter_poses.copy(), trajectory_per_scan(log, node_scans, filter_poses),
                       sequential, Loops.empty()._replace(refused=np.zeros(0, str)), np.zeros(0, int), 0,
                       {"submaps": 0.0, "search": 0.0, "accept": 0.0, "appearance": 0.0, "optimize": 0.0,
                        "total": time.perf_counter() - t0}, filter_poses.copy(), 0.0, (np.nan, np.nan), 0)


class _Pass(NamedTuple):
    """One closure from one chain (local frame, host arrays)."""

    poses: np.ndarray
    loops: Loops
    sequential: Edges
    pairs: int
    seconds: dict
    searched: SearchRecord


def _close_pass(chain, heading_rate, motions, submaps: Submaps, ranges, scans, sensor, params,
                config: ClosureConfig, bar, jumps: bool = True) -> _Pass:
    """The search in time order from ``chain`` ((S, 3) local frame) and the optimisations
    (:func:`close_trajectory_loops`' one pass); ``jumps``: whether one jump of the chain's heading
    may explain loops the vote refused (:func:`jaxslam.graph.acceptance.one_jump_explains_refused_group`;
    only where the chain carries the submaps rigidly)."""
    points, valid, _ = scans  # the search's points (S, P, 2), (S, P) and the signatures (S, R, A)
    sequential = drift.sequential_edges(chain, motions, params.motion, heading_rate)
    seconds = {"search": 0.0, "accept": 0.0, "appearance": 0.0, "optimize": 0.0}
    travelled = path_distances(chain)
    likelihood = params.likelihood._replace(sigma=jnp.float32(config.sigma))
    found, record = Loops.empty(), SearchRecord.empty()
    estimate = chain.copy()  # the current estimate: optimised up to the last block, then the chain's steps
    pairs = 0
    # In time order, a block of queries at a time, as a robot would close them: the windows grow with
    # the path since the last loop, not since the start; the guesses come from the graph so far.
    for block_start in range(0, chain.shape[0], config.query_block):
        block_end = min(block_start + config.query_block, chain.shape[0])
        queries = np.arange(block_start, block_end)
        t_a = time.perf_counter()
        todo = queries[queries % config.query_stride == 0]
        searched, distance = search_block(todo, estimate, travelled, found, submaps, points, valid, config)
        pairs += int(searched.query.size)
        record = record.extend(SearchRecord.of(searched, submaps))
        t_b = time.perf_counter()
        new = acceptance.accept(submaps, searched, ranges, sensor, likelihood, estimate, found, config)
        t_c = time.perf_counter()
        new, widened_pairs = acceptance.widen_edge_peaks(new, searched, submaps, ranges, points, valid, sensor,
                                                         likelihood, estimate, found, config)
        pairs += widened_pairs
        if jumps:
            new = acceptance.one_jump_explains_refused_group(new, found, submaps, estimate, config)
        t_e = time.perf_counter()
        if config.places_per_query:
            new, alike_pairs = places.add_appearance_loops(new, searched, distance, todo, estimate, travelled, found,
                                                           submaps, scans, ranges, sensor, likelihood, config)
            pairs += alike_pairs
        found = found.extend(new)
        t_d = time.perf_counter()
        if np.any(new.refused == ""):
            estimate = _solve(found, submaps, sequential, chain, estimate, block_end, config)
        for stage, seconds_taken in (("search", t_b - t_a + t_e - t_c), ("accept", t_c - t_b),
                                     ("appearance", t_d - t_e), ("optimize", time.perf_counter() - t_d)):
            seconds[stage] += seconds_taken
        if bar is not None:
            bar.update(block_end - block_start)
    return _Pass(estimate, found, sequential, pairs, seconds, record)
