"""``jaxslam demo``: map a simulated office (:func:`jaxslam.sim.office_scenario`) as ``jaxslam
map`` maps a log, and report the error against the simulator's ground truth."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax

from jaxslam.cli.common import _check_at_least, _check_filter_args, _check_out_folder, build_setup_from_args
from jaxslam.cli.map import _map_and_write
from jaxslam.sim import office_scenario


DEMO_DEFAULTS = {"proposal": "smp", "num_particles": 20, "linear_update": 0.25, "angular_update": 0.25,
                 "max_insert_range": 10.0, "beam_stride": 1}
"""``jaxslam demo``'s defaults: the simulated office is small, so scans are processed more often
than the library's 0.5 m / 0.25 rad, and every beam is used (its 10 m laser sees little along the
20 m corridor)."""
DEMO_PROPOSAL_NOTE = ", as map's; --proposal lp takes about twice as long on 2 CPU cores"
"""The demo's proposal is map's, the SMP (its ``--help``): measured on the project's 2-core machine
with other jobs running, the demo took 58 s with the SMP and 2 min 15 s with the LP (user CPU time
31 s against 50 s), without the compilation cache."""


def _cmd_demo(args: argparse.Namespace) -> int:
    _check_filter_args(args)
    _check_at_least("--scans", args.scans, 2, "scans along the simulated path")
    setup = build_setup_from_args(args, DEMO_DEFAULTS)
    _check_out_folder(args.out)
    if not args.no_progress:
        print(f"simulating the office ({args.scans} scans) ...", file=sys.stderr, flush=True)
    started = time.perf_counter()
    scenario = office_scenario(jax.random.key(args.seed), num_scans=args.scans)
    # The simulation stands in for reading a log: summary.json's timings.read.
    status = _map_and_write(scenario.log, setup, args, source="simulated office (jaxslam.sim.office_scenario)",
                            world=scenario.world, started=started, stages={"read": time.perf_counter() - started})
    if status == 0:
        summary = json.loads((Path(args.out) / "summary.json").read_text())
        print(_ground_truth_error_line(summary["ground_truth_error"]))
        closure = summary.get("closure")
        if closure is not None:
            print(f"loop closure: {closure['loops_kept']} loops kept of {closure['candidates']} candidates; closed path "
                  f"mean {closure['ground_truth_mean_m']:.3f} m (summary.json: closure; graph.npz)")
    return status


def _ground_truth_error_line(error: dict) -> str:
    """The demo's line on its ``summary.json`` ``ground_truth_error`` (position errors, m)."""
    return (f"ground truth error at the {error['scans']} processed scans: best path mean "
            f"{error['best_path_mean_m']:.3f} m, max {error['best_path_max_m']:.3f} m; odometry mean "
            f"{error['odometry_mean_m']:.3f} m, max {error['odometry_max_m']:.3f} m (summary.json: ground_truth_error)")
