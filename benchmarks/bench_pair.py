"""Wall time of two source trees of the library on the same run, alternating: A B A B ...

A refactor that must not slow the filter (a layout change, a moved function) is timed against
the commit before it. Each run is a fresh subprocess with ``PYTHONPATH`` set to one tree, so
both trees run with the same interpreter and libraries; the runs alternate so that a change in
the machine's load falls on both. Reported: each run's seconds after the first chunk (the steady
state: ``total - compile`` of ``slam.run``'s timings), the first chunk's (compile included), the
ratio B / A of the medians, and whether the trajectories are equal bit for bit.

    git worktree add /tmp/before <commit>
    python benchmarks/bench_pair.py --trees /tmp/before . --log ../shared/data/intel.sort.bag \\
        --scans 600 --proposal smp --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_RUN = """
import json, sys
import numpy as np, jax
from jaxslam import slam
from jaxslam.config import build_setup
from jaxslam.io import read_log

log = read_log(sys.argv[1])
log = log.subset(np.arange(min(int(sys.argv[2]), log.num_scans)))
config, settings, params = build_setup({"proposal": sys.argv[3], "num_particles": int(sys.argv[4])})
result = slam.run(jax.random.key(int(sys.argv[5])), log, config, params, settings, progress=False)
np.save(sys.argv[6], np.asarray(result.trajectory))
print(json.dumps({k: float(v) for k, v in result.timings.items()}))
"""


def _one(tree: Path, args, trajectory: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
    done = subprocess.run([sys.executable, "-c", _RUN, args.log, str(args.scans), args.proposal, str(args.particles),
                           str(args.seed), str(trajectory)], env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trees", nargs=2, required=True, metavar=("A", "B"), help="two source trees of the library")
    parser.add_argument("--log", required=True)
    parser.add_argument("--scans", type=int, default=600, help="the log's first SCANS scans")
    parser.add_argument("--proposal", default="smp")
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=3, help="runs of each tree, alternating")
    parser.add_argument("--out", help="a JSON file for the figures")
    args = parser.parse_args(argv)
    trees = [Path(t) for t in args.trees]
    for tree in trees:
        if not (tree / "jaxslam" / "__init__.py").is_file():
            parser.error(f"{tree} holds no jaxslam package")
    if not Path(args.log).exists():
        parser.error(f"--log {args.log}: no such file")
    runs = {0: [], 1: []}
    with tempfile.TemporaryDirectory() as tmp:
        paths = [Path(tmp) / "a.npy", Path(tmp) / "b.npy"]
        for round_ in range(args.rounds):
            for which in (0, 1):
                timings = _one(trees[which], args, paths[which])
                runs[which].append(timings)
                print(f"round {round_ + 1} {'AB'[which]}: {timings['total'] - timings['compile']:.1f} s after the "
                      f"first chunk, first chunk {timings['compile']:.1f} s", flush=True)
        same = bool(np.array_equal(np.load(paths[0]), np.load(paths[1])))

    steady = [float(np.median([t["total"] - t["compile"] for t in runs[w]])) for w in (0, 1)]
    report = {"trees": [str(t) for t in trees], "log": args.log, "scans": args.scans, "proposal": args.proposal,
              "particles": args.particles, "seed": args.seed, "runs": runs,
              "steady_median_s": steady, "ratio_b_over_a": steady[1] / steady[0], "trajectories_equal": same}
    print(f"median after the first chunk: A {steady[0]:.1f} s, B {steady[1]:.1f} s, B / A = "
          f"{steady[1] / steady[0]:.3f}; trajectories bit for bit equal: {same}")
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
