"""The loop closure (jaxslam.graph) against a filter made to fail: a finished run's trajectory on
a real log, its heading turned by a fault, then closed, and judged against the log's relations.

Faults (``KIND:WHERE:DEGREES[:NODES]``, ``WHERE`` a fraction of the processed scans):

- ``jump:0.5:30``: every node from the middle on turned 30 degrees about the node before it,
  rigidly (a filter whose map parted into two halves at one step; its submaps stay whole, but
  for the one across the jump);
- ``bend:0.3:30:300``: 30 degrees spread evenly over the 300 steps from 30 % of the path (a
  heading that drifted; the submaps bend a little with it).

The odometry stays the log's. A run's first row is the trajectory as the filter left it. The
closure is the library's default (``ClosureConfig()``), run from the turned trajectory as
``close_trajectory_loops`` runs from any path; the refinement is not run. Relation error: mean
over the log's relations (Kümmerle et al. 2009), of the turned input and of the closed result.

    jaxslam map DATA/aces.sort.bag --proposal smp --seed 0 --out RUN
    python experiments/closure_stress.py --log DATA/aces.sort.bag --relations DATA/aces.relations \
        --trajectory RUN/trajectory_filter.txt --out OUT/closure_stress_aces.json

``--align-clock`` finds the relations' timestamps among the log's scans where they were written on
another clock (MIT Killian's bag; as ``jaxslam eval --log``). The nodes are the scans the default
update rule processes. Faults are stored as they finish; a rerun into the same file skips them
(experiments/_runs.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from _runs import ResultStore, closure_settings  # experiments/_runs.py: the shared resume helper

FAULTS = ("jump:0.25:10", "jump:0.25:30", "jump:0.5:10", "jump:0.5:30", "jump:0.75:30", "bend:0.3:30:300",
          "bend:0.2:60:600")


def parse_fault(text: str) -> tuple[str, float, float, int]:
    """``(kind, where, radians, nodes)`` of a fault's text (``jump:0.5:30``, ``bend:0.3:30:300``);
    ValueError naming the problem otherwise."""
    parts = text.split(":")
    kind = parts[0]
    if kind not in ("jump", "bend") or len(parts) != (3 if kind == "jump" else 4):
        raise ValueError(f"fault {text!r}: expected jump:WHERE:DEGREES or bend:WHERE:DEGREES:NODES")
    try:
        where, degrees, nodes = float(parts[1]), float(parts[2]), int(parts[3]) if kind == "bend" else 1
    except ValueError:
        raise ValueError(f"fault {text!r}: WHERE and DEGREES must be numbers, NODES a whole number") from None
    if not (0 < where < 1 and np.isfinite(degrees) and nodes >= 1):
        raise ValueError(f"fault {text!r}: WHERE must lie in (0, 1), DEGREES be finite, NODES at least 1")
    return kind, where, np.radians(degrees), nodes


def turned(poses: np.ndarray, fault: str) -> np.ndarray:
    """(S, 3) ``poses`` (m, m, rad) with ``fault``'s turn added to the heading change of the steps
    it covers: every later step's translation turns with it (:func:`jaxslam.geometry.chain_np`)."""
    from jaxslam.geometry import between_np, chain_np

    _, where, radians, nodes = parse_fault(fault)
    steps = between_np(poses[:-1], poses[1:])
    start = int(where * poses.shape[0])
    if start + nodes > steps.shape[0]:
        raise ValueError(f"fault {fault!r}: its {nodes} steps from node {start} run past the path's {poses.shape[0]} nodes")
    steps[start:start + nodes, 2] += radians / nodes
    return chain_np(poses[0], steps)


def run_fault(log, relations, selection, filter_poses, fault: str, params, slam_config, closure=None) -> dict:
    """One fault's record: the turned input's and the closed result's relation error (m), the
    loops kept (and how many the search by appearance found), the pairs searched, the passes, the
    jumps of the filter's heading tried (``LoopClosure.jumps``) and the closure's wall;
    ``closure``: ClosureConfig fields set (``--set``), the rest the defaults."""
    import dataclasses

    from jaxslam.graph import ClosureConfig, close_trajectory_loops
    from jaxslam.laserlog import local_frame_offset, trajectory_per_scan
    from jaxslam.metrics import relation_error

    poses = filter_poses if fault == "none" else turned(filter_poses, fault)
    t0 = time.perf_counter()
    closure = close_trajectory_loops(log, selection.indices, poses, selection.motions, params, slam_config,
                                     local_frame_offset(log), dataclasses.replace(ClosureConfig(), **(closure or {})))
    wall = time.perf_counter() - t0
    kept = closure.loops.refused == ""
    return {"fault": fault,
            "input_m": relation_error(log.timestamps, trajectory_per_scan(log, selection.indices, poses),
                                      relations).trans_mean,
            "closed_m": relation_error(log.timestamps, closure.trajectory, relations).trans_mean,
            "kept": int(kept.sum()), "kept_by_appearance": int((kept & closure.loops.appearance).sum()),
            "pairs": int(closure.pairs_searched),
            "passes": int(closure.passes), "odometry_share": float(closure.odometry_share),
            "jumps_tried": closure.summary()["jumps_tried"], "closure_s": wall}


def table(runs: list[dict]) -> str:
    lines = ["| fault | input [m] | closed [m] | loops kept (by appearance) | passes | jumps tried (given to the filter) |",
             "|---|---|---|---|---|---|"]
    for r in runs:
        tried = ", ".join(f"node {j['node']} {j['deg']:.1f} deg ({'yes' if j['given_to_filter'] else 'no'})"
                          for j in r.get("jumps_tried", []))
        lines.append(f"| {r['fault']} | {r['input_m']:.3f} | {r['closed_m']:.4f} | {r['kept']} ({r['kept_by_appearance']}) "
                     f"| {r['passes']} | {tried} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--log", required=True, help="the log the run mapped")
    parser.add_argument("--relations", required=True, help="the log's ground-truth relations")
    parser.add_argument("--trajectory", required=True, help="the run's trajectory_filter.txt (a pose for every scan)")
    parser.add_argument("--out", required=True, help="results JSON (faults already in it are skipped)")
    parser.add_argument("--align-clock", action="store_true",
                        help="the relations were written on another clock than the log's (MIT Killian's bag): "
                             "find their timestamps among the log's scans, as jaxslam eval --log does")
    parser.add_argument("--faults", nargs="+", default=list(FAULTS), metavar="FAULT",
                        help=f"jump:WHERE:DEGREES or bend:WHERE:DEGREES:NODES (default {' '.join(FAULTS)})")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="a ClosureConfig field for every closure (e.g. window_min_xy=7), recorded in the settings")
    args = parser.parse_args(argv)
    try:
        closure = closure_settings(args.set)
    except ValueError as err:
        parser.error(str(err))
    for fault in args.faults:  # every fault checked before any work
        try:
            parse_fault(fault)
        except ValueError as err:
            parser.error(str(err))
    for name in ("log", "relations", "trajectory"):
        if not Path(getattr(args, name)).exists():
            parser.error(f"--{name} {getattr(args, name)}: no such file or folder")
    from tqdm import tqdm

    from jaxslam.config import build_setup
    from jaxslam.io import read_log, read_relations, read_trajectory
    from jaxslam.io.relation_clock import align_relations_clock
    from jaxslam.laserlog import select_updates
    from jaxslam.metrics import lookup_poses

    log = read_log(args.log)
    relations = read_relations(args.relations)
    if args.align_clock:
        relations = align_relations_clock(relations, log.timestamps, log.odometry, ranges=log.ranges,
                                          sensor=log.sensor).relations
    slam_config, settings, params = build_setup({})
    selection = select_updates(log, settings.linear_update, settings.angular_update)
    filter_poses = lookup_poses(*read_trajectory(args.trajectory), log.timestamps[selection.indices])
    for fault in args.faults:  # every fault fits this path, before any closure runs
        try:
            turned(filter_poses, fault)
        except ValueError as err:
            parser.error(str(err))
    trajectory = Path(args.trajectory).resolve()  # the run's folder and file name: no path outside it recorded
    store = ResultStore(args.out, {"log": Path(args.log).name, "align_clock": args.align_clock,
                                   "trajectory": f"{trajectory.parent.name}/{trajectory.name}", "set": closure},
                        key=lambda r: r["fault"])
    for fault in tqdm(["none", *args.faults], desc="faults", unit="closure"):
        if not store.done(fault):
            store.add(run_fault(log, relations, selection, filter_poses, fault, params, slam_config, closure))
    text = table(store.runs)
    store.write(table=text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
