"""The island filter (jaxslam.islands) at a fixed total N and island count over 1, 2 and 4 host
devices: time per update (compile excluded, best of a few runs) and memory per device (XLA's
memory analysis of the compiled program: arguments, outputs and temporaries of one device), with
a device's islands stepped one after the other (``lax.map``, the default) and as one ``vmap``
(``batch_islands=True``), timed alternately.

Host CPU devices share the machine's cores: on a 2-core machine, 2 or 4 devices are not a speed
test (they measure the cost of the sharding, not a gain); the memory per device is the point.

    python benchmarks/bench_islands.py --particles 64 --islands 4 --scans 120 --out docs/results/bench_islands.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=64, help="total N")
    parser.add_argument("--islands", type=int, default=4, help="I (a multiple of every device count)")
    parser.add_argument("--devices", default="1,2,4", help="device counts to run")
    parser.add_argument("--scans", type=int, default=120, help="scans of the simulated office")
    parser.add_argument("--proposal", default="smp")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--island-threshold", type=float, default=0.5, help="resample the islands below this x I")
    parser.add_argument("--out", help="write the rows to this JSON file")
    args = parser.parse_args(argv)
    counts = [int(d) for d in args.devices.split(",")]
    # The host device count is fixed when jax starts: set it first.
    os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={max(counts)}"
    import jax
    import numpy as np

    from jaxslam import islands, rbpf
    from jaxslam.config import RunSettings, SlamConfig, default_params
    from jaxslam.sim import office_scenario

    log = office_scenario(jax.random.key(3)).log.subset(np.arange(args.scans))
    config = SlamConfig(num_particles=args.particles, proposal=args.proposal, max_insert_range=10.0, beam_stride=2,
                        map_extent=128.0)
    prepared = rbpf.prepare(log, config, RunSettings(linear_update=0.3, angular_update=0.25))[0]
    steps = prepared.inputs.ranges.shape[0]
    rows, first_final = [], {}
    for num_devices in counts:
        # Both ways of stepping a device's islands (islands.step), timed alternately; with one
        # island per device they are the same program.
        variants = (False, True) if args.islands > num_devices else (False,)
        compiled, compile_s, times = {}, {}, {v: [] for v in variants}
        for batch in variants:
            fn = jax.jit(lambda key, d=num_devices, b=batch: islands.filter(
                key, prepared, default_params(), config, args.islands, d, args.island_threshold, batch_islands=b))
            start = time.perf_counter()
            compiled[batch] = fn.lower(jax.random.key(0)).compile()
            compile_s[batch] = time.perf_counter() - start
        outs = {}
        for r in range(args.repeats):
            for batch in variants:
                start = time.perf_counter()
                outs[batch] = jax.block_until_ready(compiled[batch](jax.random.key(r)))
                times[batch].append(time.perf_counter() - start)
        for batch in variants:
            out, memory = outs[batch], compiled[batch].memory_analysis()
            final = (np.asarray(out.state.islands.poses), float(out.marginal_loglik))
            first = first_final.setdefault(batch, final)
            row = {"devices": num_devices, "islands": args.islands, "particles": args.particles, "steps": steps,
                   "islands_stepped_by": "vmap" if batch else "lax.map",
                   "compile_s": round(compile_s[batch], 1), "ms_per_update": round(1e3 * min(times[batch]) / steps, 2),
                   "exchanges": int(np.asarray(out.info.exchanged).sum()),
                   "same_as_first_count": bool(np.array_equal(final[0], first[0]) and final[1] == first[1]),
                   "per_device_mb": {k: round(getattr(memory, k + "_size_in_bytes") / 2**20, 2)
                                     for k in ("argument", "output", "temp")} if memory is not None else None}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"args": vars(args), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
