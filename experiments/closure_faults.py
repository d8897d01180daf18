"""The loop closure's stress set: each tuning log's odometry made worse in measured steps, mapped by
``jaxslam map`` at its defaults; the refined error against the fault's size, beside the filter
alone's and the closed trajectory's (issue 81, item 5).

A fault cell (:class:`FaultCell`, named as in :data:`CELLS`) is a tuple (drift deg/m, scale %,
slip count, slip degrees), applied to the log's odometry poses (``LaserLog.odometry``) before
mapping, in this order (:func:`apply_cell`):

1. drift and scale, step by step (:func:`drift_and_scale`): each odometry step (the relative motion
   from one scan's pose to the next, :func:`jaxslam.geometry.between_np`) has its translation
   scaled by ``1 + scale / 100`` and its heading change increased by ``drift`` (deg/m, converted
   to radians) times the step's length as the log recorded it (m, before scaling); the poses are
   chained again from the first one (:func:`jaxslam.geometry.chain_np`);
2. heading slips (``experiments/faults.py``'s :func:`faults.inject_faults`, kind "heading"): at
   ``slips`` of the log's turns (:func:`faults.find_turns` on the *clean* odometry, drawn from the
   seed, so a cell's slips fall at the same scans with or without drift), every later odometry
   pose is rotated by ``slip_deg`` about the slip point.

Names: ``clean``, or the non-zero parts joined by ``+`` in the order ``drift<D>``, ``scale<S>``,
``slips<N>x<DEG>`` (``drift0.5+slips3x25``, ``drift1+scale3+slips5x40``; :func:`parse_cell`).
``--faults`` takes names of :data:`CELLS` or any other well-formed name; the clean cell is always
run (every ratio needs it).

Each faulted log is written as a CARMEN log (:func:`jaxslam.io.write_carmen`; the clean run goes
through the same writer) and mapped with ``jaxslam map`` in a subprocess (its own defaults unless
``--proposal``, ``--particles`` or ``--set`` say otherwise), into
``OUT/runs/<dataset>/<cell>/seed<k>/`` (trajectory_filter.txt, trajectory.txt,
trajectory_refined.txt, graph.npz, summary.json, ...; ``--keep-logs`` keeps the faulted log beside
it as ``seed<k>.clf``, so that the closure can be rerun on the saved filter trajectory). Each
trajectory is scored with the relation metric of Kuemmerle et al. 2009 (mean translational error,
m; the relations are keyed by the scans' timestamps, which the faults leave alone).

Writes ``OUT/results.json`` (one record per dataset, cell and seed; the settings at the top, a
folder written with other settings refused; finished runs skipped on restart:
``experiments/_runs.py``), ``OUT/closure_faults.md`` (rows dataset x cell: filter / closed /
refined error, loops kept, the refined error against the clean run's plus 1 cm, and the issue's
two targets marked pass/fail: :data:`TARGETS`) and ``OUT/closure_faults.png`` (the refined error
against the fault's size for the drift, scale and slip ladders and the combinations, a line per
dataset, the filter alone dashed).

    python experiments/closure_faults.py --out results/closure_faults --seeds 0 1 2

MIT Killian's bag is left out: its relations are on another clock, and faults.py / datasets.py
have no clock alignment for it (``experiments/closure_stress.py --align-clock`` works on a saved
trajectory, not a faulted log).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import faults  # experiments/faults.py: find_turns, inject_faults, read_dataset, DATASETS, DATA
import numpy as np
from _runs import ResultStore, SettingsMismatch, write_json  # experiments/_runs.py: the shared resume helper

from jaxslam.geometry import between_np, chain_np
from jaxslam.laserlog import LaserLog

DATASETS = faults.DATASETS
DATA = faults.DATA
DEFAULT_DATASETS = ("intel", "aces", "mit-csail")
"""The tuning logs a faulted copy of which can be written as CARMEN (FR-clinic's interleaved beam layouts cannot:
``check_arguments`` refuses it, naming why)."""


class FaultCell(NamedTuple):
    """One fault cell: drift (deg per metre travelled), scale error (%), heading slips (count, deg)."""
    drift_deg_per_m: float = 0.0
    scale_pct: float = 0.0
    slips: int = 0
    slip_deg: float = 0.0


_NUMBER = r"(\d+(?:\.\d+)?)"
_PART = {"drift": re.compile(rf"drift{_NUMBER}"), "scale": re.compile(rf"scale{_NUMBER}"),
         "slips": re.compile(rf"slips(\d+)x{_NUMBER}")}


def parse_cell(name: str) -> FaultCell:
    """The :class:`FaultCell` of a name (``clean``, ``drift0.5``, ``scale3``, ``slips3x25``, joined
    by ``+`` in that order: ``drift1+scale3+slips5x40``). ValueError naming the problem for an
    unknown part, a part out of order or repeated, a negative size, a zero part or zero slips."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"fault cell {name!r}: expected 'clean' or parts like drift0.5+scale3+slips3x25")
    if name == "clean":
        return FaultCell()
    values = {}
    order = list(_PART)
    for part in name.split("+"):
        if "-" in part:
            raise ValueError(f"fault cell {name!r}: {part!r} has a negative size (sizes are >= 0)")
        kind = next((k for k, pattern in _PART.items() if pattern.fullmatch(part)), None)
        if kind is None:
            raise ValueError(f"fault cell {name!r}: unknown part {part!r} (expected drift<D>, scale<S> or "
                             "slips<N>x<DEG>, e.g. drift0.5+scale3+slips3x25, or 'clean')")
        if kind in values or any(k in values for k in order[order.index(kind) + 1:]):
            raise ValueError(f"fault cell {name!r}: parts must appear once each, in the order drift, scale, slips")
        values[kind] = _PART[kind].fullmatch(part).groups()
    cell = FaultCell(float(values.get("drift", ("0",))[0]), float(values.get("scale", ("0",))[0]),
                     int(values.get("slips", ("0", "0"))[0]), float(values.get("slips", ("0", "0"))[1]))
    if ("drift" in values and cell.drift_deg_per_m == 0) or ("scale" in values and cell.scale_pct == 0) or \
            ("slips" in values and (cell.slips == 0 or cell.slip_deg == 0)):
        raise ValueError(f"fault cell {name!r}: a part of size zero (leave it out; no fault at all is 'clean')")
    return cell


def cell_name(cell: FaultCell) -> str:
    """The name of a cell (:func:`parse_cell`'s inverse): its non-zero parts, or ``clean``."""
    parts = []
    if cell.drift_deg_per_m:
        parts.append(f"drift{cell.drift_deg_per_m:g}")
    if cell.scale_pct:
        parts.append(f"scale{cell.scale_pct:g}")
    if cell.slips and cell.slip_deg:
        parts.append(f"slips{cell.slips}x{cell.slip_deg:g}")
    return "+".join(parts) or "clean"


CELLS = {cell_name(c): c for c in (
    FaultCell(),
    FaultCell(drift_deg_per_m=0.1), FaultCell(drift_deg_per_m=0.25), FaultCell(drift_deg_per_m=0.5),
    FaultCell(drift_deg_per_m=1.0),
    FaultCell(scale_pct=1.0), FaultCell(scale_pct=3.0), FaultCell(scale_pct=5.0),
    FaultCell(slips=3, slip_deg=10.0), FaultCell(slips=3, slip_deg=25.0), FaultCell(slips=5, slip_deg=40.0),
    FaultCell(drift_deg_per_m=0.25, scale_pct=1.0, slips=3, slip_deg=10.0),
    FaultCell(drift_deg_per_m=0.5, slips=3, slip_deg=25.0),  # the first target
    FaultCell(drift_deg_per_m=1.0, scale_pct=3.0, slips=5, slip_deg=40.0),  # the second target
)}
"""The stress set, cell name -> :class:`FaultCell`: the clean run, the single-fault ladders (drift
0.1-1 deg/m, scale 1-5 %, slips 3 x 10, 3 x 25 and 5 x 40 degrees) and the combinations."""

TARGETS = {"drift0.5+slips3x25": 1.25, "drift1+scale3+slips5x40": 2.0}
"""The issue's targets: cell -> the largest refined / (clean refined + :data:`CLEAN_FLOOR_M`) that passes."""
CLEAN_FLOOR_M = 0.01
"""Added to the clean run's refined error in the ratio (1 cm: a near-perfect clean run does not
make every faulted one look bad)."""
TURN_WINDOW_S = 2.0
"""The window of :func:`faults.find_turns` (s)."""


# ----------------------------------------------------------------------------- faults

def drift_and_scale(odometry, drift_deg_per_m: float = 0.0, scale_pct: float = 0.0) -> np.ndarray:
    """(T, 3) odometry poses (m, m, rad) with every step's translation scaled by ``1 + scale_pct / 100``
    and its heading change increased by ``radians(drift_deg_per_m)`` times the step's recorded length
    (m), chained again from the first pose (which stays as it was)."""
    odometry = np.asarray(odometry, np.float64)
    if odometry.shape[0] < 2:
        return odometry.copy()
    steps = between_np(odometry[:-1], odometry[1:])
    length = np.hypot(steps[:, 0], steps[:, 1])
    steps[:, :2] *= 1.0 + scale_pct / 100.0
    steps[:, 2] += math.radians(drift_deg_per_m) * length
    return chain_np(odometry[0], steps)


def apply_cell(log: LaserLog, cell: FaultCell, seed: int, window_s: float = TURN_WINDOW_S
               ) -> tuple[LaserLog, np.ndarray]:
    """``(faulted log, slip scans)``: :func:`drift_and_scale`, then ``cell.slips`` heading slips of
    ``cell.slip_deg`` at the clean odometry's turns drawn from ``seed`` (:func:`faults.find_turns`,
    :func:`faults.inject_faults`). The clean cell gives the log itself and no slip scans.
    Timestamps, scans, sensor and ground truth are unchanged."""
    if any(v < 0 or not math.isfinite(v) for v in cell):
        raise ValueError(f"apply_cell: every size must be finite and >= 0, got {cell}")
    faulted = log
    if cell.drift_deg_per_m or cell.scale_pct:
        odometry = drift_and_scale(log.odometry, cell.drift_deg_per_m, cell.scale_pct)
        note = f"odometry drift {cell.drift_deg_per_m:g} deg/m, scale error {cell.scale_pct:g} %"
        faulted = dataclasses.replace(log, odometry=odometry, notes=log.notes + (note,))
    turns = np.zeros(0, np.int64)
    if cell.slips and cell.slip_deg:
        turns = faults.find_turns(log.odometry, log.timestamps, cell.slips, seed, window_s)
        faulted, turns = faults.inject_faults(faulted, "heading", math.radians(cell.slip_deg), steps=turns)
    return faulted, turns


# ----------------------------------------------------------------------------- runs

def map_command(clf: Path, run_dir: Path, seed: int, settings: dict) -> list[str]:
    """``jaxslam map``'s command line for one run: its defaults but for the settings given."""
    cmd = [sys.executable, "-m", "jaxslam.cli", "map", str(clf), "--seed", str(seed), "--out", str(run_dir),
           "--no-progress"]
    if settings["proposal"] is not None:
        cmd += ["--proposal", settings["proposal"]]
    if settings["particles"] is not None:
        cmd += ["--particles", str(settings["particles"])]
    for item in settings["set"]:
        cmd += ["--set", item]
    return cmd


def relation_errors(run_dir: Path, relations) -> dict:
    """The mean translational (m) and rotational (deg) relation errors of a run folder's filter,
    closed and refined trajectories (None where the file is missing)."""
    from jaxslam.io import read_trajectory
    from jaxslam.metrics import relation_error

    files = {"filter": "trajectory_filter.txt", "closed": "trajectory.txt", "refined": "trajectory_refined.txt"}
    if not (run_dir / files["filter"]).is_file():  # no closure ran: trajectory.txt is the filter's
        files = {"filter": "trajectory.txt", "closed": None, "refined": files["refined"]}
    out = {}
    for which, name in files.items():
        err = relation_error(*read_trajectory(run_dir / name), relations) if name and (run_dir / name).is_file() \
            else None
        out[f"{which}_trans_mean"] = None if err is None else err.trans_mean
        out[f"{which}_rot_mean_deg"] = None if err is None else float(np.degrees(err.rot_mean))
        if err is not None:
            out["relations"] = err.count
    return out


def run_one(dataset: str, cell: str, seed: int, out: Path, data: Path, settings: dict,
            keep_log: bool = False) -> dict:
    """Fault the log, write it, map it with ``jaxslam map`` (subprocess), score it: the run's record,
    also written to its folder's errors.json (a later call returns that)."""
    import json

    from jaxslam.io import write_carmen

    run_dir = out / "runs" / dataset / cell / f"seed{seed}"
    scored = run_dir / "errors.json"
    if scored.is_file():
        return json.loads(scored.read_text())
    fault = parse_cell(cell)
    log, relations = faults.read_dataset(dataset, data, settings["max_scans"])
    faulted, slip_scans = apply_cell(log, fault, seed, settings["turn_window_s"])
    base = {"dataset": dataset, "cell": cell, **fault._asdict(), "seed": seed,
            "slip_scans": slip_scans.tolist(), "run_dir": str(run_dir)}
    clf = run_dir.parent / f"seed{seed}.clf"
    clf.parent.mkdir(parents=True, exist_ok=True)
    write_carmen(clf, faulted)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(map_command(clf, run_dir, seed, settings), capture_output=True, text=True)
    finally:
        if not keep_log:
            clf.unlink(missing_ok=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:  # recorded (not cached): the table shows it, a rerun retries it
        return {**base, "failed": proc.stderr[-2000:]}
    summary = json.loads((run_dir / "summary.json").read_text())
    record = {**base, **relation_errors(run_dir, relations),
              "loops_kept": summary.get("closure", {}).get("loops_kept"),
              "wall_s": wall, "filter_s": summary["timings"]["total"],
              "scans_processed": summary["scans_processed"], "warnings": summary["warnings"]}
    write_json(scored, record)
    return record


# ----------------------------------------------------------------------------- the table

def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def summarize_cells(records: list[dict], floor: float = CLEAN_FLOOR_M) -> dict:
    """Per (dataset, cell): ``{"seeds", "crashed", "filter", "closed", "refined" (mean errors, m,
    over the finished seeds), "loops_kept" (mean), "ratio", "target", "verdict"}``.

    ``ratio`` = mean refined error / (mean refined error of the clean runs of the same seeds +
    ``floor``), over the seeds where both finished (None without one). ``verdict`` for a cell of
    :data:`TARGETS`: "pass" when ratio <= target and no seed crashed, "fail" otherwise, "no clean
    run" when no seed has both runs; None for the other cells."""
    by_key = {(r["dataset"], r["cell"], r["seed"]): r for r in records}
    groups: dict = {}
    for (dataset, cell, seed), run in sorted(by_key.items()):
        groups.setdefault((dataset, cell), []).append((seed, run))
    out = {}
    for (dataset, cell), runs in groups.items():
        done = [r for _, r in runs if "failed" not in r]
        paired = [(r, by_key.get((dataset, "clean", seed))) for seed, r in runs if "failed" not in r]
        paired = [(r, c) for r, c in paired if c is not None and "failed" not in c
                  and r.get("refined_trans_mean") is not None and c.get("refined_trans_mean") is not None]
        ratio = None
        if paired:
            ratio = _mean([r["refined_trans_mean"] for r, _ in paired]) / (
                _mean([c["refined_trans_mean"] for _, c in paired]) + floor)
        crashed = len(runs) - len(done)
        target = TARGETS.get(cell)
        verdict = None
        if target is not None:
            verdict = "no clean run" if ratio is None and not crashed else \
                "pass" if ratio is not None and ratio <= target and not crashed else "fail"
        out[(dataset, cell)] = {
            "seeds": len(runs), "crashed": crashed,
            **{which: _mean([r.get(f"{which}_trans_mean") for r in done]) for which in ("filter", "closed", "refined")},
            "loops_kept": _mean([r.get("loops_kept") for r in done]),
            "ratio": ratio, "target": target, "verdict": verdict}
    return out


def cell_order(names) -> list[str]:
    """``names`` in :data:`CELLS`' order, then any others by (drift, scale, slips, slip size)."""
    names = set(names)
    known = [c for c in CELLS if c in names]
    return known + sorted(names - set(known), key=parse_cell)


def _metres(value) -> str:
    return "–" if value is None else f"{value:.3f}"


def closure_faults_markdown(records: list[dict], floor: float = CLEAN_FLOOR_M) -> str:
    """The table: a row per dataset x cell, the mean filter / closed / refined relation errors (m),
    the loops kept, the refined error against the clean run's (+ ``floor``), and the issue's targets
    (:func:`summarize_cells`)."""
    table = summarize_cells(records, floor)
    rank = {d: i for i, d in enumerate(DATASETS)}
    order = {c: i for i, c in enumerate(cell_order({c for _, c in table}))}
    lines = [f"Mean relation error [m] over the seeds (filter alone, closed, refined), the loops kept, and the "
             f"refined error / (the clean run's refined error + {floor * 100:g} cm) over the same seeds.", "",
             "| log | cell | seeds | filter [m] | closed [m] | refined [m] | loops kept | refined / (clean + 1 cm) "
             "| target |", "|---|---|---|---|---|---|---|---|---|"]
    for (dataset, cell), s in sorted(table.items(), key=lambda kv: (rank.get(kv[0][0], 99), order[kv[0][1]])):
        seeds = f"{s['seeds'] - s['crashed']}" + (f" ({s['crashed']} crashed)" if s["crashed"] else "")
        loops = "–" if s["loops_kept"] is None else f"{s['loops_kept']:.1f}"
        ratio = "–" if s["ratio"] is None else f"{s['ratio']:.2f}"
        target = "" if s["target"] is None else f"<= {s['target']:g}: **{s['verdict']}**"
        lines.append(f"| {dataset} | {cell} | {seeds} | {_metres(s['filter'])} | {_metres(s['closed'])} "
                     f"| {_metres(s['refined'])} | {loops} | {ratio} | {target} |")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- the figure

LADDERS = {"drift": ("drift [deg/m]", lambda c: c.drift_deg_per_m),
           "scale": ("scale error [%]", lambda c: c.scale_pct),
           "slips": ("heading slip [deg] (count in the cell's name)", lambda c: c.slip_deg)}


def ladder_of(cell: FaultCell) -> str | None:
    """"drift", "scale" or "slips" for a single-fault cell, "combination" for several, None for clean."""
    parts = [bool(cell.drift_deg_per_m), bool(cell.scale_pct), bool(cell.slips and cell.slip_deg)]
    if sum(parts) == 0:
        return None
    return list(LADDERS)[parts.index(True)] if sum(parts) == 1 else "combination"


def figure_lines(records: list[dict]) -> dict:
    """``{panel: {dataset: (xs, refined, filter, labels)}}`` for the panels drift, scale, slips
    (x the fault's size; the clean cell at 0) and combination (x the cell's rank; clean first)."""
    table = summarize_cells(records)
    panels: dict = {p: {} for p in (*LADDERS, "combination")}
    for panel, lines in panels.items():
        for dataset in sorted({d for d, _ in table}, key=lambda d: list(DATASETS).index(d) if d in DATASETS else 99):
            cells = [c for c in cell_order(c for d, c in table if d == dataset)
                     if ladder_of(parse_cell(c)) in (None, panel) and table[(dataset, c)]["refined"] is not None]
            if not any(ladder_of(parse_cell(c)) == panel for c in cells):
                continue
            xs = [float(i) if panel == "combination" else float(LADDERS[panel][1](parse_cell(c)))
                  for i, c in enumerate(cells)]
            lines[dataset] = (xs, [table[(dataset, c)]["refined"] for c in cells],
                              [table[(dataset, c)]["filter"] for c in cells], cells)
    return panels


def closure_faults_figure(records: list[dict], path: Path) -> Path:
    """The refined error against the fault's size (:func:`figure_lines`): a panel per ladder and one
    for the combinations, a line per dataset, the filter alone dashed in the same colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = figure_lines(records)
    fig, axes = plt.subplots(1, 4, figsize=(17, 4.2))
    for ax, (panel, lines) in zip(axes, panels.items()):
        for i, (dataset, (xs, refined, filtered, cells)) in enumerate(lines.items()):
            color = f"C{i}"
            ax.plot(xs, refined, marker="o", color=color, label=f"{dataset} refined")
            ax.plot(xs, [np.nan if v is None else v for v in filtered], ls="--", marker=".", color=color,
                    alpha=0.7, label=f"{dataset} filter alone")
            if panel == "combination":
                ax.set_xticks(xs, cells, rotation=20, ha="right", fontsize=7)
        ax.set_xlabel(LADDERS[panel][0] if panel in LADDERS else "combination")
        ax.set_title(panel)
        if lines:
            ax.set_yscale("log")
        else:
            ax.text(0.5, 0.5, "no runs", ha="center", va="center", transform=ax.transAxes, color="gray")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("relation error [m]")
    return faults.save_with_legend(fig, axes, path, max_columns=8)


def write_tables(store: ResultStore, floor: float = CLEAN_FLOOR_M):
    """Each record's ``refined_ratio`` (against the clean run of its seed), the cells' summary in
    results.json, closure_faults.md and closure_faults.png."""
    clean = {(r["dataset"], r["seed"]): r.get("refined_trans_mean") for r in store.runs
             if r["cell"] == "clean" and "failed" not in r}
    for r in store.runs:
        base = clean.get((r["dataset"], r["seed"]))
        mine = r.get("refined_trans_mean")
        r["refined_ratio"] = None if base is None or mine is None else mine / (base + floor)
    summary = {f"{d}/{c}": s for (d, c), s in summarize_cells(store.runs, floor).items()}
    store.write(cells=summary)
    folder = store.path.parent
    (folder / "closure_faults.md").write_text(closure_faults_markdown(store.runs, floor))
    if any("failed" not in r for r in store.runs):
        closure_faults_figure(store.runs, folder / "closure_faults.png")


# ----------------------------------------------------------------------------- main

def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="results/closure_faults")
    parser.add_argument("--data", default=str(DATA), help="the logs' folder (default ../shared/data)")
    parser.add_argument("--datasets", nargs="+", default=list(DEFAULT_DATASETS),
                        help=f"of {', '.join(DATASETS)} (default: {' '.join(DEFAULT_DATASETS)})")
    parser.add_argument("--faults", nargs="+", default=list(CELLS), metavar="CELL",
                        help="fault cells (default all of CELLS; the clean cell is always run)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="the seeds (default 0 1 2)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="passed to every `jaxslam map`; use a new --out (runs are cached there)")
    parser.add_argument("--proposal", choices=["op", "smp", "lp"], default=None,
                        help="jaxslam map's --proposal (default: its own, smp)")
    parser.add_argument("--particles", type=int, default=None, help="jaxslam map's --particles (default: its own)")
    parser.add_argument("--max-scans", type=int, default=None,
                        help="only the first N scans of each log (the relations among them): a smoke run")
    parser.add_argument("--keep-logs", action="store_true",
                        help="keep each faulted log beside its run folder (OUT/runs/<dataset>/<cell>/seed<k>.clf)")
    return parser


def check_arguments(args) -> tuple[list[str], str | None]:
    """``(cells to run, clean first; the problem or None)``: everything checked before any run."""
    unknown = [d for d in args.datasets if d not in DATASETS]
    if unknown:
        return [], f"unknown dataset(s) {', '.join(unknown)} (known: {', '.join(DATASETS)})"
    cells = []
    for name in args.faults:
        try:
            parse_cell(name)
        except ValueError as err:
            return [], f"--faults: {err}"
        cells.append(name)
    for flag, value, least in (("--particles", args.particles, 1), ("--max-scans", args.max_scans, 2)):
        if value is not None and value < least:
            return [], f"{flag} must be at least {least}, got {value}"
    if any(s < 0 for s in args.seeds):
        return [], f"--seeds must be >= 0, got {args.seeds}"
    data = Path(args.data)
    if not data.is_dir():
        return [], f"data folder not found: {data}"
    missing = [str(data / name) for d in args.datasets for name in DATASETS[d] if not (data / name).exists()]
    if missing:
        return [], f"not found: {', '.join(missing)}"
    from jaxslam.cli import parse_assignments
    from jaxslam.config import ConfigError, build_setup

    try:  # a bad --set is refused here, not by every run
        build_setup({**({"proposal": args.proposal} if args.proposal else {}), **parse_assignments(args.set)})
    except ConfigError as err:
        return [], f"--set: {err}"
    problem = unwritable_log(args.datasets, data, args.max_scans)
    if problem:
        return [], problem
    return ["clean"] + [c for c in cell_order(cells) if c != "clean"], None


def unwritable_log(datasets: list[str], data: Path, max_scans: int | None) -> str | None:
    """The first dataset whose log cannot be written as the CARMEN log a run maps (beams not evenly
    spaced, as FR-clinic's interleaved layouts), named with the writer's reason; None when all can."""
    import tempfile

    from jaxslam.io import write_carmen
    from jaxslam.laserlog import LogError

    with tempfile.TemporaryDirectory() as folder:
        for dataset in datasets:
            log, _ = faults.read_dataset(dataset, data, max_scans)
            try:
                write_carmen(Path(folder) / "check.clf", log)
            except LogError as err:
                return f"{dataset}: its faulted log could not be mapped: {err}"
    return None


def main(argv=None) -> int:
    args = make_parser().parse_args(argv)
    cells, problem = check_arguments(args)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    out, data = Path(args.out), Path(args.data)
    settings = {"proposal": args.proposal, "particles": args.particles, "set": list(args.set),
                "max_scans": args.max_scans, "turn_window_s": TURN_WINDOW_S, "clean_floor_m": CLEAN_FLOOR_M}
    try:  # results.json describes every run in the folder: an earlier call's runs stay in it
        store = ResultStore(out / "results.json", settings, key=lambda r: (r["dataset"], r["cell"], r["seed"]))
    except SettingsMismatch as err:
        print(err, file=sys.stderr)
        return 2
    from tqdm import tqdm

    # Seed by seed over the logs, the clean run first: a stopped run leaves whole seeds.
    jobs = [(d, c, s) for s in args.seeds for d in args.datasets for c in cells]
    todo = [job for job in jobs if store.get(job) is None or "failed" in store.get(job)]
    for job in tqdm(todo, total=len(jobs), initial=len(jobs) - len(todo), desc="runs", unit="run"):
        store.add(run_one(*job, out, data, settings, args.keep_logs))
        write_tables(store)
    write_tables(store)
    print((out / "closure_faults.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
