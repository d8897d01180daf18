"""What a gradient costs: ``rbpf.filter``'s log-likelihood and its gradient in every parameter,
against the forward pass alone, on the same run.

The simulated office of ``jaxslam demo`` (its settings), one proposal per call; both functions are
compiled first, then timed alternately (``--repeats`` times each, the median kept), so the ratio
comes from one session on one machine. Each row is merged into ``--out`` as it is measured
(keyed by proposal and scans), so calls with other settings add rows.

Reverse mode keeps every step's residuals: memory grows with the steps. Each row records the
compiled gradient's temporary buffers (XLA's ``memory_analysis``: the peak it plans, known before
anything runs). The LP (L = 100, k = 5, N = 20) planned 24.8 GB over the 116 steps of 200 scans and
ran out of the machine's 23 GB until its horizon ran without gradient (issue 35: p_J enters the
increment without gradient, so nothing of the horizon reaches it); it now plans 1.4 GB.

``--memory`` measures memory alone, one proposal per process (run it alone on the machine): the
gradient is compiled, its planned temporary bytes read, run once, and the process's peak
resident memory (``ru_maxrss``) recorded, with no forward pass and no timing:

    python benchmarks/bench_gradients.py --proposal op smp --out docs/results/bench_gradients.json
    python benchmarks/bench_gradients.py --proposal lp --out docs/results/bench_gradients.json
    /usr/bin/time -v python benchmarks/bench_gradients.py --proposal lp --memory --out docs/results/bench_gradients.json
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--proposal", nargs="+", default=["op", "smp", "lp"],
                        help="registered proposals (jaxslam.proposals.PROPOSALS)")
    parser.add_argument("--particles", type=int, default=20)
    parser.add_argument("--scans", type=int, default=200, help="scans of the simulated office")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="results/bench_gradients.json")
    parser.add_argument("--memory", action="store_true",
                        help="compile and run the gradient once, record its planned temporary bytes and the "
                             "process's peak resident memory; no timing (one proposal)")
    args = parser.parse_args(argv)
    if args.memory and len(args.proposal) != 1:
        parser.error("--memory measures one proposal per process (the peak resident memory is the process's)")

    import dataclasses

    import jax
    import numpy as np

    from jaxslam import rbpf
    from jaxslam.cli import DEMO_DEFAULTS
    from jaxslam.config import build_setup
    from jaxslam.sim import office_scenario

    log = office_scenario(jax.random.key(0)).log
    log = log.subset(np.arange(min(args.scans, log.num_scans)))
    out = Path(args.out)
    table = json.loads(out.read_text()) if out.is_file() else {"machine": platform.platform(),
                                                               "likelihood_lookup": "bilinear", "rows": {}}
    for proposal in args.proposal:
        config, settings, params = build_setup({**DEMO_DEFAULTS, "proposal": proposal,
                                                "num_particles": args.particles})
        # Motion gradients need the bilinear lookup. The LP row is the paper's LP (localizers from
        # the odometry), as the recorded figures were measured; the library's default LP adds a match.
        config = dataclasses.replace(config, likelihood_lookup="bilinear", lookahead_initial="odometry")
        prepared, selection, _ = rbpf.prepare(log, config, settings)

        def log_likelihood(p, key):
            return rbpf.filter(key, prepared, p, config).marginal_loglik

        key = jax.random.key(1)
        t0 = time.perf_counter()
        gradient = jax.jit(jax.value_and_grad(log_likelihood)).lower(params, key).compile()
        planned = gradient.memory_analysis()
        temp_gb = None if planned is None else planned.temp_size_in_bytes / 1e9
        if args.memory:
            value, _ = jax.block_until_ready(gradient(params, key))
            seconds = time.perf_counter() - t0
            rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9  # Linux: KiB
            row = {"proposal": proposal, "particles": args.particles, "scans": args.scans,
                   "steps": int(selection.indices.size - 1), "num_localizers": config.num_localizers,
                   "horizon": config.horizon, "gradient_temp_gb": temp_gb, "max_rss_gb": rss_gb,
                   "value": float(value), "compile_and_run_s": seconds}
            table["rows"][f"{proposal}_{args.particles}particles_{args.scans}scans_memory"] = row
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(table, indent=2))
            print(f"{proposal}: {row['steps']} steps, gradient's planned temporary memory {temp_gb:.2f} GB, "
                  f"peak resident {rss_gb:.2f} GB (compile and run {seconds:.0f} s)", flush=True)
            continue
        jax.block_until_ready(gradient(params, key))
        compile_gradient = time.perf_counter() - t0
        forward = jax.jit(log_likelihood)
        t0 = time.perf_counter()
        jax.block_until_ready(forward(params, key))
        compile_forward = time.perf_counter() - t0
        times = {"forward": [], "gradient": []}
        for r in range(args.repeats):
            for name, fn in (("forward", forward), ("gradient", gradient)):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(params, jax.random.key(2 + r)))
                times[name].append(time.perf_counter() - t0)
        f, g = float(np.median(times["forward"])), float(np.median(times["gradient"]))
        row = {"proposal": proposal, "particles": args.particles, "scans": args.scans,
               "steps": int(selection.indices.size - 1), "forward_s": f, "gradient_s": g, "ratio": g / f,
               "compile_forward_s": compile_forward, "compile_gradient_s": compile_gradient,
               "gradient_temp_gb": temp_gb}
        table["rows"][f"{proposal}_{args.particles}particles_{args.scans}scans"] = row
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(table, indent=2))
        print(f"{proposal}: {row['steps']} steps, forward {f:.2f} s, value and gradient {g:.2f} s, "
              f"ratio {g / f:.2f} (compile {compile_forward:.1f} / {compile_gradient:.1f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
