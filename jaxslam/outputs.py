"""Writing the results of a SLAM run: map (PGM + YAML + PNG), trajectory, summary, figure.

The folder is written atomically (:func:`jaxslam.io.files.publish_folder`): every file goes
into a temporary folder beside the target, which then replaces the target whole, so a run that
fails or is killed mid-write never leaves a folder that mixes two runs' files.
"""

from __future__ import annotations

import json
import math
import resource
import time
from pathlib import Path

import numpy as np

from jaxslam.config import config_to_dict, params_to_dict
from jaxslam.diagnose import STEPS_FILE, step_record, write_step_record
from jaxslam.io.files import publish_folder
from jaxslam.io.maps import crop_to_known, write_map
from jaxslam.io.trajectory import write_trajectory


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_warnings(result) -> list[str]:
    """Human-readable reports of what went wrong during a run, with the step where it happened."""
    info, idx = result.info, result.selection.indices
    out = []
    for name, counts, what in (
        ("outside_samples", np.asarray(info.outside_samples), "beam samples fell outside the map and were dropped"),
        ("poses_outside", np.asarray(info.poses_outside), "particle poses lay outside the map"),
        ("degenerate", np.asarray(info.degenerate).astype(int), "steps gave every particle weight zero (weights reset)"),
    ):
        steps = np.nonzero(counts)[0]
        if steps.size:
            first = int(steps[0])
            out.append(f"{int(counts.sum())} {what}; first at step {first + 1} (scan {int(idx[first + 1])} of the log)"
                       + ("; enlarge the map (--set map_extent=... m)" if name != "degenerate" else ""))
    return out


def ground_truth_error(log, result) -> dict | None:
    """Position errors (m) of the best particle's path and of the odometry against the log's
    ground truth at the processed scans, or None for a log without ground truth (a real one).

    No alignment: the filter starts at the log's first odometry pose, which a simulated log
    (:mod:`jaxslam.sim`) puts at the true one. Returns ``{"scans", "best_path_mean_m",
    "best_path_max_m", "odometry_mean_m", "odometry_max_m"}``.
    """
    if getattr(log, "ground_truth", None) is None:
        return None
    idx = np.asarray(result.selection.indices)
    truth = np.asarray(log.ground_truth, np.float64)[idx, :2]
    best = np.hypot(*(np.asarray(result.best_path, np.float64)[:, :2] - truth).T)
    odometry = np.hypot(*(np.asarray(log.odometry, np.float64)[idx, :2] - truth).T)
    return {"scans": int(idx.size), "best_path_mean_m": float(best.mean()), "best_path_max_m": float(best.max()),
            "odometry_mean_m": float(odometry.mean()), "odometry_max_m": float(odometry.max())}


def as_given(value):
    """``value`` as the user gave it: a float that a float32 holds exactly (a parameter read back
    from its array, ``0.10000000149011612``) as the shortest decimal that is the same float32
    (``0.1``); any other value (a float32 cannot hold it, a bool, an int, a string) unchanged."""
    if isinstance(value, (float, np.floating)):
        as_float32 = np.float32(value)
        if float(as_float32) == float(value):  # else a float64 the user gave: rounding would lose digits
            return float(np.format_float_positional(as_float32, unique=True, trim="0"))
    return value


def summary_params(params) -> dict:
    """``summary.json``'s ``params``: :func:`~jaxslam.config.params_to_dict`, each value
    :func:`as_given` (the parameters are float32 arrays, whose exact values print as noise)."""
    return {name: as_given(value) for name, value in params_to_dict(params).items()}


def summarize(log, result, params, seed: int, source: str) -> dict:
    """The ``summary.json`` content of a run; with ``ground_truth_error`` (:func:`ground_truth_error`)
    when the log has ground truth (a simulated log)."""
    info = result.info
    config = config_to_dict(result.config) | config_to_dict(result.settings)
    truth_error = ground_truth_error(log, result)
    return {
        "source": source,
        "seed": seed,
        "config": config,
        "params": summary_params(params),
        "scans_in_log": log.num_scans,
        "scans_processed": int(result.selection.indices.size),
        "log_duration_s": log.duration,
        "timings": dict(result.timings),
        "scans_per_second": result.selection.indices.size / result.timings["total"],
        "peak_memory_mb": peak_memory_mb(),
        "resampling_steps": int(np.sum(info.resampled)),
        "mean_ess": float(np.mean(info.ess)) if info.ess.size else None,
        "fallbacks": int(np.sum(info.num_fallbacks)),
        "slip_steps": int(np.count_nonzero(info.num_slipped)),
        "log_evidence": float(np.sum(info.log_evidence)),
        "map_pool": dict(result.map_pool),
        "warnings": list(getattr(log, "warnings", ())) + run_warnings(result)
        + [f"the map pools grew to {g['capacity']} tiles and {g['block_capacity']} blocks at step {g['step']} "
           "(that chunk was repeated and recompiled)" for g in result.map_pool.get("growths", ())],
        "log_notes": list(getattr(log, "notes", ())),
    } | ({} if truth_error is None else {"ground_truth_error": truth_error})


SLAM_OUTPUT_NAMES = ("map.pgm", "map.yaml", "map.png", "trajectory.txt", "trajectory_refined.txt",
                     "trajectory_filter.txt", "graph.npz", "graph.png", "summary.json", "slam.png", "steps.npz")
"""Every file :func:`write_slam_outputs` can write. Those of an earlier run that a new run does
not write (e.g. ``trajectory_refined.txt`` without ``--refine``) are removed, never kept stale."""


def write_slam_outputs(out_dir, log, result, params, seed: int, source: str, world=None, refined=None,
                       refine_seconds: float | None = None, timings: dict | None = None,
                       started: float | None = None) -> dict:
    """Write what :func:`jaxslam.pipeline.map_log` returned (``result``, a
    :class:`~jaxslam.pipeline.MappedLog`) into ``out_dir``: ``map.{pgm,yaml,png}`` (``map.png`` with
    a scale bar and the origin marked: :func:`jaxslam.plotting.annotate_map_png`),
    ``trajectory.txt``, ``summary.json``, ``slam.png`` (:func:`jaxslam.plotting.slam_figure`) and
    ``steps.npz`` (the per-step record ``jaxslam diagnose`` reads: :mod:`jaxslam.diagnose`).
    Nothing is computed here but the files: the map is the result's final map (``result.logodds``).

    A :class:`~jaxslam.slam.SlamResult` is taken too (a notebook's filter run): its final map is
    drawn first (:func:`jaxslam.pipeline.as_mapped`) and ``refined`` (a
    :class:`jaxslam.refine.RefinedTrajectory`, world frame; ``refine_seconds`` its wall time) is its
    refinement.

    With a loop closure (``result.closure``, :mod:`jaxslam.graph`), ``trajectory.txt`` holds the
    optimised poses, ``trajectory_filter.txt`` the filter's, ``graph.npz`` the pose graph
    (:func:`jaxslam.graph.save_graph`) and ``graph.png`` its figure over the map
    (:func:`jaxslam.plotting.graph_figure`), the map is the one drawn again at the optimised poses
    and the summary's ``closure`` counts the loops.

    The map is cropped to its known cells plus a margin of
    :data:`jaxslam.io.maps.DEFAULT_MARGIN_CELLS` cells (see :func:`jaxslam.io.maps.crop_to_known`;
    ``map.yaml``'s origin is the crop's lower-left corner, in the log's frame), and ``slam.png``
    shows the same area (widened to the paths if they leave it). The trajectory
    has one pose per scan of the log.
    With a refined trajectory also ``trajectory_refined.txt``, and the summary's ``refinement``
    gives the fraction of scans whose match held. For a log with ground truth (a simulated one)
    the summary's ``ground_truth_error`` holds :func:`ground_truth_error`.
    The figures are drawn without pyplot, so a notebook's plotting backend is left as it is.

    The summary's ``timings`` (s): the filter's (``compile``, ``total``, ``real_time_factor``), the
    closure's (``closure``), ``closed_map`` and ``refinement`` (:attr:`MappedLog.timings`), the
    caller's ``timings`` (``jaxslam map``: ``read``, the log read; ``checks``, the memory and disk
    checks), ``write`` (this function, up to ``summary.json``) and, where ``started`` (a
    ``time.perf_counter()`` value: when the user's wait began) is given, ``total_wall``.

    The folder is replaced atomically (:func:`publish_folder`): all files are written into a
    temporary folder beside it first. If ``out_dir`` holds an earlier run, this run's files
    replace its files, and its files that this run does not write (any of
    :data:`SLAM_OUTPUT_NAMES`, e.g. a stale ``trajectory_refined.txt``) are **removed**; files
    that no SLAM run writes (your notes, ``errors.json`` of ``jaxslam eval``) are kept.

    ``summary.json`` is strict JSON: a number that is not finite (a log-evidence of -inf when
    every particle's weight went to zero, ...) is written as null, with the reason under
    ``null_reasons`` (``{"log_evidence": "every particle's weight was zero at step 12 ..."}``);
    ``null_reasons`` is ``{}`` when nothing was nulled.
    Returns the summary as written.
    """
    t_write = time.perf_counter()
    from jaxslam.pipeline import as_mapped

    mapped = as_mapped(log, result, params, refined)
    stages = dict(timings or {})
    if refine_seconds is not None:  # a SlamResult's refinement, timed by the caller
        stages["refinement"] = float(refine_seconds)
    cropped, spec = crop_to_known(mapped.logodds, mapped.grid)
    summary = _slam_summary(log, mapped, params, seed, source, stages)

    def write(out: Path) -> None:
        write_map(out / "map", cropped, spec)
        _write_figures(out, log, mapped, world, cropped, spec)
        write_trajectory(out / "trajectory.txt", log.timestamps, mapped.trajectory)
        if mapped.closure is not None:
            write_trajectory(out / "trajectory_filter.txt", log.timestamps, mapped.result.trajectory)
        if mapped.refined is not None:
            write_trajectory(out / "trajectory_refined.txt", log.timestamps, mapped.refined.poses)
        write_step_record(out / STEPS_FILE, step_record(log, mapped.result))
        # Last, so that its timings hold the writing; strict JSON (non-finite numbers nulled).
        summary["timings"]["write"] = time.perf_counter() - t_write
        if started is not None:
            summary["timings"]["total_wall"] = time.perf_counter() - started
        cleaned, null_reasons = strict_json_values(summary, _known_null_reasons(summary, mapped.result))
        summary.clear()
        summary.update(cleaned, null_reasons=null_reasons)
        (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False, default=_json_default))

    publish_folder(out_dir, write, replaces=SLAM_OUTPUT_NAMES)
    return summary


def _write_figures(out: Path, log, mapped, world, cropped, spec) -> None:
    """``map.png``'s scale bar and origin, ``slam.png``, and with a closure ``graph.npz`` and ``graph.png``."""
    from jaxslam.plotting import annotate_map_png, graph_figure, slam_figure

    annotate_map_png(out / "map.png", spec)
    slam_figure(mapped, log, world=world, cropped=(cropped, spec)).savefig(out / "slam.png", dpi=150,
                                                                             bbox_inches="tight")
    if mapped.closure is not None:
        from jaxslam.graph import load_graph, save_graph

        save_graph(out / "graph.npz", mapped.closure)
        graph_figure(load_graph(out / "graph.npz"), cropped, spec).savefig(out / "graph.png", dpi=120,
                                                                          bbox_inches="tight")


def _slam_summary(log, mapped, params, seed: int, source: str, stages: dict) -> dict:
    """:func:`write_slam_outputs`' summary (before its ``write`` and ``total_wall`` timings and
    the strict-JSON nulls): :func:`summarize`'s, with the loop closure's counts and timings (s; its
    poses' mean distance to the ground truth, m, where the log has one), the refinement's, and the
    stages' seconds."""
    result, closure, refined = mapped.result, mapped.closure, mapped.refined
    summary = summarize(log, result, params, seed, source)
    if closure is not None:
        summary["closure"] = closure.summary()
        summary["timings"]["closure"] = dict(closure.timings)  # seconds vary run to run: beside the filter's
        if getattr(log, "ground_truth", None) is not None:
            truth = np.asarray(log.ground_truth, np.float64)[closure.node_scans, :2]
            summary["closure"]["ground_truth_mean_m"] = float(np.mean(np.hypot(*(closure.poses[:, :2] - truth).T)))
    if refined is not None:
        summary["refinement"] = {"matched_fraction": float(np.mean(refined.matched)),
                                 "median_score": float(np.median(refined.scores)),
                                 "odometry_noise_scale": [float(v) for v in refined.odometry_noise_scale]}
    summary["timings"].update({name: float(seconds) for name, seconds in mapped.timings.items()})
    summary["timings"].update({name: float(seconds) for name, seconds in stages.items()})
    return summary


# ---------------------------------------------------------------------------------------------
# Strict JSON.


def _known_null_reasons(summary: dict, result) -> dict[str, str]:
    """Why the summary's numbers that may be non-finite or missing are so, by dotted field name."""
    info, idx = result.info, result.selection.indices
    reasons = {}
    degenerate = np.nonzero(np.asarray(info.degenerate))[0]
    if degenerate.size:
        first = int(degenerate[0])
        reasons["log_evidence"] = (f"every particle's weight was zero at step {first + 1} (scan {int(idx[first + 1])} "
                                   f"of the log; {degenerate.size} such step(s)), so the log-evidence is -inf")
    else:
        reasons["log_evidence"] = "a step's log-evidence was not finite (NaN or infinite weights)"
    if summary.get("mean_ess") is None:
        reasons["mean_ess"] = "no step was taken: only the first scan was processed"
    else:
        reasons["mean_ess"] = "the effective sample size was not finite (NaN weights)"
    reasons["timings.real_time_factor"] = "the run took no measurable time"
    reasons["scans_per_second"] = "the run took no measurable time"
    reasons["refinement.median_score"] = "no scan was refined"
    reasons["refinement.matched_fraction"] = "no scan was refined"
    return reasons


def strict_json_values(value, reasons: dict[str, str] | None = None, _path: str = ""):
    """``value`` (dicts, lists, NumPy arrays and scalars, floats) with every float that is not
    finite replaced by None, and ``{dotted path: reason}`` for each None in a dict field (the
    non-finite ones and those that were None already): the reason from ``reasons`` where it
    names the field, else a general one. The result serialises with ``allow_nan=False``."""
    reasons = reasons or {}
    nulled: dict[str, str] = {}

    def clean(v, path):
        if isinstance(v, dict):
            return {k: clean(item, f"{path}.{k}" if path else str(k)) for k, item in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(item, f"{path}[{i}]") for i, item in enumerate(v)]
        if isinstance(v, np.ndarray):
            return clean(v.tolist(), path)
        if isinstance(v, (bool, np.bool_)):
            return bool(v)
        if isinstance(v, (np.integer,)):
            return int(v)
        if isinstance(v, (float, np.floating)):
            v = float(v)
            if math.isfinite(v):
                return v
            nulled[path] = reasons.get(path, f"the value was {v!r}, which strict JSON cannot hold")
            return None
        if v is None and path and not path.endswith("]") and path in reasons:
            nulled[path] = reasons[path]
        return v

    return clean(value, _path), nulled


def expected_output_bytes(map_cells: int, num_scans: int, checkpoint_bytes: int = 0) -> int:
    """A generous estimate of the bytes a ``jaxslam map`` run writes: the map as PGM and PNG (at
    most 2 bytes a cell of the mapped area), the trajectories (about 80 bytes a scan, twice with
    ``--refine``), the figure and summary (a few MB), and ``checkpoint_bytes`` for a checkpoint
    (``--checkpoint-every``: the particles' directories and the maps' pools)."""
    return 2 * map_cells + 2 * 80 * num_scans + 5_000_000 + checkpoint_bytes


def _json_default(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
