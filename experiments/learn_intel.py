"""Learning the odometry noise on the first minutes of a real log (Intel by default), then mapping
the whole log with it.

The fit climbs ``rbpf.filter``'s log-likelihood estimate over the scans of the first
``--seconds`` of the log (Adam, :func:`jaxslam.learning.fit`), with the untempered likelihood
(gain 1) and the bilinear lookup (as on the simulated office),
starting from the library's defaults. The sensor's sigma is learned with the motion terms (the
normaliser counts the field's distance in whole cells, so sigma has a maximum at 5 cm cells;
docs/design.md, "Endpoint model"; a sigma held wrong acts on the motion terms as tempering
does). It writes the history and the learned values as JSON and
prints the ``--set`` arguments that map with them: the comparison with the defaults is then the
datasets experiment, run twice:

    python experiments/learn_intel.py --data ../data --out docs/results/learn_intel.json
    python experiments/datasets.py --datasets intel --proposals smp --seeds 5 --out results/intel_learned \\
        --set motion.srr=... (the printed arguments)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

TERMS = ("motion.srr", "motion.srt", "motion.str", "motion.stt", "likelihood.sigma")
LOGS = {"intel": "intel.sort.bag", "aces": "aces.sort.bag", "mit-csail": "mit-csail.clf",
        "fr-clinic": "fr-clinic.bag"}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="folder of the logs")
    parser.add_argument("--dataset", default="intel", choices=list(LOGS))
    parser.add_argument("--seconds", type=float, default=300.0, help="learn on the scans of the first SECONDS")
    parser.add_argument("--proposal", default="op", choices=["op", "smp", "lp"])
    parser.add_argument("--particles", type=int, default=50)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--learning-rate", type=float, default=0.05)
    parser.add_argument("--trainable", nargs="+", default=list(TERMS), choices=list(TERMS))
    parser.add_argument("--out", default="results/learn_intel.json")
    args = parser.parse_args(argv)
    path = Path(args.data) / LOGS[args.dataset]
    if not path.is_file():
        parser.error(f"log not found: {path}")
    if args.seconds <= 0 or args.steps < 1 or args.particles < 1:
        parser.error("--seconds, --steps and --particles must be positive")

    import jax

    from jaxslam import rbpf
    from jaxslam.config import build_setup, params_to_dict
    from jaxslam.io import read_log
    from jaxslam.learning import fit
    from jaxslam.maps import PoolSize

    log = read_log(path)
    elapsed = log.timestamps - log.timestamps[0]
    log = log.subset(np.flatnonzero(elapsed <= args.seconds))
    config, settings, params = build_setup({"proposal": args.proposal, "num_particles": args.particles,
                                            "likelihood.gain": 1.0})
    config = dataclasses.replace(config, likelihood_lookup="bilinear")
    prepared, _, _ = rbpf.prepare(log, config, settings)
    # rbpf.filter cannot grow the pools: start them large enough for the whole excerpt (a step
    # that does not fit makes the objective -inf, and fit stops with a FitError saying so).
    base = rbpf.pool_size(config)
    pool = PoolSize(8 * base.capacity, base.max_new_tiles, 8 * base.block_capacity, base.max_new_blocks)

    def objective(key, p):
        return rbpf.filter(key, prepared, p, config, pool=pool).marginal_loglik

    print(f"{args.dataset}: {log.num_scans} scans in the first {args.seconds:g} s, "
          f"{prepared.inputs.motion.shape[0]} updates", flush=True)
    result = fit(jax.random.key(0), objective, params, num_steps=args.steps, learning_rate=args.learning_rate,
                 trainable=args.trainable)
    tail = max(1, args.steps // 4)  # Adam's iterates jitter about the maximum: average the last quarter
    defaults = params_to_dict(params)
    learned = {name: float(np.mean(result.history[name][-tail:])) for name in args.trainable}
    record = {"args": {**vars(args), "data": "(the --data folder)"},  # no machine's path in a result "updates": int(prepared.inputs.motion.shape[0]),
              "default": {name: float(defaults[name]) for name in args.trainable}, "learned_tail_mean": learned,
              "history": {k: v.tolist() for k, v in result.history.items()}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=2))
    for name in args.trainable:
        print(f"{name}: default {defaults[name]:.4f}, learned {learned[name]:.4f} "
              f"({learned[name] / defaults[name]:.2f} x default)")
    print("map with: " + " ".join(f"--set {name}={learned[name]:.5g}" for name in args.trainable))
    return 0


if __name__ == "__main__":
    sys.exit(main())
