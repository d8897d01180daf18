"""Throughput of the look-ahead proposal (LP): beam evaluations per second.

One LP update costs N * L * (k+1) * B beam evaluations (N SLAM particles, L localizers,
horizon k, B beams; docs/design.md). This script times the jitted RBPF step with
proposal "lp" on a realistic office-like map (after warm-up, median of repetitions),
the LP proposal alone (the step minus scan insertion and SLAM resampling), and, in the
same run, a plain vmapped nearest-cell lookup of the same number of beams (the
baseline of docs/design.md: ~5e7 beam evaluations/s on the 2-core CPU). It then measures
how the step's time grows with N, L and k (slopes of log time against log size;
1 = linear) and writes everything as JSON.

    python benchmarks/bench_lookahead.py --out results/bench_lookahead.json [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import maps as paged
from jaxslam import rbpf
from jaxslam.config import SlamConfig, default_params
from jaxslam.geometry import between, compose
from jaxslam.proposals import lookahead
from jaxslam.proposals.base import StepInputs
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.segment_map import raycast


def office_world() -> np.ndarray:
    """Segments (M, 4) of a 24 m x 16 m office: outer walls, a corridor, rooms with doorways."""
    segs = [
        (0, 0, 24, 0), (24, 0, 24, 16), (24, 16, 0, 16), (0, 16, 0, 0),
        # corridor walls at y = 7 and y = 9 with doorways every 4 m
    ]
    for y in (7.0, 9.0):
        for x0 in range(0, 24, 4):
            segs.append((x0, y, x0 + 3.0, y))
    for x in range(4, 24, 4):  # room partitions
        segs.append((x, 0, x, 7))
        segs.append((x, 9, x, 16))
    # clutter: boxes in the rooms
    rng = np.random.default_rng(0)
    for _ in range(14):
        cx, cy = rng.uniform(1, 23), rng.choice([rng.uniform(1, 6), rng.uniform(10, 15)])
        w = rng.uniform(0.3, 0.9)
        segs += [(cx - w, cy - w, cx + w, cy - w), (cx + w, cy - w, cx + w, cy + w),
                 (cx + w, cy + w, cx - w, cy + w), (cx - w, cy + w, cx - w, cy - w)]
    return np.asarray(segs, np.float32)


MAP_EXTENT = 64.0
"""Side (m) of the benchmark's virtual grid (the corridor world is 26 m x 18 m)."""


def corridor_path(num: int) -> np.ndarray:
    x = np.linspace(2.0, 2.0 + 0.8 * (num - 1), num)
    y = 8.0 + 0.3 * np.sin(x / 3.0)
    theta = np.arctan2(np.gradient(y), np.gradient(x))
    return np.stack([x, y, theta], axis=-1).astype(np.float32)


def setup(num_beams: int, horizon: int):
    segs = jnp.asarray(office_world())
    sensor = make_sensor(uniform_beams(num_beams, math.pi), range_min=0.05, range_max=15.0)
    spec = SlamConfig(map_extent=MAP_EXTENT).grid
    path = corridor_path(12 + horizon)

    @jax.jit
    def scan(pose):
        laser = compose(pose, sensor.laser_pose)
        return raycast(segs, laser[:2], laser[2] + sensor.beam_angles, sensor.range_max)[0]

    scans = np.stack([np.asarray(scan(jnp.asarray(p))) for p in path])
    params = default_params()
    insert = jax.jit(paged.insert_scans, static_argnums=(0, 6, 7))
    grid_map = paged.empty(spec, 1, 2000)  # one particle's map
    for p, r in zip(path[:10], scans[:10]):
        grid_map, _ = insert(spec, grid_map, jnp.asarray(p)[None], jnp.asarray(r), sensor, params.insertion, 15.0, 4)
    motions = np.asarray(between(path[:-1], path[1:]), np.float32)
    t = 10
    inputs = StepInputs(
        motion=jnp.asarray(motions[t - 1]), ranges=jnp.asarray(scans[t]),
        future_motions=jnp.asarray(motions[t:t + horizon]).reshape(horizon, 3),
        future_ranges=jnp.asarray(scans[t + 1:t + 1 + horizon]).reshape(horizon, num_beams),
        future_valid=jnp.ones(horizon, bool),
    )
    return spec, sensor, params, grid_map, inputs, jnp.asarray(path[t - 1])


def make_state(grid_map, pose, n):
    maps = paged.resample(grid_map, jnp.zeros((n,), jnp.int32))  # n particles sharing its tiles
    return rbpf.SlamState(jnp.broadcast_to(pose, (n, 3)), jnp.full((n,), -math.log(n), jnp.float32), maps,
                          jnp.int32(0))


def median_time(fn, reps: int) -> float:
    """Median wall time (s) of ``fn(i)`` over ``reps`` calls after one warm-up call."""
    return timings(fn, reps)["median"]


def timings(fn, reps: int) -> dict:
    """Median and minimum wall time (s) over ``reps`` calls after a warm-up (compile) call.
    On a shared machine the minimum is the better estimate of the intrinsic cost."""
    jax.block_until_ready(fn(0))
    times = []
    for i in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(i + 1))
        times.append(time.perf_counter() - t0)
    return {"median": statistics.median(times), "min": min(times)}


_step = jax.jit(rbpf.step, static_argnames="config")


def _propose_all(keys, poses, maps, inputs, sensor, params, config):
    return jax.vmap(lookahead.propose, in_axes=(0, 0, paged.FIELD_AXES, None, None, None, None))(
        keys, poses, paged.fields(maps), inputs, sensor, params, config)


_propose = jax.jit(_propose_all, static_argnames="config")


@jax.jit
def plain_lookup(poses, hit_dist2, ranges, beam_angles, resolution_inv, origin):
    """Baseline: for poses (N, P, 3) in maps (N, H, W), sum the raw cell values at B endpoints."""
    def one_map(poses_n, grid):
        angle = poses_n[:, 2:3] + beam_angles  # (P, B)
        ex = poses_n[:, 0:1] + ranges * jnp.cos(angle)
        ey = poses_n[:, 1:2] + ranges * jnp.sin(angle)
        col = jnp.floor((ex - origin[0]) * resolution_inv).astype(jnp.int32)
        row = jnp.floor((ey - origin[1]) * resolution_inv).astype(jnp.int32)
        h, w = grid.shape
        ok = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        vals = grid.reshape(-1).at[jnp.where(ok, row * w + col, h * w)].get(mode="fill", fill_value=255)
        return jnp.sum(vals.astype(jnp.float32), axis=-1)
    return jax.vmap(one_map)(poses, hit_dist2)


def measure_step(base, spec, sensor, params, grid_map, inputs_full, pose, n, l, k, reps):
    config = dataclasses.replace(base, num_particles=n, num_localizers=l, horizon=k)
    inputs = inputs_full._replace(future_motions=inputs_full.future_motions[:k],
                                  future_ranges=inputs_full.future_ranges[:k],
                                  future_valid=inputs_full.future_valid[:k])
    state = make_state(grid_map, pose, n)
    step = timings(lambda i: _step(jax.random.key(i), state, inputs, sensor, params, config), reps)
    keys = lambda i: jax.random.split(jax.random.key(i), n)  # noqa: E731
    prop = timings(lambda i: _propose(keys(i), state.poses, state.maps, inputs, sensor, params, config), reps)
    beams = n * l * (k + 1) * int(sensor.beam_angles.shape[0])
    return {"N": n, "L": l, "k": k, "beam_evals": beams,
            "step_s": step["median"], "step_min_s": step["min"],
            "proposal_s": prop["median"], "proposal_min_s": prop["min"],
            "step_beam_evals_per_s": beams / step["median"], "proposal_beam_evals_per_s": beams / prop["median"],
            "proposal_beam_evals_per_s_best": beams / prop["min"]}


def slope(xs, ys) -> float:
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="results/bench_lookahead.json")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="fewer sizes and repetitions")
    args = ap.parse_args(argv)
    reps = 3 if args.quick else args.reps
    num_beams, n0, l0, k0 = 180, 30, 100, 5
    k_max = 8
    spec, sensor, params, grid_map, inputs, pose = setup(num_beams, k_max)
    # The look-ahead's own cost: localizers from the odometry (the paper's LP, as the recorded
    # figures were measured). The library's default LP adds one scan match per SLAM particle
    # before it, the SMP's cost (bench_rbpf.py).
    base = SlamConfig(num_particles=n0, proposal="lp", map_extent=MAP_EXTENT, num_localizers=l0, horizon=k0,
                      max_insert_range=15.0, lookahead_initial="odometry")
    print(f"devices: {jax.devices()}  map {spec.num_tiles} tiles  B={num_beams}")

    main_row = measure_step(base, spec, sensor, params, grid_map, inputs, pose, n0, l0, k0, reps)

    # Baseline in the same run: the same number of beam lookups, plain nearest cell in dense maps.
    _, field, dense_grid = paged.to_dense(spec, grid_map, 0)
    dense_fields = jnp.broadcast_to(jnp.asarray(field), (n0,) + field.shape)
    num_poses = l0 * (k0 + 1)
    rng = np.random.default_rng(0)
    poses = jnp.asarray(np.asarray(pose) + rng.normal(0, 0.1, (n0, num_poses, 3)), jnp.float32)
    ranges = inputs.ranges
    plain = timings(lambda i: plain_lookup(poses + 1e-6 * i, dense_fields, ranges,
                                           sensor.beam_angles, 1.0 / spec.resolution,
                                           jnp.asarray(dense_grid.origin, jnp.float32)), reps)
    t_plain = plain["median"]
    plain_rate = main_row["beam_evals"] / t_plain

    # The same RBPF step with the odometry proposal: what the step costs besides the LP
    # (scan insertion into every map, SLAM resampling). No future scans.
    op_config = dataclasses.replace(base, proposal="op", horizon=0)
    state = make_state(grid_map, pose, n0)
    op_inputs = inputs._replace(future_motions=inputs.future_motions[:0], future_ranges=inputs.future_ranges[:0],
                                future_valid=inputs.future_valid[:0])
    op_step = timings(lambda i: _step(jax.random.key(i), state, op_inputs, sensor, params, op_config), reps)

    sizes = {"N": [10, 20, 30, 40], "L": [25, 50, 100, 200], "k": [1, 3, 5, 8]}
    if args.quick:
        sizes = {"N": [10, 30], "L": [50, 100], "k": [1, 5]}
    scaling = {}
    for name, values in sizes.items():
        rows = []
        for v in values:
            n, l, k = (v if name == "N" else n0), (v if name == "L" else l0), (v if name == "k" else k0)
            rows.append(measure_step(base, spec, sensor, params, grid_map, inputs, pose, n, l, k, reps))
            r = rows[-1]
            print(f"  {name}={v:4d}: step {r['step_s'] * 1e3:8.1f} ms (min {r['step_min_s'] * 1e3:7.1f})"
                  f"  proposal {r['proposal_s'] * 1e3:8.1f} ms (min {r['proposal_min_s'] * 1e3:7.1f})")
        x = [v + 1 if name == "k" else v for v in values]  # cost is linear in k + 1
        scaling[name] = {
            "values": values, "rows": rows,
            "step_loglog_slope": slope(x, [r["step_min_s"] for r in rows]),
            "proposal_loglog_slope": slope(x, [r["proposal_min_s"] for r in rows]),
        }

    result = {
        "device": str(jax.devices()[0]), "platform": platform.platform(), "cpu_count": os.cpu_count(),
        "map_shape": list(spec.shape), "num_beams": num_beams, "reps": reps,
        "main": main_row,
        "plain_lookup": {"seconds": t_plain, "min_seconds": plain["min"], "beam_evals_per_s": plain_rate,
                         "beam_evals_per_s_best": main_row["beam_evals"] / plain["min"]},
        "op_step": {"seconds": op_step["median"], "min_seconds": op_step["min"]},
        "step_rate_over_plain": main_row["step_beam_evals_per_s"] / plain_rate,
        "proposal_rate_over_plain": main_row["proposal_beam_evals_per_s"] / plain_rate,
        "proposal_best_rate_over_plain_best": plain["min"] / main_row["proposal_min_s"],
        "target_beam_evals_per_s": 4e7,
        "scaling": scaling,
    }
    print()
    print(f"{'what (N=30 L=100 k=5 B=180)':32s} {'median ms':>10s} {'min ms':>8s} {'beam evals/s':>14s} "
          f"{'best /s':>10s} {'/ plain':>8s}")
    beams = main_row["beam_evals"]
    for what, t, tmin in (("LP rbpf step", main_row["step_s"], main_row["step_min_s"]),
                          ("LP proposal only (vmapped)", main_row["proposal_s"], main_row["proposal_min_s"]),
                          ("plain nearest-cell lookup", t_plain, plain["min"]),
                          ("OP rbpf step (insertion etc.)", op_step["median"], op_step["min"])):
        print(f"{what:32s} {t * 1e3:10.1f} {tmin * 1e3:8.1f} {beams / t:14.3e} {beams / tmin:10.3e} "
              f"{t_plain / t:8.2f}")
    print("growth (log-log slope of time; x = N, L, k+1):",
          {k: round(v["step_loglog_slope"], 3) for k, v in scaling.items()},
          "proposal only:", {k: round(v["proposal_loglog_slope"], 3) for k, v in scaling.items()})
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
