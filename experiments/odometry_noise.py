"""Is the odometry model as wide as the logs' real odometry error? Data against model, no SLAM.

For every relation (t1, t2, motion) of a log's ground truth, the odometry's own relative motion
between the two scans is compared with the relation's, and each component of the error
(x, y in the frame at t1, and theta) is divided by the std the motion model gives that odometry
motion (:func:`jaxslam.motion.noise_std` at the default parameters, or ``--set``). A model as
wide as the real error gives a root mean square z of about 1 per component; above 1 the model is
too narrow, below 1 too wide. Relations are grouped by the length of their odometry motion
(short ones are the steps a filter takes; long ones span loops, where the model, linear in a
single motion, says little).

    python experiments/odometry_noise.py --out docs/results/odometry_noise.json
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from datasets import DATA, DATASETS as LOGS  # experiments/datasets.py (this folder comes first on sys.path)

LENGTHS = [(0.0, 0.7), (0.7, 2.0), (2.0, 5.0)]
"""Odometry motion lengths (m) the relations are grouped by."""


def odometry_against_model(log, relations, motion_params) -> list[dict]:
    """Per length group: relations, rms z of (x, y, theta), median translational error per metre
    and median rotational error per metre of the odometry."""
    import jax.numpy as jnp

    from jaxslam.geometry import between_np, wrap_angle_np
    from jaxslam.metrics import lookup_poses
    from jaxslam.motion import noise_std

    odometry = np.asarray(log.odometry, np.float64)
    stamps = np.asarray(log.timestamps, np.float64)
    motions = between_np(lookup_poses(stamps, odometry, relations.t1), lookup_poses(stamps, odometry, relations.t2))
    error = motions - relations.motion
    error[:, 2] = wrap_angle_np(error[:, 2])
    length = np.hypot(motions[:, 0], motions[:, 1])
    z = error / np.asarray(noise_std(jnp.asarray(motions, jnp.float32), motion_params), np.float64)
    rows = []
    for low, high in LENGTHS:
        group = (length >= low) & (length < high)
        if group.sum() < 5:
            continue
        per_metre = np.maximum(length[group], 1e-3)
        rows.append({
            "length_m": [low, high], "relations": int(group.sum()),
            "rms_z": dict(zip(("x", "y", "theta"), np.sqrt(np.mean(z[group] ** 2, axis=0)).round(3).tolist())),
            "median_translation_error_per_m": float(np.median(np.hypot(*error[group, :2].T) / per_metre)),
            "median_rotation_error_per_m": float(np.median(np.abs(error[group, 2]) / per_metre)),
        })
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--logs", nargs="+", default=list(LOGS), choices=list(LOGS))
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="motion.* parameters")
    parser.add_argument("--out", default="results/odometry_noise.json")
    args = parser.parse_args(argv)
    from jaxslam.cli import parse_assignments
    from jaxslam.config import params_from_dict
    from jaxslam.io import read_log
    from jaxslam.io.relations import read_relations

    data = Path(args.data)
    if not data.is_dir():
        print(f"datasets not found at {data}", file=sys.stderr)
        return 2
    overrides = parse_assignments(args.set)
    params = params_from_dict(overrides)
    out = {"motion": {k: float(v) for k, v in params.motion._asdict().items()}, "logs": {}}
    for name in args.logs:
        log_file, relations_file = LOGS[name]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the readers' notes on padding and dropped scans
            log = read_log(data / log_file)
        rows = odometry_against_model(log, read_relations(data / relations_file), params.motion)
        out["logs"][name] = rows
        for row in rows:
            z = row["rms_z"]
            print(f"{name:10s} {row['length_m'][0]:.1f}-{row['length_m'][1]:.1f} m  n={row['relations']:5d}  "
                  f"rms z x {z['x']:.2f} y {z['y']:.2f} theta {z['theta']:.2f}  "
                  f"rot. error {row['median_rotation_error_per_m']:.4f} rad/m")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
