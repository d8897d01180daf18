"""The low-structure box-world experiment of Grzonka et al. (Figs. 4 and 5).

The robot starts at checkpoint X, circles box 2 fifteen times (passing over X after
every fifth lap) and returns over X (:func:`jaxslam.sim.box_world_scenario`). For each
proposal and SLAM particle count we run R independent simulated runs (seed r draws the
odometry and range noise of run r and the filter's randomness) and score each by the
revisiting accuracy RA between the first and the last passage over X
(:func:`jaxslam.metrics.revisiting_accuracy`); a run with RA < 0.2 counts as a success.

Proposals: OP, SMP, and the look-ahead LP with L = 100 localizers and k = 5 once as
in the paper (alpha = 0, Eq. 10) and once with the defensive share ``--alpha``, plus
LP with L = 50, k = 3 (defensive); ``--lp-sm`` adds the LP with scan-matched localizers,
``--evidence-weights`` the LPs without the selection correction (label "c=0",
``lookahead.selection_correction = 0``).
Particle counts 20 and 50. Every method uses the package's default parameters except the
update rule (a scan every 0.5 m or 0.25 rad: the box world's scans are 0.1 m apart) and the
odometry noise, which is the simulator's, matched to that rule (:data:`MOTION_SCALE`);
``--set NAME=VALUE`` overrides any parameter for all methods; ``--localizers L`` and
``--horizon K`` resize every LP row (the labels follow), and ``--seeds S ...`` runs exactly
those seeds instead of ``--first-seed`` .. ``--first-seed + --runs - 1``.

Writes ``DIR/results.json`` after every run (resumable: finished cells are skipped,
a half-finished cell resumes at its next run), ``DIR/fig5.png`` (mean +- std of RA
and success rate against N, like the paper's Fig. 5), ``DIR/maps/*.npz`` and
``DIR/examples.png`` (the best particle's map and path, first run of each cell, like
Fig. 4), ``DIR/failures.png`` (the same for the worst failed run of each method), and
``DIR/ra_distribution.png``.

    python experiments/box_world.py --runs 30 --out results/box_world [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

from jaxslam import rbpf
from jaxslam.cli import parse_assignments
from jaxslam.config import SlamConfig, default_params, params_to_dict
from jaxslam.geometry import wrap_angle_np
from jaxslam.grid import GridSpec
from jaxslam.metrics import checkpoint_passages, passage_errors, revisiting_accuracy
from jaxslam.rbpf import particle_paths
from jaxslam.sim import box_world_scenario
from jaxslam.sim.scenarios import BOX_WORLD_MOTION

SUCCESS_RA = 0.2
"""RA (m) under which a run counts as a success (the paper's threshold)."""

MOTION_SCALE = 0.45
"""Default scale of the filter's odometry-noise coefficients against the simulator's.
The simulator draws independent noise for every 0.1 m step, so over the about 5 steps
between processed scans (0.5 m, or 0.25 rad on the circle) the true error std grows as
sqrt(5) times a step's, while GMapping's model, linear in the composed motion, grows as 5
times: 1 / sqrt(5) = 0.45 matches the two. With scale 1 the filter spreads its particles
2.2 times wider than the odometry errs."""


@dataclasses.dataclass(frozen=True)
class Method:
    label: str
    proposal: str
    num_localizers: int = 0
    horizon: int = 0
    alpha: float = 0.0
    initial: str = "odometry"
    selection_correction: float = 1.0


def methods(alpha: float, lp_sm: bool = False, evidence_weights: bool = False) -> list[Method]:
    out = [
        Method("OP", "op"),
        Method("SMP", "smp"),
        Method("LP a=0 L=100 k=5", "lp", 100, 5, 0.0),
        Method(f"LP a={alpha:g} L=100 k=5", "lp", 100, 5, alpha),
        Method(f"LP a={alpha:g} L=50 k=3", "lp", 50, 3, alpha),
    ]
    if lp_sm:  # not in the paper: localizers drawn around the scan-matched pose (importance-corrected)
        out.append(Method(f"LP-SM a={alpha:g} L=100 k=5", "lp", 100, 5, alpha, "scan_match"))
    if evidence_weights:  # lookahead.selection_correction = 0: the SLAM weight is the evidence estimate alone
        out.append(Method(f"LP a={alpha:g} c=0 L=100 k=5", "lp", 100, 5, alpha, selection_correction=0.0))
        if lp_sm:
            out.append(Method(f"LP-SM a={alpha:g} c=0 L=100 k=5", "lp", 100, 5, alpha, "scan_match", 0.0))
    return out


def _capped(method: Method, max_localizers: int, max_horizon: int) -> Method:
    """``--quick``: at most this many localizers and horizon steps; the label says what runs."""
    return _resized(method, min(method.num_localizers, max_localizers), min(method.horizon, max_horizon))


def _resized(method: Method, num: int, horizon: int) -> Method:
    """The LP ``method`` with ``num`` localizers and horizon ``horizon``; the label says what runs."""
    if method.proposal != "lp":
        return method
    label = method.label.replace(f"L={method.num_localizers} k={method.horizon}", f"L={num} k={horizon}")
    return dataclasses.replace(method, label=label, num_localizers=num, horizon=horizon)


def cell_key(method: Method, n: int) -> str:
    return f"{method.label} | N={n}"


def filter_setup(method: Method, n: int, scenario, args):
    """The filter's config and params for one cell. The motion model is the simulator's,
    its proportional terms scaled by ``--motion-scale`` (see :data:`MOTION_SCALE`)."""
    # One fixed grid for every run (the world's bounds plus a margin for drifting
    # estimates), so that the filter compiles once per cell, not once per run.
    xmin, ymin, xmax, ymax = scenario.world.bounds
    margin = 6.0
    grid = GridSpec.from_bounds(xmin - margin, ymin - margin, xmax + margin, ymax + margin, 0.05)
    config = SlamConfig(
        num_particles=n, proposal=method.proposal, grid=grid,
        max_insert_range=scenario.log.sensor.range_max.item() + 0.5, beam_stride=args.beam_stride,
        linear_update=args.linear_update, angular_update=args.angular_update,
        num_localizers=max(method.num_localizers, 1), horizon=method.horizon,
        lookahead_initial=method.initial, likelihood_field=args.likelihood_field,
        lookahead_weight=args.lookahead_weight,
        match_lookup=args.match_lookup,  # the tables were measured with "nearest", the default here
    )
    noise = scaled_noise(scenario.metadata["motion_params"], args.motion_scale)
    overrides = {f"motion.{name}": value for name, value in noise.items()}
    overrides["lookahead.alpha"] = method.alpha
    overrides["lookahead.selection_correction"] = method.selection_correction
    overrides.update(parse_assignments(args.set or []))
    return config, default_params(**overrides)


def scaled_noise(motion, scale: float) -> dict[str, float]:
    """The fields of ``motion`` (MotionParams) as floats, the proportional terms (srr, srt, str,
    stt) times ``scale``; the floors (minimum stds) stay."""
    values = {name: float(getattr(motion, name)) for name in motion._fields}
    for name in ("srr", "srt", "str", "stt"):
        values[name] *= scale
    return values


def run_once(method: Method, n: int, seed: int, args, scenario_kwargs):
    if args.world_odometry_scale != 1.0:
        noise = scaled_noise(BOX_WORLD_MOTION, args.world_odometry_scale)
        world_motion = BOX_WORLD_MOTION._replace(**{k: np.float32(v) for k, v in noise.items()})
        scenario_kwargs = {**scenario_kwargs, "motion": world_motion}
    scenario = box_world_scenario(jax.random.key(seed), **scenario_kwargs)
    config, params = filter_setup(method, n, scenario, args)
    t0 = time.perf_counter()
    result = rbpf.run(jax.random.key(10_000 + seed), scenario.log, config, params, progress=args.progress)
    seconds = time.perf_counter() - t0
    truth = scenario.true_poses
    passages = scenario.metadata.get("x_passages")
    if passages is None or len(passages) < 2:
        passages = checkpoint_passages(truth, scenario.metadata["checkpoint_x"], 0.3)
    idx = result.selection.indices
    # The processed scans nearest to the first and last passage; RA compares the relative
    # pose between them with the true one at the same scans.
    first = int(np.argmin(np.abs(idx - passages[0])))
    last = int(np.argmin(np.abs(idx - passages[-1])))
    paths = particle_paths(result.info.proposed_poses, result.info.ancestors, scenario.log.odometry[0])
    log_w = np.asarray(result.state.log_weights)
    ra = revisiting_accuracy(paths, log_w, first, last, truth[idx[first]], truth[idx[last]], args.rotation_weight)
    errors = passage_errors(paths, first, last, truth[idx[first]], truth[idx[last]], args.rotation_weight)
    best = int(np.argmax(log_w))
    # RA's two parts: RA is linear in lambda, so lambda = 0 gives the position part (m) and the
    # rest divided by lambda the heading part (rad).
    ra_position = revisiting_accuracy(paths, log_w, first, last, truth[idx[first]], truth[idx[last]], 0.0)
    run = {
        "seed": seed, "ra": ra, "best_particle_error": float(errors[best]), "seconds": seconds,
        "ra_position": ra_position,
        "ra_heading": (ra - ra_position) / args.rotation_weight if args.rotation_weight else None,
        **frame_diagnostics(result, scenario, passages),
        "num_steps": int(idx.size - 1), "num_fallbacks": int(result.info.num_fallbacks.sum()),
        "num_degenerate": int(result.info.degenerate.sum()), "num_resamplings": int(result.info.resampled.sum()),
        "min_ess": float(result.info.ess.min()),
    }
    return run, result, scenario


def frame_diagnostics(result, scenario, passages) -> dict:
    """Where a run's error comes from: box 2's frame, and how many hypotheses of it survive.

    While the robot circles box 2 only box 2 is in view, so each particle's pose there is
    right relative to its own map of box 2, and its error against the truth is the error of
    that map's frame, fixed when box 2 was first mapped after the blind drive from the hedge.
    At the end of the first lap (index ``lap1``):

    - ``frame_error_lap1`` (m): the best final particle's position error there;
    - ``cloud_error_lap1_min`` / ``_median`` (m): the same over the particles alive then, so
      whether the filter held a hypothesis close to the truth at all;
    - ``lineages_from_lap1``: how many distinct particles at lap 1 are ancestors of the
      particles alive at the end of laps 5, 10 and 15 and at the end (path coalescence);
    - ``odometry_heading_error_x1`` (rad): the odometry's heading error between the start and
      the first return over X, the blind U-turn at the turnaround included.
    """
    idx = result.selection.indices
    truth = scenario.true_poses[idx]
    laps = scenario.metadata.get("lap_end_indices")
    if laps is None or len(laps) == 0 or len(passages) < 2:
        return {}

    def nearest(scan):  # the processed scan nearest to a raw scan index
        return int(np.argmin(np.abs(idx - scan)))

    lap1 = nearest(laps[0])
    proposed, ancestors = np.asarray(result.info.proposed_poses), np.asarray(result.info.ancestors)
    start = scenario.log.odometry[0]

    def alive_at_lap1(step):  # the path index lap1 of the particles alive after ``step``
        return particle_paths(proposed[:step], ancestors[:step], start)[:, lap1]

    cloud = np.hypot(*(alive_at_lap1(lap1)[:, :2] - truth[lap1, :2]).T)
    checkpoints = {f"lap{k}": nearest(laps[k - 1]) for k in (5, 10, 15) if k <= len(laps)}
    checkpoints["end"] = len(idx) - 1
    lineages = {name: int(np.unique(alive_at_lap1(step), axis=0).shape[0]) for name, step in checkpoints.items()}
    odometry, true_poses = np.asarray(scenario.log.odometry), scenario.true_poses
    x1 = int(passages[1])

    def turned(poses):  # heading change from the start to the first return over X
        return poses[x1, 2] - poses[0, 2]

    return {
        "frame_error_lap1": float(np.hypot(*(result.best_path[lap1, :2] - truth[lap1, :2]))),
        "cloud_error_lap1_min": float(cloud.min()), "cloud_error_lap1_median": float(np.median(cloud)),
        "lineages_from_lap1": lineages,
        "odometry_heading_error_x1": float(np.abs(wrap_angle_np(turned(odometry) - turned(true_poses)))),
    }


def save_example(path: Path, result, scenario, ra: float):
    best = int(np.argmax(np.asarray(result.state.log_weights)))
    spec = result.config.grid
    np.savez_compressed(
        path, logodds=np.asarray(result.state.maps.logodds[best]), best_path=result.best_path,
        truth=scenario.true_poses[result.selection.indices], odometry=scenario.log.odometry[result.selection.indices],
        segments=scenario.world.segments, extent=np.asarray(spec.extent), ra=ra,
    )


def load_results(path: Path) -> dict:
    if path.exists():
        return json.loads(path.read_text())
    return {"cells": {}}


def write_json(path: Path, data: dict):
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(path)  # atomic: an interrupted write never leaves a broken results.json


def summarize_cell(runs: list[dict]) -> dict:
    ra = np.array([r["ra"] for r in runs])
    return {"mean": float(ra.mean()), "std": float(ra.std(ddof=1)) if ra.size > 1 else 0.0,
            "median": float(np.median(ra)), "success_rate": float(np.mean(ra < SUCCESS_RA)),
            "num_runs": int(ra.size)}


def make_figures(out: Path, data: dict):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = data["cells"]
    order = list(data.get("method_order", []))
    labels = sorted({c["method"] for c in cells.values()}, key=lambda s: (order.index(s) if s in order else len(order), s))
    fig, (ax_ra, ax_sr) = plt.subplots(1, 2, figsize=(11, 4))
    for i, label in enumerate(labels):
        rows = sorted((c for c in cells.values() if c["method"] == label and c["runs"]), key=lambda c: c["N"])
        if not rows:
            continue
        ns = np.array([c["N"] for c in rows]) * (1 + 0.03 * (i - len(labels) / 2))  # dodge the error bars
        stats = [summarize_cell(c["runs"]) for c in rows]
        ax_ra.errorbar(ns, [s["mean"] for s in stats], yerr=[s["std"] for s in stats], marker="o", capsize=3,
                       label=label)
        ax_sr.plot([c["N"] for c in rows], [s["success_rate"] for s in stats], marker="o", label=label)
    ax_ra.set_xlabel("SLAM particles N")
    ax_ra.set_ylabel("revisiting accuracy RA (mean +- std)")
    ax_ra.axhline(SUCCESS_RA, color="k", lw=0.5, ls=":")
    ax_sr.set_xlabel("SLAM particles N")
    ax_sr.set_ylabel(f"success rate (RA < {SUCCESS_RA})")
    ax_sr.set_ylim(-0.05, 1.05)
    ax_sr.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "fig5.png", dpi=120)
    plt.close(fig)

    # RA distribution of every cell.
    keys = [k for k in cells if cells[k]["runs"]]
    if keys:
        fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(keys)), 4))
        ax.boxplot([[r["ra"] for r in cells[k]["runs"]] for k in keys], showfliers=True)
        for j, k in enumerate(keys):
            ra = [r["ra"] for r in cells[k]["runs"]]
            ax.scatter(np.full(len(ra), j + 1) + np.random.default_rng(j).uniform(-0.15, 0.15, len(ra)), ra, s=6)
        ax.set_xticks(range(1, len(keys) + 1), [k.replace(" | ", "\n") for k in keys], fontsize=7)
        ax.set_yscale("log")
        ax.axhline(SUCCESS_RA, color="k", lw=0.5, ls=":")
        ax.set_ylabel("RA per run")
        fig.tight_layout()
        fig.savefig(out / "ra_distribution.png", dpi=120)
        plt.close(fig)

    # Example maps (first run of each method at the largest N available), like Fig. 4, and the
    # worst failed run of each method (the true world drawn over the map shows which part of
    # the map is off: box 2's frame against the hedge's).
    for key, name in (("example", "examples.png"), ("worst_example", "failures.png")):
        shown = []
        for label in labels:
            rows = sorted((c for c in cells.values() if c["method"] == label and c.get(key)), key=lambda c: -c["N"])
            if rows:
                shown.append((label, rows[0]))
        if not shown:
            continue
        fig, axes = plt.subplots(1, len(shown), figsize=(4.2 * len(shown), 3.4), squeeze=False)
        for ax, (label, cell) in zip(axes[0], shown):
            ex = np.load(out / cell[key])
            prob = 1.0 / (1.0 + np.exp(-ex["logodds"]))
            ax.imshow(prob, origin="lower", extent=tuple(ex["extent"]), cmap="gray_r", vmin=0, vmax=1)
            for seg in ex["segments"]:
                ax.plot(seg[[0, 2]], seg[[1, 3]], color="tab:blue", lw=0.6)
            ax.plot(ex["truth"][:, 0], ex["truth"][:, 1], color="tab:green", lw=0.6, label="truth")
            ax.plot(ex["best_path"][:, 0], ex["best_path"][:, 1], color="tab:red", lw=0.6, label="best particle")
            ax.set_title(f"{label}, N={cell['N']}\nRA = {float(ex['ra']):.3f}", fontsize=8)
            xs, ys = ex["segments"][:, [0, 2]], ex["segments"][:, [1, 3]]
            ax.set_xlim(xs.min() - 2.5, xs.max() + 2.5)  # the world and the circle round box 2
            ax.set_ylim(ys.min() - 2.5, ys.max() + 2.5)
            ax.set_aspect("equal")
        axes[0][0].plot([], [], color="tab:blue", lw=0.6, label="true world")
        axes[0][0].legend(fontsize=7, loc="upper right")
        fig.tight_layout()
        fig.savefig(out / name, dpi=120)
        plt.close(fig)


def print_table(data: dict):
    print(f"{'method':24s} {'N':>3s} {'runs':>4s} {'RA mean':>8s} {'RA std':>8s} {'median':>8s} {'success':>8s}")
    for key, cell in data["cells"].items():
        if not cell["runs"]:
            continue
        s = summarize_cell(cell["runs"])
        print(f"{cell['method']:24s} {cell['N']:3d} {s['num_runs']:4d} {s['mean']:8.3f} {s['std']:8.3f} "
              f"{s['median']:8.3f} {s['success_rate']:8.2f}{'' if cell.get('complete') else '  (partial)'}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=30, help="independent runs per (proposal, N) cell")
    ap.add_argument("--out", default="results/box_world")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="seeds first-seed .. first-seed + runs - 1 (tune on seeds the reported table does not use)")
    ap.add_argument("--seeds", type=int, nargs="+", default=None,
                    help="run exactly these seeds (instead of --first-seed .. + --runs)")
    ap.add_argument("--localizers", type=int, default=None,
                    help="localizers per SLAM particle in every LP row (relabels the rows 'L=...')")
    ap.add_argument("--horizon", type=int, default=None,
                    help="look-ahead steps k in every LP row (relabels the rows 'k=...')")
    ap.add_argument("--quick", action="store_true", help="3 laps, N in (4, 8), L = 20: a smoke test in minutes")
    ap.add_argument("--particles", type=int, nargs="+", default=None, help="SLAM particle counts (default 20 50)")
    ap.add_argument("--alpha", type=float, default=0.5, help="defensive share of the defensive LP")
    ap.add_argument("--only", nargs="*", default=None, help="run only methods whose label contains one of these")
    ap.add_argument("--rotation-weight", type=float, default=1.0, help="lambda of RA (m/rad)")
    ap.add_argument("--beam-stride", type=int, default=2, help="use every k-th of the 180 beams in likelihoods")
    ap.add_argument("--linear-update", type=float, default=0.5, help="process a scan after this travel (m)")
    ap.add_argument("--angular-update", type=float, default=0.25, help="... or this rotation (rad)")
    ap.add_argument("--motion-scale", type=float, default=MOTION_SCALE,
                    help="scale the filter's proportional odometry-noise coefficients (1: the simulator's "
                         "per-step values applied to the composed motion)")
    ap.add_argument("--set", action="append", metavar="NAME=VALUE",
                    help="override a filter parameter for every method (dotted name, e.g. likelihood.gain=0.2)")
    ap.add_argument("--lp-sm", action="store_true",
                    help="also run the LP with scan-matched localizers (LP-SM, not in the paper)")
    ap.add_argument("--evidence-weights", action="store_true",
                    help="also run the LPs with lookahead.selection_correction = 0 (label 'c=0'): the SLAM "
                         "weight is the evidence estimate alone, the look-ahead only picks the pose")
    ap.add_argument("--fov-deg", type=float, default=None,
                    help="the laser's field of view (degrees; default the scenario's 180), one beam per degree")
    ap.add_argument("--likelihood-field", choices=("endpoints", "occupied"), default="endpoints",
                    help="what the likelihood field measures distances to (SlamConfig.likelihood_field)")
    ap.add_argument("--lookahead-weight", choices=("filter", "lookahead"), default="filter",
                    help="the LPs' SLAM weight (SlamConfig.lookahead_weight): 'lookahead' weighs each "
                         "particle by the k scans ahead too (block sampling)")
    ap.add_argument("--match-lookup", choices=("nearest", "bilinear"), default="nearest",
                    help="how the scan matcher (SMP, LP-SM) reads the likelihood field; the tables use nearest")
    ap.add_argument("--uturn", choices=("left", "right"), default="left",
                    help="way round for the turns on the spot at the turnaround point: left (through "
                         "south, blind for part of the turn) or right (facing the hedge)")
    ap.add_argument("--world-odometry-scale", type=float, default=1.0,
                    help="scale the simulated robot's odometry noise (its proportional terms; the "
                         "filter's model follows it): < 1 is a robot with better odometry")
    ap.add_argument("--progress", action="store_true", help="a tqdm bar per filter run too")
    args = ap.parse_args(argv)

    out = Path(args.out)
    (out / "maps").mkdir(parents=True, exist_ok=True)
    scenario_kwargs = {}
    particle_counts = args.particles or [20, 50]
    method_list = methods(args.alpha, args.lp_sm, args.evidence_weights)
    if args.fov_deg is not None:
        scenario_kwargs = dict(field_of_view=float(np.radians(args.fov_deg)), num_beams=int(round(args.fov_deg)))
    if args.uturn != "left":
        scenario_kwargs["uturn"] = args.uturn
    if args.quick:
        scenario_kwargs.update(laps=3, laps_per_visit=3)
        particle_counts = args.particles or [4, 8]
        method_list = [_capped(m, 20, 3) for m in method_list]
    if not args.world_odometry_scale > 0:
        ap.error("--world-odometry-scale must be > 0")
    if args.localizers is not None and args.localizers < 1:
        ap.error("--localizers must be at least 1")
    if args.horizon is not None and args.horizon < 0:
        ap.error("--horizon must be at least 0")
    if args.localizers is not None or args.horizon is not None:
        resized = [_resized(m, args.localizers or m.num_localizers,
                            m.horizon if args.horizon is None else args.horizon) for m in method_list]
        # Two rows can become one (e.g. "L=50 k=3" resized to L=100, k=5): keep each label once.
        method_list = list({m.label: m for m in resized}.values())
    if args.only:
        method_list = [m for m in method_list if any(s in m.label for s in args.only)]

    path = out / "results.json"
    data = load_results(path)
    data["settings"] = {"runs": args.runs, "first_seed": args.first_seed, "seeds": args.seeds,
                        "localizers": args.localizers, "horizon": args.horizon, "quick": args.quick, "scenario": scenario_kwargs,
                        "alpha": args.alpha, "rotation_weight": args.rotation_weight,
                        "beam_stride": args.beam_stride, "linear_update": args.linear_update,
                        "angular_update": args.angular_update, "motion_scale": args.motion_scale,
                        "world_odometry_scale": args.world_odometry_scale,
                        "likelihood_field": args.likelihood_field, "match_lookup": args.match_lookup,
                        "lookahead_weight": args.lookahead_weight,
                        "set": args.set or [],
                        "success_ra": SUCCESS_RA}
    known = list(data.get("method_order", []))
    data["method_order"] = known + [m.label for m in methods(args.alpha, True, True) if m.label not in known]

    from tqdm.auto import tqdm

    cells = [(m, n) for n in particle_counts for m in method_list]
    seeds = list(dict.fromkeys(args.seeds)) if args.seeds else list(range(args.first_seed, args.first_seed + args.runs))
    for method, n in cells:
        key = cell_key(method, n)
        cell = data["cells"].setdefault(key, {"method": method.label, "N": n, "runs": []})
        cell.update({"proposal": method.proposal, "num_localizers": method.num_localizers,
                     "horizon": method.horizon, "alpha": method.alpha})
        done = {r["seed"] for r in cell["runs"]}
        if done.issuperset(seeds):
            cell["complete"] = True
            continue
        bar = tqdm(seeds, desc=key, unit="run", file=sys.stdout)
        bar.update(sum(seed in done for seed in seeds))
        for seed in seeds:
            if seed in done:
                continue
            run, result, scenario = run_once(method, n, seed, args, scenario_kwargs)
            cell["runs"].append(run)
            done.add(seed)
            if "params" not in cell:
                cell["params"] = params_to_dict(result_params(method, n, scenario, args))
            if seed == seeds[0] or "example" not in cell:
                name = f"maps/{method.label.replace(' ', '_').replace('=', '')}_N{n}_seed{seed}.npz"
                save_example(out / name, result, scenario, run["ra"])
                cell["example"] = name
            worst = max(cell["runs"], key=lambda r: r["ra"])
            if worst["seed"] == seed and run["ra"] >= SUCCESS_RA:
                name = f"maps/{method.label.replace(' ', '_').replace('=', '')}_N{n}_worst.npz"
                save_example(out / name, result, scenario, run["ra"])
                cell["worst_example"] = name
            cell["summary"] = summarize_cell(cell["runs"])
            cell["complete"] = done.issuperset(seeds)
            write_json(path, data)
            bar.set_postfix(ra=f"{run['ra']:.3f}", s=f"{run['seconds']:.0f}")
            bar.update(1)
        bar.close()
        cell["summary"] = summarize_cell(cell["runs"])
        cell["complete"] = True
        write_json(path, data)
        make_figures(out, data)
    write_json(path, data)
    make_figures(out, data)
    print_table(data)
    print(f"wrote {path}")


def result_params(method, n, scenario, args):
    return filter_setup(method, n, scenario, args)[1]


if __name__ == "__main__":
    main()
