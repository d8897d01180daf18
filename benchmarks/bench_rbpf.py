"""RBPF throughput on a real log, against GMapping measured on the same machine.

Runs ``jaxslam map LOG`` in a fresh subprocess (so that its peak memory is its own) and
reports wall time (compile included), processed scans per second, real-time factor
(data duration / wall time) and peak resident memory, beside the reference the project
measured for GMapping (C++, OpenSLAM) on this 2-core machine with the same log, 30
particles and default parameters: 1,051 of 13,631 Intel scans processed in 81.5 s
wall (real-time factor 33), 133 MB peak.

    python benchmarks/bench_rbpf.py --log ../shared/data/intel.sort.bag --particles 30 --proposal smp
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

GMAPPING_UPDATE_RULE = ["--set", "linear_update=1.0", "--set", "angular_update=0.5"]
"""GMapping's update rule (1 m / 0.5 rad; the library's default is half that), so that both
process the same scans; a later ``--set`` overrides it."""
GMAPPING_INTEL = {"wall_s": 81.5, "scans_processed": 1051, "real_time_factor": 33.0, "peak_memory_mb": 133.0}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--log", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "intel.sort.bag"))
    parser.add_argument("--proposal", default="smp", help="a registered proposal (jaxslam.proposals.PROPOSALS)")
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more arguments for jaxslam map")
    parser.add_argument("--out", default="results/bench_rbpf.json")
    args = parser.parse_args(argv)
    if not Path(args.log).exists():
        print(f"log not found: {args.log}", file=sys.stderr)
        return 2

    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "jaxslam.cli", "map", args.log, "--proposal", args.proposal,
               "--particles", str(args.particles), "--seed", str(args.seed), "--out", tmp, "--no-progress",
               *GMAPPING_UPDATE_RULE]
        for item in args.set:
            cmd += ["--set", item]
        cmd += args.extra
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True)
        wall = time.perf_counter() - t0
        peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
        summary = json.loads((Path(tmp) / "summary.json").read_text())
        png = Path(args.out).with_suffix(".map.png")
        png.parent.mkdir(parents=True, exist_ok=True)
        png.write_bytes((Path(tmp) / "map.png").read_bytes())

    processed = summary["scans_processed"]
    result = {
        "command": " ".join(cmd[1:]),
        "log": args.log,
        "proposal": args.proposal,
        "particles": args.particles,
        "scans_in_log": summary["scans_in_log"],
        "scans_processed": processed,
        "wall_s_process": wall,
        "wall_s_filter": summary["timings"]["total"],
        "compile_s": summary["timings"]["compile"],
        "scans_per_second": processed / wall,
        "real_time_factor": summary["log_duration_s"] / wall,
        "peak_memory_mb": peak_mb,
        "gmapping_reference": GMAPPING_INTEL,
        "wall_ratio_vs_gmapping": wall / GMAPPING_INTEL["wall_s"],
        "memory_ratio_vs_gmapping": peak_mb / GMAPPING_INTEL["peak_memory_mb"],
        "map_png": str(png),
    }
    if "refinement" in summary:  # --extra --refine: every scan localised and fused (inside the wall time)
        result["refinement"] = {**summary["refinement"], "seconds": summary["timings"].get("refinement")}
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"{'':24}{'jaxslam':>12}{'GMapping':>12}")
    print(f"{'scans processed':24}{processed:>12d}{GMAPPING_INTEL['scans_processed']:>12d}")
    print(f"{'wall time [s]':24}{wall:>12.1f}{GMAPPING_INTEL['wall_s']:>12.1f}")
    print(f"{'real-time factor':24}{result['real_time_factor']:>12.1f}{GMAPPING_INTEL['real_time_factor']:>12.1f}")
    print(f"{'peak memory [MB]':24}{peak_mb:>12.0f}{GMAPPING_INTEL['peak_memory_mb']:>12.0f}")
    if result.get("refinement", {}).get("seconds") is not None:
        print(f"{'of which refinement [s]':24}{result['refinement']['seconds']:>12.1f}")
    print(f"{'scans per second':24}{result['scans_per_second']:>12.1f}{1051 / 81.5:>12.1f}")
    print(f"wall-time ratio jaxslam / GMapping = {result['wall_ratio_vs_gmapping']:.2f}; written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
