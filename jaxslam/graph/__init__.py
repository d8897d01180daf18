"""Loop closure behind the particle filter: a pose graph over the filter's processed scans,
loops found by a branch-and-bound search of scans against submaps, a sparse robust optimiser,
and the map drawn again (:func:`close_loops`, :func:`draw_map`); the returns a closure missed
(:func:`missed_returns`)."""

from jaxslam.graph.acceptance import Loops, SearchRecord
from jaxslam.graph.closure import ClosureConfig, LoopClosure, close_loops, close_trajectory_loops
from jaxslam.graph.missed import missed_returns
from jaxslam.graph.output import GRAPH_FILE, draw_map, load_graph, plot_graph, save_graph
from jaxslam.graph.pose_graph import Edges, PoseGraph, optimize

__all__ = ["GRAPH_FILE", "ClosureConfig", "Edges", "LoopClosure", "Loops", "PoseGraph", "SearchRecord", "close_loops",
           "close_trajectory_loops", "draw_map", "load_graph", "missed_returns", "optimize", "plot_graph", "save_graph"]
