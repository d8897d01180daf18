"""``jaxslam doors``: one door scenario (:mod:`jaxslam.sim.door_worlds`), one filter (static MCL,
the memoryless or the hybrid door filter of :mod:`jaxslam.localization.doors`): figures and a
JSON summary."""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.cli.common import SEED_LIMIT, _check_out_folder, _warn_of_the_cache, check_seed
from jaxslam.config import ConfigError
from jaxslam.geometry import pose_errors
from jaxslam.localization import doors, mcl
from jaxslam.localization.plotting import figure_run, plot_door_map, plot_position_errors, save_figures
from jaxslam.sim.door_worlds import SCENARIOS, filter_settings


def _cmd_doors(args: argparse.Namespace) -> int:
    """One door scenario, one filter: figures and a JSON summary."""
    if args.particles < 1:
        raise ConfigError(f"--particles must be >= 1, got {args.particles}")
    check_seed(args.seed)
    _check_out_folder(args.out)
    _warn_of_the_cache(args)
    t0 = time.time()
    scenario = SCENARIOS[args.scenario](jax.random.key(args.seed))
    config, params = filter_settings(scenario, args.particles)
    key = jax.random.key((10_000 + args.seed) % SEED_LIMIT)
    k_init, k_run = jax.random.split(key)  # as experiments/door_harness.py: the same start for every filter
    start = mcl.init_global(k_init, jnp.asarray(scenario.start_regions), config.mcl, tuple(scenario.heading_range))
    inputs, door_map, sensor = mcl.log_inputs(scenario.log), scenario.door_map, scenario.log.sensor
    if args.filter_kind == "static":  # MCL on the map as given
        segments, active = doors.static_segments(door_map)
        mean_pose = mcl.filter(k_run, start, inputs, segments, sensor, params.mcl_params(), config.mcl,
                               active).info.mean_pose
        final_belief = np.asarray(door_map.initial_open >= 0.5, np.float32)
    else:  # the door filter (memoryless: every door 50% open before every update)
        info = doors.filter(k_run, doors.init(start, door_map), inputs, door_map, sensor, params,
                            dataclasses.replace(config, memory=args.filter_kind == "hybrid")).info
        mean_pose = info.mcl.mean_pose
        final_belief = np.asarray(info.door_belief[-1])
    position_error, heading_error = (np.asarray(e) for e in
                                     pose_errors(mean_pose, jnp.asarray(scenario.true_poses, jnp.float32)))
    result = {"scenario": args.scenario, "filter": args.filter_kind, "seed": args.seed, "particles": args.particles,
              "final_position_error_m": float(position_error[-1]),
              "final_heading_error_deg": float(np.rad2deg(heading_error[-1])),
              "final_door_belief": dict(zip(scenario.door_names, np.round(final_belief, 4).tolist())),
              "true_door_open_final": dict(zip(scenario.door_names, scenario.true_door_open[-1].tolist()))}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    errors = {args.filter_kind: position_error[None]}
    if args.filter_kind == "static":
        import matplotlib  # lazy: matplotlib.pyplot adds 0.7 s to every command's start (measured)

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(13, 4))
        plot_door_map(axes[0], scenario, final_belief, "static MCL: the map as given", path=scenario.true_poses)
        plot_position_errors(axes[1], errors)
        fig.tight_layout()
        fig.savefig(out / "static.png", dpi=110)
        plt.close(fig)
        figures = [str(out / "static.png")]
    else:
        infos, history = figure_run(key, scenario, config, params, memory=args.filter_kind == "hybrid")
        figures = save_figures(out, scenario, infos, history, params, errors)
    result["figures"] = figures
    result["seconds"] = round(time.time() - t0, 1)
    (out / "summary.json").write_text(json.dumps(result, indent=2))
    print(f"{args.scenario} / {args.filter_kind}: final position error {result['final_position_error_m']:.3f} m, "
          f"heading error {result['final_heading_error_deg']:.2f} deg; wrote {out / 'summary.json'}")
    return 0
