"""Accuracy and robustness on the standard datasets (Intel, ACES, MIT CSAIL, FR-clinic), OP / SMP / LP
side by side with GMapping.

For each log in ../shared/data and each proposal, runs ``jaxslam map`` at the library's
defaults (``SETTINGS`` below: the same for every log, no per-dataset tuning; ``--set`` makes
a row of other settings, in its own folder) for several seeds, each in its own subprocess
(its peak memory is its own), seed by seed over the logs (a stopped run leaves every log with
as many seeds), scores the
per-scan trajectory with the relation metric of Kuemmerle et al. 2009, and writes
``DIR/results.json``, ``DIR/results.md`` (the table, beside the published numbers and
GMapping measured on this machine), ``DIR/robustness.md`` (per log and method: the error's
mean ± standard error over seeds and the failed runs, :func:`failed_runs`), ``DIR/seeds.md``,
each run's map PNG and ``DIR/failed_maps.png`` (the failed runs' maps side by side). With
``--refine`` each run also localises every scan in its final map
and fuses the matches with the odometry (as ``jaxslam map`` does by default, :mod:`jaxslam.refine`;
without it the runs pass ``--no-refine``); the table shows that trajectory's error on a row of
its own.
Finished runs are skipped on restart, so the script can be stopped and resumed, and a later
call into the same folder (same settings) adds its runs to ``results.json`` beside the earlier ones
(``experiments/_runs.py``; a folder written with other settings is refused).

    python experiments/datasets.py --out results/robustness --seeds 10 --proposals op smp lp

Proposals (:data:`PROPOSALS`): op, smp, lp (the library's LP: localizers drawn around each
particle's scan match), lp-odometry (the paper's LP: localizers drawn from the motion model) and
lp-c0 (the library's LP with ``lookahead.selection_correction = 0``). Folders written before
2026-11-25 name the paper's LP "lp" and the library's "lp-sm" (the default changed then).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _runs import ResultStore, SettingsMismatch, gather_json  # experiments/_runs.py: the shared resume helper

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"

DATASETS = {
    "intel": ("intel.sort.bag", "intel.relations"),
    "aces": ("aces.sort.bag", "aces.relations"),
    "mit-csail": ("mit-csail.clf", "mit-csail.relations"),
    "fr-clinic": ("fr-clinic.bag", "fr-clinic.relations"),  # kept back from every tuning
}

# One configuration for all logs: the library's defaults (jaxslam.config; docs/tuning.md says
# what each does) and ``jaxslam map``'s 30 particles; the LP's localizers and horizon are the
# library's too, passed explicitly so that the record says them.
SETTINGS = {
    "particles": 30,
    "localizers": 100,
    "horizon": 5,
    "refine": False,
    "set": [],
}

PROPOSALS = {
    "op": [],
    "smp": [],
    "lp": [],  # the library's defaults: lookahead_initial=scan_match
    "lp-odometry": ["lookahead_initial=odometry"],  # the paper's LP
    "lp-c0": ["lookahead.selection_correction=0"],  # the SLAM weight is the evidence estimate alone
}
"""The table's proposals: ``jaxslam map --proposal`` (op, smp or lp) and the ``--set`` items each adds."""

# Translational error (m), mean +- std.
PUBLISHED = {  # Kuemmerle et al. 2009 as quoted in ../shared/data/README.md
    "intel": {"scan matching": (0.220, 0.296), "RBPF (GMapping, 50 particles)": (0.070, 0.083), "graph mapping": (0.031, 0.026)},
    "aces": {"scan matching": (0.173, 0.614), "RBPF (GMapping, 50 particles)": (0.060, 0.049), "graph mapping": (0.044, 0.044)},
    "mit-csail": {"scan matching": (0.106, 0.325), "RBPF (GMapping, 50 particles)": (0.049, 0.049), "graph mapping": (0.004, 0.009)},
}
GMAPPING_HERE = {  # GMapping (C++, 30 particles, default parameters) on this machine
    "intel": {"trans": (0.059, 0.057), "rot_deg": (2.18, 2.43), "wall_s": 81.5},
    "aces": {"trans": (0.052, 0.066), "rot_deg": (1.12, 1.30), "wall_s": 36.7},
    "mit-csail": {"trans": (0.058, 0.066), "rot_deg": (3.64, 4.10), "wall_s": 59.8},
}


def map_arguments(dataset: str, proposal: str, seed: int, run_dir: Path, data: Path, settings: dict = SETTINGS
                  ) -> list[str]:
    """``jaxslam map``'s command line (after ``jaxslam``) of one run."""
    log_name, _ = DATASETS[dataset]
    cli_proposal = "lp" if proposal.startswith("lp") else proposal
    args = ["map", str(data / log_name), "--proposal", cli_proposal, "--particles", str(settings["particles"]),
            "--seed", str(seed), "--out", str(run_dir), "--no-progress"]
    args += ["--refine"] if settings["refine"] else ["--no-refine"]
    if cli_proposal == "lp":
        args += ["--localizers", str(settings["localizers"]), "--horizon", str(settings["horizon"])]
    for item in PROPOSALS[proposal]:
        args += ["--set", item]
    for item in settings["set"]:
        args += ["--set", item]
    return args


def run_one(dataset: str, proposal: str, seed: int, out: Path, data: Path, settings: dict = SETTINGS) -> dict:
    """Map one log with one proposal and seed (subprocess), then score it. Cached in out."""
    run_dir = out / dataset / f"{proposal}-seed{seed}"
    scored = run_dir / "errors.json"
    if scored.is_file():
        return json.loads(scored.read_text())
    cmd = [sys.executable, "-m", "jaxslam.cli", *map_arguments(dataset, proposal, seed, run_dir, data, settings)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        # Recorded (not cached) so that the table shows the failure and a rerun retries it.
        return {"dataset": dataset, "proposal": proposal, "seed": seed, "failed": proc.stderr[-2000:]}
    return score_run(dataset, proposal, seed, run_dir, data, wall)


def score_run(dataset: str, proposal: str, seed: int, run_dir: Path, data: Path, wall: float, **extra) -> dict:
    """The record of a finished run (its folder holds ``jaxslam map``'s outputs): the relation
    errors of its trajectory (and of the refined one), timings and memory, and ``extra``;
    written to the folder's errors.json (the cache) and returned."""
    from jaxslam.io import read_relations, read_trajectory
    from jaxslam.metrics import relation_error

    summary = json.loads((run_dir / "summary.json").read_text())
    relations = read_relations(data / DATASETS[dataset][1])
    # The filter alone is the table's figure; the loop closure's (trajectory.txt where the run
    # closed loops) is its own column, and the relations more than 20 minutes apart their own row.
    closed_file = run_dir / "trajectory_filter.txt"
    filter_file = closed_file if closed_file.is_file() else run_dir / "trajectory.txt"
    timestamps, poses = read_trajectory(filter_file)
    err = relation_error(timestamps, poses, relations).to_dict()
    far = np.abs(np.asarray(relations.t2) - np.asarray(relations.t1)) > FAR_APART_S
    extra_errors = {"far_relations": int(far.sum()),
                    "far_trans_mean": _far_mean(timestamps, poses, relations, far)}
    if closed_file.is_file():
        closed_times, closed_poses = read_trajectory(run_dir / "trajectory.txt")
        closed_err = relation_error(closed_times, closed_poses, relations).to_dict()
        extra_errors.update({f"closed_{k}": closed_err[k] for k in ("trans_mean", "trans_std", "rot_mean_deg",
                                                                      "rot_std_deg")})
        extra_errors["closed_far_trans_mean"] = _far_mean(closed_times, closed_poses, relations, far)
        extra_errors["loops_kept"] = summary["closure"]["loops_kept"]
        extra_errors["closure_s"] = summary["timings"]["closure"]["total"]
    refined = {}
    if (run_dir / "trajectory_refined.txt").is_file():  # every scan localised in the final map
        refined_err = relation_error(*read_trajectory(run_dir / "trajectory_refined.txt"), relations).to_dict()
        refined = {f"refined_{k}": refined_err[k] for k in ("trans_mean", "trans_std", "rot_mean_deg", "rot_std_deg")}
    record = {
        "dataset": dataset, "proposal": proposal, "seed": seed,
        "trans_mean": err["trans_mean"], "trans_std": err["trans_std"],
        "rot_mean_deg": err["rot_mean_deg"], "rot_std_deg": err["rot_std_deg"],
        "trans2_mean": err["trans2_mean"], "rot2_mean_deg2": err.get("rot2_mean_deg2"),
        "relations": err["count"],
        **extra_errors,
        **refined,
        "wall_s": wall, "filter_s": summary["timings"]["total"],
        "real_time_factor": summary["log_duration_s"] / wall,
        "peak_memory_mb": summary["peak_memory_mb"],
        "scans_processed": summary["scans_processed"], "scans_in_log": summary["scans_in_log"],
        "warnings": summary["warnings"],
        "map_png": str(run_dir / "map.png"),
        **extra,
    }
    (run_dir / "errors.json").write_text(json.dumps(record, indent=2))
    return record


FAR_APART_S = 1200.0
"""Relations whose two scans are more than this many seconds apart (20 minutes) are reported on
their own: they span the long loops."""


def _far_mean(timestamps, poses, relations, far) -> float | None:
    """The mean translational relation error (m) over the relations ``far`` selects (None if none)."""
    from jaxslam.io.relations import Relations
    from jaxslam.metrics import relation_error

    if not far.any():
        return None
    subset = Relations(*(np.asarray(field)[far] for field in relations))
    return float(relation_error(timestamps, poses, subset).trans_mean)


def run_seeds_batched(dataset: str, proposal: str, seeds: list[int], out: Path, data: Path,
                      settings: dict = SETTINGS, devices=None) -> list[dict]:
    """The seeds of one (log, proposal) as one batch in this process (:func:`jaxslam.slam.run_batch`,
    spread over ``devices``: a count or None for all, every process's under ``jax.distributed``),
    each run's outputs written and scored as :func:`run_one`'s. Returns the records of the runs
    this process's devices held. ``wall_s`` is the batch's wall time over its runs (the record's
    ``batch`` says the batch's runs, devices and wall time); ``peak_memory_mb`` is the process's."""
    import jax

    from jaxslam import cli, slam

    parser = cli.make_parser()
    run_dirs = [out / dataset / f"{proposal}-seed{seed}" for seed in seeds]
    runs = [parser.parse_args(map_arguments(dataset, proposal, seed, run_dir, data, settings))
            for seed, run_dir in zip(seeds, run_dirs)]
    config, run_settings, params = cli.build_setup_from_args(runs[0], cli.MAP_DEFAULTS)  # only the seeds differ
    log = cli.read_map_log(runs[0])
    devices = slam.batch_devices(devices)
    t0 = time.perf_counter()
    results = slam.run_batch(jax.numpy.stack([jax.random.key(seed) for seed in seeds]), log, config, params,
                             run_settings, devices=devices, chunk_size=runs[0].chunk_size, progress=True)
    wall = time.perf_counter() - t0
    batch = {"runs": len(seeds), "devices": len(devices), "processes": jax.process_count(), "wall_s": wall}
    records = []
    for seed, run_dir, args, result in zip(seeds, run_dirs, runs, results):
        if result is None:  # another process's
            continue
        if not getattr(args, "no_close_loops", False):  # as `jaxslam map` does (run_batch runs the filters)
            from jaxslam.graph import ClosureConfig, close_loops

            result = result._replace(closure=close_loops(log, result, params, ClosureConfig()))
        cli.write_map_outputs(run_dir, log, result, params, seed, args.log, refine=args.refine)
        records.append(score_run(dataset, proposal, seed, run_dir, data, wall / len(seeds), batch=batch))
    return records


def aggregate(records: list[dict]) -> dict:
    """Mean over seeds of each figure, per (dataset, proposal)."""
    table: dict = {}
    for r in records:
        if "failed" in r:
            continue
        table.setdefault(r["dataset"], {}).setdefault(r["proposal"], []).append(r)
    out: dict = {}
    for dataset, by_prop in table.items():
        for proposal, runs in by_prop.items():
            keys = ["trans_mean", "trans_std", "rot_mean_deg", "rot_std_deg", "wall_s", "real_time_factor",
                    "peak_memory_mb"]
            refined_keys = [f"refined_{k}" for k in keys[:4]] if all("refined_trans_mean" in r for r in runs) else []
            closed_keys = [f"closed_{k}" for k in keys[:4]] if all("closed_trans_mean" in r for r in runs) else []
            out.setdefault(dataset, {})[proposal] = {
                **{k: float(np.mean([r[k] for r in runs])) for k in keys + refined_keys + closed_keys},
                "trans_mean_over_seeds_std": float(np.std([r["trans_mean"] for r in runs])),
                **({"refined_trans_mean_over_seeds_std": float(np.std([r["refined_trans_mean"] for r in runs]))}
                   if refined_keys else {}),
                "seeds": len(runs),
            }
    return out


def method_label(proposal: str) -> str:
    """The table's name of a proposal: "lp-c0" -> "LP c=0" (c: lookahead.selection_correction)."""
    return {"lp-odometry": "LP, paper's (localizers from the odometry)"}.get(
        proposal, proposal.upper().replace("-C0", " c=0"))


def markdown(summary: dict) -> str:
    lines = [
        "| dataset | method | trans. error [m] | rot. error [deg] | wall [s] | real-time factor | peak memory [MB] |",
        "|---|---|---|---|---|---|---|",
    ]
    for dataset in DATASETS:
        for proposal, s in summary.get(dataset, {}).items():
            lines.append(
                f"| {dataset} | jaxslam {method_label(proposal)} ({s['seeds']} seeds) | {s['trans_mean']:.3f} ± {s['trans_std']:.3f} "
                f"| {s['rot_mean_deg']:.2f} ± {s['rot_std_deg']:.2f} | {s['wall_s']:.1f} | {s['real_time_factor']:.1f} "
                f"| {s['peak_memory_mb']:.0f} |")
            if "closed_trans_mean" in s:
                lines.append(
                    f"| {dataset} | jaxslam {method_label(proposal)} + loop closure | {s['closed_trans_mean']:.3f} ± "
                    f"{s['closed_trans_std']:.3f} | {s['closed_rot_mean_deg']:.2f} ± {s['closed_rot_std_deg']:.2f} "
                    "| | | |")
            if "refined_trans_mean" in s:
                lines.append(
                    f"| {dataset} | jaxslam {method_label(proposal)} + refinement | {s['refined_trans_mean']:.3f} ± "
                    f"{s['refined_trans_std']:.3f} | {s['refined_rot_mean_deg']:.2f} ± {s['refined_rot_std_deg']:.2f} "
                    "| | | |")
        g = GMAPPING_HERE.get(dataset)
        if g is not None:
            lines.append(f"| {dataset} | GMapping, this machine (30 particles) | {g['trans'][0]:.3f} ± "
                         f"{g['trans'][1]:.3f} | {g['rot_deg'][0]:.2f} ± {g['rot_deg'][1]:.2f} | {g['wall_s']:.1f} | | |")
        for name, (m, sd) in PUBLISHED.get(dataset, {}).items():
            lines.append(f"| {dataset} | {name} (published) | {m:.3f} ± {sd:.3f} | | | | |")
    return "\n".join(lines) + "\n"


def seed_markdown(records: list[dict], over: float = 0.06) -> str:
    """Seed-to-seed spread of the refined error: mean ± standard error over seeds, the worst
    seed, and how many seeds end over ``over`` m (where part of a loop closure failed)."""
    lines = ["| dataset | method | seeds | filter [m] | refined [m] | worst seed, refined [m] "
             f"| seeds over {over:g} m, refined |", "|---|---|---|---|---|---|---|"]
    table: dict = {}
    for r in records:
        if "failed" not in r and "refined_trans_mean" in r:
            table.setdefault((r["dataset"], r["proposal"]), []).append(r)
    for (dataset, proposal), runs in table.items():
        filt = np.array([r["trans_mean"] for r in runs])
        refined = np.array([r["refined_trans_mean"] for r in runs])
        se = (lambda x: x.std(ddof=1) / np.sqrt(x.size)) if len(runs) > 1 else (lambda x: 0.0)
        lines.append(f"| {dataset} | {method_label(proposal)} | {len(runs)} | {filt.mean():.3f} ± {se(filt):.3f} "
                     f"| {refined.mean():.3f} ± {se(refined):.3f} | {refined.max():.3f} | {int((refined > over).sum())} |")
    return "\n".join(lines) + "\n"


JUDGED_FILE = "judged_by_eye.json"
"""In the output folder: ``{"DATASET/PROPOSAL-seedS": "what the map shows", ...}``, the runs whose
map shows a doubled structure (a failed closure) to someone who looked at it."""


def failed_runs(records: list[dict], judged: dict | None = None) -> dict:
    """The failed runs per (dataset, proposal): ``[(seed, reason), ...]``.

    A run fails when its relation error is above twice the log's best run (the smallest error of
    any method and seed on that log: a closure that some run makes and this one did not), or
    when ``judged`` names it (a doubled structure seen in its map; see :data:`JUDGED_FILE`)."""
    judged = judged or {}
    runs = [r for r in records if "failed" not in r]
    best = {}
    for r in runs:
        best[r["dataset"]] = min(best.get(r["dataset"], np.inf), r["trans_mean"])
    out: dict = {}
    for r in runs:
        reasons = []
        if r["trans_mean"] > 2.0 * best[r["dataset"]]:
            reasons.append(f"{r['trans_mean']:.3f} m > 2 x {best[r['dataset']]:.3f} m")
        seen = judged.get(f"{r['dataset']}/{r['proposal']}-seed{r['seed']}")
        if seen:
            reasons.append(seen)
        failures = out.setdefault((r["dataset"], r["proposal"]), [])
        if reasons:
            failures.append((r["seed"], "; ".join(reasons)))
    return out


def robustness_markdown(records: list[dict], judged: dict | None = None) -> str:
    """Per log and method: seeds, relation error mean ± standard error over seeds, failed runs
    (:func:`failed_runs`), mean wall time, real-time factor and peak memory."""
    failures = failed_runs(records, judged)
    lines = ["| log | method | seeds | relation error [m] | failed runs | wall [s] | real-time factor "
             "| peak memory [MB] |", "|---|---|---|---|---|---|---|---|"]
    table: dict = {}
    for r in records:
        if "failed" not in r:
            table.setdefault((r["dataset"], r["proposal"]), []).append(r)
    order = {d: i for i, d in enumerate(DATASETS)}
    rank = {p: i for i, p in enumerate(PROPOSALS)}
    for (dataset, proposal), runs in sorted(table.items(), key=lambda kv: (order.get(kv[0][0], 99),
                                                                          rank.get(kv[0][1], 99), kv[0][1])):
        err = np.array([r["trans_mean"] for r in runs])
        se = err.std(ddof=1) / np.sqrt(err.size) if err.size > 1 else float("nan")
        failed = failures.get((dataset, proposal), [])
        seeds = ", ".join(str(seed) for seed, _ in sorted(failed))
        lines.append(f"| {dataset} | {method_label(proposal)} | {len(runs)} | {err.mean():.3f} ± {se:.3f} "
                     f"| {len(failed)}{f' (seeds {seeds})' if failed else ''} "
                     f"| {np.mean([r['wall_s'] for r in runs]):.0f} | {np.mean([r['real_time_factor'] for r in runs]):.1f} "
                     f"| {np.mean([r['peak_memory_mb'] for r in runs]):.0f} |")
    return "\n".join(lines) + "\n"


FAILED_MAPS_FILE = "failed_maps.png"
"""In the output folder: every failed run's map (:func:`failed_runs`; the OP's left out unless
asked), one panel each, titled with its log, method, seed and relation error."""


def failed_maps_figure(records: list[dict], out: Path, judged: dict | None = None,
                       proposals: tuple[str, ...] = ("smp", "lp", "lp-odometry", "lp-c0"),
                       panel_pixels: int = 400) -> Path | None:
    """Draw the maps (``DATASET/PROPOSAL-seedS/map.png`` under ``out``) of the failed runs of
    ``proposals`` into ``out / FAILED_MAPS_FILE``, each shrunk to at most ``panel_pixels`` a
    side. Returns the file, or None when no such run failed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    order = {d: i for i, d in enumerate(DATASETS)}
    rank = {p: i for i, p in enumerate(PROPOSALS)}
    panels = []
    for (dataset, proposal), failures in sorted(failed_runs(records, judged).items(),
                                                key=lambda kv: (order.get(kv[0][0], 99), rank.get(kv[0][1], 99))):
        if proposal not in proposals:
            continue
        errors = {r["seed"]: r["trans_mean"] for r in records
                  if r.get("dataset") == dataset and r.get("proposal") == proposal and "failed" not in r}
        for seed, _ in sorted(failures):
            png = out / dataset / f"{proposal}-seed{seed}" / "map.png"
            if png.is_file():
                panels.append((png, f"{dataset} {method_label(proposal)}\nseed {seed}: {errors[seed]:.3f} m"))
    if not panels:
        return None
    cols = min(4, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 4.3 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (png, title) in zip(axes.ravel(), panels):
        image = Image.open(png)
        image.thumbnail((panel_pixels, panel_pixels))
        ax.imshow(np.asarray(image.convert("L")), cmap="gray", vmin=0, vmax=255)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path = out / FAILED_MAPS_FILE
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def write_tables(store: ResultStore):
    """The summary in results.json, results.md and seeds.md, from every run in the folder."""
    summary = aggregate(store.runs)
    judged_path = store.path.parent / JUDGED_FILE
    judged = json.loads(judged_path.read_text()) if judged_path.is_file() else {}
    failures = {f"{d}/{p}": [{"seed": seed, "reason": why} for seed, why in runs]
                for (d, p), runs in failed_runs(store.runs, judged).items()}
    store.write(summary=summary, failed_runs=failures, gmapping_this_machine=GMAPPING_HERE, published=PUBLISHED)
    (store.path.parent / "results.md").write_text(markdown(summary))
    (store.path.parent / "robustness.md").write_text(robustness_markdown(store.runs, judged))
    (store.path.parent / "seeds.md").write_text(seed_markdown(store.runs))


def write_everything(store: ResultStore, out: Path) -> int:
    """The tables, the failed runs' maps and the printed tables, at the end of a call."""
    write_tables(store)
    judged_path = out / JUDGED_FILE
    failed_maps_figure(store.runs, out, json.loads(judged_path.read_text()) if judged_path.is_file() else None)
    print(markdown(aggregate(store.runs)))
    print((out / "robustness.md").read_text())
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="results/datasets")
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(DATASETS))
    parser.add_argument("--proposals", nargs="+", default=["op", "smp", "lp"],
                        choices=list(PROPOSALS),
                        help="lp: the library's LP (localizers around the scan match); lp-odometry: the "
                             "paper's (localizers from the motion model); lp-c0: the library's with "
                             "lookahead.selection_correction=0 (the evidence alone weighs the particles)")
    parser.add_argument("--refine", action="store_true",
                        help="also localise every scan in each final map (jaxslam map's default; without it --no-refine): a refined row")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="change one of the table's settings for every run (after them, so it wins), "
                             "e.g. num_particles=100; use a new --out (runs are cached there)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="runs at a time, each its own process (a machine with many cores or a GPU); "
                             "runs that share a machine slow each other: the wall times say so")
    batching = parser.add_argument_group(
        "batches over devices and hosts", "the seeds of a (log, proposal) as one program in this process, the runs "
        "split over the devices (jaxslam.slam.run_batch); the same records, tables and resume (docs/tuning.md, "
        "'Running at scale')")
    batching.add_argument("--batch-seeds", action="store_true",
                          help="run the seeds of each (log, proposal) as one batch over the devices")
    batching.add_argument("--devices", type=int, default=None, metavar="D",
                          help="batch the seeds (--batch-seeds) over the first D devices (default all that jax "
                               "sees; on a CPU, XLA_FLAGS=--xla_force_host_platform_device_count=D before the run "
                               "makes D)")
    batching.add_argument("--coordinator", metavar="HOST:PORT",
                          help="several hosts (implies --batch-seeds): jax.distributed's coordinator, process 0's "
                               "address; start the same command in every process with its --process-id")
    batching.add_argument("--num-processes", type=int, default=1, help="with --coordinator: how many processes")
    batching.add_argument("--process-id", type=int, default=0, help="with --coordinator: this process's, 0 .. P-1")
    args = parser.parse_args(argv)
    data, out = Path(args.data), Path(args.out)
    if not data.is_dir():
        print(f"datasets not found at {data}", file=sys.stderr)
        return 2
    if args.jobs < 1:
        print(f"--jobs must be at least 1, got {args.jobs}", file=sys.stderr)
        return 2
    batched = args.batch_seeds or args.coordinator is not None or args.devices is not None
    if batched and args.jobs != 1:
        print("--jobs and --batch-seeds (--devices, --coordinator) do not go together: a batch is one process",
              file=sys.stderr)
        return 2
    if args.coordinator is not None and not 0 <= args.process_id < args.num_processes:
        print(f"--process-id must be in 0 .. {args.num_processes - 1}, got {args.process_id}", file=sys.stderr)
        return 2
    if args.devices is not None and args.devices < 1:
        print(f"--devices must be at least 1, got {args.devices}", file=sys.stderr)
        return 2
    settings = {**SETTINGS, "refine": args.refine, "set": SETTINGS["set"] + args.set}
    try:  # results.json describes every run in the folder: an earlier call's runs stay in it
        store = ResultStore(out / "results.json", settings, key=lambda r: (r["dataset"], r["proposal"], r["seed"]))
    except SettingsMismatch as err:
        print(err, file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    from concurrent.futures import ThreadPoolExecutor, as_completed

    from tqdm import tqdm

    # Seed by seed over the logs: a run stopped part way leaves every log and method with as many
    # seeds (with --jobs J, up to J runs further). Failed runs (no errors.json) are retried.
    jobs = [(d, p, s) for s in range(args.seeds) for d in args.datasets for p in args.proposals]
    todo = [job for job in jobs if store.get(job) is None or "failed" in store.get(job)]
    if batched:
        return run_batches(args, store, jobs, todo, out, data, settings)
    with tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="runs", unit="run") as progress, \
            ThreadPoolExecutor(max_workers=args.jobs) as pool:
        # Each run is a subprocess: threads only wait for them. Records are stored here, in this thread.
        futures = [pool.submit(run_one, *job, out, data, settings) for job in todo]
        for future in as_completed(futures):
            store.add(future.result())
            write_tables(store)
            progress.update()
    return write_everything(store, out)


def run_batches(args, store: ResultStore, jobs: list, todo: list, out: Path, data: Path, settings: dict) -> int:
    """``main`` with ``--batch-seeds``: each (log, proposal)'s seeds to do as one batch
    (:func:`run_seeds_batched`). Under ``--coordinator`` every process runs the same batches
    (process 0's list of runs to do), gets the records of every process's runs, and process 0
    alone writes results.json and the tables; the run folders are written by the process that
    held the run (a --out that all hosts share keeps them in one place)."""
    import jax
    from tqdm import tqdm

    if args.coordinator is not None:
        jax.distributed.initialize(args.coordinator, num_processes=args.num_processes, process_id=args.process_id)
    from jaxslam.slam import batch_devices

    try:
        batch_devices(args.devices)  # there are that many, before any work
    except ValueError as err:
        print(err, file=sys.stderr)
        return 2
    lead = jax.process_index() == 0
    todo = [tuple(job) for job in gather_json(todo)[0]]  # process 0's: every process runs the same batches
    cells = {}
    for dataset, proposal, seed in todo:
        cells.setdefault((dataset, proposal), []).append(seed)
    with tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="runs", unit="run", disable=not lead) as progress:
        for (dataset, proposal), seeds in sorted(cells.items(), key=lambda kv: (list(DATASETS).index(kv[0][0]),
                                                                             list(PROPOSALS).index(kv[0][1]))):
            try:
                records = run_seeds_batched(dataset, proposal, seeds, out, data, settings, args.devices)
            except Exception as err:  # noqa: BLE001 (recorded, as a failed subprocess is; a rerun retries it)
                records = [{"dataset": dataset, "proposal": proposal, "seed": seed,
                            "failed": f"{type(err).__name__}: {err}"[-2000:]} for seed in seeds]
                if lead:
                    print(f"{dataset} {proposal}: the batch failed: {err}", file=sys.stderr)
            records = [r for part in gather_json(records) for r in part]  # every process's runs
            if lead:
                store.add(*records)
                write_tables(store)
            progress.update(len(seeds))
    if not lead:
        return 0
    return write_everything(store, out)


if __name__ == "__main__":
    sys.exit(main())
