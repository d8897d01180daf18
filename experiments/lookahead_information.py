"""How much can k scans ahead sharpen the pose at time t? A linear-Gaussian bound.

The look-ahead proposal draws x_t from p(x_t | x_{t-1}, z_t, ..., z_{t+k}), so at best its pose
is as precise as a fixed-lag smoother's. This script computes that smoother's std of x_t for a
robot driving straight, when every scan pins its own pose to ``--scan-std`` (x, y, theta) and
consecutive processed poses are linked by the filter's odometry model (GMapping's, with the
library's default noise, for a motion of ``--step`` metres). The future scans reach x_t only
through the odometry, so when the odometry is much looser than a scan they add almost nothing:
that is the ceiling of what the LP can gain over a scan match on a well-structured log.

    python experiments/lookahead_information.py [--step 0.5] [--horizon 5] [--scan-std 0.009 0.009 0.0021]

The default scan precision is the bilinear matcher's median error in the simulated office
(``tests/test_refine.py``; docs/tuning.md, "Reading the field between cells").
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def smoothed_std(scan_std: np.ndarray, step_std: np.ndarray, step: float, horizon: int) -> np.ndarray:
    """Std of x_t (robot frame: along, lateral, heading) given the scans at t .. t + horizon.

    Args:
      scan_std: (3,) std of one scan's own pose estimate (m, m, rad).
      step_std: (3,) std of the odometry noise of one step (m, m, rad).
      step: length of one straight step (m); a heading error at s moves x_{s+1} sideways by step x it.
      horizon: k, the number of scans ahead.
    """
    size = 3 * (horizon + 1)
    information = np.zeros((size, size))
    for s in range(horizon + 1):
        information[3 * s:3 * s + 3, 3 * s:3 * s + 3] += np.diag(1.0 / scan_std**2)
    # x_{s+1} = A x_s + u + noise, linearised about a straight path.
    transition = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, step], [0.0, 0.0, 1.0]])
    for s in range(horizon):
        residual = np.zeros((3, size))
        residual[:, 3 * s:3 * s + 3] = -transition
        residual[:, 3 * s + 3:3 * s + 6] = np.eye(3)
        information += residual.T @ np.diag(1.0 / step_std**2) @ residual
    return np.sqrt(np.diag(np.linalg.inv(information))[:3])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--step", type=float, default=0.5, help="metres between processed scans")
    parser.add_argument("--horizon", type=int, default=5)
    parser.add_argument("--scan-std", type=float, nargs=3, default=[0.009, 0.009, 0.0021],
                        metavar=("X", "Y", "THETA"))
    args = parser.parse_args(argv)
    if args.step <= 0 or args.horizon < 0 or min(args.scan_std) <= 0:
        parser.error("--step and --scan-std must be > 0 and --horizon >= 0")
    import jax.numpy as jnp

    from jaxslam import default_params, motion

    params = default_params()
    step_std = np.asarray(motion.noise_std(jnp.array([args.step, 0.0, 0.0]), params.motion), dtype=np.float64)
    scan_std = np.asarray(args.scan_std, dtype=np.float64)
    print(f"odometry noise of one {args.step:g} m step (along, lateral, heading): {np.round(step_std, 4)}")
    print("scans used | std of x_t: along [m], lateral [m], heading [rad] | lateral vs the scan alone")
    for k in sorted({0, 1, args.horizon}):
        std = smoothed_std(scan_std, step_std, args.step, k)
        print(f"t .. t+{k} | {std[0]:.4f}, {std[1]:.4f}, {std[2]:.4f} | {std[1] / scan_std[1]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
