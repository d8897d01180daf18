"""Step by step through a box-world run's last lap: when do the weights pick a closing history?

A failed box-world run ends with most of its weight on histories that miss the loop
(``closing_weight`` in ``box_world.py``'s records). This script asks when that happens. For each
seed it runs one cell of a ``box_world.json`` table (default: the defaults table's library LP),
then, at each of the last ``--steps`` steps, over the particles proposed there (each on its own
history, rebuilt from ``SlamInfo.proposed_poses`` and ``ancestors``):

* ``error``: each particle's revisiting error so far, the relative pose between the first passage
  over X and the step (:func:`jaxslam.metrics.passage_errors`, the table's lambda); from the last
  passage on, between the two passages, so that at the end it is the particle's own RA;
* ``weight``: the step's weight on particles whose error is below the table's success threshold
  (``SlamInfo.log_weights``, after the update and before resampling), and ``share``: the fraction
  of the particles that are (what the weights would give if they said nothing);
* the weighted and unweighted mean error;

and, for each final particle, its own RA and its history's error so far 5, 10 and 20 steps
before the end (which errors the closure's proposals pulled back under the threshold).

Over the whole run, ``one_step`` compares each proposed particle's one-step motion (its parent's
pose to its own) with the true one, in the parent's frame (along the track, across it, heading):
``slope``, the least-squares slope of the particles' mean error per step on the odometry's error
(1: the proposals keep the odometry's error, 0: they remove it), and ``spread``, the particles'
standard deviation per step, averaged.

A weight above the share means the weights favour the closing histories at that step. The
records go to ``--out``/closing_steps.json, the figure to closing_steps.png.

    python experiments/closing_steps.py --out OUT --first-seed 18 --runs 10
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import box_world  # noqa: E402  (experiments/box_world.py: the table's cells and scoring)

from jaxslam.cli import parse_assignments  # noqa: E402
from jaxslam.diagnose import pair_coalescence, weight_persistence  # noqa: E402
from jaxslam.geometry import between_np  # noqa: E402
from jaxslam.metrics import motion_error_components, normalized_weights, passage_errors  # noqa: E402
from jaxslam.rbpf import particle_paths  # noqa: E402


BEFORE = (5, 10, 20)
"""Steps before the end at which each final particle's history's error so far is kept."""


def proposed_histories(proposed: np.ndarray, ancestors: np.ndarray, step: int, start) -> np.ndarray:
    """(N, step + 2, 3): the history of each particle proposed at ``step`` (its pose there last)."""
    anc = ancestors[: step + 1].copy()
    anc[step] = np.arange(anc.shape[1])  # the proposed particles themselves, before that step's resampling
    return particle_paths(proposed[: step + 1], anc, start)


def one_step_drift(proposed: np.ndarray, ancestors: np.ndarray, start, truth: np.ndarray, odometry: np.ndarray
                   ) -> dict:
    """``slope`` and ``spread`` (per axis: along, across, heading) of the proposals' one-step errors
    (the module's doc). ``proposed`` (S-1, N, 3) and ``start`` in one frame with ``truth`` and
    ``odometry`` (S, 3), the processed scans' poses."""
    parents = np.concatenate([np.broadcast_to(start, (1,) + proposed.shape[1:]),
                              np.take_along_axis(proposed[:-1], ancestors[:-1, :, None], axis=1)])
    true_motion = between_np(truth[:-1], truth[1:])
    errors = motion_error_components(parents, proposed, true_motion[:, None, :])
    odometry_errors = motion_error_components(odometry[:-1], odometry[1:], true_motion)
    common = errors.mean(axis=1)
    return {"slope": [float(np.polyfit(odometry_errors[:, k], common[:, k], 1)[0]) for k in range(3)],
            "spread": errors.std(axis=1).mean(axis=0).tolist(),
            "odometry_error_rms": np.sqrt((odometry_errors**2).mean(axis=0)).tolist()}


def trace(record: dict, seed: int, world: dict, steps: int) -> dict:
    """One run of the cell and its per-step closing figures (the module's doc)."""
    t0 = time.perf_counter()
    run, result, scenario = box_world.run_once(record, seed, world)
    truth, lam, success = scenario.true_poses, world["rotation_weight"], world["success_ra"]
    idx = np.asarray(result.selection.indices)
    first, last, start = box_world.passage_steps(result, scenario)
    proposed = np.asarray(result.info.proposed_poses)
    ancestors = np.asarray(result.info.ancestors)
    log_weights = np.asarray(result.info.log_weights)
    num_steps = ancestors.shape[0]
    rows = []
    for step in range(max(num_steps - steps, 0), num_steps):
        paths = result.to_world(proposed_histories(proposed, ancestors, step, start))
        until = min(step + 1, last)
        errors = passage_errors(paths, first, until, truth[idx[first]], truth[idx[until]], lam)
        w = normalized_weights(log_weights[step])
        closing = errors < success
        rows.append({"step": step, "steps_to_end": num_steps - 1 - step, "past_last_passage": step + 1 >= last,
                     "weight": float(w[closing].sum()), "share": float(closing.mean()),
                     "weighted_error": float(np.sum(w * errors)), "mean_error": float(errors.mean()),
                     "min_error": float(errors.min()), "ess": float(np.asarray(result.info.ess)[step]),
                     "resampled": bool(np.asarray(result.info.resampled)[step])})
    # Each final particle's own RA, and its history's error so far at the steps before the end
    # listed in BEFORE (its ancestor's then): which errors the last steps' proposals pulled back.
    finals = result.to_world(particle_paths(proposed, ancestors, start))
    final_errors = {"end": passage_errors(finals, first, last, truth[idx[first]], truth[idx[last]], lam).tolist()}
    for k in BEFORE:
        at = max(min(num_steps - k, last), 1)  # path index k steps before the end (at most the last passage)
        final_errors[f"{k}_before"] = passage_errors(finals, first, at, truth[idx[first]], truth[idx[at]],
                                                     lam).tolist()
        final_errors[f"{k}_before_distinct"] = int(np.unique(finals[:, at], axis=0).shape[0])  # their ancestors then
    world_proposed = result.to_world(proposed)
    drift = one_step_drift(world_proposed, ancestors, result.to_world(np.asarray(start)[None])[0], truth[idx],
                           np.asarray(scenario.log.odometry, np.float64)[idx])
    # Whether the weights the resamplings acted on lasted (diagnose.weight_persistence).
    persistence = weight_persistence(log_weights, ancestors, np.asarray(result.info.resampled))
    weights = {"resamplings": int(np.sum(np.asarray(result.info.resampled))),
               "median_correlation": persistence["median_correlation"],
               "median_increment_spread": persistence["median_increment_spread"],
               "stretches": len(persistence["stretches"]),
               "pair_coalescence_per_step": float(np.mean(pair_coalescence(ancestors)))}
    return {"seed": seed, "ra": run["ra"], "closing_weight": run["closing_weight"], "success": run["ra"] < success,
            "weights": weights,
            "final_particle_errors": final_errors, "one_step": drift,
            "first_passage_step": first - 1, "last_passage_step": last - 1, "num_steps": num_steps,
            "seconds": time.perf_counter() - t0, "steps": rows}


def figure(path: Path, runs: list[dict], success_ra: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for run in runs:
        x = [-r["steps_to_end"] for r in run["steps"]]
        colour = "tab:blue" if run["success"] else "tab:red"
        axes[0].plot(x, [r["weight"] for r in run["steps"]], color=colour, lw=1)
        axes[0].plot(x, [r["share"] for r in run["steps"]], color=colour, lw=0.8, ls=":")
        axes[1].plot(x, [r["weighted_error"] for r in run["steps"]], color=colour, lw=1)
        axes[1].plot(x, [r["min_error"] for r in run["steps"]], color=colour, lw=0.8, ls=":")
        axes[0].axvline(run["last_passage_step"] - (run["num_steps"] - 1), color=colour, lw=0.4, alpha=0.5)
    axes[0].set(xlabel="steps before the end", ylabel="closing histories: weight (solid), share (dotted)",
                ylim=(-0.02, 1.02))
    axes[1].axhline(success_ra, color="k", lw=0.6)
    axes[1].set(xlabel="steps before the end", ylabel="revisiting error so far [m]: weighted (solid), min (dotted)",
                ylim=(0, None))
    fig.suptitle("box world, last lap: successes blue, failures red; thin vertical lines: last passage over X")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(box_world.DEFAULT_CONFIG))
    ap.add_argument("--table", default="defaults")
    ap.add_argument("--method", default="LP-SM", help="a method of the file (default the library's LP)")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--steps", type=int, default=150, help="the last steps to trace")
    ap.add_argument("--particles", type=int, help="N (default the table's first)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a build_setup name for the cell (a diagnostic, not the table's cell)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    exp = box_world.load_experiment(args.config)
    if args.table not in exp["tables"] or args.method not in exp["methods"]:
        print(f"closing_steps.py: no table {args.table!r} or method {args.method!r} in {args.config}", file=sys.stderr)
        return 2
    table = exp["tables"][args.table]
    particles = [args.particles] if args.particles else table["particles"][:1]
    first_cell = {**table, "particles": particles, "odometry_scales": table["odometry_scales"][:1]}
    overrides = {**table.get("set", {}), **parse_assignments(args.set)}
    cell = box_world.table_cells(exp, first_cell, [args.method], overrides)[0]
    world = box_world.world_settings(exp, table)
    args.out.mkdir(parents=True, exist_ok=True)
    target = args.out / "closing_steps.json"
    stored = json.loads(target.read_text()) if target.exists() else {"cell": cell, "runs": []}
    if box_world.cell_key(stored["cell"]) != box_world.cell_key(cell):
        print(f"closing_steps.py: {target} holds another cell's runs; give another --out", file=sys.stderr)
        return 2
    done = {r["seed"] for r in stored["runs"]}
    from tqdm.auto import tqdm

    for seed in tqdm(range(args.first_seed, args.first_seed + args.runs), desc="runs", unit="run"):
        if seed in done:
            continue
        stored["runs"].append(trace(cell, seed, world, args.steps))
        target.write_text(json.dumps(stored, indent=1) + "\n")  # each run kept as it ends (resumable)
    runs = sorted(stored["runs"], key=lambda r: r["seed"])
    figure(args.out / "closing_steps.png", runs, world["success_ra"])
    for run in runs:
        end = run["steps"][-1]
        drift = run.get("one_step")
        print(f"seed {run['seed']}: RA {run['ra']:.3f} ({'success' if run['success'] else 'failure'}), final "
              f"closing weight {end['weight']:.2f} against a share of {end['share']:.2f}"
              + (f"; one-step slope on the odometry's error {np.round(drift['slope'], 2)}, spread "
                 f"{np.round(drift['spread'], 4)} (along, across, heading)" if drift else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
