"""Simulation: segment worlds, exact ray casting, noisy odometry, scenarios."""

from jaxslam.sim.paths import circle_path, concat_paths, passage_indices, waypoint_path, waypoint_path_length
from jaxslam.segment_map import raycast
from jaxslam.sim.box_world import box_world, box_world_path, box_world_scenario
from jaxslam.sim.scenarios import (
    Scenario,
    hall_scenario,
    hall_waypoints,
    hall_world,
    office_scenario,
    office_waypoints,
    office_world,
    symmetric_junction_scenario,
    symmetric_junction_world,
)
from jaxslam.sim.simulate import noisy_odometry, simulate_log, simulate_scan, simulate_scans
from jaxslam.sim.world import (
    SegmentWorld,
    box_segments,
    concat_worlds,
    make_world,
    path_crossings,
    point_segment_distance,
    polyline_segments,
    wall_segments,
)

__all__ = [
    "Scenario",
    "SegmentWorld",
    "box_segments",
    "box_world",
    "box_world_path",
    "box_world_scenario",
    "circle_path",
    "concat_paths",
    "concat_worlds",
    "hall_scenario",
    "hall_waypoints",
    "hall_world",
    "make_world",
    "noisy_odometry",
    "office_scenario",
    "office_waypoints",
    "office_world",
    "passage_indices",
    "path_crossings",
    "point_segment_distance",
    "polyline_segments",
    "raycast",
    "simulate_log",
    "simulate_scan",
    "simulate_scans",
    "symmetric_junction_scenario",
    "symmetric_junction_world",
    "waypoint_path",
    "waypoint_path_length",
    "wall_segments",
]
