"""A loop closure's outputs: the map drawn again at the optimised poses (:func:`draw_map`), the
graph as a NumPy archive (:func:`save_graph`, :func:`load_graph`, what ``jaxslam map`` writes as
``graph.npz``) and its figure (:func:`plot_graph`, what ``jaxslam diagnose`` draws)."""

from __future__ import annotations

import numpy as np

from jaxslam.graph import pose_graph
from jaxslam.graph.closure import LoopClosure
from jaxslam.grid import GridSpec
from jaxslam.laserlog import grid_to_world, to_local
from jaxslam.occupancy import map_from_scans


def draw_map(closure: LoopClosure, log, params, slam_config, frame_offset) -> tuple[np.ndarray, np.ndarray, GridSpec]:
    """The map drawn again at the optimised poses: every node's scan inserted into one dense grid
    with the filter's insertion. Returns ``(logodds (H, W) float16, hit_dist2 (H, W) uint8,
    grid)``, the grid in the world frame (as :meth:`jaxslam.slam.SlamResult.dense_map`)."""
    grid_map, grid = map_from_scans(to_local(closure.poses, frame_offset), log.ranges[closure.node_scans],
                                    log.sensor, params.insertion, slam_config.resolution,
                                    slam_config.max_insert_range, slam_config.field_radius)
    return np.asarray(grid_map.logodds), np.asarray(grid_map.hit_dist2), grid_to_world(grid, frame_offset)


GRAPH_FILE = "graph.npz"
"""The pose graph in a run's output folder (:func:`save_graph`)."""


def save_graph(path, closure: LoopClosure) -> None:
    """Write the graph of a loop closure as a NumPy archive: the nodes (``node_scans``,
    ``filter_poses``, ``poses``), the edges (``edge_first``, ``edge_second``,
    ``edge_measurement``, ``edge_information``, ``edge_kind``, and ``edge_chi2`` at the optimised
    poses), every candidate loop (``loop_*``: the fields of :class:`Loops`, ``loop_node`` its
    submap's first node), ``submap_first_node``, and the chain the last pass searched from
    (``chain_poses``, ``odometry_share``, ``drift_rates`` (filter, odometry) in rad^2 per step,
    ``passes``: :mod:`jaxslam.graph.drift`), ``jumps`` ((J, 4): node, rad, robust standard
    deviations, 1 where given to the filter; :mod:`jaxslam.graph.jumps`), and every pair the
    windowed search ran (``searched_*``: the fields of :class:`~jaxslam.graph.acceptance.SearchRecord`)."""
    edges = closure.edges
    loops = closure.loops
    arrays = {"node_scans": closure.node_scans, "filter_poses": closure.filter_poses, "poses": closure.poses,
              "submap_first_node": closure.submap_first_node,
              "edge_first": edges.first, "edge_second": edges.second, "edge_measurement": edges.measurement,
              "edge_information": edges.information, "edge_kind": edges.kind,
              "edge_chi2": pose_graph.chi2(closure.poses, edges),
              "loop_node": closure.submap_first_node[loops.submap] if loops.submap.size else np.zeros(0, int),
              "chain_poses": closure.chain_poses, "odometry_share": np.float64(closure.odometry_share),
              "drift_rates": np.asarray(closure.drift_rates, np.float64), "passes": np.int64(closure.passes),
              "jumps": np.asarray(closure.jumps, np.float64).reshape(-1, 4)}
    arrays.update({f"loop_{name}": np.asarray(value) for name, value in loops._asdict().items()})
    arrays.update({f"searched_{name}": np.asarray(value) for name, value in closure.searched._asdict().items()})
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def load_graph(path) -> dict[str, np.ndarray]:
    """The arrays :func:`save_graph` wrote."""
    with np.load(path, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def plot_graph(ax, graph: dict[str, np.ndarray], truth: np.ndarray | None = None,
               missed: list[dict] | None = None) -> None:
    """Draw a saved graph (:func:`load_graph`) on a map's axes (world frame): the filter's path,
    the optimised path, and every candidate loop as a line from its submap's first node to its
    query at the optimised poses: kept in green (purple where the search by appearance found it),
    refused in red (thin), each set labelled with its count; each jump of the filter's heading
    tried (:mod:`jaxslam.graph.jumps`) as a cross on the filter's path, black where given to the
    filter; and each return the closure missed (``missed``: :func:`jaxslam.graph.missed.missed_returns`)
    as a dashed orange line between the middles of its earlier and later nodes, numbered worst first."""
    poses, filt = graph["poses"], graph["filter_poses"]
    ax.plot(filt[:, 0], filt[:, 1], color="tab:red", lw=0.6, alpha=0.6, label="filter")
    share = float(graph.get("odometry_share", 0.0))
    if share > 0:
        chain = graph["chain_poses"]
        ax.plot(chain[:, 0], chain[:, 1], color="tab:orange", lw=0.6, ls=":",
                label=f"chain ({share:.2f} of the heading the odometry's)")
    ax.plot(poses[:, 0], poses[:, 1], color="tab:blue", lw=0.8, label="closed")
    if truth is not None:
        ax.plot(truth[:, 0], truth[:, 1], color="tab:green", lw=0.8, ls="--", label="ground truth")
    refused = graph["loop_refused"]
    # Archives written before the search by appearance have no ``loop_appearance``.
    appearance = graph.get("loop_appearance", np.zeros(refused.size, bool))
    from matplotlib.collections import LineCollection

    for mask, colour, lw, label in ((refused != "", "tab:red", 0.4, "loops refused"),
                                    ((refused == "") & ~appearance, "tab:green", 0.8, "loops kept"),
                                    ((refused == "") & appearance, "tab:purple", 0.8, "loops kept, found by appearance")):
        if not mask.any():
            continue
        a, b = poses[graph["loop_node"][mask]], poses[graph["loop_query"][mask]]
        segments = np.stack([a[:, :2], b[:, :2]], axis=1)
        ax.add_collection(LineCollection(segments, colors=colour, linewidths=lw, label=f"{label} ({int(mask.sum())})"))
    for node, jump, _, given in graph.get("jumps", np.zeros((0, 4))):  # older archives have none
        at = filt[int(node)]
        whose = "given to" if given else "kept by"
        ax.plot(at[0], at[1], "x", color="black" if given else "tab:gray", ms=8, mew=2,
                label=f"jump of {np.degrees(jump):.0f} deg at node {int(node)}, {whose} the filter")
    for rank, m in enumerate(missed or [], start=1):
        a, b = poses[int(np.mean(m["earlier_nodes"]))], poses[int(np.mean(m["later_nodes"]))]
        ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:orange", lw=1.2, ls="--",
                label=f"returns missed ({len(missed)})" if rank == 1 else None)
        ax.annotate(str(rank), b[:2], color="tab:orange", fontsize=8)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=7)
