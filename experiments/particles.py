"""How many particles a loop needs: coalescence, failures, relation error and cost against N.

A particle filter can revise its past only back to the final particles' common ancestor: before
that step every surviving history is one (:func:`jaxslam.diagnose.surviving_lineages`). A loop
closes only if, when the robot comes back, some particle's history of the whole loop is right;
with few particles the histories coalesce a few minutes back, and an hour-long loop is closed
only when the one history left is right. This sweep measures, against the number of SLAM
particles N:

* the *coalescence lag*: how long before the run's end the final particles' common ancestor
  lies (s of log time; the whole run when the histories never coalesce);
* failures (the relation error above twice the best run of that log at any N, as
  ``datasets.py`` judges), the relation error; on the box world RA and success (RA < 0.2 m);
* the cost: milliseconds per update (compilation left out) and the peak resident memory.

Logs run as ``datasets.py`` runs them (``jaxslam map`` in a subprocess at the library's
defaults, ``--particles N``; each run's folder under ``DIR/n{N}/``); the box world as
``box_world.py``'s "defaults" table (its settings; N replaced), in this process, N ascending, so
that the process's peak so far is the current N's (recorded as ``peak_memory_mb``). Finished runs
are skipped on restart (``experiments/_runs.py``). Writes ``DIR/results.json``, ``DIR/particles.md``
(the table) and ``DIR/particles.png`` (four panels against N).

    python experiments/particles.py --out results/particles --logs fr-clinic --proposals smp lp \\
        --particles 30 100 300 1000 --seeds 3
    python experiments/particles.py --out results/particles_box --box-world --proposals smp lp \\
        --particles 30 100 300 --seeds 10
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from _runs import ResultStore, SettingsMismatch  # experiments/_runs.py: the shared resume helper

import datasets  # experiments/datasets.py: the log runs and the failure rule

BOX_METHODS = {"op": "OP", "smp": "SMP", "lp": "LP-SM", "lp-odometry": "LP"}
"""``--proposals`` names (datasets.py's) and the box world's method names (box_world.json)."""


def coalescence_lag(ancestors: np.ndarray, step_times: np.ndarray) -> float:
    """Seconds from the final particles' common ancestor to the last step (the whole run when the
    histories never coalesce): ``ancestors`` (S-1, N) as ``SlamInfo.ancestors``, ``step_times``
    (S-1,) the log time of each step's scan."""
    from jaxslam.diagnose import surviving_lineages

    single = np.flatnonzero(surviving_lineages(np.asarray(ancestors)) == 1)
    since = step_times[single[-1]] if single.size else step_times[0]
    return float(step_times[-1] - since)


def run_log(dataset: str, proposal: str, n: int, seed: int, out: Path, data: Path) -> dict:
    """One log run at N particles (``datasets.run_one``), with its coalescence lag and cost per update."""
    from jaxslam.diagnose import read_step_record

    settings = {**datasets.SETTINGS, "particles": n}
    record = datasets.run_one(dataset, proposal, seed, out / f"n{n}", data, settings)
    if "failed" in record:
        return {**record, "world": dataset, "N": n}
    steps = read_step_record(out / f"n{n}" / dataset / f"{proposal}-seed{seed}")
    updates = max(int(record["scans_processed"]) - 1, 1)
    return {"world": dataset, "proposal": proposal, "N": n, "seed": seed, "error": record["trans_mean"],
            "coalescence_lag_s": coalescence_lag(steps["ancestors"], np.asarray(steps["timestamp"])[1:]),
            "log_duration_s": float(steps["timestamp"][-1] - steps["timestamp"][0]),
            "ms_per_update": 1e3 * record["filter_s"] / updates, "wall_s": record["wall_s"],
            "peak_memory_mb": record["peak_memory_mb"], "updates": updates}


def run_box(proposal: str, n: int, seed: int) -> dict:
    """One box-world run at N particles: box_world.py's "defaults" table's method and world."""
    import box_world

    from jaxslam.outputs import peak_memory_mb

    exp = box_world.load_experiment()
    table = exp["tables"]["defaults"]
    record = box_world.cell_record(box_world.method_settings(exp, BOX_METHODS[proposal], table.get("set")), n, 1.0)
    run, result, scenario = box_world.run_once(record, seed, box_world.world_settings(exp, table))
    times = np.asarray(scenario.log.timestamps, np.float64)[result.selection.indices]
    steady = max(run["num_steps"] - 32, 1)  # slam.run's first chunk (32 steps) holds the compilation
    return {"world": "box", "proposal": proposal, "N": n, "seed": seed, "error": run["ra"],
            "best_particle_error": run["best_particle_error"], "closest_particle_error": run["closest_particle_error"],
            "coalescence_lag_s": coalescence_lag(result.info.ancestors, times[1:]),
            "log_duration_s": float(times[-1] - times[0]),
            "ms_per_update": 1e3 * (result.timings["total"] - result.timings["compile"]) / steady,
            "wall_s": run["seconds"], "peak_memory_mb": peak_memory_mb(), "updates": run["num_steps"]}


def failures(runs: list[dict], success_ra: float) -> dict:
    """Per (world, proposal, N): the seeds that failed. A log run fails as in ``datasets.py`` (its
    relation error above twice the log's best run, over every N and proposal here), a box-world
    run when its RA is ``success_ra`` or more."""
    out: dict = {}
    logs = [dict(r, dataset=r["world"], proposal=f"{r['proposal']}@{r['N']}", trans_mean=r["error"])
            for r in runs if r["world"] != "box" and "failed" not in r]
    for (world, label), failed in datasets.failed_runs(logs).items():
        proposal, n = label.split("@")
        out[(world, proposal, int(n))] = [seed for seed, _ in failed]
    for r in runs:
        if r["world"] == "box":
            out.setdefault((r["world"], r["proposal"], r["N"]), [])
            if r["error"] >= success_ra:
                out[(r["world"], r["proposal"], r["N"])].append(r["seed"])
    return out


def summary_rows(runs: list[dict], success_ra: float) -> list[dict]:
    """A row per (world, proposal, N): runs, failures, error, coalescence lag, cost."""
    failed = failures(runs, success_ra)
    rows = []
    for key in sorted({(r["world"], r["proposal"], r["N"]) for r in runs if "failed" not in r}):
        cell = [r for r in runs if (r["world"], r["proposal"], r["N"]) == key and "failed" not in r]

        def column(name):
            return np.array([r[name] for r in cell], np.float64)

        error, lag = column("error"), column("coalescence_lag_s")
        rows.append({"world": key[0], "proposal": key[1], "N": key[2], "runs": len(cell),
                     "failed": len(failed.get(key, [])), "error_mean": float(error.mean()),
                     "error_se": float(error.std(ddof=1) / np.sqrt(error.size)) if error.size > 1 else 0.0,
                     "coalescence_lag_s_median": float(np.median(lag)),
                     # The box world's: the median over runs of the final particle nearest the truth
                     # (is any history right?); None on a log, whose relations score one trajectory.
                     "closest_particle_error_median": (float(np.median(column("closest_particle_error")))
                                                       if all("closest_particle_error" in r for r in cell) else None),
                     "ms_per_update": float(np.median(column("ms_per_update"))),
                     "peak_memory_mb": float(np.max(column("peak_memory_mb")))})
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["| world | proposal | N | runs | failed | error [m] (RA on the box world) | closest particle's RA [m], "
             "median | coalescence lag [s], median | ms / update | peak [MB] |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        closest = r.get("closest_particle_error_median")
        lines.append(f"| {r['world']} | {r['proposal']} | {r['N']} | {r['runs']} | {r['failed']} | "
                     f"{r['error_mean']:.3f} ± {r['error_se']:.3f} | {'-' if closest is None else f'{closest:.3f}'} | "
                     f"{r['coalescence_lag_s_median']:.0f} | "
                     f"{r['ms_per_update']:.0f} | {r['peak_memory_mb']:.0f} |")
    return "\n".join(lines) + "\n"


def figure(path: Path, rows: list[dict]):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("coalescence_lag_s_median", "coalescence lag (s)"), ("failed", "failed runs (share)"),
              ("error_mean", "error (m; RA on the box world)"), ("ms_per_update", "ms per update"))
    fig, axes = plt.subplots(1, 4, figsize=(17, 4), constrained_layout=True)
    for ax, (name, label) in zip(axes, panels):
        for world, proposal in sorted({(r["world"], r["proposal"]) for r in rows}):
            line = [r for r in rows if (r["world"], r["proposal"]) == (world, proposal)]
            values = [r[name] / r["runs"] if name == "failed" else r[name] for r in line]
            ax.plot([r["N"] for r in line], values, "o-", label=f"{world} {proposal}")
        ax.set_xscale("log")
        ax.set_xlabel("SLAM particles N")
        ax.set_ylabel(label)
        if name in ("ms_per_update", "coalescence_lag_s_median"):
            ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="results/particles")
    parser.add_argument("--data", default=str(datasets.DATA))
    parser.add_argument("--logs", nargs="*", default=[], choices=list(datasets.DATASETS))
    parser.add_argument("--box-world", action="store_true", help="also the box world (box_world.json's defaults)")
    parser.add_argument("--proposals", nargs="+", default=["smp", "lp"], choices=list(BOX_METHODS))
    parser.add_argument("--particles", nargs="+", type=int, default=[30, 100, 300, 1000])
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args(argv)
    if not args.logs and not args.box_world:
        parser.error("nothing to run: name --logs and/or --box-world")
    if min(args.particles) < 1 or args.seeds < 1:
        parser.error("--particles and --seeds must be positive")
    data, out = Path(args.data), Path(args.out)
    if args.logs and not data.is_dir():
        print(f"datasets not found at {data}", file=sys.stderr)
        return 2
    import box_world

    success_ra = box_world.load_experiment()["success_ra"]
    try:
        store = ResultStore(out / "results.json", {"log_settings": datasets.SETTINGS, "success_ra": success_ra},
                            key=lambda r: (r["world"], r["proposal"], r["N"], r["seed"]))
    except SettingsMismatch as err:
        print(err, file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    # N ascending (so that a box-world run's peak so far is its own), seed by seed within an N.
    jobs = [(world, p, n, s) for n in sorted(args.particles) for s in range(args.seeds)
            for world in [*args.logs, *(["box"] if args.box_world else [])] for p in args.proposals]
    todo = [job for job in jobs if store.get(job) is None or "failed" in store.get(job)]
    for world, proposal, n, seed in tqdm(todo, desc="runs", unit="run", initial=len(jobs) - len(todo),
                                         total=len(jobs)):
        record = (run_box(proposal, n, seed) if world == "box"
                  else run_log(world, proposal, n, seed, out, data))
        store.add(record)
        rows = summary_rows(store.runs, success_ra)
        (out / "particles.md").write_text(markdown(rows))
    rows = summary_rows(store.runs, success_ra)
    if rows:
        (out / "particles.md").write_text(markdown(rows))
        figure(out / "particles.png", rows)
        print(markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
