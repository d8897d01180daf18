"""Why the weights did not pick the closure: a box-family run's weights from the last passage over X
to the end of the log, and the final revisiting accuracy had the weights been sharper.

``box_family.py`` sorts a failure as "the weights did not pick it" when some particle proposed at
the last passage over X closed the loop (revisiting error < 0.2 m) and the weights put the mean
above 0.2 m. This script runs the worlds again (the same draw, keys and settings) and, for every
step t from that passage to the end, over the particles proposed at t (each on its own history):

* ``closing``: how many closed the loop, and ``share``, their weight;
* ``prior_gap`` and ``increment_gap``: the mean log-weight before step t, and the mean increment
  of step t, of the closing particles less the others' (the increment is
  :func:`jaxslam.diagnose.weight_increments`': the step's normalised log-weight less the one the
  particle carried into it, its proposal's increment up to a constant);
  ``raw_gap`` is ``increment_gap`` / the likelihood gain, the untempered log-likelihood's.

Then the counterfactual ``ra_at_gain``: the final particles re-weighted as if the last ``back``
steps had the likelihood gain g (their lineages' increments over those steps times g / gain),
the particles themselves unchanged. It asks whether sharper weights over the same particles
would have picked the closure; a run at that gain would also draw other particles.

    python experiments/closure_weights.py --worlds 1009 1010 1014 1015 1017 1004 1019 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import box_family  # noqa: E402  (experiments/box_family.py: the worlds' runs)
import box_world  # noqa: E402
import closing_steps  # noqa: E402

from jaxslam.diagnose import weight_increments  # noqa: E402
from jaxslam.io.files import write_file_atomic  # noqa: E402
from jaxslam.metrics import normalized_weights, passage_errors  # noqa: E402
from jaxslam.rbpf import particle_paths  # noqa: E402
from jaxslam.sim import box_family as family  # noqa: E402


def passage_table(record: dict, first: int, last: int, true_first, true_last, start, rotation_weight: float,
                  gain: float, success_ra: float) -> list[dict]:
    """The module's per-step rows from the last passage's step (``last`` - 1) to the end.
    ``record``: ``proposed`` (S, N, 3), ``ancestors`` (S, N), ``log_weights`` (S, N), ``resampled`` (S,)
    in the frame of ``start`` and the true poses."""
    increment = weight_increments(record["log_weights"], record["ancestors"], record["resampled"])
    prior = record["log_weights"] - increment  # the weight each carried into the step (up to a constant per step)
    rows = []
    for step in range(last - 1, record["log_weights"].shape[0]):
        histories = closing_steps.proposed_histories(record["proposed"], record["ancestors"], step, start)
        errors = passage_errors(histories, first, last, true_first, true_last, rotation_weight)
        closing = errors < success_ra
        both = bool(closing.any() and (~closing).any())
        gap = (lambda a: float(np.nanmean(a[closing]) - np.nanmean(a[~closing])) if both else float("nan"))
        rows.append({"step": step, "closing": int(closing.sum()),
                     "share": float(normalized_weights(record["log_weights"][step])[closing].sum()),
                     "prior_gap": gap(prior[step]), "increment_gap": gap(increment[step]),
                     "raw_gap": gap(increment[step]) / gain, "resampled": bool(record["resampled"][step])})
    return rows


def lineage_increments(record: dict, back: int) -> np.ndarray:
    """(N,) each final particle's increments summed along its lineage over the last ``back`` steps."""
    increment = weight_increments(record["log_weights"], record["ancestors"], record["resampled"])
    increment = np.nan_to_num(increment, nan=0.0)  # a zero-weight particle's (its weight stays zero)
    num_steps, num_particles = increment.shape
    total, index = np.zeros(num_particles), np.arange(num_particles)
    for step in range(num_steps - 1, max(num_steps - 1 - back, -1), -1):
        index = record["ancestors"][step][index]  # the proposed particle each final one descends from
        total += increment[step][index]
    return total


def ra_at_gains(record: dict, final_log_weights: np.ndarray, errors: np.ndarray, gain: float, gains, back: int
                ) -> dict[str, float]:
    """The final RA (weighted mean of the final particles' ``errors``) re-weighted as if the last
    ``back`` steps had each likelihood gain of ``gains`` (the module's counterfactual)."""
    summed = lineage_increments(record, back)
    return {f"{g:g}": float(np.sum(normalized_weights(final_log_weights + (g / gain - 1.0) * summed) * errors))
            for g in gains}


def analyse_world(cell: dict, seed: int, world: dict, gains, backs, max_laps: int | None = None) -> dict:
    """One world's run, table and counterfactuals."""
    run, result, scenario, params = box_family.run_world_result(cell, seed, world, max_laps)
    first, last, start = box_world.passage_steps(result, scenario)
    idx = np.asarray(result.selection.indices)
    truth = scenario.true_poses
    info = result.info
    # The histories in the true poses' frame (the filter runs in a local frame).
    offset = np.r_[np.asarray(result.frame_offset), 0.0]
    record = {"proposed": np.asarray(info.proposed_poses) + offset, "ancestors": np.asarray(info.ancestors),
              "log_weights": np.asarray(info.log_weights, np.float64), "resampled": np.asarray(info.resampled)}
    start = start + offset
    gain = float(params.likelihood.gain)
    lam = world["rotation_weight"]
    rows = passage_table(record, first, last, truth[idx[first]], truth[idx[last]], start, lam, gain,
                         world["success_ra"])
    paths = particle_paths(record["proposed"], record["ancestors"], start)
    errors = passage_errors(paths, first, last, truth[idx[first]], truth[idx[last]], lam)
    final = np.asarray(result.state.log_weights, np.float64)
    counterfactual = {str(back): ra_at_gains(record, final, errors, gain, gains, back) for back in backs}
    return {"seed": seed, "ra": run["ra"], "cause": run["cause"], "steps": int(record["log_weights"].shape[0]),
            "passage_step": last - 1, "gain": gain, "rows": rows, "ra_at_gain": counterfactual,
            "landmarks": [lm["kind"] for lm in box_family.world_draw(seed, max_laps).to_json()["landmarks"]]}


def print_world(out: dict) -> None:
    print(f"world {out['seed']}: RA {out['ra']:.3f} ({out['cause'] or 'success'}), last passage at step {out['passage_step']} "
          f"of {out['steps']}, landmarks {', '.join(out['landmarks'])}")
    for row in out["rows"]:
        print("  step {step}: closing {closing:2d}, share {share:.3f}, prior gap {prior_gap:+.3f}, increment gap "
              "{increment_gap:+.3f} (raw {raw_gap:+.2f}){r}".format(**row, r=", resampled" if row["resampled"] else ""))
    for back, ras in out["ra_at_gain"].items():
        print(f"  RA re-weighted over the last {back} steps at gain " + ", ".join(f"{g}: {ra:.3f}" for g, ra in ras.items()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=box_family.THE_RULE)
    ap.add_argument("--worlds", type=int, nargs="+", required=True, help="tuning-family seeds (1000 on)")
    ap.add_argument("--method", default="LP-SM", help="a box_world.json method (default LP-SM, the library's LP)")
    ap.add_argument("--particles", type=int, default=50)
    ap.add_argument("--gains", type=float, nargs="+", default=[0.1, 0.2, 0.3, 0.5, 1.0])
    ap.add_argument("--back", type=int, nargs="+", default=[5, 20, 50], help="steps re-weighted (from the end)")
    ap.add_argument("--max-laps", type=int, default=None, help="cut every world to at most K laps (a smoke test)")
    ap.add_argument("--out", type=Path, default=None, help="the rows and counterfactuals (JSON)")
    args = ap.parse_args(argv)
    test_family = [s for s in args.worlds if s < family.family_seeds("tuning", 1)[0]]
    if test_family:
        print(f"closure_weights.py: worlds {test_family} are the test family's. {box_family.THE_RULE}", file=sys.stderr)
        return 2
    if args.particles < 1 or any(g <= 0 for g in args.gains) or any(b < 1 for b in args.back):
        print("closure_weights.py: --particles, --gains and --back must be positive", file=sys.stderr)
        return 2
    exp = box_world.load_experiment(box_world.DEFAULT_CONFIG)
    if args.method not in exp["methods"]:
        print(f"closure_weights.py: unknown method {args.method}; known: {list(exp['methods'])}", file=sys.stderr)
        return 2
    cell = box_family.family_cells(exp, [args.method], [args.particles], {})[0]
    world = box_family.family_world_settings(exp, "tuning", args.max_laps)
    outs = []
    for seed in args.worlds:
        outs.append(analyse_world(cell, seed, world, args.gains, args.back, args.max_laps))
        print_world(outs[-1])
        if args.out is not None:
            write_file_atomic(args.out, json.dumps({"method": args.method, "N": args.particles, "worlds": outs},
                                                   indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
