"""Where one SLAM step's memory and time go, at one particle count (one process per call).

Runs Intel's first ``--max-scans`` scans (SMP, GMapping's update rule, as ``bench_maps.py
sweep``) for ``--warm-chunks`` chunks of 32 steps, then, from that state:

* XLA's memory analysis of the compiled chunk (``jax.jit(...).lower(...).compile()
  .memory_analysis()``: arguments, outputs, temporaries) and of the step's parts compiled
  alone (the proposals under the filter's vmap, the insertion, the resampling of the maps);
* the largest buffers of the chunk's buffer assignment (``--xla_dump_to``), by what they hold;
* the steady-state time of each part and of the whole step (best of ``--repeats``), and the
  time per update of the run's own compiled chunk over the next 32 steps (``chunk_ms_per_update``:
  what a run pays per update, compilation excluded);
* the peak resident memory of the process.

    python benchmarks/profile_step.py --particles 1000 --out profile_1000.json

With ``--reads``, where the proposals' time goes (``read_costs``): the same proposals with the
map reads changed, each a bound, not a variant (their poses differ): the page table's two
dependent gathers skipped (each read's tile slot from its tile index, spread over the pool);
no map read at all; and, at the same reads, fewer of them (every 4th beam, one level less).

The figures go to ``--out`` (JSON) and stdout; run one process per N. The parts are called
without donating the maps, so the insertion's and the whole step's times include a copy of the
pools (their memory analysis counts it as an output); the chunk's figures are the run's.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import resource
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _top_buffers(dump_dir: str, module_pattern: str, count: int) -> list[dict]:
    """The ``count`` largest allocations of the buffer assignment of the module matching
    ``module_pattern`` in an XLA dump folder: size (MB) and the first value it holds."""
    files = sorted(glob.glob(os.path.join(dump_dir, f"*{module_pattern}*buffer-assignment.txt")))
    if not files:
        return []
    text = Path(files[-1]).read_text()
    rows = []
    for block in re.split(r"\n(?=allocation \d+:)", text):
        head = re.match(r"allocation (\d+): size (\d+)(.*)", block)
        if not head:
            continue
        values = re.findall(r"value: <\d+ ([^ ]+) @\d+> \(size=\d+,offset=\d+\): (\S+)", block)
        rows.append({"allocation": int(head.group(1)), "mb": int(head.group(2)) / 2**20,
                     "kind": head.group(3).strip(" ,")[:80], "values": [f"{name} {shape}" for name, shape in values[:3]]})
    return sorted(rows, key=lambda r: -r["mb"])[:count]


def _memory(compiled) -> dict:
    m = compiled.memory_analysis()
    return {"argument_mb": m.argument_size_in_bytes / 2**20, "output_mb": m.output_size_in_bytes / 2**20,
            "temp_mb": m.temp_size_in_bytes / 2**20, "alias_mb": m.alias_size_in_bytes / 2**20}


def _best_time(fn, args, repeats: int) -> float:
    import jax

    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def _proposals_fn(config, step_inputs, sensor, params):
    """The step's proposals for every particle, jitted, as :func:`jaxslam.rbpf.step` runs them
    (``config.particle_block`` particles at a time, the likelihood's beams subsampled)."""
    import jax

    from jaxslam import maps as paged
    from jaxslam import particle_filter
    from jaxslam.laser import subsample_beams
    from jaxslam.proposals import PROPOSALS

    lik_sensor, lik_ranges = subsample_beams(sensor, step_inputs.ranges, config.beam_stride)
    lik_inputs = step_inputs._replace(ranges=lik_ranges,
                                      future_ranges=subsample_beams(sensor, step_inputs.future_ranges,
                                                                    config.beam_stride)[1])
    propose_fn = PROPOSALS[config.proposal].propose_fn

    @jax.jit
    def proposals(key, state):
        field = paged.fields(state.maps)
        return particle_filter.map_in_blocks(
            lambda p: propose_fn(p[0], p[1], field._replace(directory=p[2]), lik_inputs, lik_sensor, params, config),
            (jax.random.split(key, config.num_particles), state.poses, field.directory), config.particle_block)

    return proposals


def _read_costs(config, step_inputs, sensor, params, state, repeats: int) -> dict:
    """Seconds of the proposals (best of ``repeats``) as they are and with their map reads changed:
    bounds on what a cheaper read could save, not variants (the poses differ)."""
    import contextlib
    import dataclasses
    from unittest import mock

    import jax

    from jaxslam import map_view
    from jaxslam import maps as paged

    capacity = state.maps.hit_dist2.shape[0]

    def slots_without_page_table(spec, directory, blocks, tiles):
        # Each tile's slot from its index alone, spread over the whole pool (no dependent gathers).
        return (tiles[..., 0] * 7919 + tiles[..., 1] * 104729) % capacity

    def no_read(spec, field, cells, fill):
        return (cells[..., 0] & 7).astype(field.pool.dtype)

    cases = {
        "as_is": (config, contextlib.nullcontext()),
        "no_page_table": (config, mock.patch.object(paged.lookup, "tile_slots", slots_without_page_table)),
        "no_map_read": (config, mock.patch.object(map_view, "cell_values", no_read)),
        "beam_stride_4": (dataclasses.replace(config, beam_stride=4), contextlib.nullcontext()),
    }
    if config.window_levels > 1:
        cases["one_level_less"] = (dataclasses.replace(config, window_levels=config.window_levels - 1),
                                   contextlib.nullcontext())
    seconds = {}
    for name, (case_config, patch) in cases.items():
        with patch:  # jit traces inside it, so the patch is in the compiled function
            fn = _proposals_fn(case_config, step_inputs, sensor, params)
            seconds[name] = _best_time(fn, (jax.random.key(2), state), repeats)
    return {"seconds": seconds, "ratio_to_as_is": {k: v / seconds["as_is"] for k, v in seconds.items()}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", type=int, required=True)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--max-scans", type=int, default=3000)
    ap.add_argument("--warm-chunks", type=int, default=1, help="chunks of 32 steps run before measuring")
    ap.add_argument("--repeats", type=int, default=3, help="timed calls of each part (0: memory analysis only)")
    ap.add_argument("--top", type=int, default=12, help="largest buffers listed")
    ap.add_argument("--reads", action="store_true",
                    help="also time the proposals with their map reads changed (read_costs: bounds, not variants)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)

    dump = tempfile.mkdtemp(prefix="jaxslam_dump_")
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --xla_dump_to={dump}"
                               " --xla_dump_hlo_module_re=.*_run_chunk.*").strip()
    os.environ.setdefault("JAXSLAM_CACHE_DIR", "off")
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxslam import maps as paged
    from jaxslam import growth, particle_filter, rbpf, slam
    from jaxslam.config import build_setup
    from jaxslam.io import read_log
    from jaxslam.laserlog import check_log

    # GMapping's update rule, as bench_maps.py's runs.
    values = {"proposal": "smp", "num_particles": args.particles, "linear_update": 1.0, "angular_update": 0.5}
    config, settings, params = build_setup(values)
    log = read_log(args.data / "intel.sort.bag")
    log = check_log(log.subset(np.arange(min(args.max_scans, log.num_scans))))
    prepared, selection, frame_offset = rbpf.prepare(log, config, settings)
    sensor = prepared.sensor
    inputs = jax.tree.map(jnp.asarray, prepared.inputs)
    chunk = 32
    key_steps = jax.random.key(1)
    state = rbpf.init(jax.random.key(0), jnp.asarray(prepared.first_ranges), sensor, params, config,
                      jnp.asarray(prepared.initial_pose))
    valid = jnp.ones(chunk, bool)

    def chunk_inputs(i):
        return jax.tree.map(lambda a: a[i * chunk:(i + 1) * chunk], inputs)

    keys = jax.random.split(key_steps, chunk)
    lowered = slam._run_chunk.lower(state, keys, chunk_inputs(0), valid, sensor, params, config)
    t0 = time.perf_counter()
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    report = {"particles": args.particles, "chunk_memory": _memory(compiled), "compile_s": compile_s,
              "pool": state.maps.pool_size._asdict()}
    for i in range(args.warm_chunks):
        state, info = compiled(state, jax.random.split(jax.random.fold_in(key_steps, i), chunk), chunk_inputs(i),
                               valid, sensor, params)
        if bool(info.pool_overflow.any()):
            pool = growth.larger_pool(state.maps, config.grid)
            state = state._replace(maps=paged.grow(config.grid, state.maps, pool))
    report["tiles_in_use"] = int(paged.tiles_in_use(state.maps))
    report["top_buffers"] = _top_buffers(dump, "_run_chunk", args.top)

    # The step's parts alone, from that state, at the next step's inputs.
    step_inputs = jax.tree.map(lambda a: a[args.warm_chunks * chunk], inputs)
    n = config.num_particles
    proposals = _proposals_fn(config, step_inputs, sensor, params)
    out = proposals(jax.random.key(2), state)
    update = particle_filter.reweight_and_resample(jax.random.key(3), out.pose, state.log_weights,
                                                   out.log_weight_increment, params.resample_threshold,
                                                   config.resampler)
    survivors = jnp.zeros((n,), bool).at[update.ancestors].set(True)

    @jax.jit
    def insertion(maps, poses, survivors):
        return paged.insert_scans(config.grid, maps, poses, step_inputs.ranges, sensor, params.insertion,
                                      config.max_insert_range, config.field_radius, survivors,
                                      config.particle_block)

    resample_maps = jax.jit(paged.resample)
    step = jax.jit(lambda key, state: rbpf.step(key, state, step_inputs, sensor, params, config))
    parts = {"proposals": (proposals, (jax.random.key(2), state)),
             "insertion": (insertion, (state.maps, out.pose, survivors)),
             "resample_maps": (resample_maps, (state.maps, update.ancestors)),
             "whole_step": (step, (jax.random.key(4), state))}
    report["survivors"] = int(survivors.sum())
    report["parts"] = {}
    for name, (fn, fn_args) in parts.items():
        report["parts"][name] = {"memory": _memory(fn.lower(*fn_args).compile()),
                                 "seconds": _best_time(fn, fn_args, args.repeats) if args.repeats else None}
    if args.reads and args.repeats:
        report["read_costs"] = _read_costs(config, step_inputs, sensor, params, state, args.repeats)
    # The run's own program in steady state: the next chunk of 32 steps, the maps donated as in
    # slam.run (the parts above copy the pools; this does not).
    state = jax.tree.map(jnp.copy, state)
    t0 = time.perf_counter()
    state, info = compiled(state, jax.random.split(jax.random.fold_in(key_steps, args.warm_chunks), chunk),
                           chunk_inputs(args.warm_chunks), valid, sensor, params)
    jax.block_until_ready(state)
    report["chunk_ms_per_update"] = 1e3 * (time.perf_counter() - t0) / chunk
    report["chunk_overflowed"] = bool(info.pool_overflow.any())
    report["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({k: v for k, v in report.items() if k != "top_buffers"}, indent=1))
    for row in report["top_buffers"]:
        print(f"{row['mb']:9.1f} MB  {row['kind'][:40]:40s} {'; '.join(row['values'])[:150]}")
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
