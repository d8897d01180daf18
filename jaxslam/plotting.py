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


def plot_slam_result(result, log=None, world=None, ax=None, cropped=None):
    """Draw a run's result on ``ax`` (a new pyplot figure where None; returns the figure).

    ``result``: a :class:`jaxslam.pipeline.MappedLog` (what ``jaxslam map`` draws as ``slam.png``):
    its final map (the closed map drawn again where loops were kept, else the filter's), with the
    refined path on it where refined, else the closed path (else the filter's), the filter's best
    path faint, the kept loops (a thin line from each loop's query node to its submap's first
    node, at the closed poses), the start (circle) and the end (square), the ground truth and the
    world's walls where given (a simulated log), and a title that names the map and the path.
    A :class:`jaxslam.slam.SlamResult` is drawn as the filter's map with its paths (its closure's
    map is not drawn again here: :func:`jaxslam.pipeline.as_mapped` does that).
    ``cropped``: ``(logodds (h, w), GridSpec)``, the final map already cropped to its known cells
    (:func:`jaxslam.io.maps.crop_to_known`); cropped here where None.
    """
    from jaxslam.io.maps import crop_to_known
    from jaxslam.pipeline import MappedLog

    fig = None
    if ax is None:
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 8))
    mapped = result if isinstance(result, MappedLog) else _filter_only(result)
    logodds, spec = crop_to_known(mapped.logodds, mapped.grid) if cropped is None else cropped
    plot_map(ax, logodds, spec)
    if world is not None:
        plot_segments(ax, world.segments, colors="tab:green", linewidths=0.5, alpha=0.5)
    path, path_name = _final_path(mapped)
    run = mapped.result
    if log is not None and log.ground_truth is not None:
        plot_path(ax, log.ground_truth[run.selection.indices], label="ground truth", color="tab:green", lw=1.0)
    if path is not run.trajectory:
        plot_path(ax, run.best_path, label="filter's path (best particle)", color="tab:red", lw=0.8, alpha=0.35)
    loops = _kept_loop_segments(mapped.closure)
    if loops.size:
        plot_segments(ax, loops, colors="tab:purple", linewidths=0.5, alpha=0.8,
                      label=f"loops kept ({loops.shape[0]})")
    plot_path(ax, path, label=path_name, color="tab:blue" if mapped.closure is not None else "tab:red", lw=1.0)
    ax.plot(*path[0, :2], "o", color="black", mfc="none", ms=7, label="start")
    ax.plot(*path[-1, :2], "s", color="black", mfc="none", ms=7, label="end")
    ax.set_title(f"{mapped.map_name}, {path_name}\n{run.config.proposal.upper()}, N = {run.config.num_particles}, "
                 f"{run.selection.indices.size} scans processed", fontsize=10)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8, frameon=False)
    _limit_to_map(ax, spec, (path, run.best_path))
    return fig if fig is not None else ax.figure


def _filter_only(result):
    """A SlamResult as a MappedLog of the filter's map (nothing drawn again, nothing refined)."""
    from jaxslam.pipeline import MappedLog

    logodds, field, grid = result.dense_map()
    trajectory = result.trajectory if result.closure is None else result.closure.trajectory
    return MappedLog(result, result.closure, logodds, field, grid, trajectory, None, {}, "filter's map")


def _final_path(mapped) -> tuple[np.ndarray, str]:
    """The most accurate path a result holds, (T, 3), and its name: the refined one, the closed
    one, or the filter's (one pose per scan of the log)."""
    if mapped.refined is not None:
        return np.asarray(mapped.refined.poses), "refined path"
    if mapped.closure is not None:
        return np.asarray(mapped.trajectory), f"closed path ({mapped.closure.num_loops} loops)"
    return np.asarray(mapped.trajectory), "filter's path"


def _kept_loop_segments(closure) -> np.ndarray:
    """(L, 4) [x1, y1, x2, y2]: each kept loop from its query node to its submap's first node,
    at the closed poses (m); (0, 4) without a closure or a kept loop."""
    if closure is None:
        return np.zeros((0, 4))
    kept = closure.loops.refused == ""
    query = np.asarray(closure.loops.query)[kept]
    node = np.asarray(closure.submap_first_node)[np.asarray(closure.loops.submap)[kept]]
    return np.concatenate([closure.poses[query, :2], closure.poses[node, :2]], axis=1).reshape(-1, 4)


def _limit_to_map(ax, spec, paths) -> None:
    """Show the (cropped) map's extent, widened to hold each path (T, 3) of ``paths`` that leaves it."""
    xmin, xmax, ymin, ymax = spec.extent
    xy = np.concatenate([np.asarray(path)[:, :2] for path in paths])
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if xy.size:
        margin = 2 * spec.resolution
        xmin, ymin = np.minimum([xmin, ymin], xy.min(axis=0) - margin)
        xmax, ymax = np.maximum([xmax, ymax], xy.max(axis=0) + margin)
    ax.set_xlim(float(xmin), float(xmax))
    ax.set_ylim(float(ymin), float(ymax))


def _fitted_figure(spec, longest_inches: float = 9.0):
    """A pyplot-free Figure whose axes fit the map's extent (``spec``): the longer side
    ``longest_inches``, the other in proportion (at least 3 in), with room for the title and
    legend (saved with ``bbox_inches="tight"``, so no margin is wasted)."""
    from matplotlib.figure import Figure

    xmin, xmax, ymin, ymax = spec.extent
    width, height = max(xmax - xmin, 1e-9), max(ymax - ymin, 1e-9)
    scale = longest_inches / max(width, height)
    return Figure(figsize=(max(width * scale, 3.0), max(height * scale, 3.0) + 1.5))


def slam_figure(mapped, log=None, world=None, cropped=None):
    """``slam.png``: :func:`plot_slam_result` on a pyplot-free Figure sized to the map's extent
    (a notebook's plotting backend is left as it is). Returns the Figure."""
    from jaxslam.io.maps import crop_to_known

    cropped = crop_to_known(mapped.logodds, mapped.grid) if cropped is None else cropped
    fig = _fitted_figure(cropped[1])
    plot_slam_result(mapped, log, world=world, ax=fig.subplots(), cropped=cropped)
    return fig


def graph_figure(graph: dict, logodds, spec: GridSpec):
    """``graph.png``: a saved pose graph (:func:`jaxslam.graph.load_graph`) drawn over the map
    (log-odds (H, W) on ``spec``) by :func:`jaxslam.graph.plot_graph`, as ``jaxslam diagnose``
    draws it (without the returns missed, which need the relations). Returns the Figure."""
    from jaxslam.graph import plot_graph

    fig = _fitted_figure(spec)
    ax = fig.subplots()
    plot_map(ax, logodds, spec)
    plot_graph(ax, graph)
    kept = int((graph["loop_refused"] == "").sum())
    ax.set_title(f"pose graph: {kept} loops kept of {graph['loop_refused'].size} candidates", fontsize=10)
    return fig


def scale_bar_metres(width_m: float) -> float:
    """The scale bar's length (m) for a map ``width_m`` wide: the largest 1, 2 or 5 times a power
    of ten that is at most a quarter of the width."""
    quarter = max(width_m / 4.0, 1e-9)
    power = 10.0 ** np.floor(np.log10(quarter))
    return float(max(f for f in (1.0, 2.0, 5.0, 10.0) if f * power <= quarter * (1 + 1e-9)) * power)


def annotate_map_png(path, spec: GridSpec) -> dict:
    """Add a scale bar and the origin to ``map.png`` (the map's image, one pixel a cell, as
    :func:`jaxslam.io.maps.write_map` wrote it on ``spec``), in place: a white strip below the
    map holds a black bar :func:`scale_bar_metres` long with its length in metres, and the
    log's origin (x, y) = (0, 0) is a red cross on the map (noted in the strip where it lies off
    the map). The map's own pixels are kept, but the cross's.

    Returns ``{"bar_m", "bar_px", "bar_rows", "bar_cols", "origin_px"}``: the bar's length (m,
    pixels), its pixel rows and columns (``range``), and the origin's pixel (row, col) or None."""
    from PIL import Image, ImageDraw, ImageFont

    grey = np.asarray(Image.open(path).convert("L"))
    height, width = grey.shape
    strip = max(24, height // 25)
    canvas = np.full((height + strip, width, 3), 255, np.uint8)
    canvas[:height] = grey[..., None]
    bar_m = scale_bar_metres(width * spec.resolution)
    bar_px = max(int(round(bar_m / spec.resolution)), 1)
    left, thickness = max(strip // 3, 2), max(strip // 6, 2)
    bar_rows = range(height + strip // 2 - thickness // 2, height + strip // 2 - thickness // 2 + thickness)
    bar_cols = range(left, min(left + bar_px, width))
    canvas[bar_rows.start:bar_rows.stop, bar_cols.start:bar_cols.stop] = 0
    col = int(np.floor((0.0 - spec.origin[0]) / spec.resolution))
    row = height - 1 - int(np.floor((0.0 - spec.origin[1]) / spec.resolution))  # image rows run top-down
    origin_px = (row, col) if 0 <= row < height and 0 <= col < width else None
    if origin_px is not None:
        arm = max(3, min(height, width) // 60)
        canvas[row, max(col - arm, 0):col + arm + 1] = (220, 0, 0)
        canvas[max(row - arm, 0):row + arm + 1, col] = (220, 0, 0)
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default(size=max(10, int(strip * 0.55)))
    note = f"{bar_m:g} m" + ("; origin (0, 0): red cross" if origin_px is not None else "; origin (0, 0) off the map")
    draw.text((bar_cols.stop + left, height + strip // 2), note, fill=(0, 0, 0), font=font, anchor="lm")
    image.save(path)
    return {"bar_m": bar_m, "bar_px": bar_px, "bar_rows": bar_rows, "bar_cols": bar_cols, "origin_px": origin_px}


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
