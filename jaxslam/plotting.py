"""Matplotlib figures: maps, particles, paths, a run's diagnosis."""

from __future__ import annotations

import numpy as np

from jaxslam.binary_bayes import probability
from jaxslam.grid import GridSpec


def plot_map(ax, logodds, spec: GridSpec, cmap: str = "gray_r", max_pixels: int = 4096):
    """Draw an occupancy map (log-odds (H, W)) as p(occupied): white free, black occupied, grey unknown.

    A map larger than ``max_pixels`` on a side is shown in blocks of cells (each block its
    largest log-odds, so that walls stay visible): a figure of a campus-sized map then costs
    megabytes, not gigabytes."""
    logodds = np.asarray(logodds)
    block = -(-max(logodds.shape) // max_pixels)
    if block > 1:
        h, w = (-(-d // block) * block for d in logodds.shape)
        padded = np.zeros((h, w), logodds.dtype)
        padded[:logodds.shape[0], :logodds.shape[1]] = logodds
        logodds = padded.reshape(h // block, block, w // block, block).max(axis=(1, 3))
        spec = GridSpec((h // block, w // block), spec.resolution * block, spec.origin)
    prob = probability(logodds.astype(np.float32))
    image = ax.imshow(prob, origin="lower", extent=spec.extent, cmap=cmap, vmin=0.0, vmax=1.0,
                      interpolation="nearest")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    return image


def plot_path(ax, poses, label=None, **kwargs):
    """Draw a path of poses (T, 3) as a line."""
    poses = np.asarray(poses)
    return ax.plot(poses[:, 0], poses[:, 1], label=label, **kwargs)


def plot_segments(ax, segments, **kwargs):
    """Draw line segments (M, 4) [x1, y1, x2, y2]."""
    from matplotlib.collections import LineCollection

    segments = np.asarray(segments).reshape(-1, 2, 2)
    kwargs.setdefault("colors", "tab:blue")
    kwargs.setdefault("linewidths", 0.8)
    collection = LineCollection(segments, **kwargs)
    ax.add_collection(collection)
    return collection


def plot_slam_result(result, log=None, world=None, ax=None):
    """The final best particle's map with its path, the odometry and (simulated logs) the truth."""
    import matplotlib.pyplot as plt

    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(8, 8))
    logodds, _, grid = result.dense_map()
    plot_map(ax, logodds, grid)
    idx = result.selection.indices
    if log is not None:
        plot_path(ax, log.odometry[idx], label="odometry", color="tab:orange", lw=0.8, alpha=0.8)
        if log.ground_truth is not None:
            plot_path(ax, log.ground_truth[idx], label="ground truth", color="tab:green", lw=1.0)
    if world is not None:
        plot_segments(ax, world.segments, colors="tab:green", linewidths=0.5, alpha=0.5)
    plot_path(ax, result.best_path, label=f"{result.config.proposal.upper()} best particle", color="tab:red", lw=1.0)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{result.config.proposal.upper()}, N = {result.config.num_particles}, "
                 f"{idx.size} scans processed")
    return fig if fig is not None else ax.figure


def plot_diagnosis(diagnosis: dict, record: dict[str, np.ndarray], title: str = ""):
    """A figure of :func:`jaxslam.diagnose.diagnose`'s series against time, and the best path with the events."""
    import matplotlib.pyplot as plt

    s = {k: np.asarray(v) for k, v in diagnosis["series"].items()}
    t = s["time"] - (s["time"][0] if s["time"].size else 0.0)
    fig = plt.figure(figsize=(13, 11), constrained_layout=True)
    grid = fig.add_gridspec(5, 2, width_ratios=(2.2, 1))
    axes = [fig.add_subplot(grid[i, 0]) for i in range(5)]
    axes[0].plot(t, s["ess_fraction"], lw=0.8)
    axes[0].plot(t[s["resampled"]], s["ess_fraction"][s["resampled"]], "r.", ms=2, label="resampled")
    axes[0].set_ylabel("ESS / N")
    axes[0].legend(loc="upper right", fontsize=8)
    panels = (  # (y label, ((series, legend label), ...))
        ("particles", ((s["distinct_ancestors"], "particles kept by the step's resampling"),
                       (s["surviving_lineages"], "the step's particles with final descendants"))),
        ("correction of odometry", ((s["correction_trans"], "translation (m)"),
                                    (np.degrees(s["correction_rot"]) / 10.0, "rotation (10 deg)"))),
        ("spread, fallbacks", ((s["spread"], "particle spread (m)"), (s["fallbacks"], "fallbacks"),
                               (s["slipped"], "particles drawn from the slip component"))),
    )
    for ax, (ylabel, lines) in zip(axes[1:4], panels):
        for values, label in lines:
            ax.plot(t, values, lw=0.8, label=label)
        ax.set_ylabel(ylabel)
        ax.legend(loc="upper left", fontsize=8)
    relations = diagnosis.get("relations")
    if relations:
        relation_times = np.asarray(relations["time"]) - (s["time"][0] if s["time"].size else 0.0)
        axes[4].plot(relation_times, relations["trans"], ".", ms=2, label="the run's")
        if "weighted_then" in relations:
            axes[4].plot(relation_times, relations["weighted_then"], ".", ms=2, alpha=0.5,
                         label="the particles' weighted mean at its later scan")
        if "closest_then" in relations:
            axes[4].plot(relation_times, relations["closest_then"], ".", ms=2, alpha=0.5,
                         label="the best particle's at its later scan")
        axes[4].legend(loc="upper left", fontsize=8)
        axes[4].set_ylabel("relation error (m)")
        axes[4].set_yscale("log")
    else:
        axes[4].plot(t, s["log_evidence"], lw=0.8)
        axes[4].set_ylabel("log evidence")
    axes[4].set_xlabel("time since the first scan (s)")
    path_ax = fig.add_subplot(grid[:, 1])
    best = np.asarray(record["best_path"])
    path_ax.plot(best[:, 0], best[:, 1], lw=0.6, color="k")
    for name, marker, color in (("largest_corrections", "o", "tab:red"), ("worst_relations", "s", "tab:blue")):
        for rank, event in enumerate(diagnosis["events"].get(name, ())):
            path_ax.plot(event["x"], event["y"], marker, mfc="none", color=color, ms=8,
                         label=name.replace("_", " ") if rank == 0 else None)
            path_ax.annotate(str(rank + 1), (event["x"], event["y"]), color=color, fontsize=8)
    path_ax.set_aspect("equal")
    path_ax.set_title("best path (m)")
    path_ax.legend(loc="best", fontsize=8)
    fig.suptitle(title)
    return fig
