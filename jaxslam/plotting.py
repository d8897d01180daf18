"""Matplotlib figures: maps, particles, paths."""

from __future__ import annotations

import numpy as np

from jaxslam.binary_bayes import probability
from jaxslam.grid import GridSpec


def plot_map(ax, logodds, spec: GridSpec, cmap: str = "gray_r"):
    """Draw an occupancy map (log-odds (H, W)) as p(occupied): white free, black occupied, grey unknown."""
    prob = probability(np.asarray(logodds))
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


def plot_particles(ax, poses, weights=None, arrow_length: float = 0.0, **kwargs):
    """Scatter particle positions (N, 3), sized or coloured by weight when given."""
    poses = np.asarray(poses)
    if weights is not None:
        kwargs.setdefault("c", np.asarray(weights))
        kwargs.setdefault("cmap", "viridis")
    kwargs.setdefault("s", 6)
    artist = ax.scatter(poses[:, 0], poses[:, 1], **kwargs)
    if arrow_length > 0:
        ax.quiver(poses[:, 0], poses[:, 1], np.cos(poses[:, 2]), np.sin(poses[:, 2]),
                  angles="xy", scale_units="xy", scale=1.0 / arrow_length, width=0.002, color="tab:red")
    return artist


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
    best = result.best_particle
    plot_map(ax, result.state.maps.logodds[best], result.config.grid)
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
