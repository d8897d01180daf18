"""One step whose window holds two poses that explain the scan: what the hill climber and the window
posterior make of it (a figure).

A room's walls are in the map twice, the second copy ``--shift`` metres along x (a map that
doubled a wall, as a false closure leaves one), and the odometry predicts the point between the
two poses the scan fits. From the prediction, the hill climber of the earlier SMP
(:func:`jaxslam.scan_matching.match`, 24 rounds) climbs to one of them; the window posterior
(:mod:`jaxslam.window_posterior`) keeps both, each with its mass. The figure shows log pi over
(x, y) (the best heading at each) and over theta (the best position at each) on a lattice of the
window, the climber's end and the modes' means.

    python experiments/window_modes.py --out docs/results/window_modes.png
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOM = np.array([
    [0.0, 0.0, 6.0, 0.0], [6.0, 0.0, 6.0, 4.0], [6.0, 4.0, 0.0, 4.0], [0.0, 4.0, 0.0, 0.0],
    [2.0, 1.5, 2.6, 1.5], [2.6, 1.5, 2.6, 2.1], [4.2, 3.0, 4.8, 2.6],
], np.float32)
"""A 6 m x 4 m room with a box and a slanted panel (segments x0, y0, x1, y1 in metres)."""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shift", type=float, default=0.3, help="how far (m, along x) the map's second copy lies")
    parser.add_argument("--lattice", type=int, default=40, help="lattice points a side of the window for the figure")
    parser.add_argument("--out", default="results/window_modes.png")
    args = parser.parse_args(argv)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxslam import motion, window_posterior
    from jaxslam.config import default_params
    from jaxslam.geometry import between, compose
    from jaxslam.grid import GridSpec
    from jaxslam.laser import make_sensor, uniform_beams
    from jaxslam.likelihood_field import endpoint_log_likelihoods
    from jaxslam.occupancy import empty_map, insert_scan
    from jaxslam.scan_matching import match
    from jaxslam.segment_map import expected_ranges

    sensor = make_sensor(uniform_beams(181, math.pi), range_min=0.05, range_max=8.0)
    spec = GridSpec.from_bounds(-1.0, -1.0, 7.0, 5.0, 0.05)
    params = default_params()
    previous, true_pose = np.array([1.6, 0.9, 0.3], np.float32), np.array([2.4, 1.12, 0.43], np.float32)
    scan = lambda pose: expected_ranges(jnp.asarray(ROOM), jnp.asarray(pose), sensor)[0]
    grid_map = empty_map(spec)
    for pose in (previous, true_pose):
        for dx in (0.0, args.shift):
            grid_map, _ = insert_scan(spec, grid_map, jnp.asarray(pose) + jnp.asarray([dx, 0.0, 0.0]), scan(pose),
                                      sensor, params.insertion, 10.0, 4)
    # The window posterior reads a dense field through a config whose grid is the dense one.
    dense_config = _DenseConfig(spec)
    predicted = true_pose + np.array([args.shift / 2, 0.0, 0.0], np.float32)
    motion_step = jnp.asarray(between(jnp.asarray(previous), jnp.asarray(predicted)))
    ranges = scan(true_pose)
    post = window_posterior.window_posterior(jnp.asarray(previous), grid_map.hit_dist2, motion_step, ranges, sensor,
                                             params, dense_config, fit_gain=1.0)
    climbed = match(spec, grid_map.hit_dist2, jnp.asarray(predicted), ranges, sensor, params.likelihood,
                    params.scan_match.linear_step, params.scan_match.angular_step, 24, "bilinear")
    half = window_posterior.half_widths(motion_step, params)
    lattice = window_posterior.coarse_offsets(half, args.lattice)
    poses = compose(jnp.asarray(previous), motion_step + lattice)
    untempered = params.likelihood._replace(gain=1.0)
    log_pi = np.concatenate([np.asarray(params.likelihood.gain * endpoint_log_likelihoods(
        spec, grid_map.hit_dist2, chunk, ranges, sensor, untempered, "nearest")
        + motion.log_density(chunk, jnp.asarray(previous), motion_step, params.motion))
        for chunk in jnp.split(poses, 8)]).reshape((args.lattice,) * 3)
    poses = np.asarray(poses).reshape((args.lattice,) * 3 + (3,))

    kept = np.isfinite(np.asarray(post.log_masses))
    shares = np.exp(np.asarray(window_posterior.mixture_log_weights(post)))
    fig, (ax_xy, ax_theta) = plt.subplots(1, 2, figsize=(11, 4.5))
    image = ax_xy.pcolormesh(poses[:, :, 0, 0], poses[:, :, 0, 1], log_pi.max(axis=2), shading="auto", cmap="viridis")
    fig.colorbar(image, ax=ax_xy, label="log pi (best heading)")
    ax_theta.plot(poses[0, 0, :, 2], log_pi.max(axis=(0, 1)), color="0.3", label="log pi (best position)")
    for ax in (ax_xy,):
        ax.plot(*true_pose[:2], "w+", ms=14, mew=2, label="pose the scan was taken at")
        ax.plot(true_pose[0] + args.shift, true_pose[1], "wx", ms=12, mew=2, label="its double in the map")
        ax.plot(*predicted[:2], "o", mfc="none", mec="w", ms=10, label="odometry prediction")
        ax.plot(*np.asarray(climbed.pose)[:2], "r^", ms=10, label="hill climber's end (24 rounds)")
        for m in np.flatnonzero(kept):
            ax.plot(*np.asarray(post.means[m])[:2], "s", mfc="none", mec="orange", ms=12, mew=2)
            ax.annotate(f"mode, share {shares[m]:.2f}", np.asarray(post.means[m])[:2] + np.array([-0.08, 0.04 + 0.04 * m]),
                        color="orange")
    ax_xy.set(xlabel="x [m]", ylabel="y [m]", title="the window over (x, y)", aspect="equal")
    ax_xy.legend(loc="lower left", fontsize=7, facecolor="0.55")
    ax_theta.axvline(float(climbed.pose[2]), color="r", ls="--", label="hill climber's end")
    for m in np.flatnonzero(kept):
        ax_theta.axvline(float(post.means[m][2]), color="orange", label="a mode's mean")
    ax_theta.set(xlabel="theta [rad]", ylabel="log pi", title="the window over theta")
    ax_theta.legend(fontsize=7)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"modes kept {int(kept.sum())}: means {np.asarray(post.means)[kept].round(3).tolist()}, "
          f"shares {shares[kept].round(3).tolist()}; hill climber's end {np.asarray(climbed.pose).round(3).tolist()}; "
          f"wrote {out}")
    return 0


class _DenseConfig:
    """The few ``SlamConfig`` fields the window posterior reads, on a dense grid."""

    def __init__(self, spec):
        from jaxslam.config import SlamConfig
        defaults = SlamConfig()
        self.grid = spec
        for name in ("window_cells", "window_levels", "window_modes", "window_keep", "likelihood_lookup",
                     "match_lookup", "field_radius", "sensor_model"):
            setattr(self, name, getattr(defaults, name))
        self.max_insert_range = 10.0


if __name__ == "__main__":
    sys.exit(main())
