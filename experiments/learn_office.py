"""Learning the odometry noise from a simulated office log with the RBPF's log-likelihood.

The simulated office (:func:`jaxslam.sim.office_scenario`) draws its odometry with known terms
(srr 0.05, srt 0.02, str 0.05, stt 0.05 per 0.18 m step). Starting from twice them, Adam
(:func:`jaxslam.learning.fit`) climbs ``rbpf.filter``'s log-likelihood estimate (score
gradients through resampling) with the bilinear likelihood (the nearest-cell weights give the OP
and LP no motion gradient) and, with ``--gain 1``, the untempered likelihood. Writes the history
as JSON.

    python experiments/learn_office.py --steps 40 --out results/learn_office.json

With ``--profile S [S ...]`` it fits nothing: it evaluates the log-likelihood estimate with
the ``--vary`` terms (default all four odometry terms together) at S times the truth, the other
odometry terms at the truth and ``likelihood.sigma`` at the demo's value, over ``--seeds`` keys (mean and standard error), to see where its maximum
sits and how flat it is (the "truth" of ``likelihood.sigma`` is the simulated range noise):

    python experiments/learn_office.py --proposal op --particles 50 --profile 0.25 0.5 1 2 --seeds 4
    python experiments/learn_office.py --proposal op --particles 50 --profile 0.5 0.75 1 1.5 2 --vary motion.srr
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

TERMS = ("motion.srr", "motion.srt", "motion.str", "motion.stt")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--proposal", default="smp", choices=["op", "smp", "lp"])
    parser.add_argument("--particles", type=int, default=20)
    parser.add_argument("--scans", type=int, default=300)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--learning-rate", type=float, default=0.05)
    parser.add_argument("--gain", type=float, default=1.0, help="likelihood.gain during the fit")
    parser.add_argument("--start-scale", type=float, default=2.0, help="start at this times the true terms")
    parser.add_argument("--profile", type=float, nargs="+", help="scales of the true terms to evaluate (no fit)")
    parser.add_argument("--seeds", type=int, default=4, help="--profile: keys per scale")
    parser.add_argument("--vary", nargs="+", default=list(TERMS), choices=list(TERMS) + ["likelihood.sigma"],
                        help="--profile: the terms scaled together (the others stay at the truth)")
    parser.add_argument("--trainable", nargs="+", default=list(TERMS), choices=list(TERMS) + ["likelihood.sigma"],
                        help="the fitted terms, each started at --start-scale times its truth")
    parser.add_argument("--out", default="results/learn_office.json")
    args = parser.parse_args(argv)

    import dataclasses

    import jax

    from jaxslam import rbpf
    from jaxslam.cli import DEMO_DEFAULTS
    from jaxslam.config import build_setup
    from jaxslam.learning import fit
    from jaxslam.sim import office_scenario

    scenario = office_scenario(jax.random.key(0))
    log = scenario.log.subset(np.arange(min(args.scans, scenario.log.num_scans)))
    truth = {f"motion.{k}": float(v) for k, v in scenario.metadata["motion_params"]._asdict().items()}
    truth["likelihood.sigma"] = float(scenario.metadata["range_noise_std"])
    start = {name: args.start_scale * truth[name] for name in args.trainable}
    config, settings, params = build_setup({**DEMO_DEFAULTS, "proposal": args.proposal,
                                            "num_particles": args.particles, "likelihood.gain": args.gain, **start})
    config = dataclasses.replace(config, likelihood_lookup="bilinear")
    prepared, _, _ = rbpf.prepare(log, config, settings)

    def objective(key, p):
        return rbpf.filter(key, prepared, p, config).marginal_loglik

    if args.profile:
        from jaxslam.config import params_from_dict, params_to_dict

        evaluate = jax.jit(jax.vmap(objective, in_axes=(0, None)))
        keys = jax.random.split(jax.random.key(5), args.seeds)
        rows = []
        at_truth = {n: truth[n] for n in TERMS}
        for scale in args.profile:
            varied = {n: scale * truth[n] for n in args.vary}
            scaled = params_from_dict({**params_to_dict(params), **at_truth, **varied})
            values = np.asarray(evaluate(keys, scaled))
            rows.append({"scale": scale, "mean": float(values.mean()),
                         "standard_error": float(values.std(ddof=1) / np.sqrt(values.size)), "values": values.tolist()})
            print(f"{scale:g} x truth: log-likelihood {rows[-1]['mean']:.1f} ± {rows[-1]['standard_error']:.1f}",
                  flush=True)
        if 1.0 in args.profile:
            # The keys are the same at every scale (common random numbers): the paired difference
            # to the truth is far more precise than either estimate.
            base = np.asarray(rows[args.profile.index(1.0)]["values"])
            for row in rows:
                diff = np.asarray(row["values"]) - base
                row["difference_to_truth"] = float(diff.mean())
                row["difference_standard_error"] = float(diff.std(ddof=1) / np.sqrt(diff.size))
                print(f"{row['scale']:g} x truth - truth: {row['difference_to_truth']:.1f} "
                      f"± {row['difference_standard_error']:.1f} (paired keys)", flush=True)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"args": vars(args), "truth": {k: truth[k] for k in TERMS + ("likelihood.sigma",)},
                                              "profile": rows}, indent=2))
        return 0

    result = fit(jax.random.key(1), objective, params, num_steps=args.steps, learning_rate=args.learning_rate,
                 trainable=args.trainable)
    final = {name: float(result.history[name][-1]) for name in args.trainable}
    tail = max(1, args.steps // 4)  # Adam's iterates jitter about the maximum: average the last quarter
    learned = {name: float(np.mean(result.history[name][-tail:])) for name in args.trainable}
    record = {"args": vars(args), "truth": {k: truth[k] for k in args.trainable}, "start": start, "final": final,
              "learned_tail_mean": learned, "history": {k: v.tolist() for k, v in result.history.items()}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=2))
    for name in args.trainable:
        print(f"{name}: truth {truth[name]:.4f}, start {start[name]:.4f}, learned {learned[name]:.4f} "
              f"({learned[name] / truth[name]:.2f} x truth; last step {final[name]:.4f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
