"""Odometry faults: heading and translation slips injected at a log's turns; does the filter recover?

For each log (Intel, ACES, MIT CSAIL), proposal (SMP and LP; OP with ``--proposals``) and seed,
the log's odometry gets ``num_faults`` = 3 slips of one kind and size (:data:`FAULTS`: heading
slips of 10, 20, 30 and 45 degrees, translation slips of 0.25, 0.5 and 1 m), placed at three of
the log's turns spread over it (:func:`find_turns`, drawn from the seed) by :func:`inject_faults`:
from the slip on, every odometry pose is rotated about the slip point (heading) or shifted
along the robot's heading there (translation), so the odometry's relative motion is wrong at
exactly those three steps. The faulted log is written as a CARMEN log
(:func:`jaxslam.io.write_carmen`, read back exactly; deleted after the run unless
``--keep-logs``) and mapped by ``jaxslam map`` in a subprocess, as ``experiments/datasets.py``
does; the clean run (the same log through the same writer, no fault) is mapped with each seed
too. Each run is scored with the relation metric of Kuemmerle et al. 2009 (the relations are
keyed by the scans' timestamps, which the faults leave alone).

A run *succeeds* when its relation error (mean translational error, m) is at most
:data:`SUCCESS_FACTOR` = 1.25 times the clean run's **of the same log, proposal and seed**
(:func:`judge`). Per seed, because with one seed the faulted run draws the same random numbers
as its clean twin and is the same run up to the first slip: the comparison measures what the
slips did, not the seed-to-seed spread of the filter (some seeds miss a loop closure with clean
odometry too; docs/results.md). A cell whose clean run crashed or is missing is marked "no
clean run", not counted as a success or a failure.

Writes ``DIR/results.json`` (every run; resumes on restart: finished runs are skipped, a folder
written with other settings is refused, ``experiments/_runs.py``), ``DIR/faults.md`` (rows log x
proposal, columns the fault cells: successes / judged seeds and the mean relation error) and
``DIR/faults.png`` (the success fraction against the slip's size, a panel for heading slips and
one for translation slips, a line per log x proposal).

    python experiments/faults.py --out results/faults --proposals smp lp --seeds 3

``--ambiguous`` runs the built-to-be-ambiguous case instead
(:func:`jaxslam.sim.symmetric_junction_scenario`: a corridor forking into two identical lanes,
where from inside a lane the scan cannot tell the lanes apart) with the Python API, a few seeds
per proposal, and writes ``DIR/ambiguous.json`` and ``DIR/ambiguous.md``: at the scans in the
lane, the share of particles within 0.3 m and 10 degrees of the true pose and of the mirror pose
in the other lane (:func:`ambiguous_case`).

    python experiments/faults.py --ambiguous --out results/faults --proposals smp lp --seeds 5
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from _runs import ResultStore, SettingsMismatch, write_json  # experiments/_runs.py: the shared resume helper

from jaxslam.geometry import between_np, compose_np
from jaxslam.laserlog import LaserLog, LogError


def _datasets_module():
    """experiments/datasets.py, loaded from its file (the name ``datasets`` may be another package)."""
    name = "experiments_datasets"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parent / "datasets.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


DATASETS = _datasets_module().DATASETS
"""Log name -> (log file, relations file), as in ``experiments/datasets.py``."""
DATA = _datasets_module().DATA
"""The logs' folder, as in ``experiments/datasets.py`` (../shared/data)."""
DEFAULT_DATASETS = ("intel", "aces", "mit-csail")

FAULTS = {
    "clean": ("none", 0.0),
    "heading-10": ("heading", 10.0),
    "heading-20": ("heading", 20.0),
    "heading-30": ("heading", 30.0),
    "heading-45": ("heading", 45.0),
    "translation-0.25": ("translation", 0.25),
    "translation-0.5": ("translation", 0.5),
    "translation-1": ("translation", 1.0),
}
"""Fault cell -> (kind, size): heading slips in degrees, translation slips in metres; "clean"
is the run every cell is judged against (always run)."""

PROPOSALS = ("op", "smp", "lp")
SUCCESS_FACTOR = 1.25
"""A faulted run succeeds when its relation error is at most this many times its clean run's."""

SETTINGS = {
    "particles": 30,
    "localizers": 100,
    "horizon": 5,
    "num_faults": 3,
    "turn_window_s": 2.0,
    "success_factor": SUCCESS_FACTOR,
    "max_scans": None,
    "set": [],
}
"""What every run depends on beyond its own cell (stored in results.json; a folder written with
other settings is refused). particles / localizers / horizon: ``jaxslam map``'s (the library's
defaults, as ``experiments/datasets.py``); num_faults and turn_window_s: :func:`find_turns`;
max_scans: only the log's first scans (a smoke run); set: ``--set`` items for ``jaxslam map``."""


# ----------------------------------------------------------------------------- faults

def turn_strength(odometry, timestamps, window_s: float = 2.0) -> np.ndarray:
    """(T,) rad: how far the odometry heading turns within ``window_s`` seconds centred on each
    scan (the unwrapped heading, interpolated at ``t - window_s / 2`` and ``t + window_s / 2``,
    clipped to the log's span).

    Args:
        odometry: (T, 3) poses [x, y, theta] (m, m, rad).
        timestamps: (T,) s, non-decreasing.
        window_s: the window's length (s).
    """
    odometry = np.asarray(odometry, np.float64)
    t = np.asarray(timestamps, np.float64)
    heading = odometry[0, 2] + np.concatenate([[0.0], np.cumsum(between_np(odometry[:-1], odometry[1:])[:, 2])])
    before = np.interp(t - 0.5 * window_s, t, heading)
    after = np.interp(t + 0.5 * window_s, t, heading)
    return np.abs(after - before)


def find_turns(odometry, timestamps, num_turns: int = 3, seed: int = 0, window_s: float = 2.0,
               margin: float = 0.1, choices: int = 3) -> np.ndarray:
    """Scans at ``num_turns`` of the log's turns, spread over it, drawn from ``seed``.

    The turns are the peaks of :func:`turn_strength` (the strongest scan of each stretch of
    ``window_s`` seconds, strongest first, every peak at least ``window_s`` from a stronger
    one). The scans from ``margin`` of the log to ``1 - margin`` (by index) are cut into
    ``num_turns`` equal parts, and in each part one of its ``choices`` strongest peaks is drawn
    (``np.random.default_rng(seed)``); a part without a peak gives its scan of greatest turn
    strength.

    Returns:
        (num_turns,) int64 increasing scan indices, each >= 1 (a slip at scan k happens
        between scans k - 1 and k).

    Raises:
        ValueError: ``num_turns`` < 1, ``margin`` outside [0, 0.5), ``window_s`` <= 0, or a log
            too short for ``num_turns`` parts of at least one scan each.
    """
    odometry = np.asarray(odometry, np.float64)
    t = np.asarray(timestamps, np.float64)
    if int(num_turns) != num_turns or num_turns < 1:
        raise ValueError(f"find_turns: num_turns must be a positive integer, got {num_turns!r}")
    if not 0 <= margin < 0.5:
        raise ValueError(f"find_turns: margin must be in [0, 0.5), got {margin!r}")
    if not window_s > 0:
        raise ValueError(f"find_turns: window_s must be positive, got {window_s!r}")
    num_scans = t.shape[0]
    first = max(1, int(math.floor(margin * num_scans)))
    last = int(math.ceil((1.0 - margin) * num_scans))  # exclusive
    if last - first < num_turns:
        raise ValueError(f"find_turns: a log of {num_scans} scans is too short for {num_turns} turns "
                         f"(scans {first}..{last - 1} are used)")
    strength = turn_strength(odometry, t, window_s)
    peaks: list[int] = []
    for i in np.argsort(-strength, kind="stable"):
        if strength[i] <= 0:
            break
        if all(abs(t[i] - t[j]) >= window_s for j in peaks):
            peaks.append(int(i))
    peaks_arr = np.asarray(peaks, dtype=np.int64)
    rng = np.random.default_rng(seed)
    edges = np.linspace(first, last, num_turns + 1).round().astype(np.int64)
    chosen = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = peaks_arr[(peaks_arr >= lo) & (peaks_arr < hi)]  # strongest first
        if inside.size:
            chosen.append(int(rng.choice(inside[:choices])))
        else:
            chosen.append(int(lo + np.argmax(strength[lo:hi])))
    return np.asarray(chosen, dtype=np.int64)


def inject_faults(log: LaserLog, kind: str, size: float, num_faults: int = 3, seed: int = 0,
                  steps=None, window_s: float = 2.0) -> tuple[LaserLog, np.ndarray]:
    """The log with ``num_faults`` odometry slips of one kind and size at its turns.

    A slip at scan k (between scans k - 1 and k; the ``steps``, default :func:`find_turns`
    with ``num_faults``, ``seed`` and ``window_s``) moves every odometry pose from scan k on:

    * ``"heading"``: rotated by ``size`` (rad, counter-clockwise) about the position of the
      odometry pose at scan k - 1 (the slip point); the motion from k - 1 to k is turned by
      ``size`` (its heading change gains ``size``, its translation turns with it).
    * ``"translation"``: shifted by ``size`` (m) along the heading of the pose at k - 1; the
      motion from k - 1 to k gains ``size`` forward.

    Each slip moves the poses after it rigidly, so every other relative motion of the
    odometry is unchanged; the slips are applied in order, each to the odometry the earlier
    ones left. Timestamps, scans, sensor and ground truth are unchanged. ``size`` 0 returns
    the odometry as it was.

    Args:
        log: the log (its odometry (T, 3) m, m, rad).
        kind: "heading" or "translation".
        size: the slip: rad for heading, m for translation.
        num_faults, seed, window_s: where the slips go (:func:`find_turns`), unless ``steps``.
        steps: optional increasing scan indices in [1, T - 1], one per slip.

    Returns:
        ``(faulted log, steps)``: steps (num_faults,) int64.

    Raises:
        ValueError: an unknown ``kind``, a non-finite ``size``, or ``steps`` not increasing
            within [1, T - 1] (before any work).
    """
    if kind not in ("heading", "translation"):
        raise ValueError(f"inject_faults: kind must be 'heading' or 'translation', got {kind!r}")
    if not math.isfinite(size):
        raise ValueError(f"inject_faults: size must be a finite number, got {size!r}")
    if steps is None:
        steps = find_turns(log.odometry, log.timestamps, num_faults, seed, window_s)
    steps = np.asarray(steps, dtype=np.int64).reshape(-1)
    if steps.size == 0 or steps.min() < 1 or steps.max() > log.num_scans - 1 or np.any(np.diff(steps) <= 0):
        raise ValueError(f"inject_faults: steps must be increasing scan indices in [1, {log.num_scans - 1}], "
                         f"got {steps.tolist()}")
    odometry = log.odometry.copy()
    for k in steps:
        pivot = odometry[k - 1]
        if kind == "heading":
            turned = pivot + np.array([0.0, 0.0, size])
            odometry[k:] = compose_np(turned, between_np(pivot, odometry[k:]))
        else:
            odometry[k:, :2] += size * np.array([np.cos(pivot[2]), np.sin(pivot[2])])
    what = {"heading": f"{math.degrees(size):g} deg", "translation": f"{size:g} m"}[kind]
    note = f"{steps.size} {kind} slips of {what} injected into the odometry at scans {steps.tolist()}"
    return dataclasses.replace(log, odometry=odometry, notes=log.notes + (note,)), steps


def fault_log(log: LaserLog, fault: str, seed: int, settings: dict = SETTINGS) -> tuple[LaserLog, np.ndarray]:
    """The log of one fault cell (:data:`FAULTS`) and seed: ``(log, steps)``; "clean" gives the log
    unchanged and the steps the seed's faults would have."""
    kind, size = FAULTS[fault]
    if kind == "none":
        steps = find_turns(log.odometry, log.timestamps, settings["num_faults"], seed, settings["turn_window_s"])
        return log, steps
    slip = math.radians(size) if kind == "heading" else size  # rad or m
    return inject_faults(log, kind, slip, settings["num_faults"], seed, window_s=settings["turn_window_s"])


# ----------------------------------------------------------------------------- runs

_LOGS: dict = {}
_LOGS_LOCK = threading.Lock()


def read_dataset(dataset: str, data: Path, max_scans: int | None):
    """``(log, relations)`` of ``dataset``, read once per process (the threads of ``--jobs`` share them).

    With ``max_scans`` the log is its first ``max_scans`` scans and the relations are those
    between its scans (a LogError if there are none)."""
    from jaxslam.io import Relations, read_log, read_relations

    with _LOGS_LOCK:
        key = (dataset, str(data), max_scans)
        if key not in _LOGS:
            log_name, rel_name = DATASETS[dataset]
            log = read_log(data / log_name)
            relations = read_relations(data / rel_name)
            if max_scans is not None:
                log = log.subset(np.arange(min(max_scans, log.num_scans)))
                end = log.timestamps[-1] + 1e-4
                inside = (relations.t1 <= end) & (relations.t2 <= end)
                if not inside.any():
                    raise LogError(f"{data / rel_name}: no relation lies within the first {max_scans} scans")
                relations = Relations(relations.t1[inside], relations.t2[inside], relations.motion[inside])
            _LOGS[key] = (log, relations)
        return _LOGS[key]


def run_one(dataset: str, proposal: str, fault: str, seed: int, out: Path, data: Path,
            settings: dict = SETTINGS, keep_log: bool = False) -> dict:
    """Write the faulted log, map it with ``jaxslam map`` (subprocess), score it. Cached in out."""
    from jaxslam.io import read_trajectory, write_carmen
    from jaxslam.metrics import relation_error

    run_dir = out / dataset / f"{proposal}-{fault}-seed{seed}"
    scored = run_dir / "errors.json"
    if scored.is_file():
        return json.loads(scored.read_text())
    base = {"dataset": dataset, "proposal": proposal, "fault": fault, "kind": FAULTS[fault][0],
            "size": FAULTS[fault][1], "seed": seed}
    log, relations = read_dataset(dataset, data, settings["max_scans"])
    faulted, steps = fault_log(log, fault, seed, settings)
    base.update(fault_scans=steps.tolist(), fault_times=log.timestamps[steps].tolist())
    clf = out / "logs" / f"{dataset}-{proposal}-{fault}-seed{seed}.clf"
    clf.parent.mkdir(parents=True, exist_ok=True)
    write_carmen(clf, faulted)
    cmd = [sys.executable, "-m", "jaxslam.cli", "map", str(clf), "--proposal", proposal,
           "--particles", str(settings["particles"]), "--seed", str(seed), "--out", str(run_dir), "--no-progress"]
    if proposal == "lp":
        cmd += ["--localizers", str(settings["localizers"]), "--horizon", str(settings["horizon"])]
    for item in settings["set"]:
        cmd += ["--set", item]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True)
    finally:
        if not keep_log:
            clf.unlink(missing_ok=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        # Recorded (not cached) so that the table shows the failure and a rerun retries it.
        return {**base, "failed": proc.stderr[-2000:]}
    summary = json.loads((run_dir / "summary.json").read_text())
    err = relation_error(*read_trajectory(run_dir / "trajectory.txt"), relations).to_dict()
    record = {
        **base,
        "trans_mean": err["trans_mean"], "trans_std": err["trans_std"],
        "rot_mean_deg": err["rot_mean_deg"], "rot_std_deg": err["rot_std_deg"],
        "relations": err["count"],
        "wall_s": wall, "filter_s": summary["timings"]["total"],
        "scans_processed": summary["scans_processed"], "scans_in_log": summary["scans_in_log"],
        "warnings": summary["warnings"],
    }
    write_json(scored, record)
    return record


# ----------------------------------------------------------------------------- judging and tables

SUCCESS, FAILURE, CRASHED, NO_CLEAN = "success", "failure", "crashed", "no clean run"


def judge(run: dict, clean: dict | None, factor: float = SUCCESS_FACTOR) -> str:
    """A faulted run's verdict against its clean run (same log, proposal and seed):

    * ``"no clean run"``: the clean run is missing or crashed (nothing to compare with);
    * ``"crashed"``: the faulted run itself crashed (``jaxslam map`` failed; not a success);
    * ``"success"``: relation error (``trans_mean``, m) <= ``factor`` x the clean run's;
    * ``"failure"``: above it.
    """
    if clean is None or "failed" in clean:
        return NO_CLEAN
    if "failed" in run:
        return CRASHED
    return SUCCESS if run["trans_mean"] <= factor * clean["trans_mean"] else FAILURE


def cells(records: list[dict], factor: float = SUCCESS_FACTOR) -> dict:
    """Per (dataset, proposal, fault): ``{"verdicts": {seed: verdict}, "errors": [m, ...],
    "successes", "judged" (seeds with a verdict other than "no clean run"), "no_clean",
    "mean_error" (m, over the runs that finished; None without)}``; the clean cell's verdicts
    are "success" for every finished clean run."""
    by_key = {(r["dataset"], r["proposal"], r["fault"], r["seed"]): r for r in records}
    out: dict = {}
    for (dataset, proposal, fault, seed), run in sorted(by_key.items()):
        clean = by_key.get((dataset, proposal, "clean", seed))
        if fault == "clean":
            verdict = CRASHED if "failed" in run else SUCCESS
        else:
            verdict = judge(run, clean, factor)
        cell = out.setdefault((dataset, proposal, fault), {"verdicts": {}, "errors": []})
        cell["verdicts"][seed] = verdict
        if "failed" not in run:
            cell["errors"].append(run["trans_mean"])
    for cell in out.values():
        verdicts = list(cell["verdicts"].values())
        cell["successes"] = verdicts.count(SUCCESS)
        cell["no_clean"] = verdicts.count(NO_CLEAN)
        cell["judged"] = len(verdicts) - cell["no_clean"]
        cell["mean_error"] = float(np.mean(cell["errors"])) if cell["errors"] else None
    return out


def _fault_order(faults) -> list[str]:
    """The cells of ``faults`` (any iterable of names) in :data:`FAULTS`' order."""
    wanted = set(faults)
    return [f for f in FAULTS if f in wanted]


def faults_markdown(records: list[dict], factor: float = SUCCESS_FACTOR) -> str:
    """The table: a row per log x proposal, a column per fault cell; each entry ``s/n, e m``:
    s of the n judged seeds succeeded (:func:`judge`; a crashed run is judged, and fails), e the
    mean relation error (m) of the cell's finished runs; ``(k no clean run)`` where k seeds had no
    clean run to compare with. The clean column: finished clean runs / seeds."""
    table = cells(records, factor)
    faults = _fault_order({f for _, _, f in table})
    rows = sorted({(d, p) for d, p, _ in table},
                  key=lambda dp: (list(DATASETS).index(dp[0]) if dp[0] in DATASETS else 99,
                                  PROPOSALS.index(dp[1]) if dp[1] in PROPOSALS else 99))
    lines = [f"Successes / seeds (relation error within {factor:g} x the clean run's of the same seed) "
             "and the mean relation error [m] of the finished runs; the clean column: finished runs / seeds.", "",
             "| log | proposal | " + " | ".join(faults) + " |", "|---|---|" + "---|" * len(faults)]
    for dataset, proposal in rows:
        entries = []
        for fault in faults:
            cell = table.get((dataset, proposal, fault))
            if cell is None:
                entries.append("")
                continue
            error = "–" if cell["mean_error"] is None else f"{cell['mean_error']:.3f} m"
            no_clean = f" ({cell['no_clean']} no clean run)" if cell["no_clean"] else ""
            entries.append(f"{cell['successes']}/{cell['judged']}, {error}{no_clean}")
        lines.append(f"| {dataset} | {proposal.upper()} | " + " | ".join(entries) + " |")
    return "\n".join(lines) + "\n"


def success_curves(records: list[dict], factor: float = SUCCESS_FACTOR) -> dict:
    """The figure's lines: ``{kind: {(dataset, proposal): (sizes, fractions)}}`` for kind
    "heading" (sizes in degrees) and "translation" (m); a fraction is successes / judged seeds
    (:func:`judge`); the clean run is size 0 (its finished seeds count as successes). Cells
    without a judged seed are left out."""
    table = cells(records, factor)
    curves: dict = {"heading": {}, "translation": {}}
    for kind, lines in curves.items():
        for dataset, proposal in sorted({(d, p) for d, p, _ in table}):
            sizes, fractions = [], []
            for fault in _fault_order(f for d, p, f in table if (d, p) == (dataset, proposal)):
                fault_kind, size = FAULTS[fault]
                cell = table[(dataset, proposal, fault)]
                if fault_kind in (kind, "none") and cell["judged"]:
                    sizes.append(size)
                    fractions.append(cell["successes"] / cell["judged"])
            if sizes:
                lines[(dataset, proposal)] = (sizes, fractions)
    return curves


def faults_figure(records: list[dict], path: Path, factor: float = SUCCESS_FACTOR) -> Path:
    """The success fraction against the slip's size (:func:`success_curves`): a panel for
    heading slips (degrees) and one for translation slips (m), a line per log x proposal.
    Writes and returns ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = success_curves(records, factor)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, kind, unit in ((axes[0], "heading", "heading slip [deg]"),
                           (axes[1], "translation", "translation slip [m]")):
        for (dataset, proposal), (sizes, fractions) in curves[kind].items():
            ax.plot(sizes, fractions, marker="o", label=f"{dataset} {proposal.upper()}")
        ax.set_xlabel(unit)
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        ax.set_title(f"{kind} slips")
    axes[0].set_ylabel(f"success fraction (error <= {factor:g} x clean)")
    return save_with_legend(fig, axes, path, max_columns=6)


def save_with_legend(fig, axes, path, max_columns: int) -> Path:
    """Save ``fig`` to ``path`` (PNG, 100 dpi) with one legend below the panels, from the first of
    ``axes`` that has labelled lines, and close it; returns the path."""
    import matplotlib.pyplot as plt

    handles, labels = next(((h, lab) for h, lab in (a.get_legend_handles_labels() for a in axes) if h), ([], []))
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=min(max_columns, len(labels)), fontsize=8)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_tables(store: ResultStore, factor: float = SUCCESS_FACTOR):
    """faults.md and faults.png from every run in the folder; the cells in results.json."""
    folder = store.path.parent
    table = cells(store.runs, factor)
    summary = {f"{d}/{p}/{f}": {k: v for k, v in c.items() if k != "verdicts"} | {
        "verdicts": {str(s): v for s, v in c["verdicts"].items()}} for (d, p, f), c in table.items()}
    store.write(cells=summary)
    (folder / "faults.md").write_text(faults_markdown(store.runs, factor))
    if store.runs:
        faults_figure(store.runs, folder / "faults.png", factor)


# ----------------------------------------------------------------------------- the ambiguous case

NEAR_M = 0.3
NEAR_DEG = 10.0


def near(poses, target, near_m: float = NEAR_M, near_deg: float = NEAR_DEG) -> np.ndarray:
    """(N,) bool: which poses ((N, 3) m, m, rad) lie within ``near_m`` and ``near_deg`` of ``target`` ((3,))."""
    d = between_np(np.broadcast_to(target, np.shape(poses)), poses)
    return (np.hypot(d[:, 0], d[:, 1]) <= near_m) & (np.abs(d[:, 2]) <= math.radians(near_deg))


def ambiguous_run(proposal: str, seed: int, particles: int = 30, overrides: dict | None = None) -> dict:
    """One filter run (Python API, ``jaxslam.slam.run``) on :func:`jaxslam.sim.symmetric_junction_scenario`
    (key ``seed``; the filter's key is ``seed`` too), with the scenario's motion noise as the
    filter's motion model. At each processed scan in the lane (``metadata["ambiguous_scans"]``):
    the share of the particles (after resampling) within :data:`NEAR_M` / :data:`NEAR_DEG` of the
    true pose and of the mirror pose in the other lane.

    Returns:
        ``{"proposal", "seed", "scans": [...], "near_true": [...], "near_mirror": [...],
        "min_near_true", "any_near_true_everywhere", "first_near_true", "last_near_true",
        "last_near_mirror", "wall_s"}``.
    """
    import jax

    from jaxslam import slam
    from jaxslam.config import build_setup
    from jaxslam.sim import symmetric_junction_scenario

    scenario = symmetric_junction_scenario(jax.random.key(seed))
    motion = scenario.metadata["motion_params"]
    values = {"proposal": proposal, "num_particles": particles, "max_insert_range": 10.0,
              "linear_update": 0.2, "angular_update": 0.2,
              **{f"motion.{name}": float(getattr(motion, name)) for name in motion._fields},
              **(overrides or {})}
    config, settings, params = build_setup(values)
    t0 = time.perf_counter()
    result = slam.run(jax.random.key(seed), scenario.log, config, params, settings, progress=False)
    wall = time.perf_counter() - t0
    info = result.info
    processed = np.asarray(result.selection.indices)[1:]  # info's steps: the scans after the first
    lane = set(int(i) for i in scenario.metadata["ambiguous_scans"])
    offset = scenario.metadata["mirror_offset"]
    scans, near_true, near_mirror = [], [], []
    for step, scan in enumerate(processed):
        if int(scan) not in lane:
            continue
        poses = result.to_world(np.asarray(info.proposed_poses[step])[np.asarray(info.ancestors[step])])
        truth = scenario.true_poses[scan]
        scans.append(int(scan))
        near_true.append(float(near(poses, truth).mean()))
        near_mirror.append(float(near(poses, truth + offset).mean()))
    if not scans:
        raise AssertionError("no processed scan lies in the lane: the update rule skipped them all")
    return {"proposal": proposal, "seed": seed, "particles": particles, "scans": scans,
            "near_true": near_true, "near_mirror": near_mirror,
            "min_near_true": min(near_true), "any_near_true_everywhere": bool(min(near_true) > 0),
            "first_near_true": near_true[0], "last_near_true": near_true[-1],
            "last_near_mirror": near_mirror[-1], "wall_s": wall}


def ambiguous_markdown(runs: list[dict]) -> str:
    """The ambiguous case's table: per proposal and seed, the share of particles near the true
    pose (and near the mirror pose) at the first and last processed scan in the lane, the least
    share near the true pose over the lane's scans, and whether some particle stayed near it."""
    lines = [f"Share of particles within {NEAR_M:g} m / {NEAR_DEG:g} deg of the true pose (and of the "
             "mirror pose in the other lane) at the processed scans inside the lane.", "",
             "| proposal | seed | first in lane: true / mirror | last: true / mirror | least near true "
             "| true mode kept |", "|---|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {r['proposal'].upper()} | {r['seed']} | {r['near_true'][0]:.2f} / {r['near_mirror'][0]:.2f} "
                     f"| {r['near_true'][-1]:.2f} / {r['near_mirror'][-1]:.2f} | {r['min_near_true']:.2f} "
                     f"| {'yes' if r['any_near_true_everywhere'] else 'no'} |")
    return "\n".join(lines) + "\n"


def ambiguous_case(out: Path, proposals=("smp", "lp"), seeds: int = 3, particles: int = 30,
                   overrides: dict | None = None) -> list[dict]:
    """:func:`ambiguous_run` for each proposal and seed; writes ``out/ambiguous.json`` and
    ``out/ambiguous.md`` and returns the runs."""
    from tqdm import tqdm

    runs = [ambiguous_run(p, s, particles, overrides)
            for s, p in tqdm([(s, p) for s in range(seeds) for p in proposals], desc="ambiguous", unit="run")]
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "ambiguous.json", {"particles": particles, "near_m": NEAR_M, "near_deg": NEAR_DEG,
                                        "overrides": overrides or {}, "runs": runs})
    (out / "ambiguous.md").write_text(ambiguous_markdown(runs))
    return runs


# ----------------------------------------------------------------------------- main

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="results/faults")
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--datasets", nargs="+", default=list(DEFAULT_DATASETS), choices=list(DATASETS))
    parser.add_argument("--proposals", nargs="+", default=["smp", "lp"], choices=list(PROPOSALS))
    parser.add_argument("--faults", nargs="+", default=[f for f in FAULTS if f != "clean"],
                        choices=[f for f in FAULTS if f != "clean"],
                        help="fault cells to run (the clean run is always run: every cell is judged against it)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="passed to every `jaxslam map` (after the table's settings, so it wins); "
                             "use a new --out (runs are cached there)")
    parser.add_argument("--max-scans", type=int, default=None,
                        help="only the first N scans of each log (the faults fall within them, the "
                             "relations are those among them): a smoke run")
    parser.add_argument("--jobs", type=int, default=1,
                        help="runs at a time, each its own process; runs that share a machine slow each other")
    parser.add_argument("--keep-logs", action="store_true", help="keep the faulted logs (OUT/logs/*.clf)")
    parser.add_argument("--ambiguous", action="store_true",
                        help="run the symmetric-junction case instead (Python API; --proposals, --seeds, "
                             "--particles, --set as filter settings)")
    parser.add_argument("--particles", type=int, default=SETTINGS["particles"])
    args = parser.parse_args(argv)
    out = Path(args.out)
    for flag, value in (("--seeds", args.seeds), ("--jobs", args.jobs), ("--particles", args.particles)):
        if value < 1:
            print(f"{flag} must be at least 1, got {value}", file=sys.stderr)
            return 2
    if args.max_scans is not None and args.max_scans < 2:
        print(f"--max-scans must be at least 2, got {args.max_scans}", file=sys.stderr)
        return 2
    from jaxslam.cli import parse_assignments
    from jaxslam.config import ConfigError, build_setup

    try:  # a bad --set is refused here, not by every run
        overrides = parse_assignments(args.set)
        for proposal in args.proposals:
            build_setup({"proposal": proposal, **overrides})
    except ConfigError as err:
        print(f"--set: {err}", file=sys.stderr)
        return 2
    if args.ambiguous:
        runs = ambiguous_case(out, tuple(args.proposals), args.seeds, args.particles, overrides)
        print(ambiguous_markdown(runs))
        return 0
    data = Path(args.data)
    if not data.is_dir():
        print(f"datasets not found at {data}", file=sys.stderr)
        return 2
    missing = [str(data / name) for d in args.datasets for name in DATASETS[d] if not (data / name).exists()]
    if missing:
        print(f"not found: {', '.join(missing)}", file=sys.stderr)
        return 2
    settings = {**SETTINGS, "particles": args.particles, "max_scans": args.max_scans, "set": SETTINGS["set"] + args.set}
    try:  # results.json describes every run in the folder: an earlier call's runs stay in it
        store = ResultStore(out / "results.json", settings,
                            key=lambda r: (r["dataset"], r["proposal"], r["fault"], r["seed"]))
    except SettingsMismatch as err:
        print(err, file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    from concurrent.futures import ThreadPoolExecutor, as_completed

    from tqdm import tqdm

    # Seed by seed over the logs, the clean run first: a stopped run leaves whole seeds.
    faults = ["clean"] + _fault_order(args.faults)
    jobs = [(d, p, f, s) for s in range(args.seeds) for d in args.datasets for p in args.proposals for f in faults]
    todo = [job for job in jobs if store.get(job) is None or "failed" in store.get(job)]
    with tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="runs", unit="run") as progress, \
            ThreadPoolExecutor(max_workers=args.jobs) as pool:
        # Each run is a subprocess: threads only write its log and wait. Records are stored here.
        futures = [pool.submit(run_one, *job, out, data, settings, args.keep_logs) for job in todo]
        for future in as_completed(futures):
            store.add(future.result())
            write_tables(store, settings["success_factor"])
            progress.update()
    write_tables(store, settings["success_factor"])
    print((out / "faults.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
