"""The low-structure box-world experiment of Grzonka et al. (Figs. 4 and 5), run from a table.

The robot circles box 2 fifteen times from checkpoint X and returns over X
(:func:`jaxslam.sim.box_world_scenario`). A run is scored by the revisiting accuracy RA between
its first and last passage over X (:func:`jaxslam.metrics.revisiting_accuracy`), a success when
RA < 0.2 m; seed r draws run r's odometry and range noise and the filter's randomness.

``box_world.json`` is the experiment as data: the settings common to every method, the methods
(a name and a flat dict of names for :func:`jaxslam.config.build_setup`, the builder behind the
CLI's ``--set``) and named tables: methods x SLAM particle counts N x odometry scales (the
simulated robot's proportional odometry-noise terms times the scale; the filter's model
follows). Its "notes" say what each number is. A cell is (method record, N, scale), keyed by the
JSON of the method's resolved names, N and the scale, never by the method's name: tables share
their common cells, and a renamed method keeps its runs.

Writes DIR/results.json after every run (``experiments/_runs.py``: finished runs are skipped on
restart, earlier calls' runs are kept, a folder written with other world settings is refused),
then for the table's cells DIR/ra_distribution.png, DIR/fig5.png (RA and success rate against N,
the paper's Fig. 5; for several N), DIR/examples.png and DIR/failures.png (the best particle's
map and path: each method's first seed and worst failure, as Fig. 4), and for several scales
DIR/noise_scale.png and DIR/noise_scale.md (success rate +- binomial standard error).
``box_world_merge.py`` merges result folders into one.

    python experiments/box_world.py --table table --out results/box_world
    python experiments/box_world.py --table noise --out results/box_world_noise
    python experiments/box_world.py --table quick --runs 2 --out /tmp/bw          # a smoke test
    python experiments/box_world.py --methods LP --set lookahead.alpha=0.3 --out results/bw_a03
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np
from _runs import ResultStore, SettingsMismatch  # experiments/_runs.py: the shared resume helper

from jaxslam import slam
from jaxslam.laserlog import local_frame_offset
from jaxslam.cli import parse_assignments
from jaxslam.config import SETTINGS_FIELDS, ConfigError, build_setup, config_names
from jaxslam.metrics import checkpoint_passages, normalized_weights, passage_errors, revisiting_accuracy
from jaxslam.rbpf import particle_paths
from jaxslam.sim import box_world_scenario
from jaxslam.sim.box_world import BOX_WORLD_MOTION

DEFAULT_CONFIG = Path(__file__).resolve().parent / "box_world.json"
WORLD_KEYS = ("success_ra", "rotation_weight", "motion_scale", "grid_margin", "grid_resolution",
              "insert_range_margin")
"""The json's numbers that every run of a folder shares (with the table's scenario)."""
RUN_FIELDS = ("seed", "ra", "ra_position", "ra_heading", "best_particle_error", "closest_particle_error",
              "closing_weight", "seconds",
              "num_steps", "num_fallbacks", "num_slip_steps", "num_degenerate", "num_resamplings", "min_ess")
"""A run record's fields (besides its cell's key)."""


# ----------------------------------------------------------------------------- the experiment as data

def load_experiment(path=DEFAULT_CONFIG) -> dict:
    """The experiment file, checked: every table names known methods and every method builds."""
    exp = json.loads(Path(path).read_text())
    missing = [k for k in (*WORLD_KEYS, "common", "methods", "tables") if k not in exp]
    if missing:
        raise ConfigError(f"{path}: missing {missing}")
    for name, table in exp["tables"].items():
        unknown = [m for m in table["methods"] if m not in exp["methods"]]
        if unknown or not table["particles"] or not table["odometry_scales"]:
            raise ConfigError(f"{path}: table {name!r}: unknown methods {unknown} or no particles/odometry_scales")
    for name in exp["methods"]:
        method_settings(exp, name)
    return exp


def method_settings(exp: dict, name: str, overrides: dict | None = None) -> dict:
    """Method ``name``'s flat names: the json's common ones, the method's, then ``overrides``; checked
    and typed by ``build_setup`` (so "2" and 2 give one record), sorted."""
    flat = {**exp["common"], **exp["methods"][name], **(overrides or {})}
    if {"map_extent", "resolution", "num_particles"} & set(flat):
        raise ConfigError("map_extent, resolution and num_particles are the experiment's (grid_margin, "
                          "grid_resolution, a table's particles)")
    config, settings, _ = build_setup(flat)
    typed = {k: getattr(config, k) if k in config_names() else getattr(settings, k) if k in SETTINGS_FIELDS
             else float(v) for k, v in flat.items()}
    return dict(sorted(typed.items()))


def cell_record(settings: dict, n: int, scale: float) -> dict:
    return {"settings": settings, "N": int(n), "odometry_scale": float(scale)}


def cell_key(record: dict) -> str:
    """The cell's identity: its record as canonical JSON (the method's name is not part of it)."""
    return json.dumps({k: record[k] for k in ("settings", "N", "odometry_scale")}, sort_keys=True,
                      separators=(",", ":"))


def world_settings(exp: dict, table: dict) -> dict:
    """What every run in a results folder shares beyond its cell record."""
    return {"scenario": table.get("scenario", {}), **{k: exp[k] for k in WORLD_KEYS}}


def table_cells(exp: dict, table: dict, methods: list[str], overrides: dict) -> list[dict]:
    """The table's cells in order (scale, N, method), each {"method": name, **record}."""
    return [{"method": name, **cell_record(method_settings(exp, name, overrides), n, scale)}
            for scale in table["odometry_scales"] for n in table["particles"] for name in methods]


# ----------------------------------------------------------------------------- one run

def scaled_noise(motion, scale: float) -> dict[str, float]:
    """The fields of ``motion`` (MotionParams) as floats, the proportional terms (srr, srt, str,
    stt) times ``scale``; the floors (minimum stds) stay."""
    values = {name: float(getattr(motion, name)) for name in motion._fields}
    for name in ("srr", "srt", "str", "stt"):
        values[name] *= scale
    return values


def scenario_for(seed: int, scale: float, world: dict):
    """Run ``seed``'s box world, the robot's proportional odometry noise times ``scale``."""
    kwargs = dict(world["scenario"])
    if scale != 1.0:
        noise = scaled_noise(BOX_WORLD_MOTION, scale)
        kwargs["motion"] = BOX_WORLD_MOTION._replace(**{k: np.float32(v) for k, v in noise.items()})
    return box_world_scenario(jax.random.key(seed), **kwargs)


def filter_setup(record: dict, scenario, world: dict):
    """The filter's config, run settings and params for one cell: the cell's names, over the fixed
    virtual grid (the world and ``grid_margin`` metres round it, from the filter's local origin),
    the insertion range and the simulator's odometry noise times ``motion_scale``."""
    xmin, ymin, xmax, ymax = scenario.world.bounds
    x0, y0 = local_frame_offset(scenario.log)
    reach = max(abs(xmin - x0), abs(xmax - x0), abs(ymin - y0), abs(ymax - y0)) + world["grid_margin"]
    noise = scaled_noise(scenario.metadata["motion_params"], world["motion_scale"])
    flat = {"max_insert_range": scenario.log.sensor.range_max.item() + world["insert_range_margin"],
            **{f"motion.{name}": value for name, value in noise.items()}, **record["settings"],
            "num_particles": record["N"], "map_extent": 2.0 * reach, "resolution": world["grid_resolution"]}
    return build_setup(flat)


def run_once(record: dict, seed: int, world: dict, progress: bool = False):
    """One run of a cell: its record (fields :data:`RUN_FIELDS`), the filter's result and the scenario."""
    scenario = scenario_for(seed, record["odometry_scale"], world)
    config, settings, params = filter_setup(record, scenario, world)
    t0 = time.perf_counter()
    result = slam.run(jax.random.key(10_000 + seed), scenario.log, config, params, settings, progress=progress)
    return score_run(seed, result, scenario, world, time.perf_counter() - t0), result, scenario


def run_batch(record: dict, seeds: list[int], world: dict, devices=None, progress: bool = False):
    """The runs of ``seeds`` of a cell as one batch (:func:`jaxslam.slam.run_batch`: each seed's
    world is its own log, the runs split over ``devices``, a count or None for all): a list of
    :func:`run_once`'s triples, each run the one ``run_once`` makes up to how XLA compiles the
    batch (a near tie may round the other way: docs/design.md). A run's ``seconds`` is the
    batch's wall time over its runs."""
    scenarios = [scenario_for(seed, record["odometry_scale"], world) for seed in seeds]
    setups = [filter_setup(record, scenario, world) for scenario in scenarios]
    config, settings, params = setups[0]
    for seed, (c, s, p) in zip(seeds, setups):
        if c != config or s != settings or not all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(p),
                                                                                     jax.tree.leaves(params))):
            raise ConfigError(f"seed {seed}'s filter setup differs from seed {seeds[0]}'s: a batch runs one setup")
    t0 = time.perf_counter()
    results = slam.run_batch(jax.numpy.stack([jax.random.key(10_000 + seed) for seed in seeds]),
                             [scenario.log for scenario in scenarios], config, params, settings, devices=devices,
                             progress=progress)
    seconds = (time.perf_counter() - t0) / len(seeds)
    return [(score_run(seed, result, scenario, world, seconds), result, scenario)
            for seed, result, scenario in zip(seeds, results, scenarios)]


def passage_steps(result, scenario) -> tuple[int, int, np.ndarray]:
    """``(first, last, start)``: the processed scans (path indices) nearest to the run's first and
    last passage over X, between which RA compares the relative pose with the true one, and the
    paths' shared initial pose in the filter's local frame (``particle_paths``' ``initial_pose``)."""
    passages = scenario.metadata.get("x_passages")
    if passages is None or len(passages) < 2:
        passages = checkpoint_passages(scenario.true_poses, scenario.metadata["checkpoint_x"], 0.3)
    idx = result.selection.indices
    first, last = (int(np.argmin(np.abs(idx - p))) for p in (passages[0], passages[-1]))
    start = np.asarray(scenario.log.odometry[0], np.float64) - np.r_[result.frame_offset, 0.0]
    return first, last, start


def score_run(seed: int, result, scenario, world: dict, seconds: float) -> dict:
    """A run's record (fields :data:`RUN_FIELDS`): RA between the first and last passage over X."""
    truth, lam = scenario.true_poses, world["rotation_weight"]
    idx = result.selection.indices
    first, last, start = passage_steps(result, scenario)
    paths = result.to_world(particle_paths(result.info.proposed_poses, result.info.ancestors, start))
    log_w = np.asarray(result.state.log_weights)
    ends = (first, last, truth[idx[first]], truth[idx[last]])
    ra = revisiting_accuracy(paths, log_w, *ends, lam)
    ra_position = revisiting_accuracy(paths, log_w, *ends, 0.0)  # RA is linear in lambda
    errors = passage_errors(paths, *ends, lam)  # (N,): each final particle's own RA
    run = {
        "seed": seed, "ra": ra, "ra_position": ra_position, "ra_heading": (ra - ra_position) / lam if lam else None,
        "best_particle_error": float(errors[result.best_particle]),
        # Is any history near the truth at all (the weights' failure to pick it), or none?
        "closest_particle_error": float(errors.min()),
        # How much of the final posterior those closing histories hold (RA averages by it).
        "closing_weight": float(np.sum(normalized_weights(log_w)[errors < world["success_ra"]])),
        "seconds": seconds,
        "num_steps": int(idx.size - 1), "num_fallbacks": int(result.info.num_fallbacks.sum()),
        "num_slip_steps": int(np.count_nonzero(result.info.num_slipped)),
        "num_degenerate": int(result.info.degenerate.sum()), "num_resamplings": int(result.info.resampled.sum()),
        "min_ess": float(result.info.ess.min()),
    }
    return run


def save_example(path: Path, result, scenario, ra: float):
    idx = result.selection.indices
    logodds, _, grid = result.dense_map()
    np.savez_compressed(
        path, logodds=logodds, best_path=result.best_path, truth=scenario.true_poses[idx],
        odometry=scenario.log.odometry[idx], segments=scenario.world.segments, extent=np.asarray(grid.extent), ra=ra)


# ----------------------------------------------------------------------------- summaries and figures

def binomial_se(successes: int, n: int) -> float:
    """Standard error sqrt(p (1 - p) / n) of a success rate p = successes / n."""
    if n == 0:
        return float("nan")
    p = successes / n
    return math.sqrt(p * (1 - p) / n)


def summarize(runs: list[dict], success_ra: float) -> dict:
    ra = np.array([r["ra"] for r in runs], dtype=float)
    k = int((ra < success_ra).sum())
    return {"num_runs": int(ra.size), "mean": float(ra.mean()) if ra.size else float("nan"),
            "std": float(ra.std(ddof=1)) if ra.size > 1 else 0.0,
            "median": float(np.median(ra)) if ra.size else float("nan"), "successes": k,
            "success_rate": k / ra.size if ra.size else float("nan"), "standard_error": binomial_se(k, ra.size)}


def runs_by_cell(runs: list[dict]) -> dict[str, list[dict]]:
    out: dict = {}
    for r in sorted(runs, key=lambda r: r["seed"]):
        out.setdefault(r["cell"], []).append(r)
    return out


def noise_rows(cells: list[dict], runs: list[dict], success_ra: float) -> list[dict]:
    """Success count, rate and its binomial standard error of every (method, N, scale) cell."""
    by_cell = runs_by_cell(runs)
    rows = []
    for c in cells:
        s = summarize(by_cell.get(cell_key(c), []), success_ra)
        rows.append({"method": c["method"], "N": c["N"], "odometry_scale": c["odometry_scale"], "runs": s["num_runs"],
                     "successes": s["successes"], "success_rate": s["success_rate"],
                     "standard_error": s["standard_error"]})
    return rows


def _lines(rows: list[dict]) -> dict[str, list[dict]]:
    """``rows`` grouped by method (and N, when there are several), in order."""
    several_n = len({r["N"] for r in rows}) > 1
    out: dict = {}
    for r in rows:
        out.setdefault(f"{r['method']}, N={r['N']}" if several_n else r["method"], []).append(r)
    return out


def noise_markdown(rows: list[dict], success_ra: float) -> str:
    scales = sorted({r["odometry_scale"] for r in rows})
    lines = [f"Success rate (RA < {success_ra:g} m) against the odometry noise scale: successes / runs, "
             "rate ± binomial standard error.", "",
             "| method | " + " | ".join(f"scale {s:g}" for s in scales) + " |", "|---" * (len(scales) + 1) + "|"]
    for label, group in _lines(rows).items():
        at = {r["odometry_scale"]: r for r in group}
        lines.append(f"| {label} | " + " | ".join(
            f"{at[s]['successes']}/{at[s]['runs']}: {at[s]['success_rate']:.2f} ± {at[s]['standard_error']:.2f}"
            if s in at and at[s]["runs"] else "" for s in scales) + " |")
    return "\n".join(lines) + "\n"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def noise_figure(path: Path, rows: list[dict], success_ra: float):
    plt = _pyplot()
    groups = _lines([r for r in rows if r["runs"]])
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for i, (label, group) in enumerate(groups.items()):
        dodge = 0.012 * (i - (len(groups) - 1) / 2)  # keep the error bars apart
        ax.errorbar([r["odometry_scale"] + dodge for r in group], [r["success_rate"] for r in group],
                    yerr=[r["standard_error"] for r in group], marker="o", capsize=3, label=label)
    n = sorted({r["runs"] for r in rows if r["runs"]})
    ax.set_xlabel("odometry noise scale (robot and filter model)")
    ax.set_ylabel(f"success rate (RA < {success_ra:g} m)")
    ax.set_title(f"{'/'.join(map(str, n))} runs a point, bars: binomial standard error", fontsize=9)
    ax.set_ylim(-0.05, 1.05)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _fig5(path: Path, lines: dict, by_cell: dict, success_ra: float, plt):
    """RA (mean +- std) and success rate (+- binomial s.e.) against N, one line per method (the paper's Fig. 5)."""
    fig, (ax_ra, ax_sr) = plt.subplots(1, 2, figsize=(11, 4))
    for i, (name, group) in enumerate(lines.items()):
        group = sorted(group, key=lambda c: c["N"])
        stats = [summarize(by_cell[cell_key(c)], success_ra) for c in group]
        ns = np.array([c["N"] for c in group], float)
        ax_ra.errorbar(ns * (1 + 0.03 * (i - len(lines) / 2)), [s["mean"] for s in stats],
                       yerr=[s["std"] for s in stats], marker="o", capsize=3, label=name)
        ax_sr.errorbar(ns, [s["success_rate"] for s in stats], yerr=[s["standard_error"] for s in stats],
                       marker="o", capsize=3, label=name)
    ax_ra.set_ylabel("revisiting accuracy RA (mean +- std)")
    ax_ra.axhline(success_ra, color="k", lw=0.5, ls=":")
    ax_sr.set_ylabel(f"success rate (RA < {success_ra:g}) +- s.e.")
    ax_sr.set_ylim(-0.05, 1.05)
    ax_sr.legend(fontsize=8)
    for ax in (ax_ra, ax_sr):
        ax.set_xlabel("SLAM particles N")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def make_figures(out: Path, cells: list[dict], stored: dict, runs: list[dict], success_ra: float):
    """fig5.png (for several N), ra_distribution.png, examples.png and failures.png of the table's ``cells``."""
    plt = _pyplot()
    by_cell = runs_by_cell(runs)
    several = len({c["odometry_scale"] for c in cells}) > 1
    label = {id(c): c["method"] + (f", scale {c['odometry_scale']:g}" if several else "") for c in cells}
    lines: dict = {}
    for c in cells:
        if by_cell.get(cell_key(c)):
            lines.setdefault(label[id(c)], []).append(c)
    if not lines:
        return
    if len({c["N"] for c in cells}) > 1:
        _fig5(out / "fig5.png", lines, by_cell, success_ra, plt)

    shown = [c for c in cells if by_cell.get(cell_key(c))]
    fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(shown)), 4))
    ax.boxplot([[r["ra"] for r in by_cell[cell_key(c)]] for c in shown], showfliers=True)
    for j, c in enumerate(shown):
        ra = [r["ra"] for r in by_cell[cell_key(c)]]
        ax.scatter(j + 1 + np.random.default_rng(j).uniform(-0.15, 0.15, len(ra)), ra, s=6)
    ax.set_xticks(range(1, len(shown) + 1), [f"{label[id(c)]}\nN={c['N']}".replace(", ", "\n") for c in shown],
                  fontsize=7)
    ax.set_yscale("log")
    ax.axhline(success_ra, color="k", lw=0.5, ls=":")
    ax.set_ylabel("RA per run")
    fig.tight_layout()
    fig.savefig(out / "ra_distribution.png", dpi=120)
    plt.close(fig)

    # Each method's map at its largest N (first seed; worst failure): the true world drawn over
    # the map shows which part is off (box 2's frame against the hedge's).
    for field, name in (("example", "examples.png"), ("worst_example", "failures.png")):
        picks = {}
        for c in sorted(cells, key=lambda c: (c["N"], -abs(c["odometry_scale"] - 1))):
            if (out / stored.get(cell_key(c), {}).get(field, "-")).is_file():
                picks[label[id(c)]] = (c, stored[cell_key(c)][field])
        if not picks:
            continue
        fig, axes = plt.subplots(1, len(picks), figsize=(4.2 * len(picks), 3.4), squeeze=False)
        for ax, (text, (c, file)) in zip(axes[0], picks.items()):
            ex = np.load(out / file)
            ax.imshow(1 / (1 + np.exp(-ex["logodds"])), origin="lower", extent=tuple(ex["extent"]), cmap="gray_r",
                      vmin=0, vmax=1)
            for seg in ex["segments"]:
                ax.plot(seg[[0, 2]], seg[[1, 3]], color="tab:blue", lw=0.6)
            ax.plot(ex["truth"][:, 0], ex["truth"][:, 1], color="tab:green", lw=0.6, label="truth")
            ax.plot(ex["best_path"][:, 0], ex["best_path"][:, 1], color="tab:red", lw=0.6, label="best particle")
            ax.set_title(f"{text}, N={c['N']}\nRA = {float(ex['ra']):.3f}", fontsize=8)
            xs, ys = ex["segments"][:, [0, 2]], ex["segments"][:, [1, 3]]
            ax.set_xlim(xs.min() - 2.5, xs.max() + 2.5)  # the world and the circle round box 2
            ax.set_ylim(ys.min() - 2.5, ys.max() + 2.5)
            ax.set_aspect("equal")
        axes[0][0].plot([], [], color="tab:blue", lw=0.6, label="true world")
        axes[0][0].legend(fontsize=7, loc="upper right")
        fig.tight_layout()
        fig.savefig(out / name, dpi=120)
        plt.close(fig)


def print_table(cells: list[dict], runs: list[dict], success_ra: float):
    by_cell = runs_by_cell(runs)
    print(f"{'method':18s} {'N':>4s} {'scale':>5s} {'runs':>4s} {'RA mean':>8s} {'RA std':>8s} {'median':>8s} "
          f"{'success':>13s}")
    for c in cells:
        s = summarize(by_cell.get(cell_key(c), []), success_ra)
        if s["num_runs"]:
            print(f"{c['method']:18s} {c['N']:4d} {c['odometry_scale']:5g} {s['num_runs']:4d} {s['mean']:8.3f} "
                  f"{s['std']:8.3f} {s['median']:8.3f} {s['success_rate']:6.2f} ± {s['standard_error']:.2f}")


def write_summaries(out: Path, store: ResultStore, cells: list[dict], success_ra: float):
    """Each cell's summary in results.json, the noise-scale numbers when the table has several
    scales, the figures and the printed table."""
    stored, by_cell = store.sections.setdefault("cells", {}), runs_by_cell(store.runs)
    for key, cell in stored.items():
        cell["summary"] = summarize(by_cell.get(key, []), success_ra)
    if len({c["odometry_scale"] for c in cells}) > 1:
        rows = noise_rows(cells, store.runs, success_ra)
        store.write(noise_scale=rows)
        noise_figure(out / "noise_scale.png", rows, success_ra)
        (out / "noise_scale.md").write_text(noise_markdown(rows, success_ra))
    store.write()
    make_figures(out, cells, stored, store.runs, success_ra)


# ----------------------------------------------------------------------------- main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(DEFAULT_CONFIG), help="the experiment file (default box_world.json)")
    ap.add_argument("--table", default="table", help="a table of the experiment file (table, noise, quick, ...)")
    ap.add_argument("--methods", nargs="+", metavar="NAME", help="run these methods of the file instead of the table's")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a build_setup name for every method (e.g. lookahead.alpha=0.3); a new cell record")
    ap.add_argument("--runs", type=int, default=30, help="seeds per cell")
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + runs - 1")
    ap.add_argument("--out", default="results/box_world")
    ap.add_argument("--progress", action="store_true", help="a tqdm bar per filter run too")
    ap.add_argument("--batch-seeds", action="store_true",
                    help="run a cell's seeds as one batch over the devices (jaxslam.slam.run_batch); the same "
                         "runs and records (a run's seconds: the batch's over its runs); a stopped batch is redone")
    ap.add_argument("--devices", type=int, default=None, metavar="D",
                    help="batch the seeds (--batch-seeds) over the first D devices (default all; on a CPU, "
                         "XLA_FLAGS=--xla_force_host_platform_device_count=D before the run makes D)")
    args = ap.parse_args(argv)
    try:
        if args.devices is not None:
            slam.batch_devices(args.devices)  # there are that many, before any work
        exp = load_experiment(args.config)
        if args.table not in exp["tables"]:
            raise ConfigError(f"no table {args.table!r} in {args.config}; tables: {sorted(exp['tables'])}")
        table = exp["tables"][args.table]
        unknown = [m for m in args.methods or [] if m not in exp["methods"]]
        if unknown:
            raise ConfigError(f"unknown methods {unknown}; known: {list(exp['methods'])}")
        overrides = {**table.get("set", {}), **parse_assignments(args.set)}
        cells = table_cells(exp, table, args.methods or table["methods"], overrides)
        world = world_settings(exp, table)
        out = Path(args.out)
        store = ResultStore(out / "results.json", world, key=lambda r: (r["cell"], r["seed"]))
    except (ConfigError, SettingsMismatch, OSError, json.JSONDecodeError, ValueError) as err:
        print(f"box_world.py: {err}", file=sys.stderr)
        return 2
    from tqdm.auto import tqdm

    (out / "maps").mkdir(parents=True, exist_ok=True)
    stored = store.sections.setdefault("cells", {})
    seeds = range(args.first_seed, args.first_seed + args.runs)
    for c in cells:
        key = cell_key(c)
        cell = stored.setdefault(key, {})
        cell.update(c)  # the record and its (latest) name
        todo = [s for s in seeds if not store.done((key, s))]
        if not todo:
            continue
        stem = (f"maps/{c['method'].replace(' ', '_').replace('=', '')}_N{c['N']}_s{c['odometry_scale']:g}_"
                f"{hashlib.sha1(key.encode()).hexdigest()[:8]}")
        bar = tqdm(total=len(todo), desc=f"{c['method']} N={c['N']} scale={c['odometry_scale']:g}", unit="run",
                   file=sys.stdout)
        if args.batch_seeds or args.devices is not None:  # the cell's seeds as one batch over the devices
            outcomes = iter(run_batch(c, todo, world, args.devices, args.progress))
        else:
            outcomes = (run_once(c, seed, world, args.progress) for seed in todo)
        for seed, (run, result, scenario) in zip(todo, outcomes):
            if "example" not in cell:
                save_example(out / f"{stem}_seed{seed}.npz", result, scenario, run["ra"])
                cell["example"] = f"{stem}_seed{seed}.npz"
            worst = max((r["ra"] for r in store.runs if r["cell"] == key), default=-np.inf)
            if run["ra"] >= world["success_ra"] and run["ra"] > worst:
                save_example(out / f"{stem}_worst.npz", result, scenario, run["ra"])
                cell["worst_example"] = f"{stem}_worst.npz"
            store.add({"cell": key, **run}, cells=stored)
            bar.set_postfix(ra=f"{run['ra']:.3f}", s=f"{run['seconds']:.0f}")
            bar.update()
        bar.close()
    write_summaries(out, store, cells, world["success_ra"])
    print_table(cells, store.runs, world["success_ra"])
    print(f"wrote {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
