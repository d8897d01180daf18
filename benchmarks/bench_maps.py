"""What paged maps cost: memory and time of whole runs, against N, and under vmap.

Sections (each merges its figures into ``--out``, a JSON file):

* ``intel``: ``jaxslam map`` on Intel, SMP, 30 particles, seed 1: peak resident memory and
  wall time, and the same command on the log's first 50 scans (the map's *marginal* memory is
  the difference). With ``--previous DIR [DIR ...]`` (checkouts of earlier commits, e.g. git
  worktrees) the same two commands run there too, in the same session, one after the other;
  the ratios are against the first.
* ``killian``: the whole MIT Killian log, SMP, 30 particles: peak memory, real-time factor.
* ``sweep``: Intel's first ``--max-scans`` scans at N = ``--particles``: peak memory, time per
  processed scan (compile excluded), the bytes each extra particle costs (a least-squares
  slope of peak memory against N) and the log-log slope of the time against N. With
  ``--previous DIR [DIR ...]`` the same runs in those checkouts too, N by N, alternating.
* ``first-pool``: FR-clinic's first ``--updates`` updates at each N of ``--particles`` (the
  library's update rule and defaults, SMP, in this process): the run as it starts (pools sized
  from the first scan's footprint) against the same run started in pools sized from N alone
  (Intel's footprint; ``rbpf.pool_size(config)``): wall time, the growths (each a recompile),
  the pools' final sizes, and whether the paths are the same bit for bit.
* ``vmap``: the simulated office of ``jaxslam demo``, 8 seeds: one ``vmap`` of the whole filter
  over the seeds against a loop of the same 8 runs (both compiled first, then timed).

Every run is a separate process (peak memory per run, from ``os.wait4``); logs are read from
``--data`` (default ``../shared/data`` beside the repository). Ratios are meaningful within
one invocation only (the machine is shared).

    python benchmarks/bench_maps.py intel --previous OTHER_CHECKOUT --out docs/results/bench_maps.json
    python benchmarks/bench_maps.py sweep --particles 30 100 300 1000 --max-scans 3000 --previous OTHER_CHECKOUT
    python benchmarks/bench_maps.py killian
    python benchmarks/bench_maps.py vmap --seeds 8
    python benchmarks/bench_maps.py first-pool --particles 100 --updates 64
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
GMAPPING_UPDATE_RULE = ["--set", "linear_update=1.0", "--set", "angular_update=0.5"]
"""Every run processes a scan after 1 m or 0.5 rad, GMapping's rule (the library's default is
half that): the figures stay comparable with GMapping's and with the earlier measurements."""


def run_map(log: Path, particles: int, *, max_scans: int | None = None, repo: Path = REPO, proposal: str = "smp",
            seed: int = 1) -> dict:
    """One ``jaxslam map`` process in ``repo``: wall seconds, peak resident MB, and its summary."""
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "jaxslam.cli", "map", str(log), "--proposal", proposal, "--particles",
               str(particles), "--seed", str(seed), "--out", out, "--no-progress", *GMAPPING_UPDATE_RULE]
        if max_scans is not None:
            cmd += ["--max-scans", str(max_scans)]
        env = dict(os.environ, PYTHONPATH=str(repo))
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=repo, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        stdout, stderr = proc.stdout.read(), proc.stderr.read()
        if os.waitstatus_to_exitcode(status) != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{stderr[-3000:]}")
        summary = json.loads((Path(out) / "summary.json").read_text())
    return {"command": " ".join(cmd[1:]), "repo": str(repo), "wall_s": wall, "peak_mb": usage.ru_maxrss / 1024,
            "filter_s": summary["timings"]["total"], "compile_s": summary["timings"]["compile"],
            "real_time_factor": summary["timings"]["real_time_factor"],
            "scans_processed": summary["scans_processed"], "map_pool": summary.get("map_pool"),
            "stdout": stdout.strip().splitlines()[-1:]}


def section_intel(args) -> dict:
    log = args.data / "intel.sort.bag"
    out = {}
    previous = [("previous", p.resolve()) if i == 0 else (f"previous_{p.name}", p.resolve())
                for i, p in enumerate(args.previous or [])]
    for name, repo in [("this", REPO)] + previous:
        full = run_map(log, 30, repo=repo)
        first = run_map(log, 30, repo=repo, max_scans=50)
        out[name] = {"full": full, "first_50_scans": first, "marginal_mb": full["peak_mb"] - first["peak_mb"]}
        print(f"{name}: {full['wall_s']:.1f} s wall ({full['filter_s']:.1f} s filter), peak {full['peak_mb']:.0f} MB, "
              f"marginal {out[name]['marginal_mb']:.0f} MB", flush=True)
    if args.previous:
        out["wall_ratio_this_over_previous"] = out["this"]["full"]["wall_s"] / out["previous"]["full"]["wall_s"]
        out["filter_ratio_this_over_previous"] = out["this"]["full"]["filter_s"] / out["previous"]["full"]["filter_s"]
    return out


def section_killian(args) -> dict:
    row = run_map(args.data / "mit-killian.bag", 30)
    print(f"killian: {row['filter_s']:.0f} s filter, real-time factor {row['real_time_factor']:.1f}, "
          f"peak {row['peak_mb']:.0f} MB", flush=True)
    return row


def _sweep_fit(particles: list[int], rows: list[dict]) -> dict:
    """The least-squares MB per extra particle (peak against N) and the log-log slope of the time
    per update against N."""
    ns = np.array(particles, float)
    peaks = np.array([r["peak_mb"] for r in rows])
    seconds = np.array([r["seconds_per_update"] for r in rows])
    if len(rows) < 2:
        return {"mb_per_extra_particle": None, "loglog_slope": None}
    return {"mb_per_extra_particle": float(np.polyfit(ns, peaks, 1)[0]),
            "loglog_slope": float(np.polyfit(np.log(ns), np.log(seconds), 1)[0])}


def section_sweep(args) -> dict:
    """Intel's first ``--max-scans`` scans at each N; with ``--previous``, the same runs in each
    earlier checkout too, N by N, one after the other (the machine's load then hits both alike)."""
    repos = [("this", REPO)] + [(f"previous_{p.name}" if i else "previous", p.resolve())
                                for i, p in enumerate(args.previous or [])]
    rows = {name: [] for name, _ in repos}
    for n in args.particles:
        for name, repo in repos:
            row = run_map(args.data / "intel.sort.bag", n, max_scans=args.max_scans, repo=repo)
            steps = max(row["scans_processed"] - 1, 1)
            row["seconds_per_update"] = (row["filter_s"] - row["compile_s"]) / steps
            rows[name].append(row)
            print(f"{name} N={n}: {row['seconds_per_update'] * 1000:.1f} ms per update, peak {row['peak_mb']:.0f} MB",
                  flush=True)
    out = {"max_scans": args.max_scans, "particles": args.particles, "rows": rows["this"],
           **_sweep_fit(args.particles, rows["this"])}
    for name, _ in repos[1:]:
        out[name] = {"rows": rows[name], **_sweep_fit(args.particles, rows[name])}
    return out


def section_vmap(args) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxslam import rbpf
    from jaxslam.cli import DEMO_DEFAULTS
    from jaxslam.config import build_setup
    from jaxslam.sim import office_scenario

    log = office_scenario(jax.random.key(0)).log
    config, settings, params = build_setup(dict(DEMO_DEFAULTS))
    prepared, selection, _ = rbpf.prepare(log, config, settings)  # the local frame's arrays
    inputs = jax.tree.map(jnp.asarray, prepared.inputs)
    sensor = prepared.sensor
    steps = selection.indices.size - 1
    pool = rbpf.pool_size(config)
    pool = pool._replace(capacity=4 * pool.capacity)  # room for the whole run: no growth inside the timed calls

    def one_run(key):
        state = rbpf.init(key, jnp.asarray(prepared.first_ranges), sensor, params, config,
                          jnp.asarray(prepared.initial_pose), pool=pool)
        keys = jax.random.split(key, steps)
        state, info = jax.lax.scan(lambda s, x: rbpf.step(x[0], s, x[1], sensor, params, config), state,
                                   (keys, inputs))
        return state.poses, state.maps.overflow, info.log_evidence

    keys = jax.random.split(jax.random.key(1), args.seeds)
    single, batched = jax.jit(one_run), jax.jit(jax.vmap(one_run))
    jax.block_until_ready(single(keys[0]))
    jax.block_until_ready(batched(keys))
    t0 = time.perf_counter()
    loop = [single(k) for k in keys]
    jax.block_until_ready(loop)
    loop_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(batched(keys))
    vmap_s = time.perf_counter() - t0
    if bool(np.any(np.asarray(out[1]))) or any(bool(o[1]) for o in loop):
        raise RuntimeError("the pool overflowed inside a timed run; raise its capacity")
    np.testing.assert_allclose(np.asarray(out[0][0]), np.asarray(loop[0][0]), atol=1e-4)  # the same runs
    print(f"vmap over {args.seeds} seeds: {vmap_s:.2f} s, loop {loop_s:.2f} s, speed-up {loop_s / vmap_s:.2f}x",
          flush=True)
    return {"seeds": args.seeds, "steps": steps, "num_particles": config.num_particles, "loop_s": loop_s,
            "vmap_s": vmap_s, "speedup": loop_s / vmap_s}


def section_first_pool(args) -> dict:
    import jax

    from jaxslam import io, rbpf, slam
    from jaxslam.config import build_setup, default_values

    full = io.read_log(args.data / "fr-clinic.bag")
    out = {"log": "fr-clinic.bag", "updates": args.updates}
    for n in args.particles:
        config, settings, params = build_setup({**default_values(), "num_particles": n})
        _, selection, _ = rbpf.prepare(full, config, settings)
        log = full.subset(np.arange(int(selection.indices[min(args.updates, selection.indices.size - 1)]) + 1))
        rows, paths = {}, {}
        for name, pool in (("first_scan_footprint", None), ("particles_only", rbpf.pool_size(config))):
            t0 = time.perf_counter()
            result = slam.run(jax.random.key(0), log, config, params, settings, progress=False, initial_pool=pool)
            pools = result.map_pool
            rows[name] = {"wall_s": time.perf_counter() - t0, "growth_steps": [g["step"] for g in pools["growths"]],
                          **{k: pools[k] for k in ("capacity", "max_new_tiles", "peak_request", "bytes")}}
            paths[name] = result.best_path
            print(f"N = {n}, {name}: {rows[name]}", flush=True)
        out[str(n)] = {**rows, "same_path": bool(np.array_equal(*paths.values())),
                       "wall_ratio": rows["first_scan_footprint"]["wall_s"] / rows["particles_only"]["wall_s"]}
    return out


SECTIONS = {"intel": section_intel, "killian": section_killian, "sweep": section_sweep, "vmap": section_vmap,
            "first-pool": section_first_pool}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sections", nargs="+", choices=sorted(SECTIONS))
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data", help="folder of the logs")
    ap.add_argument("--previous", type=Path, nargs="+", help="checkouts of earlier commits to compare with (intel, sweep)")
    ap.add_argument("--particles", type=int, nargs="+", default=[30, 100, 300, 1000])
    ap.add_argument("--max-scans", type=int, default=3000, help="sweep: scans of Intel to use")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--updates", type=int, default=64, help="first-pool: FR-clinic's first updates")
    ap.add_argument("--out", type=Path, default=Path("results/bench_maps.json"))
    args = ap.parse_args(argv)
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    for name in args.sections:
        results[name] = SECTIONS[name](args)
        results[name]["measured"] = time.strftime("%Y-%m-%d %H:%M")
        results["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count()}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
