"""The ``jaxslam doors`` subcommand: one door scenario, one filter, figures and a JSON summary.

    jaxslam doors --scenario {corridors,office} --particles N --seed S --out DIR
                  [--filter {hybrid,static,memoryless}]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``doors`` subcommand on an argparse ``subparsers`` object."""
    p = subparsers.add_parser("doors", help="localization with door-state estimation (Avots et al. 2002)")
    p.add_argument("--scenario", choices=("corridors", "office"), default="corridors",
                   help="corridors: two corridors told apart only by their doors (Fig. 2); "
                        "office: doors closed on the way out, opened, then the return pass (Fig. 1)")
    p.add_argument("--particles", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated log and of the filter")
    p.add_argument("--filter", dest="filter_kind", choices=("hybrid", "static", "memoryless"), default="hybrid")
    p.add_argument("--out", default="out/doors", help="folder for summary.json and the figures")
    p.set_defaults(func=run_command)
    return p


def run_command(args) -> int:
    import jax
    import numpy as np

    from jaxslam.plotting_doors import corridor_settings, evaluate, figure_run, save_figures, summary
    from jaxslam.sim.door_worlds import SCENARIOS

    if args.particles < 1:
        raise ValueError("--particles must be >= 1")
    t0 = time.time()
    scenario = SCENARIOS[args.scenario](jax.random.key(args.seed))
    config, params = corridor_settings(scenario, args.particles)
    key = jax.random.key(10_000 + args.seed)
    ev = evaluate(key[None], [scenario], args.filter_kind, config, params, batch_size=1)
    out = Path(args.out)
    result = summary(ev) | {"scenario": args.scenario, "seed": args.seed, "particles": args.particles,
                            "final_position_error_m": float(ev.position_error[0, -1]),
                            "final_heading_error_deg": float(ev.heading_error_deg[0, -1]),
                            "final_door_belief": dict(zip(scenario.door_names,
                                                          np.round(ev.door_belief[0, -1], 4).tolist())),
                            "true_door_open_final": dict(zip(scenario.door_names,
                                                             scenario.true_door_open[-1].tolist()))}
    if args.filter_kind == "static":
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from jaxslam.plotting_doors import plot_door_map, plot_position_errors

        out.mkdir(parents=True, exist_ok=True)
        fig, axes = plt.subplots(1, 2, figsize=(13, 4))
        plot_door_map(axes[0], scenario, ev.door_belief[0, -1], "static MCL: the map as given",
                      path=scenario.true_poses)
        plot_position_errors(axes[1], [ev])
        fig.tight_layout()
        fig.savefig(out / "static.png", dpi=110)
        plt.close(fig)
        figures = [str(out / "static.png")]
    else:
        infos, history = figure_run(key, scenario, config, params, memory=args.filter_kind == "hybrid")
        figures = save_figures(out, scenario, infos, history, params, [ev])
    result["figures"] = figures
    result["seconds"] = round(time.time() - t0, 1)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(result, indent=2))
    print(f"{args.scenario} / {args.filter_kind}: final position error {result['final_position_error_m']:.3f} m, "
          f"heading error {result['final_heading_error_deg']:.2f} deg; wrote {out / 'summary.json'}")
    return 0
