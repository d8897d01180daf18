"""Avots et al. (IROS 2002), Fig. 2 experiment: localization with door-state estimation in the
two-corridor building (scenario (a) of :mod:`jaxslam.sim.door_worlds`).

For each filter (hybrid, static MCL, memoryless) over S seeds: success rate (final position
error < 0.5 m and heading error < 10 degrees), mean position error over time, and the hybrid
filter's door-state accuracy. Writes DIR/results.json and the figures (belief histograms of
doors D1 and D2 at four times, the map with doors drawn by belief, the decay of D1's belief once
the robot has passed it, position error over time).

    python experiments/doors.py --seeds 50 --out results/doors [--quick]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

from jaxslam import doors
from jaxslam.plotting_doors import corridor_settings, evaluate, figure_run, save_figures, summary
from jaxslam.sim.door_worlds import corridors_scenario


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
    config, params = corridor_settings(scenarios[0], particles)
    keys = jax.random.split(jax.random.key(10_000 + args.seed_offset), seeds)
    evaluations, results = [], {"scenario": "corridors", "seeds": seeds, "particles": particles,
                                "beams_used": int(scenarios[0].log.num_beams // config.beam_stride + 1),
                                "scans": scenarios[0].num_scans, "filters": {}}
    for kind in doors.FILTERS:
        t = time.time()
        ev = evaluate(keys, scenarios, kind, config, params)
        evaluations.append(ev)
        results["filters"][kind] = summary(ev) | {"seconds": round(time.time() - t, 1)}
        acc = results["filters"][kind]["door_state_accuracy"]
        print(f"{kind:>10}: success {100 * ev.success.mean():5.1f}%  door accuracy "
              f"{'-' if acc is None else f'{100 * acc:.1f}%'}  ({time.time() - t:.0f} s)", flush=True)
    infos, history = figure_run(keys[0], scenarios[0], config, params)
    results["figures"] = save_figures(args.out, scenarios[0], infos, history, params, evaluations)
    results["seconds"] = round(time.time() - t0, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out / 'results.json'} ({results['seconds']} s)")
    return results


if __name__ == "__main__":
    main()
