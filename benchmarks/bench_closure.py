"""What the loop closure costs against the filter it follows, in one process, one after the other.

For each log: ``slam.run`` (the SMP at the library's defaults, seed 0, ``--max-scans`` scans),
then the back end ``jaxslam map`` runs after it twice (the second timed, compiled):
:func:`jaxslam.graph.close_loops`, the map drawn again at the closed poses, and the refinement
on it (:func:`jaxslam.refine.refine_in_rounds`). Prints and writes (``--out``, JSON) the
filter's wall, each stage's wall (the closure's by its own stages), their ratios to the
filter's, and the loop search's pairs per second with the device JAX ran on; on a machine with a GPU, run it there and on the
CPU (``JAX_PLATFORMS=cpu``) for the GPU's ratio. Ratios are meaningful within one invocation
only (the machine is shared).

    python benchmarks/bench_closure.py --logs intel fr-clinic --out OUT/bench_closure.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

LOGS = {"intel": "intel.sort.bag", "aces": "aces.sort.bag", "mit-csail": "mit-csail.clf", "fr-clinic": "fr-clinic.bag"}


def bench(path: Path, max_scans: int | None) -> dict:
    import jax
    import numpy as np

    from jaxslam import slam
    from jaxslam.config import build_setup
    from jaxslam.graph import ClosureConfig, close_loops
    from jaxslam.io import read_log
    from jaxslam.laserlog import grid_to_world
    from jaxslam.refine import refine_in_rounds, trusts_odometry

    log = read_log(path)
    if max_scans:
        log = log.subset(np.arange(min(max_scans, log.num_scans)))
    config, settings, params = build_setup({"proposal": "smp"})
    t0 = time.perf_counter()
    result = slam.run(jax.random.key(0), log, config, params, settings, progress=False)
    filter_s = time.perf_counter() - t0

    def back_end():
        t0 = time.perf_counter()
        closure = close_loops(log, result, params, ClosureConfig())
        t1 = time.perf_counter()
        closed = result._replace(closure=closure)
        _, field, grid = closed.closed_map(log, params)
        t2 = time.perf_counter()
        refined = refine_in_rounds(grid_to_world(grid, -result.frame_offset), field,
                                   result.to_local(closure.trajectory), log.ranges, log.sensor, params,
                                   result.config, result.selection.indices, odometry=result.to_local(log.odometry),
                                   trust_odometry=trusts_odometry(closure))
        np.asarray(refined.poses)
        return closure, t1 - t0, t2 - t1, time.perf_counter() - t2

    back_end()  # compiles
    closure, closure_s, redraw_s, refine_s = back_end()
    search_s = closure.timings["search"] + closure.timings["appearance"]  # every pair searched
    back_s = closure_s + redraw_s + refine_s
    return {"log": path.name, "scans": int(log.num_scans), "nodes": int(closure.node_scans.size),
            "filter_s": filter_s, "closure_s": closure_s, "ratio": closure_s / filter_s,
            "redraw_s": redraw_s, "refine_s": refine_s, "back_end_s": back_s, "back_end_ratio": back_s / filter_s,
            "stages_s": closure.timings, "pairs": closure.pairs_searched,
            "pairs_per_s": closure.pairs_searched / search_s if search_s > 0 else None,
            "loops_kept": closure.num_loops, "device": str(jax.devices()[0])}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--logs", nargs="+", choices=list(LOGS), default=["intel"])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--max-scans", type=int, default=None, help="only the first N scans of each log")
    parser.add_argument("--out", help="JSON file for the figures")
    args = parser.parse_args(argv)
    missing = [name for name in args.logs if not (Path(args.data) / LOGS[name]).is_file()]
    if missing:
        parser.error(f"no {', '.join(LOGS[m] for m in missing)} in {args.data} (--data)")
    rows = []
    for name in args.logs:
        rows.append(bench(Path(args.data) / LOGS[name], args.max_scans))
        print(json.dumps(rows[-1]), flush=True)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
