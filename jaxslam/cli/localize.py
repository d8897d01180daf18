"""``jaxslam localize``: Monte Carlo localization of a log in a saved map
(:mod:`jaxslam.localization.grid_mcl`): ``trajectory.txt``, ``summary.json`` and ``localize.png``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.cli.common import _check_at_least, _check_out_folder, _warn_of_the_cache, check_seed
from jaxslam.cli.map import read_map_log
from jaxslam.config import ConfigError
from jaxslam.io.files import publish_folder
from jaxslam.io.maps import read_map
from jaxslam.io.trajectory import write_trajectory
from jaxslam.laserlog import to_local, to_world
from jaxslam.localization import grid_mcl, mcl
from jaxslam.outputs import as_given

LOCALIZE_DEFAULTS = {"particles": 5000, "seed": 0, "out": "out/localize", "initial_std": "0.2,0.2,0.1"}
"""``jaxslam localize``'s defaults: AMCL's most particles (5,000); the initial pose's std (m, m, rad)."""
CONVERGED_SPREAD_M = 0.5
"""The filter counts as converged from the scan after which the particles' spread stays below this (m)."""
OUTPUTS = ("trajectory.txt", "summary.json", "localize.png")


def add_localize_options(p: argparse.ArgumentParser) -> None:
    """``jaxslam localize``'s arguments."""
    p.add_argument("map", help="the map's YAML file (map_server format, as jaxslam map writes map.yaml)")
    p.add_argument("log", help="path of the log (ROS 1/2 bag or CARMEN log); the format is read from the file")
    p.add_argument("--initial-pose", metavar="X,Y,THETA",
                   help="the robot's pose at the first scan in the map's frame (m, m, rad), e.g. 1.5,2,0.3 (a "
                        "negative first value as --initial-pose=-1.5,2,0); tracked from there. Without it: global "
                        "localization, the particles spread over the map's free cells")
    p.add_argument("--initial-std", metavar="SX,SY,STHETA", default=LOCALIZE_DEFAULTS["initial_std"],
                   help="std of the initial pose (m, m, rad), with --initial-pose (default %(default)s)")
    p.add_argument("--particles", type=int, default=LOCALIZE_DEFAULTS["particles"],
                   help="the most particles, >= 1; KLD sampling uses fewer when the particles agree "
                        "(default %(default)s)")
    p.add_argument("--seed", type=int, default=LOCALIZE_DEFAULTS["seed"],
                   help="seed of the filter (default %(default)s)")
    p.add_argument("--out", default=LOCALIZE_DEFAULTS["out"],
                   help="folder for trajectory.txt, summary.json and localize.png (default %(default)s)")
    p.add_argument("--max-scans", type=int, help="use only the first N scans of the log")
    p.add_argument("--no-cache", action="store_true",
                   help="do not use the persistent compilation cache (as JAXSLAM_CACHE_DIR=off)")
    # read_map_log's other settings: the log as recorded, its default topics and frames.
    p.set_defaults(func=_cmd_localize, scan_topic=None, odom_topic=None, odometry=None, odom_frame=None,
                   base_frame=None, laser_pose=None, odometry_lead=None, no_progress=False)


def parse_pose(flag: str, text: str, example: str) -> np.ndarray:
    """``"x,y,theta"`` -> (3,) float64; anything else raises ``ConfigError`` naming ``flag``."""
    parts = text.split(",")
    try:
        values = np.array([float(v) for v in parts], np.float64)
    except ValueError:
        values = np.array([np.nan])
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise ConfigError(f"{flag} expects three finite numbers separated by commas (m, m, rad), e.g. {example}, "
                          f"got {text!r}")
    return values


def _cmd_localize(args: argparse.Namespace) -> int:
    """Read and check every input, run the filter over the log, write the three outputs."""
    _check_at_least("--particles", args.particles, 1, "the most particles")
    _check_at_least("--max-scans", args.max_scans, 1, "scans of the log to use")
    check_seed(args.seed)
    initial = None if args.initial_pose is None else parse_pose("--initial-pose", args.initial_pose, "1.5,2,0.3")
    initial_std = parse_pose("--initial-std", args.initial_std, "0.2,0.2,0.1")
    if np.any(initial_std < 0):
        raise ConfigError(f"--initial-std must be >= 0, got {args.initial_std!r}")
    _check_out_folder(args.out)
    probability, spec = read_map(args.map)
    grid, offset = grid_mcl.prepare_map(probability, spec)
    if initial is not None and not grid_mcl.pose_in_map(spec, initial):
        x0, x1, y0, y1 = spec.extent
        raise ConfigError(f"--initial-pose {args.initial_pose}: ({initial[0]:g}, {initial[1]:g}) lies outside the map "
                          f"{args.map}, which spans x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m")
    _warn_of_the_cache(args)
    started = time.perf_counter()
    log = read_map_log(args)
    config = grid_mcl.GridMclConfig(max_particles=args.particles, min_particles=min(100, args.particles))
    params = grid_mcl.make_params()
    k_init, k_run = jax.random.split(jax.random.key(args.seed))
    if initial is None:
        state = grid_mcl.init_global(k_init, grid, config)
    else:
        state = grid_mcl.init_tracked(k_init, jnp.asarray(to_local(initial, offset), jnp.float32),
                                      jnp.asarray(initial_std, jnp.float32), config)
    print(f"localizing {log.num_scans} scans with at most {config.max_particles} particles ...", file=sys.stderr,
          flush=True)
    out = grid_mcl.filter(k_run, state, mcl.log_inputs(log), grid, log.sensor, params, config)
    info = jax.device_get(out.info)
    seconds = time.perf_counter() - started
    poses = to_world(np.asarray(info.mcl.mean_pose, np.float64), offset)
    spread = np.asarray(info.spread, np.float64)
    final = jax.device_get(out.state)
    particles = to_world(np.asarray(final.poses)[: int(final.num_active)], offset)
    summary = _summary(args, log, config, params, info, spread, seconds)

    def write(folder):
        write_trajectory(folder / "trajectory.txt", log.timestamps, poses)
        (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        _figure(folder / "localize.png", probability, spec, poses, particles)

    publish_folder(args.out, write, OUTPUTS)
    converged = summary["time_to_converge_s"]
    print(f"localized {log.num_scans} scans in {seconds:.1f} s: "
          + (f"converged after {converged:.1f} s of the log" if converged is not None else "not converged")
          + f", mean spread {summary['mean_spread_m']:.3f} m; wrote {args.out}")
    return 0


def _summary(args, log, config, params, info, spread, seconds) -> dict:
    """summary.json: the settings, when the spread settled and how wide it was."""
    below = spread < CONVERGED_SPREAD_M
    # The first scan from which the spread stays below the threshold (None: it never settles).
    settled = np.flatnonzero(~below)
    first = 0 if settled.size == 0 else int(settled[-1]) + 1
    converged = first < log.num_scans
    return {
        "map": str(args.map), "log": str(args.log), "scans": int(log.num_scans), "seed": args.seed,
        "mode": "global" if args.initial_pose is None else "tracking",
        "initial_pose": args.initial_pose, "initial_std": args.initial_std if args.initial_pose else None,
        "config": dataclasses.asdict(config),
        "params": {name: as_given(float(value)) for name, value in (
            ("likelihood_sigma_m", params.likelihood.sigma), ("z_hit", params.likelihood.z_hit),
            ("z_rand", params.likelihood.z_rand), ("likelihood_gain", params.likelihood.gain),
            ("alpha_slow", params.alpha_slow), ("alpha_fast", params.alpha_fast),
            ("kld_epsilon", params.kld_epsilon), ("kld_z", params.kld_z))},
        "converged_spread_m": CONVERGED_SPREAD_M,
        "converged_at_scan": first if converged else None,
        "time_to_converge_s": float(log.timestamps[first] - log.timestamps[0]) if converged else None,
        "mean_spread_m": float(np.mean(spread)),
        "mean_spread_after_convergence_m": float(np.mean(spread[first:])) if converged else None,
        "final_spread_m": float(spread[-1]),
        "mean_particles": float(np.mean(info.num_active)),
        "scans_with_recovery": int(np.sum(np.asarray(info.redrawn_share) > 0)),
        "seconds": round(seconds, 2),
    }


def _figure(path, probability, spec, poses, particles) -> None:
    """localize.png: the map, the mean path and the final particles."""
    from jaxslam.plotting import _fitted_figure, plot_map, plot_path  # lazy: matplotlib slows every start

    p = np.clip(probability, 1e-3, 1 - 1e-3)
    fig = _fitted_figure(spec)
    ax = fig.subplots()
    plot_map(ax, np.log(p / (1 - p)), spec)
    plot_path(ax, poses, label="mean pose", color="tab:red", lw=1.2)
    ax.scatter(particles[:, 0], particles[:, 1], s=2, color="tab:blue", alpha=0.5, label="final particles")
    heading = poses[-1]
    ax.annotate("", xy=(heading[0] + 0.5 * math.cos(heading[2]), heading[1] + 0.5 * math.sin(heading[2])),
                xytext=(heading[0], heading[1]), arrowprops=dict(arrowstyle="->", color="tab:red"))
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"jaxslam localize: {poses.shape[0]} scans")
    fig.savefig(path, dpi=110, bbox_inches="tight")
