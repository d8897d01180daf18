"""Figures of the door filter, after Avots et al.: the map with doors drawn by belief (Figs.
1, 3), the histogram of a door's belief over the particles (Fig. 4), the decay of an
unobserved door's belief toward the stationary value, and position error over time.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import binary_bayes
from jaxslam.localization import doors, mcl

def _door_style(p_open: float):
    """Black when > 65% closed, grey within 15% of 50%, blank (dotted outline) when > 65% open."""
    if p_open < 0.35:
        return dict(color="black", lw=4.0, ls="-")
    if abs(p_open - 0.5) <= 0.15:
        return dict(color="0.6", lw=4.0, ls="-")
    return dict(color="0.85", lw=1.0, ls=":")


def plot_door_map(ax, scenario, door_belief, title: str = "", path=None, particles=None):
    """The map, its doors drawn by belief (Figs. 1 and 3 of Avots et al.), optionally a path
    ((T, 2+), m) and particles ((N, 2+), m)."""
    dm = scenario.door_map
    for x1, y1, x2, y2 in np.asarray(dm.walls):
        ax.plot([x1, x2], [y1, y2], color="0.2", lw=1.2)
    for k, (x1, y1, x2, y2) in enumerate(np.asarray(dm.doors)):
        ax.plot([x1, x2], [y1, y2], solid_capstyle="butt", **_door_style(float(door_belief[k])))
        ax.annotate(f"{scenario.door_names[k]} {float(door_belief[k]):.2f}", ((x1 + x2) / 2, (y1 + y2) / 2),
                    textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7)
    if particles is not None:
        ax.scatter(np.asarray(particles)[:, 0], np.asarray(particles)[:, 1], s=1, color="tab:blue", alpha=0.4)
    if path is not None:
        ax.plot(np.asarray(path)[:, 0], np.asarray(path)[:, 1], color="tab:red", lw=1)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_belief_histograms(axes, door_open_history, log_weight_history, door: int, times, door_name: str = ""):
    """Fig. 4: particle weight per 0.01 bin of p(open) of ``door`` at each of ``times``.

    ``door_open_history`` (T, N, K) and ``log_weight_history`` (T, N) from
    :func:`jaxslam.localization.doors.filter_history`.
    """
    bins = np.linspace(0.0, 1.0, 101)
    for ax, t in zip(axes, times):
        lw = np.asarray(log_weight_history[t], np.float64)
        w = np.exp(lw - lw.max())
        w /= w.sum()
        ax.hist(np.asarray(door_open_history[t, :, door]), bins=bins, weights=w, color="0.3")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_title(f"{door_name} after scan {t}", fontsize=9)
        ax.set_xlabel("p(open)")
    axes[0].set_ylabel("particle weight per 0.01 bin")


def plot_belief_decay(ax, door_belief, observed, p_open_open: float, p_open_closed: float, door_name: str = "",
                      dt: float = 1.0):
    """A door's marginal belief over time (T,), the scans at which the robot saw it (T,) bool, and the
    closed-form drift toward the stationary value from the last scan that saw it."""
    belief = np.asarray(door_belief)
    t = np.arange(belief.shape[0]) * dt
    ax.plot(t, belief, color="black", label=f"{door_name} p(open), filter")
    seen = np.nonzero(np.asarray(observed))[0]
    if seen.size:
        ax.scatter(t[seen], belief[seen], s=6, color="tab:blue", label="scans that see the door", zorder=3)
        last = int(seen[-1])
        n = np.arange(belief.shape[0] - last)
        closed_form = np.asarray(binary_bayes.predict_n(belief[last], p_open_open, p_open_closed, n))
        ax.plot(t[last:], closed_form, "--", color="tab:red", label="closed form (Eq. 24)^n")
    s = float(binary_bayes.stationary(p_open_open, p_open_closed))
    ax.axhline(s, color="0.5", lw=0.8, ls=":", label=f"stationary {s:.2f}")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("time (s)" if dt != 1.0 else "scan")
    ax.set_ylabel("p(open)")
    ax.legend(fontsize=7)


def plot_position_errors(ax, position_errors: dict[str, np.ndarray]):
    """Mean position error over time of each filter (with the 10-90% band over seeds).

    ``position_errors`` maps a label (the filter, say) to its (S, T) errors (m) over S seeds.
    """
    for label, errors in position_errors.items():
        errors = np.asarray(errors)
        t = np.arange(errors.shape[1])
        ax.plot(t, errors.mean(axis=0), label=label)
        lo, hi = np.percentile(errors, [10, 90], axis=0)
        ax.fill_between(t, lo, hi, alpha=0.15)
    ax.set_xlabel("scan")
    ax.set_ylabel("position error (m)")
    ax.legend(fontsize=8)


def figure_run(key, scenario, config: doors.DoorConfig, params: doors.DoorParams,
               memory: bool = True):
    """One hybrid run (``memory=False``: the memoryless baseline) with every step's particles, for
    the figures: ``(infos, DoorHistory)``. The key is split as the door experiment's harness does
    (experiments/door_harness.py): ``(initial particles, filter)``."""
    k_init, k_run = jax.random.split(key)
    state = doors.init(mcl.init_global(k_init, jnp.asarray(scenario.start_regions), config.mcl,
                                       tuple(scenario.heading_range)), scenario.door_map)
    out = doors.filter_history(k_run, state, mcl.log_inputs(scenario.log), scenario.door_map, scenario.log.sensor,
                               params, dataclasses.replace(config, memory=memory))
    return out.info


def save_figures(out_dir, scenario, infos, history, params: doors.DoorParams,
                 position_errors: dict[str, np.ndarray] | None = None, hist_door: int = 0,
                 decay_door: int = 0) -> list[str]:
    """Write the figures of one run (and the position errors of filters over seeds, see
    :func:`plot_position_errors`) to ``out_dir``; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    t_count = scenario.num_scans
    times = sorted({0, t_count // 4, t_count // 2, t_count - 1})
    while len(times) < 4:
        times.append(t_count - 1)
    for door in sorted({hist_door, 1 % scenario.num_doors}):
        fig, axes = plt.subplots(1, 4, figsize=(12, 2.8), sharey=True)
        plot_belief_histograms(axes, history.door_open, history.log_weights, door, times, scenario.door_names[door])
        fig.tight_layout()
        p = out / f"belief_histogram_{scenario.door_names[door]}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(str(p))
    belief = np.asarray(infos.door_belief)
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    for ax, t in zip(axes.ravel(), times):
        plot_door_map(ax, scenario, belief[t], f"door beliefs after scan {t}", path=scenario.true_poses[: t + 1],
                      particles=np.asarray(history.poses[t]))
    fig.tight_layout()
    p = out / "door_map.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(str(p))
    fig, ax = plt.subplots(figsize=(7, 3.5))
    plot_belief_decay(ax, belief[:, decay_door], np.asarray(infos.door_observed[:, decay_door]) > 0.5,
                      float(params.p_open_open[decay_door]), float(params.p_open_closed[decay_door]),
                      scenario.door_names[decay_door])
    fig.tight_layout()
    p = out / "belief_decay.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(str(p))
    if position_errors:
        fig, ax = plt.subplots(figsize=(7, 3.5))
        plot_position_errors(ax, position_errors)
        fig.tight_layout()
        p = out / "position_error.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(str(p))
    return paths
