"""Learning the odometry noise from a simulated office log with the RBPF's log-likelihood.

The simulated office (:func:`jaxslam.sim.office_scenario`) draws its odometry with known terms
(srr 0.05, srt 0.02, str 0.05, stt 0.05 per 0.18 m step). Starting from twice them, Adam
(:func:`jaxslam.learning.fit`) climbs ``rbpf.filter``'s log-likelihood estimate (score
gradients through resampling) with the bilinear likelihood (the nearest-cell weights give the OP
and LP no motion gradient) and, with ``--gain 1``, the untempered likelihood. Writes the history
as JSON.

    python experiments/learn_office.py --steps 40 --out results/learn_office.json

With ``--profile S [S ...]`` it fits nothing: it evaluates the log-likelihood estimate with
all four terms at S times the truth, over ``--seeds`` keys (mean and standard error), to see
where its maximum sits:

    python experiments/learn_office.py --proposal op --particles 50 --profile 0.25 0.5 1 2 --seeds 4
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
    start = {name: args.start_scale * truth[name] for name in TERMS}
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
        for scale in args.profile:
            scaled = params_from_dict({**params_to_dict(params), **{n: scale * truth[n] for n in TERMS}})
            values = np.asarray(evaluate(keys, scaled))
            rows.append({"scale": scale, "mean": float(values.mean()),
                         "standard_error": float(values.std(ddof=1) / np.sqrt(values.size)), "values": values.tolist()})
            print(f"{scale:g} x truth: log-likelihood {rows[-1]['mean']:.1f} ± {rows[-1]['standard_error']:.1f}",
                  flush=True)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"args": vars(args), "truth": {k: truth[k] for k in TERMS},
                                              "profile": rows}, indent=2))
        return 0

    result = fit(jax.random.key(1), objective, params, num_steps=args.steps, learning_rate=args.learning_rate,
                 trainable=list(TERMS))
    final = {name: float(result.history[name][-1]) for name in TERMS}
    record = {"args": vars(args), "truth": {k: truth[k] for k in TERMS}, "start": start, "final": final,
              "history": {k: v.tolist() for k, v in result.history.items()}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=2))
    for name in TERMS:
        print(f"{name}: truth {truth[name]:.4f}, start {start[name]:.4f}, learned {final[name]:.4f} "
              f"({final[name] / truth[name]:.2f} x truth)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
