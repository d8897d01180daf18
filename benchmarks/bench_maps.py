"""Dense against paged maps: the cost of inserting a scan into every particle's map and of a resampling.

The dense maps are what the filters use today: an (N, H, W) stack sized like Intel's grid
(1,451 x 1,649 cells at 5 cm), one ``occupancy.insert_scan`` per particle under ``vmap``, and
resampling as a gather of whole maps. The paged maps (``jaxslam.paged_map``) keep tiles in one
shared pool: insertion gathers a window of tiles per particle and writes back the changed ones,
resampling copies page tables. Both insert the same scans (a 180-degree laser, 181 beams,
ranges from the simulated office, 15 m reach) at poses spread as a particle cloud is; the
figures are the median of ``--reps`` timed calls after one compiling call.

    python benchmarks/bench_maps.py --out results/bench_maps.json [--particles 30 100]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import paged_map
from jaxslam.config import default_params
from jaxslam.grid import GridSpec
from jaxslam.occupancy import empty_map, insert_scan
from jaxslam.sim import office_scenario

MAX_RANGE, RADIUS = 15.0, 4


def _median_seconds(fn, reps):
    jax.block_until_ready(fn())  # compile
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def measure(num_particles: int, reps: int) -> dict:
    log = office_scenario(jax.random.key(0), num_scans=200, num_beams=181).log
    sensor, ranges = log.sensor, jnp.asarray(log.ranges[100])
    center = log.odometry[100]
    rng = np.random.default_rng(0)
    poses = jnp.asarray(center + rng.normal(0, [0.1, 0.1, 0.02], (num_particles, 3)), jnp.float32)
    insertion = default_params().insertion
    ancestors = jnp.asarray(rng.integers(0, num_particles, num_particles), jnp.int32)

    dense_spec = GridSpec((1451, 1649), 0.05, (float(center[0]) - 36.0, float(center[1]) - 41.0))
    dense = jax.tree.map(lambda a: jnp.broadcast_to(a, (num_particles,) + a.shape), empty_map(dense_spec))
    dense_insert = jax.jit(jax.vmap(insert_scan, in_axes=(None, 0, 0, None, None, None, None, None)),
                           static_argnums=(0, 6, 7))
    dense_resample = jax.jit(lambda maps, anc: jax.tree.map(lambda a: a[anc], maps))

    spec = paged_map.PagedGridSpec()
    window = spec.window_tiles(MAX_RANGE, RADIUS)
    paged = paged_map.empty(spec, num_particles, capacity=num_particles * window * window)
    paged_insert = jax.jit(paged_map.insert_scans, static_argnums=(0, 6, 7))
    paged_resample = jax.jit(paged_map.resample)
    filled, _ = paged_insert(spec, paged, poses, ranges, sensor, insertion, MAX_RANGE, RADIUS)
    shared = paged_resample(filled, jnp.zeros(num_particles, jnp.int32))  # every particle shares one map

    return {
        "particles": num_particles,
        "dense_insert_s": _median_seconds(
            lambda: dense_insert(dense_spec, dense, poses, ranges, sensor, insertion, MAX_RANGE, RADIUS), reps),
        "dense_resample_s": _median_seconds(lambda: dense_resample(dense, ancestors), reps),
        "dense_map_bytes_per_particle": int(dense_spec.num_cells * 3),
        "paged_insert_into_empty_s": _median_seconds(
            lambda: paged_insert(spec, paged, poses, ranges, sensor, insertion, MAX_RANGE, RADIUS), reps),
        "paged_insert_into_shared_s": _median_seconds(
            lambda: paged_insert(spec, shared, poses, ranges, sensor, insertion, MAX_RANGE, RADIUS), reps),
        "paged_resample_s": _median_seconds(lambda: paged_resample(filled, ancestors), reps),
        "paged_page_table_bytes_per_particle": int(np.prod(spec.num_tiles) * 4),
        "paged_tiles_written_per_particle": float(paged_map.tiles_in_use(filled)) / num_particles,
        "paged_tile_bytes": int(spec.tile_size**2 * 3),
        "window_tiles": window,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--particles", type=int, nargs="+", default=[30])
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--out", default="results/bench_maps.json")
    args = parser.parse_args(argv)
    rows = [measure(n, args.reps) for n in args.particles]
    for row in rows:
        print(json.dumps(row))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows, "device": str(jax.devices()[0])}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
