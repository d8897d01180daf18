"""Bias and spread of the filters' score estimates: the path-space score (the gradient of the
log-likelihood estimate through :func:`jaxslam.resampling.resample_if_needed`) against the
fixed-lag smoothed score (:func:`jaxslam.particle_filter.fixed_lag_score`) at a few lags.

* Linear-Gaussian model (tests/linear_gaussian.py: x_t = a x_t-1 + N(0, q), y_t = x_t + N(0, r),
  theta = (0.9, 0.5, 0.3)): the bootstrap filter in the OP's score form
  (``score_log_likelihood``) against the Kalman filter's exact score d log p(y | theta) / d theta,
  on ``--seeds`` simulated datasets, over ``--lg-keys`` filter keys each; and, beside it, the
  path-space score of the fully adapted proposal (``proposal="adapted"``: each state drawn from
  its exact posterior given the previous state and the observation, weighed by gamma / q), the
  counterpart of the SMP's importance weight (docs/design.md, "What a gradient of the filter is").
* The simulated office (:func:`jaxslam.sim.office_scenario`, set up as
  experiments/learn_office.py does: OP, every scan an update, the simulator's minimum stds,
  bilinear lookup, gain 1, the first ``--scans`` scans, the motion terms at the simulated values
  and sigma at its known-path optimum): no exact score exists. The score in log coordinates
  (d log p / d log term) of N = ``--particles`` filters over ``--office-keys`` keys is compared
  with a reference: the mean path-space score at N = ``--ref-particles`` (consistent as N
  grows), and, for the motion terms, the known path's score (the motion model's
  log-density of the true path given the odometry: what the score is when the scans pin the path).

All estimators of one filter run come from the same particles (one forward pass; the lags only
change the surrogate added to the log-likelihood estimate), so their differences are paired.
The office's table ends with the particles' genealogy: the mean ESS after each weight update,
and from how many distinct particles of a step the particles 1, 2 and 5 steps later descend
(1: every estimator gives that step's term the same value). Writes ``score_bias.json`` and
``score_bias.md`` (the tables) into ``--out``; about 5 minutes on 2 CPU cores:

    python experiments/score_bias.py --out results/score_bias

With ``--fits`` it measures nothing else: Adam fits of the linear-Gaussian model's q and r from
twice the truth on each score, at N = 50 and 200, against the Kalman maximum-likelihood estimate
(``score_bias_fits.json`` and ``.md``):

    python experiments/score_bias.py --out results/score_bias --fits
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MOTION = ("motion.srr", "motion.srt", "motion.str", "motion.stt")
OFFICE_NAMES = MOTION + ("likelihood.sigma",)


ADAPTED = "adapted proposal"
"""The linear-Gaussian model's estimator with the fully adapted proposal (the SMP's counterpart)."""


def estimator_names(lags) -> list[str]:
    return ["path-space"] + [f"lag {lag}" for lag in lags]


def linear_gaussian(args, bar) -> list[dict]:
    """Rows (seed, parameter, estimator, exact, bias, sd, se) of the linear-Gaussian model."""
    import jax

    sys.path.insert(0, str(ROOT / "tests"))
    from linear_gaussian import THETA, kalman_score, score_log_likelihood, simulate

    rows = []
    for seed in range(args.seeds):
        ys = simulate(jax.random.key(100 + seed), THETA, args.lg_steps)
        exact = np.asarray(kalman_score(THETA, ys), np.float64)
        keys = jax.random.split(jax.random.key(200 + seed), args.lg_keys)
        # The bootstrap's estimators, then the SMP's counterpart: the fully adapted proposal,
        # weighed by gamma / q, with the path-space score.
        estimators = [(name, lag, "bootstrap") for name, lag in zip(estimator_names(args.lags), [None, *args.lags])]
        for name, lag, proposal in estimators + [(ADAPTED, None, "adapted")]:
            grad_fn = jax.jit(jax.vmap(jax.grad(lambda th, k, lag=lag, proposal=proposal: score_log_likelihood(
                th, k, ys, args.lg_particles, "systematic", args.lg_threshold, lag, proposal)), in_axes=(None, 0)))
            grads = np.asarray(grad_fn(THETA, keys), np.float64)
            for i, param in enumerate("aqr"):
                g = grads[:, i]
                rows.append({"model": "linear-Gaussian", "seed": seed, "parameter": param, "estimator": name,
                             "reference": float(exact[i]), "bias": float(g.mean() - exact[i]),
                             "sd": float(g.std(ddof=1)), "se": float(g.std(ddof=1) / np.sqrt(g.size))})
            bar.update(1)
    return rows


def linear_gaussian_fits(args, bar) -> list[dict]:
    """``--fits``: Adam (:func:`jaxslam.learning.fit`) on q and r of the linear-Gaussian model from
    twice the truth (a frozen), on the path-space and on the fixed-lag score at each ``--fit-lags``
    lag, N = ``--fit-particles`` each; the learned values (mean of the last third of the steps)
    as multiples of the Kalman maximum-likelihood estimate (the same fit on the exact
    log-likelihood)."""
    from typing import NamedTuple

    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(ROOT / "tests"))
    from linear_gaussian import THETA, kalman_log_likelihood, score_log_likelihood, simulate

    from jaxslam.learning import fit

    class LgParams(NamedTuple):
        a: jax.Array
        q: jax.Array
        r: jax.Array

    def theta(p):
        return jnp.stack([p.a, p.q, p.r])

    start = LgParams(jnp.float32(THETA[0]), jnp.float32(2 * THETA[1]), jnp.float32(2 * THETA[2]))
    rows = []
    for seed in range(args.seeds):
        ys = simulate(jax.random.key(100 + seed), THETA, args.lg_steps)
        exact = fit(jax.random.key(1), lambda k, p: kalman_log_likelihood(theta(p), ys), start, num_steps=300,
                    learning_rate=0.05, trainable=["q", "r"], progress=False)
        mle = {n: float(getattr(exact.params, n)) for n in "qr"}
        for n_particles in args.fit_particles:
            for name, lag in zip(estimator_names(args.fit_lags), [None, *args.fit_lags]):
                result = fit(jax.random.key(10 + seed), lambda k, p, lag=lag, n=n_particles: score_log_likelihood(
                    theta(p), k, ys, n, "systematic", args.lg_threshold, lag), start, num_steps=args.fit_steps,
                    learning_rate=0.05, trainable=["q", "r"], progress=False)
                tail = max(1, args.fit_steps // 3)
                learned = {n: float(np.mean(result.history[n][-tail:])) for n in "qr"}
                rows.append({"seed": seed, "particles": n_particles, "estimator": name, "mle": mle,
                             "learned": learned, "ratio_to_mle": {n: learned[n] / mle[n] for n in "qr"}})
                bar.update(1)
    return rows


def fits_table(rows) -> str:
    seeds = sorted({r["seed"] for r in rows})
    lines = ["| N | estimator | " + " | ".join(f"seed {s}: q, r / MLE" for s in seeds) + " |",
             "|" + "---|" * (2 + len(seeds))]
    for n in sorted({r["particles"] for r in rows}):
        for name in dict.fromkeys(r["estimator"] for r in rows):
            sel = [next(r for r in rows if r["seed"] == s and r["particles"] == n and r["estimator"] == name)
                   for s in seeds]
            lines.append(f"| {n} | {name} | " + " | ".join(f"{r['ratio_to_mle']['q']:.2f}, {r['ratio_to_mle']['r']:.2f}"
                                                         for r in sel) + " |")
    return "\n".join(lines)


def office(args, bar) -> list[dict]:
    """Rows of the simulated office (see the module's docstring)."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(ROOT / "experiments"))
    from learn_office import setup_office

    from jaxslam import motion, particle_filter, rbpf
    from jaxslam.config import params_from_dict, params_to_dict
    from jaxslam.learning import param_names

    setup_args = argparse.Namespace(range_noise=None, scans=args.scans, proposal="op", particles=args.particles,
                                    gain=1.0, resolution=0.05)
    compiled = {}
    rows = []
    for seed in range(args.seeds):
        setup = setup_office(seed, setup_args)
        truth, prepared = setup["truth"], setup["prepared"]
        base = params_from_dict({**params_to_dict(setup["params"]), **{n: truth[n] for n in OFFICE_NAMES}})
        position = [param_names(base).index(n) for n in OFFICE_NAMES]
        log_truth = jnp.log(jnp.array([truth[n] for n in OFFICE_NAMES], jnp.float32))

        def at(log_values, base):  # ``base`` with the named terms at exp(log_values), traceable
            leaves, treedef = jax.tree.flatten(base)
            for i, j in enumerate(position):
                leaves[j] = jnp.exp(log_values[i]).astype(leaves[j].dtype)
            return jax.tree.unflatten(treedef, leaves)

        def make(num_particles):
            config = dataclasses.replace(setup["config"], num_particles=num_particles)

            def estimates(log_values, key, base, prepared):
                # rbpf.filter's body, keeping the steps' score terms: every estimator from one run.
                params = at(log_values, base)
                key_init, key_steps = jax.random.split(key)
                state = rbpf.init(key_init, prepared.first_ranges, prepared.sensor, params, config,
                                  prepared.initial_pose)

                def step(k, s, inp):
                    new, info, terms = rbpf.step_with_score_terms(k, s, inp, prepared.sensor, params, config)
                    return new, (info, terms)

                out = particle_filter.scan_filter(step, key_steps, state, prepared.inputs,
                                                  lambda it: it[0].log_evidence, checkpoint=False)
                info, terms = out.info
                loglik = out.marginal_loglik
                return jnp.stack([loglik] + [loglik + particle_filter.fixed_lag_score(terms, lag)
                                             for lag in args.lags]), (info.ess, info.ancestors)

            return jax.jit(jax.jacrev(estimates, has_aux=True))

        for n in (args.particles, args.ref_particles):
            if n not in compiled:
                compiled[n] = make(n)
        known = np.asarray(jax.grad(lambda x: motion.path_log_density(setup["path"], setup["motions"],
                                                                       at(x, base).motion))(log_truth), np.float64)
        runs, genealogy = {}, {}
        for n, num_keys in ((args.particles, args.office_keys), (args.ref_particles, args.ref_keys)):
            grads, ess, distinct = [], [], {lag: [] for lag in (1, 2, 5)}
            for k in jax.random.split(jax.random.key(300 + seed), num_keys):
                jac, (step_ess, ancestors) = compiled[n](log_truth, k, base, prepared)
                grads.append(np.asarray(jac, np.float64))  # (E, P)
                ess.append(np.asarray(step_ess))
                for lag, counts in distinct.items():
                    counts.extend(distinct_ancestors(np.asarray(ancestors), lag))
                bar.update(1)
            runs[n] = np.array(grads)  # (keys, estimators, parameters)
            genealogy[n] = {"particles": n, "mean_ess": float(np.mean(ess)), "median_ess": float(np.median(ess)),
                            **{f"distinct_ancestors_{lag}_steps_back": float(np.mean(c)) for lag, c in distinct.items()}}
        # The path-space score at the large N: consistent as N grows (a fixed lag is not).
        reference = runs[args.ref_particles][:, 0].mean(axis=0)
        ref_se = runs[args.ref_particles][:, 0].std(axis=0, ddof=1) / np.sqrt(args.ref_keys)
        for e, name in enumerate(estimator_names(args.lags)):
            for i, param in enumerate(OFFICE_NAMES):
                g = runs[args.particles][:, e, i]
                h = runs[args.ref_particles][:, e, i]
                rows.append({"model": "office", "seed": seed, "parameter": param, "estimator": name,
                             "reference": float(reference[i]), "reference_se": float(ref_se[i]),
                             "known_path": float(known[i]) if param in MOTION else None,
                             "mean": float(g.mean()), "bias": float(g.mean() - reference[i]),
                             "sd": float(g.std(ddof=1)), "se": float(g.std(ddof=1) / np.sqrt(g.size)),
                             "ref_particles_mean": float(h.mean()), "ref_particles_sd": float(h.std(ddof=1)),
                             "genealogy": genealogy[args.particles], "ref_genealogy": genealogy[args.ref_particles]})
    return rows


def distinct_ancestors(ancestors: np.ndarray, lag: int) -> list[int]:
    """For every step t of a run ((T, N) ``ancestors``), how many distinct particles of step t the
    particles of step t + ``lag`` descend from: the particles a fixed-lag term at that lag is
    averaged over (1: every estimator gives that step's term the same value)."""
    steps, n = ancestors.shape
    counts = []
    for t in range(steps - lag):
        idx = np.arange(n)
        for u in range(t + lag - 1, t - 1, -1):
            idx = ancestors[u, idx]
        counts.append(int(np.unique(idx).size))
    return counts


def summary_table(rows, model, params, lags) -> str:
    """Markdown: per parameter and estimator, the bias and sd of every seed, and the mean |bias|."""
    names = [n for n in estimator_names(lags) + [ADAPTED]
             if any(r["model"] == model and r["estimator"] == n for r in rows)]
    seeds = sorted({r["seed"] for r in rows if r["model"] == model})
    head = "| parameter | estimator | " + " | ".join(f"seed {s}: bias ± se (sd)" for s in seeds) + \
        " | mean abs bias | mean sd |"
    lines = [head, "|" + "---|" * (4 + len(seeds))]
    for p in params:
        for name in names:
            sel = [next(r for r in rows if r["model"] == model and r["seed"] == s and r["parameter"] == p
                        and r["estimator"] == name) for s in seeds]
            cells = [f"{r['bias']:+.2f} ± {r['se']:.2f} ({r['sd']:.2f})" for r in sel]
            lines.append(f"| {p} | {name} | " + " | ".join(cells)
                         + f" | {np.mean([abs(r['bias']) for r in sel]):.2f} | {np.mean([r['sd'] for r in sel]):.2f} |")
    return "\n".join(lines)


def genealogy_table(rows) -> str:
    lines = ["| seed | N | mean ESS | median ESS | distinct ancestors 1 / 2 / 5 steps back |", "|---|---|---|---|---|"]
    for seed in sorted({r["seed"] for r in rows if r["model"] == "office"}):
        r = next(r for r in rows if r["model"] == "office" and r["seed"] == seed)
        for g in (r["genealogy"], r["ref_genealogy"]):
            lines.append(f"| {seed} | {g['particles']} | {g['mean_ess']:.2f} | {g['median_ess']:.2f} | "
                         f"{g['distinct_ancestors_1_steps_back']:.2f} / {g['distinct_ancestors_2_steps_back']:.2f} / "
                         f"{g['distinct_ancestors_5_steps_back']:.2f} |")
    return "\n".join(lines)


def reference_table(rows, params) -> str:
    seeds = sorted({r["seed"] for r in rows if r["model"] == "office"})
    lines = ["| parameter | " + " | ".join(f"seed {s}: reference ± se (known path)" for s in seeds) + " |",
             "|" + "---|" * (1 + len(seeds))]
    for p in params:
        cells = []
        for s in seeds:
            r = next(r for r in rows if r["model"] == "office" and r["seed"] == s and r["parameter"] == p)
            known = "-" if r["known_path"] is None else f"{r['known_path']:+.1f}"
            cells.append(f"{r['reference']:+.1f} ± {r['reference_se']:.1f} ({known})")
        lines.append(f"| {p} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="folder for score_bias.json and score_bias.md")
    parser.add_argument("--seeds", type=int, default=3, help="datasets per model")
    parser.add_argument("--lags", type=int, nargs="+", default=[0, 5, 10, 20],
                        help="fixed lags to measure (0: the filtering weights alone)")
    parser.add_argument("--lg-steps", type=int, default=200, help="linear-Gaussian: T")
    parser.add_argument("--lg-particles", type=int, default=50, help="linear-Gaussian: N")
    parser.add_argument("--lg-threshold", type=float, default=0.5, help="linear-Gaussian: resample when ESS < this N")
    parser.add_argument("--lg-keys", type=int, default=400, help="linear-Gaussian: filter runs per seed")
    parser.add_argument("--scans", type=int, default=60, help="office: scans of the log")
    parser.add_argument("--particles", type=int, default=20, help="office: N of the estimators measured")
    parser.add_argument("--office-keys", type=int, default=16, help="office: runs per seed at --particles")
    parser.add_argument("--ref-particles", type=int, default=100, help="office: N of the reference")
    parser.add_argument("--ref-keys", type=int, default=4, help="office: runs per seed at --ref-particles")
    parser.add_argument("--skip-office", action="store_true")
    parser.add_argument("--fits", action="store_true",
                        help="measure nothing else: fit q and r of the linear-Gaussian model from 2x the truth on "
                             "each score (score_bias_fits.json and .md)")
    parser.add_argument("--fit-lags", type=int, nargs="+", default=[10], help="--fits: the fixed lags")
    parser.add_argument("--fit-particles", type=int, nargs="+", default=[50, 200], help="--fits: the N of each fit")
    parser.add_argument("--fit-steps", type=int, default=150, help="--fits: Adam steps")
    args = parser.parse_args(argv)
    if min(args.seeds, args.lg_steps, args.lg_particles, args.lg_keys, args.scans, args.particles,
           args.office_keys, args.ref_particles) < 1 or args.ref_keys < 2 or min(args.lags) < 0:
        parser.error("counts must be positive (--ref-keys at least 2) and lags >= 0")

    from tqdm.auto import tqdm

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.time()
    if args.fits:
        with tqdm(total=args.seeds * len(args.fit_particles) * (1 + len(args.fit_lags)), desc="fits", unit="fit") as bar:
            rows = linear_gaussian_fits(args, bar)
        seconds = time.time() - start
        (out / "score_bias_fits.json").write_text(json.dumps(
            {"args": {**vars(args), "out": "OUT/"}, "seconds": seconds, "rows": rows}, indent=1))
        text = (f"Linear-Gaussian fits of q and r from 2x the truth (T = {args.lg_steps}, resample when ESS < "
                f"{args.lg_threshold:g} N, {args.fit_steps} Adam steps of 0.05, one key per step; the mean of the "
                f"last third as a multiple of the Kalman MLE):\n\n{fits_table(rows)}\n\n{seconds:.0f} s")
        (out / "score_bias_fits.md").write_text(text + "\n")
        print(text)
        return 0
    total = args.seeds * (2 + len(args.lags)) + (0 if args.skip_office else
                                                 args.seeds * (args.office_keys + args.ref_keys))
    with tqdm(total=total, desc="score estimates", unit="batch") as bar:
        rows = linear_gaussian(args, bar)
        if not args.skip_office:
            rows += office(args, bar)
    seconds = time.time() - start
    (out / "score_bias.json").write_text(json.dumps({"args": {**vars(args), "out": "OUT/"}, "seconds": seconds, "rows": rows},
                                                    indent=1))
    text = [f"Linear-Gaussian (T = {args.lg_steps}, N = {args.lg_particles}, resample when ESS < "
            f"{args.lg_threshold:g} N, {args.lg_keys} keys per seed): bias = mean estimate - Kalman score.", "",
            summary_table(rows, "linear-Gaussian", "aqr", args.lags)]
    if not args.skip_office:
        text += ["", f"Office (OP, {args.scans} scans, N = {args.particles}, {args.office_keys} keys per seed; "
                 f"reference: the path-space score at N = {args.ref_particles}, {args.ref_keys} keys), score in "
                 f"log coordinates: bias = mean estimate - reference.", "",
                 summary_table(rows, "office", OFFICE_NAMES, args.lags), "", reference_table(rows, OFFICE_NAMES),
                 "", genealogy_table(rows)]
    text.append(f"\n{seconds:.0f} s")
    (out / "score_bias.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
