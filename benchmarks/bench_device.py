"""SLAM on one device (a GPU, or the CPU) under a time budget: ms per update, projected wall.

Runs the library's defaults (``jaxslam map``'s SMP or LP, the log's own update rule) on a log
for each ``PROPOSAL:N`` given, one after the other in this process, on the platform JAX picks
(``JAX_PLATFORMS=cpu`` forces the CPU). Each run stops at the first chunk boundary after
``--budget-s`` seconds (once at least two chunks after the compiling one have run), so a
device check fits a short lease; a run that finishes reports its real wall and relation error.
For every run the JSON (``--out``, rewritten after each run) holds:

* ``first_chunk_s``: the first chunk's wall (compilation included), ``chunk_s``: every chunk's;
* ``ms_per_update``: the steady rate, the chunks after the first (pool growths included);
* ``projected_wall_s``: preparation + first chunk + the steady rate over the remaining steps,
  and ``projected_real_time_factor``: the log's duration over it (``wall_s`` and
  ``real_time_factor`` when the run finished);
* ``peak_device_mb``: the device's peak allocation (GPU) or the process's peak resident memory.

    JAX_PLATFORMS=cpu python benchmarks/bench_device.py --log LOG --runs smp:30 lp:30 --out cpu.json
    python benchmarks/bench_device.py --log LOG --relations REL --runs smp:30 lp:30 smp:1000 --out gpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time
import traceback
from pathlib import Path


def parse_run(text: str) -> tuple[str, int]:
    """``'smp:30'`` -> ``('smp', 30)``; a clear error for anything else."""
    proposal, _, count = text.partition(":")
    if proposal not in ("op", "smp", "lp", "lp-odometry") or not count.isdigit() or int(count) < 1:
        raise argparse.ArgumentTypeError(f"--runs: expected PROPOSAL:N (PROPOSAL op, smp, lp or lp-odometry; N >= 1), "
                                         f"got {text!r}")
    return proposal, int(count)


def _peak_mb(device) -> float:
    stats = device.memory_stats() if device.platform != "cpu" else None
    if stats and "peak_bytes_in_use" in stats:
        return stats["peak_bytes_in_use"] / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def one_run(log, relations, proposal: str, num_particles: int, seed: int, budget_s: float, chunk_size: int) -> dict:
    """One budgeted run of the library's defaults; the figures listed in the module's doc."""
    import jax
    import numpy as np

    from jaxslam.config import build_setup
    from jaxslam.metrics import relation_error
    from jaxslam.slam import RunInterrupted, run

    values = {"proposal": proposal, "num_particles": num_particles}
    if proposal == "lp-odometry":  # the paper's LP, as experiments/datasets.py names it
        values = {"proposal": "lp", "num_particles": num_particles, "lookahead_initial": "odometry"}
    config, settings, params = build_setup(values)
    marks: list[float] = []
    last = {}
    t0 = time.perf_counter()

    def on_chunk(progress) -> bool:
        jax.block_until_ready(progress.state)
        marks.append(time.perf_counter() - t0)
        last.update(steps_done=progress.steps_done, num_steps=progress.num_steps,
                    pool=progress.state.maps.pool_size._asdict())
        return marks[-1] > budget_s and len(marks) >= 3

    finished, failure = True, None
    try:
        result = run(jax.random.key(seed), log, config, params, settings, chunk_size=chunk_size, progress=False,
                     on_chunk=on_chunk)
    except RunInterrupted:
        finished = False
    except Exception as err:  # e.g. the maps outgrew the pool: keep the chunks' figures
        if not marks:
            raise
        finished, failure = False, f"{type(err).__name__}: {err}"[:2000]
    wall = time.perf_counter() - t0
    chunk_s = np.diff([0.0] + marks)
    num_steps, done = last["num_steps"], last["steps_done"]
    steady = (marks[-1] - marks[0]) / max(done - chunk_size, 1) if len(marks) > 1 else float("nan")
    duration = float(log.timestamps[-1] - log.timestamps[0])
    projected = marks[0] + steady * max(num_steps - chunk_size, 0)
    row = {"proposal": proposal, "num_particles": num_particles, "seed": seed, "chunk_size": chunk_size,
           "finished": finished, "steps_done": done, "num_steps": num_steps, "first_chunk_s": marks[0],
           "chunk_s": [round(float(c), 4) for c in chunk_s], "ms_per_update": 1000 * steady,
           "updates_per_s": 1.0 / steady, "projected_wall_s": projected,
           "projected_real_time_factor": duration / projected, "log_duration_s": duration,
           "elapsed_s": wall, "pool": last["pool"], "peak_device_mb": _peak_mb(jax.devices()[0]), "error": failure}
    if finished:
        row.update(wall_s=wall, real_time_factor=duration / wall, timings=result.timings)
        if relations is not None:
            end = log.timestamps[-1]  # with --max-scans, the relations inside the part mapped
            inside = (relations.t1 <= end) & (relations.t2 <= end)
            if inside.any():
                part = type(relations)(*(field[inside] for field in relations))
                row["relation_error_m"] = float(relation_error(log.timestamps, result.trajectory, part).trans_mean)
                row["relations"] = int(inside.sum())
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", type=Path, required=True, help="the log (a bag, a CARMEN file, or a pickled LaserLog)")
    ap.add_argument("--relations", type=Path, help="its ground-truth relations (relation error of finished runs)")
    ap.add_argument("--runs", type=parse_run, nargs="+", required=True, metavar="PROPOSAL:N")
    ap.add_argument("--budget-s", type=float, nargs="+", default=[120.0],
                    help="seconds per run (one for all, or one per run)")
    ap.add_argument("--chunk-size", type=int, default=32, help="steps per compiled call (runs with N >= 1000 use 8)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-scans", type=int, help="use the log's first scans only")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if len(args.budget_s) not in (1, len(args.runs)):
        ap.error(f"--budget-s: give one value or one per run ({len(args.runs)}), got {len(args.budget_s)}")
    budgets = args.budget_s if len(args.budget_s) == len(args.runs) else args.budget_s * len(args.runs)
    for path in (args.log, args.relations):
        if path is not None and not path.exists():
            ap.error(f"no such file: {path}")

    import jax

    from jaxslam.io import read_log, read_relations

    if args.log.suffix == ".pkl":  # a LaserLog pickled where the log's reader is installed (a bag without rosbags)
        import pickle

        log = pickle.loads(args.log.read_bytes())
    else:
        log = read_log(args.log)
    if args.max_scans:
        import numpy as np

        log = log.subset(np.arange(min(args.max_scans, log.num_scans)))
    relations = read_relations(args.relations) if args.relations else None
    device = jax.devices()[0]
    out = {"device": str(device.device_kind), "platform": device.platform, "jax": jax.__version__,
           "cpus": os.cpu_count(), "affinity": len(os.sched_getaffinity(0)), "host": platform.platform(),
           "log": args.log.name, "runs": []}
    for (proposal, count), budget in zip(args.runs, budgets):
        chunk = args.chunk_size if count < 1000 else min(args.chunk_size, 8)
        try:
            row = one_run(log, relations, proposal, count, args.seed, budget, chunk)
        except Exception as err:  # one failed configuration must not lose the others' figures
            traceback.print_exc()
            row = {"proposal": proposal, "num_particles": count, "error": f"{type(err).__name__}: {err}"[:2000]}
        out["runs"].append(row)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=2, default=str) + "\n")
        brief = {k: row.get(k) for k in ("proposal", "num_particles", "finished", "steps_done", "first_chunk_s",
                                         "ms_per_update", "projected_wall_s", "relation_error_m", "error")}
        print(f"[{out['platform']}] {json.dumps(brief, default=str)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
