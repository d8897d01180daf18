"""Avots et al. (IROS 2002), Fig. 2 experiment: localization with door-state estimation in the
two-corridor building (scenario (a) of :mod:`jaxslam.sim.door_worlds`).

For each filter (hybrid, static MCL, memoryless) over S seeds: success rate (final position
error < 0.5 m and heading error < 10 degrees), mean position error over time, and the hybrid
filter's door-state accuracy. Writes DIR/results.json and the figures (belief histograms of
doors D1 and D2 at four times, the map with doors drawn by belief, the decay of D1's belief once
the robot has passed it, position error over time). Resumable: each finished filter's summary
is in DIR/results.json and its arrays in DIR/<filter>.npz, so a stopped run goes on with the
next filter.

    python experiments/doors.py --seeds 50 --out results/doors [--quick]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from _runs import ResultStore, SettingsMismatch  # experiments/_runs.py: the shared resume helper
from door_harness import FILTERS, door_state_accuracy, run_filter_batch  # experiments/door_harness.py

from jaxslam.localization import doors, mcl
from jaxslam.localization.plotting import figure_run, save_figures
from jaxslam.sim.door_worlds import DoorScenario, corridors_scenario, filter_settings

SUCCESS_POSITION = 0.5
"""Final position error (m) below which a run succeeds."""
SUCCESS_HEADING_DEG = 10.0
"""... and final heading error (degrees)."""


def stack_inputs(scenarios: list[DoorScenario]) -> tuple[mcl.ScanInputs, jnp.ndarray]:
    """(S, T, ...) inputs and (S, T, 3) true poses of same-length scenario logs."""
    inputs = [mcl.log_inputs(s.log) for s in scenarios]
    stacked = mcl.ScanInputs(jnp.stack([i.motion for i in inputs]), jnp.stack([i.ranges for i in inputs]))
    return stacked, jnp.stack([jnp.asarray(s.true_poses, jnp.float32) for s in scenarios])


class Evaluation(NamedTuple):
    """One filter over S seeds (NumPy)."""

    filter_kind: str
    position_error: np.ndarray
    """(S, T) m."""
    heading_error_deg: np.ndarray
    """(S, T) degrees."""
    success: np.ndarray
    """(S,) bool: final position error < 0.5 m and heading error < 10 degrees."""
    door_belief: np.ndarray
    """(S, T, K) marginal p(open)."""
    door_accuracy: float
    """Fraction of (seed, door) pairs, over doors the robot observed, whose final belief is on the
    right side of 0.65 / 0.35 (NaN for static MCL, which has no door beliefs)."""


def evaluate(keys, scenarios: list[DoorScenario], filter_kind: str, config: doors.DoorConfig,
             params: doors.DoorParams, batch_size: int = 5) -> Evaluation:
    """Run ``filter_kind`` on every scenario (one key each; global initialisation over the
    scenario's start regions) in one jitted ``lax.map`` over vmapped batches of seeds."""
    first = scenarios[0]
    inputs, truth = stack_inputs(scenarios)
    out = run_filter_batch(keys, inputs, truth, jnp.asarray(first.start_regions), first.door_map,
                           first.log.sensor, params, config, filter_kind, tuple(first.heading_range), batch_size)
    pos = np.asarray(out.position_error)
    head = np.rad2deg(np.asarray(out.heading_error))
    success = (pos[:, -1] < SUCCESS_POSITION) & (head[:, -1] < SUCCESS_HEADING_DEG)
    belief = np.asarray(out.door_belief)
    observed = np.stack([s.observed_doors.any(axis=0) for s in scenarios])
    truth_open = np.stack([s.true_door_open[-1] for s in scenarios])
    accuracy = float("nan") if filter_kind == "static" else door_state_accuracy(belief[:, -1], truth_open, observed)
    return Evaluation(filter_kind, pos, head, success, belief, accuracy)


def summary(ev: Evaluation) -> dict:
    """JSON-ready numbers of an :class:`Evaluation`."""
    return {
        "filter": ev.filter_kind,
        "seeds": int(ev.success.shape[0]),
        "success_rate": float(ev.success.mean()),
        "final_position_error_median_m": float(np.median(ev.position_error[:, -1])),
        "mean_position_error_over_time_m": np.round(ev.position_error.mean(axis=0), 4).tolist(),
        "door_state_accuracy": None if np.isnan(ev.door_accuracy) else ev.door_accuracy,
    }



def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--out", type=Path, default=Path("results/doors"))
    parser.add_argument("--particles", type=int, default=None, help="default 1000 (300 with --quick)")
    parser.add_argument("--quick", action="store_true", help="few seeds and particles: a smoke run")
    parser.add_argument("--seed-offset", type=int, default=0)
    args = parser.parse_args(argv)
    seeds = min(args.seeds, 4) if args.quick else args.seeds
    particles = args.particles or (300 if args.quick else 1000)
    t0 = time.time()
    scenarios = [corridors_scenario(jax.random.key(args.seed_offset + s)) for s in range(seeds)]
    config, params = filter_settings(scenarios[0], particles)
    keys = jax.random.split(jax.random.key(10_000 + args.seed_offset), seeds)
    settings = {"scenario": "corridors", "seeds": seeds, "particles": particles, "seed_offset": args.seed_offset,
                "beams_used": int(scenarios[0].log.num_beams // config.mcl.beam_stride + 1),
                "scans": scenarios[0].num_scans}
    # Resumable by filter: a finished filter's summary is in results.json and its arrays beside it.
    try:
        store = ResultStore(args.out / "results.json", settings, key=lambda r: r["filter"])
    except SettingsMismatch as err:
        raise SystemExit(f"experiments/doors.py: error: {err}") from None
    evaluations = []
    for kind in FILTERS:
        arrays = args.out / f"{kind}.npz"
        if store.done(kind) and arrays.is_file():
            with np.load(arrays) as saved:
                ev = Evaluation(kind, saved["position_error"], saved["heading_error_deg"], saved["success"],
                                saved["door_belief"], float(saved["door_accuracy"]))
            print(f"{kind:>10}: done before ({arrays})", flush=True)
        else:
            t = time.time()
            ev = evaluate(keys, scenarios, kind, config, params)
            args.out.mkdir(parents=True, exist_ok=True)
            np.savez(arrays, position_error=ev.position_error, heading_error_deg=ev.heading_error_deg,
                     success=ev.success, door_belief=ev.door_belief, door_accuracy=ev.door_accuracy)
            store.add(summary(ev) | {"seconds": round(time.time() - t, 1)})
            acc = store.get(kind)["door_state_accuracy"]
            print(f"{kind:>10}: success {100 * ev.success.mean():5.1f}%  door accuracy "
                  f"{'-' if acc is None else f'{100 * acc:.1f}%'}  ({time.time() - t:.0f} s)", flush=True)
        evaluations.append(ev)
    infos, history = figure_run(keys[0], scenarios[0], config, params)
    errors = {f"{ev.filter_kind} ({100 * ev.success.mean():.0f}% ok)": ev.position_error for ev in evaluations}
    figures = save_figures(args.out, scenarios[0], infos, history, params, errors)
    store.write(figures=figures, seconds=round(time.time() - t0, 1))
    print(f"wrote {store.path}")
    results = {**store.settings, "filters": {r["filter"]: r for r in store.runs}, "figures": figures}
    return results


if __name__ == "__main__":
    main()
