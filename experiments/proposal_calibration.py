"""How much of the odometry's one-step error the window posterior corrects, and how wide it says it
is, in the box world with the map built at the true poses.

For each processed scan t of a box-world seed, the map holds scans 0 .. t-1 inserted at their true
poses (a dense grid); the window posterior (:mod:`jaxslam.window_posterior`, the SMP's, fit gain 1)
is searched from the true x_{t-1} with the odometry's u_t and the scan z_t, and ``--draws`` poses
drawn from its mixture. Every error is the one-step motion's (x_{t-1} to the pose) against the true
one, in x_{t-1}'s frame (along the track, across it, heading):

* ``slope``: the least-squares slope of the draws' mean error on the prediction's (the odometry's)
  error, per axis: 1 keeps the odometry's error, 0 removes it;
* ``draw_sd``: the draws' standard deviation (the proposal's width); ``calibration``: the rms of
  the draws' mean error over that width (1 for a proposal as wide as its own error);
* the same for the *exact* posterior of the world's walls (``exact_*``: the endpoint model of
  ``likelihood.sigma`` on the distances to the true segments, no grid, no cells, the filter's
  motion prior; on a 13^3 lattice of +-3 prior stds, every ``--exact-every``-th step), what any
  map of cells can at best give.

    python experiments/proposal_calibration.py --seeds 18 19 --out OUT/calibration.json [--set NAME=VALUE]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import box_world  # noqa: E402

from jaxslam import motion, rbpf, window_posterior  # noqa: E402
from jaxslam.cli import parse_assignments  # noqa: E402
from jaxslam.geometry import between_np, compose  # noqa: E402
from jaxslam.grid import GridSpec  # noqa: E402
from jaxslam.laser import beam_endpoints, subsample_beams  # noqa: E402
from jaxslam.metrics import motion_error_components  # noqa: E402
from jaxslam.occupancy import empty_map, insert_scan  # noqa: E402
from jaxslam.sim.world import point_segment_distance  # noqa: E402

AXES = ("along", "across", "heading")


class _DenseConfig:
    """The ``SlamConfig`` fields the window posterior reads, over a dense grid."""

    def __init__(self, config, spec):
        for name in ("window_cells", "window_levels", "window_modes", "window_keep", "likelihood_lookup",
                     "match_lookup", "field_radius", "sensor_model", "max_insert_range"):
            setattr(self, name, getattr(config, name))
        self.grid = spec


def segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(...,) distance (m) from each point (..., 2) to the nearest of the segments (M, 4)."""
    points = np.asarray(points, np.float64)
    return point_segment_distance(points.reshape(-1, 2), segments).min(axis=1).reshape(points.shape[:-1])


def exact_posterior(previous, motion_step, ranges, sensor, segments, params, beam_stride, true_motion, lattice=13):
    """Mean and std (3,) of the one-step error under the exact posterior of the true walls."""
    std = np.asarray(motion.noise_std(jnp.asarray(motion_step, jnp.float32), params.motion), np.float64)
    axis = np.linspace(-3.0, 3.0, lattice)
    offsets = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) * std
    poses = np.asarray(compose(jnp.asarray(previous, jnp.float32), jnp.asarray(motion_step + offsets, jnp.float32)),
                       np.float64)
    lik_sensor, lik_ranges = subsample_beams(sensor, jnp.asarray(ranges), beam_stride)
    ends, valid = beam_endpoints(jnp.asarray(poses, jnp.float32), lik_ranges, lik_sensor)
    ends = np.asarray(ends, np.float64)[:, np.asarray(valid)]
    lik = params.likelihood
    log_lik = np.log(float(lik.z_hit) * np.exp(-0.5 * (segment_distances(ends, segments) / float(lik.sigma)) ** 2)
                     + float(lik.z_rand)).sum(-1)
    log_post = log_lik - 0.5 * ((offsets / std) ** 2).sum(-1)
    weights = np.exp(log_post - log_post.max())
    weights /= weights.sum()
    errors = motion_error_components(previous, poses, true_motion)
    mean = weights @ errors
    return mean, np.sqrt(weights @ (errors - mean) ** 2)


def calibrate(seed: int, overrides: dict, draws: int = 200, exact_every: int = 3, max_steps: int | None = None) -> dict:
    """One seed's figures (the module's doc)."""
    exp = box_world.load_experiment()
    table = exp["tables"]["defaults"]
    world = box_world.world_settings(exp, table)
    cell = box_world.table_cells(exp, {**table, "particles": table["particles"][:1],
                                       "odometry_scales": [1.0]}, ["SMP"], {**table.get("set", {}), **overrides})[0]
    scenario = box_world.scenario_for(seed, 1.0, world)
    config, settings, params = box_world.filter_setup(cell, scenario, world)
    _, selection, _ = rbpf.prepare(scenario.log, config, settings)
    idx = np.asarray(selection.indices)[: max_steps]
    truth = np.asarray(scenario.true_poses, np.float64)[idx]
    odometry = np.asarray(scenario.log.odometry, np.float64)[idx]
    scans = np.asarray(scenario.log.ranges)[idx]
    sensor = scenario.log.sensor
    xmin, ymin, xmax, ymax = scenario.world.bounds
    spec = GridSpec.from_bounds(xmin - 1.0, ymin - 1.0, xmax + 1.0, ymax + 1.0, config.grid.resolution)
    dense = _DenseConfig(config, spec)
    lik_sensor, _ = subsample_beams(sensor, jnp.asarray(scans[0]), config.beam_stride)

    @jax.jit
    def propose(key, previous, motion_step, ranges, field):
        _, lik_ranges = subsample_beams(sensor, ranges, config.beam_stride)
        post = window_posterior.window_posterior(previous, field, motion_step, lik_ranges, lik_sensor, params, dense,
                                                 fit_gain=1.0)
        return window_posterior.sample(key, post, window_posterior.mixture_log_weights(post), (draws,))

    insert = jax.jit(lambda grid_map, pose, ranges: insert_scan(spec, grid_map, pose, ranges, sensor, params.insertion,
                                                                config.max_insert_range, config.field_radius)[0])
    segments = np.asarray(scenario.world.segments, np.float64)
    grid_map = empty_map(spec)
    predicted, drawn_mean, drawn_sd, exact_predicted, exact_mean, exact_sd = [], [], [], [], [], []
    for t in range(len(idx)):
        if t:
            u = between_np(odometry[t - 1], odometry[t])
            true_motion = between_np(truth[t - 1], truth[t])
            poses = np.asarray(propose(jax.random.fold_in(jax.random.key(seed), t), jnp.asarray(truth[t - 1], jnp.float32),
                                       jnp.asarray(u, jnp.float32), jnp.asarray(scans[t]), grid_map.hit_dist2), np.float64)
            errors = motion_error_components(truth[t - 1], poses, true_motion)
            prediction_error = motion_error_components(odometry[t - 1], odometry[t], true_motion)
            predicted.append(prediction_error)
            drawn_mean.append(errors.mean(0))
            drawn_sd.append(errors.std(0))
            if t % exact_every == 0:
                mean, sd = exact_posterior(truth[t - 1], u, scans[t], sensor, segments, params, config.beam_stride,
                                           true_motion)
                exact_predicted.append(prediction_error)
                exact_mean.append(mean)
                exact_sd.append(sd)
        grid_map = insert(grid_map, jnp.asarray(truth[t], jnp.float32), jnp.asarray(scans[t]))

    def summary(prediction, mean, sd):
        prediction, mean, sd = map(np.asarray, (prediction, mean, sd))
        return {"slope": [float(np.polyfit(prediction[:, k], mean[:, k], 1)[0]) for k in range(3)],
                "error_rms": np.sqrt((mean**2).mean(0)).tolist(), "sd": sd.mean(0).tolist(),
                "calibration": np.sqrt(((mean / sd) ** 2).mean(0)).tolist()}

    return {"seed": seed, "steps": len(idx) - 1, "axes": AXES,
            "odometry_error_rms": np.sqrt((np.asarray(predicted) ** 2).mean(0)).tolist(),
            "proposal": summary(predicted, drawn_mean, drawn_sd),
            "exact": summary(exact_predicted, exact_mean, exact_sd)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[18])
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--exact-every", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a build_setup name (diagnostic)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    overrides = parse_assignments(args.set)
    rows = [calibrate(seed, overrides, args.draws, args.exact_every) for seed in args.seeds]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"set": overrides, "runs": rows}, indent=1) + "\n")
    for row in rows:
        p, e = row["proposal"], row["exact"]
        print(f"seed {row['seed']}: odometry error rms {np.round(row['odometry_error_rms'], 4)} (along, across, heading)")
        print(f"  proposal: slope {np.round(p['slope'], 2)}, sd {np.round(p['sd'], 4)}, calibration {np.round(p['calibration'], 2)}")
        print(f"  exact:    slope {np.round(e['slope'], 2)}, sd {np.round(e['sd'], 4)}, calibration {np.round(e['calibration'], 2)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
