"""Does the free-space evidence prefer the true pose? A check on maps drawn at the true poses.

The free-space evidence (:func:`jaxslam.likelihood_field.see_through_log_likelihood`) counts the
beams whose free path crosses a cell the map holds as an endpoint. It is evidence only if the
true pose crosses fewer than the poses round it; otherwise it pulls every pose one way, and the
next insertion moves the map with it. For each box-family world given, the script inserts every
scan of the log at its true pose into one dense map, then, at every ``--every``-th scan from
``--first`` on, counts the crossing beams at the true pose and at poses moved in the robot's
frame (``PERTURBATIONS``), in that full map. A second map holds the same scans plus, again, those
of the first visit to X rotated ``--rotation`` degrees about X (a landmark the map holds twice,
as a wrong closure leaves it): the crossings at the true poses of the scans near X in it are the
evidence the check exists for.

    python experiments/free_space_bias.py --worlds 1000 1011 1010
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import box_family as family_experiment  # noqa: E402  (experiments/box_family.py: the worlds' draws and keys)

from jaxslam.config import default_params  # noqa: E402
from jaxslam.geometry import compose  # noqa: E402
from jaxslam.grid import GridSpec  # noqa: E402
from jaxslam.laser import subsample_beams  # noqa: E402
from jaxslam.likelihood_field import see_through_log_likelihood  # noqa: E402
from jaxslam.metrics import checkpoint_passages  # noqa: E402
from jaxslam.occupancy import empty_map, free_lengths, insert_scan  # noqa: E402
from jaxslam.sim import box_family  # noqa: E402

PERTURBATIONS = ((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (-0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, -0.1, 0.0),
                 (0.0, 0.0, 0.03), (0.0, 0.0, -0.03), (0.2, 0.0, 0.0), (-0.2, 0.0, 0.0), (0.0, 0.2, 0.0),
                 (0.0, -0.2, 0.0))
"""Poses round the truth, (forward m, left m, heading rad) in the robot's frame; the first is the truth."""
MAX_INSERT_RANGE = 5.5
"""The family's insertion range (its longest laser plus the json's margin), as the filter's."""


def crossing_counts(world_seed: int, first: int, every: int, rotation_deg: float, max_laps: int | None = None):
    """``(counts, doubled)``: the crossing beams summed over the checked scans at each of
    :data:`PERTURBATIONS` in the map drawn at the true poses, and, at the true poses of the scans
    within 3 m of X after the first visit, in the map with the first visit's scans twice (the
    plain map's count, the doubled map's)."""
    draw = family_experiment.world_draw(world_seed, max_laps)
    simulation_key, _ = family_experiment.world_keys(world_seed)
    scenario = box_family.family_scenario(draw, simulation_key)
    log, truth = scenario.log, np.asarray(scenario.true_poses, np.float32)
    xmin, ymin, xmax, ymax = scenario.world.bounds
    spec = GridSpec.from_bounds(xmin - 3.0, ymin - 3.0, xmax + 3.0, ymax + 3.0, 0.05)
    params = default_params()
    sensor = log.sensor
    samples = int(math.ceil(MAX_INSERT_RANGE / spec.resolution))
    insert = jax.jit(insert_scan, static_argnums=(0, 6, 7))
    crossings = jax.jit(lambda hit, pose, free, lik_sensor: see_through_log_likelihood(
        spec, hit, pose, free, lik_sensor, params.likelihood._replace(gain=jnp.float32(1.0), see_through=jnp.float32(
            math.e ** -1)), samples) * -1.0)  # gain 1 and log(see_through) = -1: the count itself
    full = empty_map(spec)
    for t in range(truth.shape[0]):
        full, _ = insert(spec, full, jnp.asarray(truth[t]), log.ranges[t], sensor, params.insertion, MAX_INSERT_RANGE, 4)
    checkpoint = np.asarray(scenario.metadata["checkpoint_x"], np.float64)
    passages = checkpoint_passages(truth, checkpoint, 0.3)
    # The first visit: from the start to the first return over X, rotated about X.
    turn = np.array([checkpoint[0], checkpoint[1], 0.0], np.float32)
    rotate = np.array([0.0, 0.0, math.radians(rotation_deg)], np.float32)
    doubled = full
    for t in range(int(passages[1]) + 1):
        local = compose(-turn * np.array([1, 1, 0], np.float32), truth[t])  # relative to X, heading kept
        moved = compose(turn, compose(rotate, local))
        doubled, _ = insert(spec, doubled, jnp.asarray(moved), log.ranges[t], sensor, params.insertion,
                            MAX_INSERT_RANGE, 4)

    def scan(t):
        lik_sensor, ranges = subsample_beams(sensor, log.ranges[t], 2)
        return lik_sensor, free_lengths(ranges, lik_sensor, params.insertion, MAX_INSERT_RANGE)

    counts = np.zeros(len(PERTURBATIONS))
    for t in range(first, truth.shape[0], every):
        lik_sensor, free = scan(t)
        for k, p in enumerate(PERTURBATIONS):
            counts[k] += float(crossings(full.hit_dist2, compose(jnp.asarray(truth[t]), jnp.asarray(p, jnp.float32)),
                                         free, lik_sensor))
    near_x = [t for t in range(int(passages[1]) + 1, truth.shape[0])
              if np.hypot(*(truth[t, :2] - checkpoint)) < 3.0]
    plain_twice = np.zeros(2)
    for t in near_x:
        lik_sensor, free = scan(t)
        plain_twice += [float(crossings(m.hit_dist2, jnp.asarray(truth[t]), free, lik_sensor)) for m in (full, doubled)]
    return counts, plain_twice, len(range(first, truth.shape[0], every)), len(near_x)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", type=int, nargs="+", default=[1000, 1011, 1010], help="box-family world seeds")
    ap.add_argument("--first", type=int, default=100, help="the first scan checked")
    ap.add_argument("--every", type=int, default=10, help="check every EVERY-th scan from --first")
    ap.add_argument("--rotation", type=float, default=10.0, help="degrees the first visit's second copy is turned about X")
    ap.add_argument("--max-laps", type=int, help="cut every world to at most K laps (a smoke test)")
    args = ap.parse_args(argv)
    header = " ".join(f"{p[0]:+.1f},{p[1]:+.1f},{p[2]:+.2f}" for p in PERTURBATIONS)
    print(f"crossing beams summed over the checked scans at (forward m, left m, heading rad) from the truth:\n"
          f"world scans | {header} | scans near X: plain map, first visit twice")
    for seed in args.worlds:
        counts, twice, num_scans, num_near = crossing_counts(seed, args.first, args.every, args.rotation, args.max_laps)
        print(f"{seed} {num_scans} | " + " ".join(f"{int(c):>15d}" for c in counts)
              + f" | {num_near}: {int(twice[0])}, {int(twice[1])}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
