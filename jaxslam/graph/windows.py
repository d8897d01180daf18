"""Which scan-submap pairs the loop closure searches, and how wide: the path travelled along the
chain (:func:`path_distances`), the distance over the graph through the kept loops that a window
grows with (:func:`graph_distances`), the pairs with their windows (:func:`candidate_pairs`), and
a block's search of them (:func:`search_block`, :func:`search_from`)."""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from jaxslam.geometry import between_np
from jaxslam.graph.acceptance import Loops, Searched
from jaxslam.graph.loop_search import search_pairs
from jaxslam.graph.submaps import Submaps


def path_distances(poses: np.ndarray) -> np.ndarray:
    """(S,) metres travelled along the nodes from the first."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])


def graph_distances(travelled: np.ndarray, queries: np.ndarray, submap_last: np.ndarray, loop_query: np.ndarray,
                    loop_node: np.ndarray) -> np.ndarray:
    """(Q, M) how far each query is from each submap along the graph: the shortest path over the
    chain (each step its length) and the kept loops (each of length 0, query to the loop's submap
    node), through any number of loops. The drift a window must allow grows with it.

    A path through one loop is not enough where a return reaches old submaps through several:
    FR-clinic's return to its start reaches its first submaps through the loop at node 2,166 and
    then those of nodes 765-849, 105 m of graph (a 4 m window) against 560 m through one loop (an
    18 m window). On FR-clinic seeds 0-2 the closed errors came out the same either way
    (docs/design.md, "Loop closure behind the filter"); the window is what the drift allows.

    Args:
        travelled: (S,) :func:`path_distances` along the chain (m).
        queries: (Q,) int query nodes.
        submap_last: (M,) int each submap's last node.
        loop_query: (L,) int kept loops' query nodes.
        loop_node: (L,) int the node each loop reaches (its submap's last node).
    """
    num = travelled.size
    steps = np.arange(num - 1)
    # A loop's length is 0, stored as the smallest positive float: a sparse matrix may drop an
    # explicit 0 (eliminate_zeros), and with it the edge.
    tiny = np.finfo(np.float64).tiny
    graph = scipy.sparse.coo_matrix(
        (np.concatenate([np.maximum(np.diff(travelled), tiny), np.full(loop_query.size, tiny)]),
         (np.concatenate([steps, loop_query]), np.concatenate([steps + 1, loop_node]))), shape=(num, num)).tocsr()
    return scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=queries)[:, submap_last]


def candidate_pairs(poses: np.ndarray, submaps: Submaps, config, queries: np.ndarray,
                    travelled: np.ndarray, distance: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The (query, submap) pairs to search and their windows: each query against the
    ``submaps_per_query`` nearest submaps that end at least ``min_separation`` metres of path
    before it and have a node within its window plus ``max_node_distance`` of it.

    Args:
        poses: (S, 3) the current node estimates.
        submaps: the submaps.
        config: the closure's settings (:class:`jaxslam.graph.closure.ClosureConfig`).
        queries: (Q,) nodes to search from.
        travelled: (S,) :func:`path_distances`.
        distance: (Q, M) :func:`graph_distances`: what the windows grow with.

    Returns:
        ``(query (P,), submap (P,), half_xy (P,) m, half_theta (P,) rad)``.
    """
    last = submaps.last_node
    since = travelled[queries][:, None] - travelled[last][None]
    eligible = (queries[:, None] > last[None]) & (since >= config.min_separation)
    half_xy = np.minimum(config.window_max_xy, config.window_min_xy + config.window_xy_per_metre * distance)
    half_theta = np.minimum(config.window_max_theta, config.window_min_theta + config.window_theta_per_metre * distance)
    near = np.full(eligible.shape, np.inf)
    for j in range(last.size):  # M is small: a loop over submaps
        nodes = poses[submaps.first_node[j]:last[j] + 1, :2]
        near[:, j] = np.min(np.linalg.norm(poses[queries, None, :2] - nodes[None], axis=-1), axis=1)
    ok = eligible & (near <= half_xy + config.max_node_distance)
    order = np.argsort(np.where(ok, near, np.inf), axis=1, kind="stable")
    position = np.empty_like(order)
    np.put_along_axis(position, order, np.arange(order.shape[1])[None], axis=1)  # each submap's place by distance
    allowed = np.ceil(config.submaps_per_query * np.maximum(1.0, (half_xy / config.near_window_xy) ** 2))
    q_idx, j_idx = np.nonzero(ok & (position < allowed))
    by_distance = np.lexsort((position[q_idx, j_idx], q_idx))  # per query, nearest first
    q_idx, j_idx = q_idx[by_distance], j_idx[by_distance]
    return queries[q_idx], j_idx, half_xy[q_idx, j_idx], half_theta[q_idx, j_idx]


def search_block(queries: np.ndarray, estimate: np.ndarray, travelled: np.ndarray, found: Loops, submaps: Submaps,
                 points: np.ndarray, valid: np.ndarray, config) -> tuple[Searched, np.ndarray]:
    """Search a block's queries against their candidate submaps from the current estimate, in
    windows grown over the graph's distance (through the loops kept so far).

    Returns:
        ``(searched, distance)``: the :class:`~jaxslam.graph.acceptance.Searched` pairs, and the
        (Q, M) :func:`graph_distances` of the queries.
    """
    kept = found.refused == ""
    distance = graph_distances(travelled, queries, submaps.last_node, found.query[kept],
                               submaps.last_node[found.submap[kept]])
    query, submap, half_xy, half_theta = candidate_pairs(estimate, submaps, config, queries, travelled, distance)
    rel = between_np(estimate[submaps.first_node][submap], estimate[query])
    return search_from(submaps, query, submap, rel, half_xy, half_theta, points, valid, config), distance


def search_from(submaps: Submaps, query: np.ndarray, submap: np.ndarray, rel: np.ndarray, half_xy: np.ndarray,
                half_theta: np.ndarray, points: np.ndarray, valid: np.ndarray, config) -> Searched:
    """The pairs (P,) searched round ``rel`` (P, 3), the query's pose in its submap's first
    node's frame, in windows ``half_xy`` (P,) m and ``half_theta`` (P,) rad."""
    guess = np.concatenate([rel[:, :2] - submaps.corner[submap], rel[:, 2:]], axis=-1)
    resolution = submaps.grid.resolution
    result = search_pairs(submaps, submap, points[query], valid[query], guess,
                          np.ceil(half_xy / resolution).astype(np.int32), half_theta, config.window(resolution),
                          batch=config.batch)
    return Searched(query, submap, guess, half_xy, half_theta, result)
