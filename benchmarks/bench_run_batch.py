"""R seeds of one log as one batch over D devices (``slam.run_batch``) against a loop of the same
runs (``slam.run``), in one process: the batch as each device takes its runs one after the
other (the default) and vmapped (``vectorize=True``); checks that each run of the default batch
is its run alone, bit for bit (and says whether the vmapped ones are).

The device count must be set before jax is imported: on a CPU the script sets
``XLA_FLAGS=--xla_force_host_platform_device_count=D`` itself. D host devices on a machine's
shared cores are no speed test (the loop's runs already use the cores); the figure says what
the batching costs or saves there, and a GPU or a machine per device is where it pays.

    python benchmarks/bench_run_batch.py --devices 2 --seeds 4 --out results/bench_run_batch.json
    python benchmarks/bench_run_batch.py --log ../shared/data/intel.sort.bag --max-scans 2000 --devices 2
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--devices", type=int, default=2, help="devices of the batch (host devices on a CPU)")
    parser.add_argument("--seeds", type=int, default=4, help="runs R (seeds 0 .. R-1)")
    parser.add_argument("--log", default=None, help="a log file (default: the simulated office, --max-scans scans)")
    parser.add_argument("--max-scans", type=int, default=300)
    parser.add_argument("--proposal", default="smp", help="a registered proposal (jaxslam.proposals.PROPOSALS)")
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--out", default="results/bench_run_batch.json")
    args = parser.parse_args(argv)
    if "jax" not in sys.modules:  # host devices: before jax starts
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                                   + f" --xla_force_host_platform_device_count={args.devices}").strip()
    import jax
    import numpy as np

    from jaxslam import slam
    from jaxslam.config import build_setup

    if args.log is None:
        from jaxslam.sim import office_scenario

        log, source = office_scenario(jax.random.key(3)).log, "simulated office (key 3)"
    else:
        from jaxslam.io import read_log

        log, source = read_log(args.log), args.log
    log = log.subset(np.arange(min(args.max_scans, log.num_scans)))
    values = {"proposal": args.proposal, "num_particles": args.particles}
    if args.log is None:
        values["map_extent"] = 128.0
    config, settings, params = build_setup(values)
    seeds = list(range(args.seeds))

    t0 = time.perf_counter()
    alone = [slam.run(jax.random.key(s), log, config, params, settings, progress=False) for s in seeds]
    loop_s = time.perf_counter() - t0
    report = {
        "log": source, "scans": int(log.num_scans), "steps": int(alone[0].selection.indices.size - 1),
        "proposal": args.proposal, "particles": args.particles, "runs": len(seeds), "devices": args.devices,
        "platform": jax.devices()[0].platform, "cpu_count": os.cpu_count(),
        "loop_s": loop_s, "loop_first_chunk_s": alone[0].timings["compile"],
    }
    same = True
    for name, vectorize in (("batch", False), ("batch_vmap", True)):
        t0 = time.perf_counter()
        batched = slam.run_batch(jax.numpy.stack([jax.random.key(s) for s in seeds]), log, config, params, settings,
                                 devices=args.devices, progress=False, vectorize=vectorize)
        seconds = time.perf_counter() - t0
        first = batched[0].timings["compile"]
        # bit for bit: the particles' poses and weights and the best path of every run
        equal = [bool(np.array_equal(a.best_path, b.best_path)
                      and np.array_equal(np.asarray(a.state.poses), np.asarray(b.state.poses))
                      and np.array_equal(np.asarray(a.state.log_weights), np.asarray(b.state.log_weights)))
                 for a, b in zip(alone, batched)]
        same &= all(equal) or vectorize  # vmapped runs are the runs alone to float rounding only
        loop_after_first = loop_s - report["loop_first_chunk_s"]
        report.update({f"{name}_s": seconds, f"{name}_first_chunk_s": first, f"{name}_over_loop": seconds / loop_s,
                       f"{name}_over_loop_after_first_chunk": (seconds - first) / loop_after_first,
                       f"{name}_runs_equal_bit_for_bit": equal})
    for key, value in report.items():
        print(f"{key:36s} {value:.3f}" if isinstance(value, float) else f"{key:36s} {value}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
