"""Writing the results of a SLAM run: map (PGM + YAML + PNG), trajectory, summary, figure."""

from __future__ import annotations

import json
import resource
from pathlib import Path

import numpy as np

from jaxslam.config import config_to_dict, params_to_dict


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
                       + ("; enlarge the map (map_padding or grid)" if name != "degenerate" else ""))
    return out


def summarize(log, result, params, seed: int, source: str) -> dict:
    """The ``summary.json`` content of a run."""
    info = result.info
    config = config_to_dict(result.config) | config_to_dict(result.settings)
    return {
        "source": source,
        "seed": seed,
        "config": config,
        "params": params_to_dict(params),
        "scans_in_log": log.num_scans,
        "scans_processed": int(result.selection.indices.size),
        "log_duration_s": log.duration,
        "timings": dict(result.timings),
        "scans_per_second": result.selection.indices.size / result.timings["total"],
        "peak_memory_mb": peak_memory_mb(),
        "resampling_steps": int(np.sum(info.resampled)),
        "mean_ess": float(np.mean(info.ess)) if info.ess.size else None,
        "fallbacks": int(np.sum(info.num_fallbacks)),
        "log_evidence": float(np.sum(info.log_evidence)),
        "warnings": run_warnings(result),
        "log_notes": list(getattr(log, "notes", ())),
    }


def write_slam_outputs(out_dir, log, result, params, seed: int, source: str, world=None, refined=None,
                       refine_seconds: float | None = None) -> dict:
    """Write ``map.{pgm,yaml,png}``, ``trajectory.txt``, ``summary.json`` and ``slam.png`` into ``out_dir``.

    The map is the final best particle's, cropped to its known cells plus a margin of
    :data:`jaxslam.io.maps.DEFAULT_MARGIN_CELLS` cells (see :func:`jaxslam.io.maps.crop_to_known`;
    ``map.yaml``'s origin is the crop's lower-left corner), and ``slam.png`` shows the same area
    (widened to the best particle's path if that leaves it). The trajectory has one pose per scan of the log.
    With ``refined`` (a :class:`jaxslam.refine.RefinedTrajectory`) also ``trajectory_refined.txt``,
    and the summary's ``refinement`` gives the fraction of scans whose match held (and, when
    given, ``refine_seconds``: the refinement's wall time).
    Returns the summary.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxslam.io.maps import crop_to_known, write_map
    from jaxslam.io.trajectory import write_trajectory
    from jaxslam.plotting import plot_slam_result

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    best = result.best_particle
    logodds = np.asarray(result.state.maps.logodds[best])
    cropped, spec = crop_to_known(logodds, result.config.grid)
    write_map(out / "map", cropped, spec)
    write_trajectory(out / "trajectory.txt", log.timestamps, result.trajectory)
    fig = plot_slam_result(result, log, world=world)
    _limit_to_map(fig.axes[0], spec, result.best_path)
    fig.savefig(out / "slam.png", dpi=150)
    plt.close(fig)
    summary = summarize(log, result, params, seed, source)
    if refined is not None:
        write_trajectory(out / "trajectory_refined.txt", log.timestamps, refined.poses)
        summary["refinement"] = {"matched_fraction": float(np.mean(refined.matched)),
                                 "median_score": float(np.median(refined.scores))}
        if refine_seconds is not None:
            summary["refinement"]["seconds"] = float(refine_seconds)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    return summary


def _limit_to_map(ax, spec, path) -> None:
    """Show the (cropped) map's extent, widened to hold ``path`` (T, 3) if it leaves it."""
    xmin, xmax, ymin, ymax = spec.extent
    xy = np.asarray(path)[:, :2]
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if xy.size:
        margin = 2 * spec.resolution
        xmin, ymin = np.minimum([xmin, ymin], xy.min(axis=0) - margin)
        xmax, ymax = np.maximum([xmax, ymax], xy.max(axis=0) + margin)
    ax.set_xlim(float(xmin), float(xmax))
    ax.set_ylim(float(ymin), float(ymax))


def _json_default(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
