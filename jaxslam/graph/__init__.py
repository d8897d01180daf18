"""Loop closure behind the particle filter: a pose graph over the filter's processed scans,
loops found by a branch-and-bound search of scans against submaps, a sparse robust optimiser,
and the map drawn again (:func:`close_loops`, :func:`draw_map`)."""

from jaxslam.graph.acceptance import Loops
from jaxslam.graph.closure import ClosureConfig, LoopClosure, close_loops, close_trajectory_loops
from jaxslam.graph.output import GRAPH_FILE, draw_map, load_graph, plot_graph, save_graph
from jaxslam.graph.pose_graph import Edges, PoseGraph, optimize

__all__ = ["GRAPH_FILE", "ClosureConfig", "Edges", "LoopClosure", "Loops", "PoseGraph", "close_loops",
           "close_trajectory_loops", "draw_map", "load_graph", "optimize", "plot_graph", "save_graph"]
