"""Learning the odometry noise and the sensor's sigma from a simulated office log with the RBPF's
log-likelihood.

The simulated office (:func:`jaxslam.sim.office_scenario`) draws its odometry with known terms
(srr 0.05, srt 0.02, str 0.05, stt 0.05 per 0.18 m step); ``--world hall`` runs everything below
on a second world instead (:func:`jaxslam.sim.hall_scenario`: an open hall with pillars, a
figure-of-eight tour, srr 0.08, srt 0.01, str 0.03, stt 0.08), so that a fit table is not the
office's doing. Every scan is an update and the
minimum stds are the simulator's (docs/design.md, "Tempering and learning"). Starting from twice
the truth, Adam (:func:`jaxslam.learning.fit`) climbs ``rbpf.filter``'s log-likelihood estimate
(score gradients through resampling; the OP's motion terms by the score of its draws) with the
bilinear likelihood and, with ``--gain 1``, the untempered likelihood. Writes the history as
JSON.

    python experiments/learn_office.py --proposal op --particles 50 --steps 80 --keys-per-step 4

Two references for what a fit can reach, both from the ground truth:

* the motion terms' *known-path optimum*: where :func:`jaxslam.motion.path_log_density` of the
  true path given the odometry peaks. The simulator takes each step's noise std at the true
  motion, the filter's model at the odometry reading, so the simulated values are not quite a
  point of the model (about 0.8x in str and 1.3x in stt on these offices);
* the sensor's sigma, which has no simulated value (the endpoint model measures the distance to
  the nearest earlier endpoint, in cells): where one noise-free particle on the true path scores
  best, on a grid from 1 mm to 0.1 m.

With ``--profile S [S ...]`` it fits nothing: it evaluates the log-likelihood estimate with
the ``--vary`` terms (default all four odometry terms together) at S times the truth, the other
odometry terms at the truth and ``likelihood.sigma`` at its known-path optimum unless varied,
over ``--seeds`` keys (mean and standard error, and the paired difference to the truth):

    python experiments/learn_office.py --proposal op --particles 50 --profile 0.5 0.75 1 1.5 2 --seeds 8
    python experiments/learn_office.py --proposal op --particles 50 --profile 0.5 0.75 1 1.5 2 --vary motion.srr

With ``--score OFFICES`` it fits nothing either: on offices 0..OFFICES-1 it prints the filter's
score at the truth (sigma at its known-path optimum) beside the known path's score of the motion
terms, whose difference is what the filter's own estimate adds:

    python experiments/learn_office.py --proposal op --particles 50 --score 5 --seeds 8
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

TERMS = ("motion.srr", "motion.srt", "motion.str", "motion.stt")


def setup_office(office: int, args) -> dict:
    """The simulated office ``jax.random.key(office)`` cut to ``--scans``, the filter set up to
    match its simulator, and the references a fit is judged against: the sensor's sigma and the
    motion terms where the model scores the *known* true path best."""
    import dataclasses

    import jax

    from jaxslam import motion, rbpf
    from jaxslam.cli import DEMO_DEFAULTS
    from jaxslam.config import build_setup, params_from_dict, params_to_dict
    from jaxslam.geometry import between
    from jaxslam.learning import LEARNING_SETTINGS, fit
    from jaxslam.sim import hall_scenario, office_scenario

    make_scenario = {"office": office_scenario, "hall": hall_scenario}[args.world]
    scenario = make_scenario(jax.random.key(office), **({} if args.range_noise is None
                                                         else {"range_noise_std": args.range_noise}))
    log = scenario.log.subset(np.arange(min(args.scans, scenario.log.num_scans)))
    truth = {f"motion.{k}": float(v) for k, v in scenario.metadata["motion_params"]._asdict().items()}
    range_noise = float(scenario.metadata["range_noise_std"])
    # The filter's motion model must be the simulator's for the truth to be a point of it: the
    # simulator draws each scan's odometry noise with stds linear in that one step, plus
    # minimum stds of 1 mm and 1 mrad. So every scan is an update (over several steps the noise
    # composes as a random walk, std ~ sqrt(steps), which no linear model matches), and the
    # minimum stds are the simulator's (the library's defaults, 1 cm and 5 mrad, are not learned).
    minimum_stds = {name: truth[name] for name in ("motion.min_translation_std", "motion.min_rotation_std")}
    # learning.LEARNING_SETTINGS over the demo's office settings (its 10 m laser, every beam).
    config, settings, params = build_setup({**DEMO_DEFAULTS, **LEARNING_SETTINGS, "proposal": args.proposal,
                                            "num_particles": args.particles, "likelihood.gain": args.gain,
                                            **minimum_stds})
    if args.resolution != config.resolution:  # the same field radius in metres (at most 11 cells)
        radius = int(min(11, max(1, round(config.field_radius * config.resolution / args.resolution))))
        config = dataclasses.replace(config, resolution=args.resolution, map_extent=64.0, field_radius=radius)
    # The sensor's sigma has no simulated value: the endpoint model's distance is to the nearest
    # earlier endpoint, in cells, not to the wall. Its truth is the model's own: where the
    # log-likelihood of one noise-free particle on the true path peaks.
    sigma_grid = np.geomspace(0.001, 0.1, 41)  # from far below a cell to twice the widest cell used
    true_path = dataclasses.replace(log, odometry=np.asarray(log.ground_truth, log.odometry.dtype))
    known_path_loglik = rbpf.known_path_loglik_fn(true_path, config, settings)
    profile = np.array([float(known_path_loglik(params_from_dict({**params_to_dict(params), "likelihood.sigma": s})))
                        for s in sigma_grid])
    best = int(np.argmax(profile))
    truth["likelihood.sigma"] = float(sigma_grid[best])
    identified = 0 < best < sigma_grid.size - 1
    print(f"{args.world} {office}: likelihood.sigma on the true path: peak at {sigma_grid[best]:.4f} m "
          f"({args.resolution:g} m cells; range noise {range_noise:g} m)"
          + ("" if identified else ": at the end of the grid, not identified"))
    # The motion model's own optimum on this log: the simulator takes each step's std at the true
    # motion, the filter's model at the odometry reading, so the simulated terms need not be the
    # model's best; the known path (odometry against ground truth) says where it is.
    path = jax.numpy.asarray(log.ground_truth, jax.numpy.float32)
    odometry = jax.numpy.asarray(log.odometry, jax.numpy.float32)
    motions = between(odometry[:-1], odometry[1:])
    at_truth = params_from_dict({**params_to_dict(params), **{n: truth[n] for n in TERMS}})
    best_fit = fit(jax.random.key(0), lambda _, p: motion.path_log_density(path, motions, p.motion), at_truth,
                   num_steps=600, learning_rate=0.01, trainable=list(TERMS), progress=False)
    known_path_motion = {n: float(np.mean(best_fit.history[n][-200:])) for n in TERMS}
    print(f"{args.world} {office}: motion terms' known-path optimum / simulated: "
          + ", ".join(f"{n.split('.')[1]} {known_path_motion[n] / truth[n]:.2f}" for n in TERMS))
    prepared, _, frame_offset = rbpf.prepare(log, config, settings)
    record = {"range_noise_std": range_noise, "sigma_identified": identified,
              "true_path_sigma_profile": {"sigma": sigma_grid.tolist(), "log_likelihood": profile.tolist()},
              "known_path_motion_optimum": known_path_motion}
    return {"log": log, "truth": truth, "config": config, "params": params, "prepared": prepared,
            "record": record, "known_path_motion": known_path_motion, "path": path, "motions": motions,
            "frame_offset": np.asarray(frame_offset, np.float64)}


def score_at_truth(args) -> int:
    """``--score OFFICES``: on offices 0..OFFICES-1, the filter's score at the simulated terms (d log p
    / d log term; mean and standard error over ``--seeds`` keys) beside the known path's (the
    motion model's log-density of the true path: what the filter's score estimates when the scans
    pin the path). Their difference is what the filter's own estimate adds."""
    import jax

    from jaxslam import motion, rbpf
    from jaxslam.config import params_from_dict, params_to_dict
    from jaxslam.geometry import between_np, wrap_angle_np
    from jaxslam.learning import param_names
    from jaxslam.metrics import normalized_weights

    names = list(TERMS) + ["likelihood.sigma"]  # the sensor's sigma at its known-path optimum too
    rows, filter_score = [], None
    for office in range(args.score):
        setup = setup_office(office, args)
        truth, prepared, config = setup["truth"], setup["prepared"], setup["config"]
        base = params_from_dict({**params_to_dict(setup["params"]), **{n: truth[n] for n in names}})
        position = [param_names(base).index(n) for n in names]

        def at(log_values, base):  # ``base`` with the named terms at exp(log_values), traceable
            leaves, treedef = jax.tree.flatten(base)
            for i, j in enumerate(position):
                leaves[j] = jax.numpy.exp(log_values[i]).astype(leaves[j].dtype)
            return jax.tree.unflatten(treedef, leaves)

        if filter_score is None:  # compiled once: every office's log has the same length and config
            def loglik(k, x, base, prepared):  # the estimate, and what the residuals need
                out = rbpf.filter(k, prepared, at(x, base), config)
                return out.marginal_loglik, (out.info.proposed_poses, out.info.ancestors, out.state.log_weights)

            filter_score = jax.jit(jax.grad(loglik, argnums=1, has_aux=True))
        log_truth = jax.numpy.log(jax.numpy.array([truth[n] for n in names]))
        known_score = np.asarray(jax.grad(lambda x: motion.path_log_density(setup["path"], setup["motions"],
                                                                             at(x, base).motion))(log_truth))
        # Where the filter puts the motion: each standardised residual's mean square (1 = the
        # model's own width) along the final particles' ancestral paths, weighted by the final
        # weights, against the true path's, on straight and on turning steps.
        motions = np.asarray(setup["motions"], np.float64)
        std = np.asarray(motion.noise_std(setup["motions"], base.motion), np.float64)
        turning = np.abs(motions[:, 2]) > 0.02

        def residual_squares(paths):  # (..., T, 3) -> (..., T-1, 3), in any one frame
            residual = between_np(paths[..., :-1, :], paths[..., 1:, :]) - motions
            residual[..., 2] = wrap_angle_np(residual[..., 2])
            return (residual / std) ** 2

        # The filter runs in its local frame (rbpf.prepare): its first pose is the log's first
        # odometry pose shifted by the frame offset.
        start = np.asarray(setup["log"].odometry[0], np.float64) - np.append(setup["frame_offset"], 0.0)
        scores, along_filter = [], []
        for k in jax.random.split(jax.random.key(5), args.seeds):
            grads, (proposed, ancestors, log_weights) = filter_score(k, log_truth, base, prepared)
            scores.append(np.asarray(grads))
            paths = rbpf.particle_paths(proposed, ancestors, start)[:, -motions.shape[0] - 1:]
            along_filter.append(np.einsum("n,nsc->sc", normalized_weights(log_weights), residual_squares(paths)))
        scores, along_filter = np.array(scores), np.mean(along_filter, axis=0)
        along_truth = residual_squares(np.asarray(setup["log"].ground_truth, np.float64))
        squares = {f"{which}_{kind}": z[mask].mean(axis=0).tolist()
                   for which, z in (("filter", along_filter), ("true_path", along_truth))
                   for kind, mask in (("straight", ~turning), ("turning", turning))}
        mean, se = scores.mean(0), scores.std(0, ddof=1) / np.sqrt(scores.shape[0])
        rows.append({"office": office, "names": names, "filter_score": scores.tolist(),
                     "known_path_score": known_score.tolist(), "known_path_motion_optimum": setup["known_path_motion"],
                     "residual_mean_squares": squares})
        for i, n in enumerate(names):
            known = f"{known_score[i]:+.1f}" if n in TERMS else "-"
            print(f"office {office} {n}: filter {mean[i]:+.1f} ± {se[i]:.1f}, known path {known}", flush=True)
        for key, value in squares.items():
            print(f"office {office} residual mean squares (x, y, theta), {key}: {np.round(value, 2).tolist()}")
    filt = np.array([np.mean(r["filter_score"], axis=0) for r in rows])
    known = np.array([r["known_path_score"] for r in rows])
    for i, n in enumerate(names[:4]):
        diff = filt[:, i] - known[:, i]
        se = diff.std(ddof=1) / np.sqrt(diff.size) if diff.size > 1 else float("nan")
        print(f"{n}: filter {filt[:, i].mean():+.1f}, known path {known[:, i].mean():+.1f}, "
              f"filter - known path {diff.mean():+.1f} ± {se:.1f} over {diff.size} offices")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"args": vars(args), "offices": rows}, indent=2))
    return 0


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
    parser.add_argument("--keys-per-step", type=int, default=1,
                        help="fit: runs averaged per Adam step (each with its own key)")
    parser.add_argument("--seeds", type=int, default=4, help="--profile: keys per scale")
    parser.add_argument("--vary", nargs="+", default=list(TERMS), choices=list(TERMS) + ["likelihood.sigma"],
                        help="--profile: the terms scaled together (the others stay at the truth)")
    parser.add_argument("--trainable", nargs="+", default=list(TERMS) + ["likelihood.sigma"],
                        choices=list(TERMS) + ["likelihood.sigma"],
                        help="the fitted terms, each started at --start-scale times its truth")
    parser.add_argument("--resolution", type=float, default=0.05,
                        help="map cells (m)")
    parser.add_argument("--range-noise", type=float, help="the simulated laser's range noise std (m; default "
                        "the office's 0.02): with less, the map's walls are thinner")
    parser.add_argument("--score", type=int, metavar="OFFICES",
                        help="fit nothing: the score at the simulated terms on offices 0..OFFICES-1, "
                             "over --seeds keys, "
                             "beside the known path's")
    parser.add_argument("--world", default="office", choices=["office", "hall"],
                        help="the simulated world: the office (jaxslam.sim.office_scenario) or the hall, a second "
                             "world with other odometry terms (jaxslam.sim.hall_scenario)")
    parser.add_argument("--out", default="results/learn_office.json")
    args = parser.parse_args(argv)
    if min(args.particles, args.scans, args.steps, args.keys_per_step, args.seeds) < 1:
        parser.error("--particles, --scans, --steps, --keys-per-step and --seeds must be positive")
    if not args.resolution > 0:
        parser.error("--resolution must be positive (m)")
    if args.range_noise is not None and not args.range_noise >= 0:
        parser.error("--range-noise must be a std >= 0 (m)")
    if args.score is not None and args.score < 1:
        parser.error("--score needs at least one office")

    import jax

    from jaxslam import rbpf
    from jaxslam.config import params_from_dict, params_to_dict
    from jaxslam.learning import fit

    if args.score:
        return score_at_truth(args)
    office = setup_office(0, args)
    truth, config, params, prepared = office["truth"], office["config"], office["params"], office["prepared"]
    start = {name: args.start_scale * truth[name] for name in args.trainable}
    params = params_from_dict({**params_to_dict(params), **start})
    sigma_record = office["record"]

    def objective(key, p):
        # The mean over --keys-per-step independent runs: a less noisy gradient per Adam step.
        keys = jax.random.split(key, args.keys_per_step)
        return jax.vmap(lambda k: rbpf.filter(k, prepared, p, config).marginal_loglik)(keys).mean()

    if args.profile:
        evaluate = jax.jit(jax.vmap(lambda k, p: rbpf.filter(k, prepared, p, config).marginal_loglik,
                                    in_axes=(0, None)))
        keys = jax.random.split(jax.random.key(5), args.seeds)
        rows = []
        at_truth = {n: truth[n] for n in TERMS + ("likelihood.sigma",)}
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
                                              **sigma_record, "profile": rows}, indent=2))
        return 0

    result = fit(jax.random.key(1), objective, params, num_steps=args.steps, learning_rate=args.learning_rate,
                 trainable=args.trainable)
    final = {name: float(result.history[name][-1]) for name in args.trainable}
    tail = max(1, args.steps // 4)  # Adam's iterates jitter about the maximum: average the last quarter
    learned = {name: float(np.mean(result.history[name][-tail:])) for name in args.trainable}
    record = {"args": vars(args), "truth": {k: truth[k] for k in args.trainable}, **sigma_record,
              "start": start, "final": final,
              "learned_tail_mean": learned, "history": {k: v.tolist() for k, v in result.history.items()}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=2))
    for name in args.trainable:
        optimum = office["known_path_motion"].get(name)
        against = f", {learned[name] / optimum:.2f} x the known path's optimum" if optimum else ""
        print(f"{name}: truth {truth[name]:.4f}, start {start[name]:.4f}, learned {learned[name]:.4f} "
              f"({learned[name] / truth[name]:.2f} x truth{against}; last step {final[name]:.4f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
