"""Matplotlib figures: maps, particles, paths."""

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
