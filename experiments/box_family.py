"""The paper's claim over a family of box worlds: success (RA < 0.2 m) world by world.

The box world (``box_world.py``) is one world, and the library's defaults were tuned on it. This
script runs the methods on a family of worlds drawn one per seed (:mod:`jaxslam.sim.box_family`:
one or two boxes of any size and angle, hedges, fences or barrels at the checkpoint X, circles of
1.5-2.5 m, 8-15 laps either way round, visits to X every 3-5 laps, a 3-5 m laser, 0.5-1.5 times
the default robot's odometry noise), one filter seed per world, and counts the successes of every
method at every N with binomial standard errors.

The two families are kept apart. Every choice of a default or a mechanism is made on the
*tuning* family (seeds 1000 on); the *test* family (seeds 0-99) is measured once, after the
choice is made, and the script refuses it without ``--i-have-made-the-choice``.

The methods are ``box_world.json``'s, at its "defaults" table's settings (the library's defaults
but for the filter's odometry noise, the simulated robot's times ``motion_scale``, and the fixed
grid): OP, SMP, LP-SM (the library's LP: localizers from the scan match) and LP (the paper's:
localizers from the odometry). One setting differs from ``box_world.py``'s cells: the maps take
beams up to the family's longest laser range plus ``insert_range_margin`` in every world (a beam
never exceeds its laser's range, so this inserts the same beams as the laser's own range plus
the margin), so that one cell compiles once for all worlds.

A run's record is ``box_world.score_run``'s (RA, the closest final particle, the closing weight,
...) and, as ``jaxslam diagnose`` judges a relation (:func:`jaxslam.diagnose.closest_then`,
:func:`~jaxslam.diagnose.weighted_then`) with the box world's revisiting error in place of the
relation error: over the particles proposed at the last passage over X, each on its own history
(``closing_steps.proposed_histories``), the smallest error (``closest_then``) and the mean by
that step's weights (``weighted_then``). A failure's ``cause`` is then

* "no particle had the closure": ``closest_then`` >= 0.2 m (the proposal or the particles'
  diversity failed before X);
* "the weights did not pick it": some particle had it, and the weights there put the mean
  above 0.2 m;
* "a later step lost it": the weights there picked it, and the steps after X (the drive to the
  turnaround point, the resamplings) lost it.

``--out`` is the results file (JSON, rewritten atomically after every run, ``_runs.ResultStore``):
rerun with the same ``--out`` and the finished (world, method, N) runs are skipped; a file written
with other settings (family, version, ``--max-laps``, the json's numbers) is refused.

    python experiments/box_family.py --family tuning --worlds 20 --out results/box_family_tuning.json \\
        --figure results/box_family_tuning.png
    python experiments/box_family.py --family tuning --draw-worlds docs/results/box_family_worlds.png
    python experiments/box_family.py --family tuning --worlds 1 --methods OP --particles 4 --max-laps 1 \\
        --out /tmp/bf.json                                            # a smoke test
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections import Counter
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import box_world  # noqa: E402  (experiments/box_world.py: the methods, the filter's setup, scoring)
import closing_steps  # noqa: E402  (experiments/closing_steps.py: the histories proposed at a step)
from _runs import ResultStore, SettingsMismatch  # noqa: E402

from jaxslam import slam  # noqa: E402
from jaxslam.cli import parse_assignments  # noqa: E402
from jaxslam.config import ConfigError  # noqa: E402
from jaxslam.metrics import normalized_weights, passage_errors  # noqa: E402
from jaxslam.sim import box_family  # noqa: E402

DEFAULT_METHODS = ("OP", "SMP", "LP-SM", "LP")
"""``box_world.json``'s methods run by default: the OP, the SMP, the library's LP and the paper's."""
METHOD_LABELS = {"LP-SM": "LP (library's)", "LP": "LP (paper's)"}
"""How the figures and the printed table name the methods whose json names are not plain."""
DEFAULT_PARTICLES = (20, 50, 100)
SETTINGS_TABLE = "defaults"
"""The ``box_world.json`` table whose ``set`` every method takes (the library's defaults)."""
CAUSES = ("no particle had the closure", "the weights did not pick it", "a later step lost it")
"""A failure's causes (the module's doc), in the order the table prints them."""
THE_RULE = ("Every choice of a default or a mechanism is made on the tuning family (seeds 1000 on); "
            "the test family (seeds 0-99) is measured once, after the choice is made.")
DIFFICULTIES = (("heading_drift_per_lap", "odometry's heading drift per lap [deg]", np.degrees),
                ("box_size", "largest box side [m]", lambda x: x),
                ("range_max", "laser range [m]", lambda x: x))
"""The figure's panels: a difficulty's key, its axis label and its unit conversion."""


# ----------------------------------------------------------------------------- worlds and runs

def world_draw(seed: int, max_laps: int | None = None) -> box_family.BoxWorldDraw:
    """World ``seed``'s draw, its laps (and laps between visits) cut to ``max_laps`` when given (a smoke test)."""
    draw = box_family.draw_world(seed)
    if max_laps is not None:
        draw = dataclasses.replace(draw, laps=min(draw.laps, max_laps),
                                   laps_per_visit=min(draw.laps_per_visit, max_laps))
    return draw


def world_keys(seed: int):
    """``(simulation, filter)``: world ``seed``'s two PRNG keys, the range and odometry noise's and
    the filter's (one filter seed per world), folded from one key so that no two worlds share either."""
    root = jax.random.key(seed)
    return jax.random.fold_in(root, 0), jax.random.fold_in(root, 1)


def filter_motion_params(draw: box_family.BoxWorldDraw, world: dict) -> dict[str, float]:
    """The filter's odometry noise for a draw, by ``box_world.json``'s rule (its note "motion_scale"):
    the simulated robot's (:func:`jaxslam.sim.box_family.robot_motion_params`) with the proportional
    terms times ``motion_scale``, the floors as they are; the same numbers
    ``box_world.filter_setup`` gives the filter from the scenario's ``motion_params``."""
    return box_world.scaled_noise(box_family.robot_motion_params(draw), world["motion_scale"])


def closure_then(result, scenario, world: dict) -> dict:
    """How the run stood at the last passage over X: over the particles proposed there, each on its
    own history, the smallest revisiting error (``closest_then``, m), the mean by that step's
    weights (``weighted_then``, m) and the weight on the histories under the success threshold
    (``closing_weight_then``): :func:`jaxslam.diagnose.closest_then`'s and ``weighted_then``'s
    reading with the revisiting error (``passage_errors``, the json's lambda) for the relation error."""
    first, last, start = box_world.passage_steps(result, scenario)
    step = last - 1  # the step whose proposals are the paths' index ``last``
    idx = np.asarray(result.selection.indices)
    truth = scenario.true_poses
    histories = result.to_world(closing_steps.proposed_histories(
        np.asarray(result.info.proposed_poses), np.asarray(result.info.ancestors), step, start))
    errors = passage_errors(histories, first, last, truth[idx[first]], truth[idx[last]], world["rotation_weight"])
    weights = normalized_weights(np.asarray(result.info.log_weights)[step])
    return {"closest_then": float(errors.min()), "weighted_then": float(np.sum(weights * errors)),
            "closing_weight_then": float(np.sum(weights[errors < world["success_ra"]]))}


def failure_cause(run: dict, success_ra: float) -> str | None:
    """A run's failure's cause (:data:`CAUSES`; the module's doc), or None for a success."""
    if run["ra"] < success_ra:
        return None
    if run["closest_then"] >= success_ra:
        return CAUSES[0]
    return CAUSES[1] if run["weighted_then"] >= success_ra else CAUSES[2]


def run_world(cell: dict, seed: int, world: dict, max_laps: int | None = None, progress: bool = False) -> dict:
    """One run of a cell (a ``box_world`` cell record with its method's name) on world ``seed``: its
    record, ``box_world.score_run``'s fields with :func:`closure_then`'s and ``cause`` added."""
    return run_world_result(cell, seed, world, max_laps, progress)[0]


def run_world_result(cell: dict, seed: int, world: dict, max_laps: int | None = None, progress: bool = False):
    """:func:`run_world`, returning ``(record, slam result, scenario, filter params)``."""
    draw = world_draw(seed, max_laps)
    simulation_key, filter_key = world_keys(seed)
    scenario = box_family.family_scenario(draw, simulation_key)
    config, settings, params = box_world.filter_setup(cell, scenario, world)
    t0 = time.perf_counter()
    result = slam.run(filter_key, scenario.log, config, params, settings, progress=progress)
    run = box_world.score_run(seed, result, scenario, world, time.perf_counter() - t0)
    run.update(closure_then(result, scenario, world))
    run["cause"] = failure_cause(run, world["success_ra"])
    return run, result, scenario, params


# ----------------------------------------------------------------------------- summaries

def label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def summary_rows(cells: list[dict], runs: list[dict], success_ra: float) -> list[dict]:
    """Per cell: ``box_world.summarize``'s figures (successes, rate, binomial standard error, RA)
    and the failures counted by cause."""
    by_cell = box_world.runs_by_cell(runs)
    rows = []
    for c in cells:
        done = by_cell.get(box_world.cell_key(c), [])
        causes = Counter(r["cause"] for r in done if r["cause"] is not None)
        rows.append({"method": c["method"], "N": c["N"], **box_world.summarize(done, success_ra),
                     "causes": {cause: causes.get(cause, 0) for cause in CAUSES}})
    return rows


def print_table(rows: list[dict]):
    print(f"{'method':16s} {'N':>4s} {'worlds':>6s} {'success':>14s} {'RA median':>9s}   failures: "
          + ", ".join(f"{k + 1} = {c}" for k, c in enumerate(CAUSES)))
    for r in rows:
        if r["num_runs"]:
            print(f"{label(r['method']):16s} {r['N']:4d} {r['num_runs']:6d} {r['successes']:3d}: "
                  f"{r['success_rate']:.2f} ± {r['standard_error']:.2f} {r['median']:9.3f}   "
                  + " / ".join(str(r["causes"][c]) for c in CAUSES))


def difficulty_figure(path: Path, cells: list[dict], runs: list[dict], worlds: dict, success_ra: float):
    """Success against each difficulty (:data:`DIFFICULTIES`), a row per N, a line per method: the
    worlds in up to three bins of equal counts by the difficulty, each bin's rate +- binomial s.e.
    at its mean, and every world's outcome as a dot at 0 or 1."""
    plt = box_world._pyplot()
    by_cell = box_world.runs_by_cell(runs)
    ns = sorted({c["N"] for c in cells if by_cell.get(box_world.cell_key(c))})
    if not ns:
        return
    fig, axes = plt.subplots(len(ns), len(DIFFICULTIES), figsize=(4.2 * len(DIFFICULTIES), 3.3 * len(ns)),
                             squeeze=False)
    methods = list(dict.fromkeys(c["method"] for c in cells))
    colours = {m: f"C{i}" for i, m in enumerate(methods)}
    for row, n in zip(axes, ns):
        for ax, (name, text, unit) in zip(row, DIFFICULTIES):
            span = float(np.ptp([unit(w["difficulty"][name]) for w in worlds.values()])) or 1.0
            for i, c in enumerate(x for x in cells if x["N"] == n):
                done = by_cell.get(box_world.cell_key(c), [])
                if not done:
                    continue
                x = np.array([unit(worlds[str(r["seed"])]["difficulty"][name]) for r in done])
                ok = np.array([r["ra"] < success_ra for r in done], float)
                dodge = i - (len(methods) - 1) / 2  # keep the methods' dots and bars apart
                ax.scatter(x, ok + 0.04 * dodge, s=8, color=colours[c["method"]], alpha=0.5)
                order = np.argsort(x, kind="stable")
                bins = [b for b in np.array_split(order, min(3, len(order))) if b.size]
                rates = [ok[b].mean() for b in bins]
                ax.errorbar([x[b].mean() + 0.012 * span * dodge for b in bins], rates,
                            yerr=[box_world.binomial_se(int(ok[b].sum()), b.size) for b in bins], marker="o",
                            capsize=3, color=colours[c["method"]], label=label(c["method"]))
            ax.set_xlabel(text)
            ax.set_ylim(-0.1, 1.1)
        row[0].set_ylabel(f"N = {n}: success (RA < {success_ra:g} m)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{len(worlds)} worlds; points: the worlds in thirds by the difficulty, bars: binomial s.e.; "
                 "dots: each world", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


LANDMARK_COLOURS = {"hedge": "tab:green", "fence": "tab:brown", "barrels": "tab:orange"}


def draw_worlds_figure(path: Path, seeds) -> None:
    """The worlds of ``seeds`` side by side (four a row): their segments (boxes blue, landmarks by
    kind), the true path, the checkpoint X and the laser's range round it."""
    plt = box_world._pyplot()
    seeds = list(seeds)
    cols = 4
    rows = -(-len(seeds) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.9 * rows), squeeze=False)
    xmin, ymin, xmax, ymax = box_family.FAMILY_BOUNDS
    for ax in axes.flat[len(seeds):]:
        ax.axis("off")
    for ax, seed in zip(axes.flat, seeds):
        draw = box_family.draw_world(seed)
        world = box_family.family_world(draw)
        poses, _ = box_family.family_path(draw)
        ax.plot(poses[:, 0], poses[:, 1], color="0.6", lw=0.4)
        for name, colour in [("box2", "tab:blue"), *LANDMARK_COLOURS.items()]:
            for seg in world.segments[world.groups.get(name, [])]:
                ax.plot(seg[[0, 2]], seg[[1, 3]], color=colour, lw=1.2)
        ax.add_patch(plt.Circle(tuple(box_family.CHECKPOINT), draw.range_max, fill=False, ls="--", color="tab:red",
                                lw=0.7))
        ax.plot(*box_family.CHECKPOINT, "x", color="tab:red", ms=7, mew=2)
        ax.plot(*draw.turnaround, "+", color="k", ms=6)
        direction = "cw" if draw.clockwise else "ccw"
        kinds = ", ".join(m.kind for m in draw.landmarks)
        ax.set_title(f"world {seed}: {draw.laps} laps {direction}, X every {draw.laps_per_visit}; "
                     f"r {draw.circle_radius:.2f} m\nlaser {draw.range_max:.1f} m, odometry "
                     f"x{draw.odometry_scale:.2f}; {kinds}", fontsize=7.5)
        ax.set_xlim(xmin, xmax)
        ax.set_ylim(ymin, ymax)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
    fig.suptitle("box-world family: boxes (blue), hedges (green), fences (brown), barrels (orange), the true path "
                 "(grey), X (red x) and the laser's range round it (dashed), the turnaround point (+)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- main

def parse_args(argv):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=f"The rule: {THE_RULE} The test family needs --i-have-made-the-choice.")
    ap.add_argument("--family", choices=box_family.FAMILIES, default="tuning",
                    help=f"which family of worlds (default tuning). {THE_RULE}")
    ap.add_argument("--i-have-made-the-choice", dest="choice_made", action="store_true",
                    help="run (or draw) the test family: every default and mechanism was chosen on the tuning "
                         "family, and this is the one measurement of the test family")
    ap.add_argument("--worlds", type=int, default=20, help="the family's first WORLDS worlds (the test family has 100)")
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), metavar="NAME",
                    help=f"box_world.json methods (default {' '.join(DEFAULT_METHODS)}: OP, SMP, the library's LP, "
                         "the paper's LP)")
    ap.add_argument("--particles", nargs="+", type=int, default=list(DEFAULT_PARTICLES), metavar="N",
                    help="SLAM particle counts (default 20 50 100)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a build_setup name for every method (a new cell record)")
    ap.add_argument("--out", type=Path, help="the results file (JSON; rerun with it to resume)")
    ap.add_argument("--figure", type=Path, metavar="PNG", help="success against the worlds' difficulty")
    ap.add_argument("--draw-worlds", type=Path, metavar="PNG", help="the family's first twelve worlds, side by side")
    ap.add_argument("--max-laps", type=int, metavar="K", help="cut every world to at most K laps (a smoke test)")
    ap.add_argument("--config", default=str(box_world.DEFAULT_CONFIG), help="the experiment file (box_world.json)")
    ap.add_argument("--progress", action="store_true", help="a tqdm bar per filter run too")
    return ap.parse_args(argv)


def family_cells(exp: dict, methods: list[str], particles: list[int], assignments: dict) -> list[dict]:
    """The cells (``box_world`` cell records with their method's name) of ``methods`` x ``particles``
    at the json's "defaults" table's settings, ``assignments`` (``--set``) over them."""
    table = exp["tables"][SETTINGS_TABLE]
    # One insertion range for every world (the module's doc): one compile per cell.
    insert_range = box_family.RANGE_MAX_RANGE[1] + exp["insert_range_margin"]
    overrides = {**table.get("set", {}), "max_insert_range": insert_range, **assignments}
    return [{"method": name, **box_world.cell_record(box_world.method_settings(exp, name, overrides), n, 1.0)}
            for n in particles for name in methods]


def family_world_settings(exp: dict, family: str, max_laps: int | None) -> dict:
    """The runs' shared settings (``box_world.world_settings`` with the family's name and version)."""
    return {**box_world.world_settings(exp, {}), "family": family, "family_version": box_family.FAMILY_VERSION,
            "max_laps": max_laps}


def check_args(args) -> None:
    """Refuse bad input before any work (ValueError naming the problem)."""
    if args.family == "test" and not args.choice_made:
        raise ValueError(f"the test family is refused without --i-have-made-the-choice. {THE_RULE}")
    box_family.family_seeds(args.family, args.worlds)
    if args.out is None and args.draw_worlds is None:
        raise ValueError("nothing to do: give --out (and --figure) to run, or --draw-worlds PNG")
    if args.figure is not None and args.out is None:
        raise ValueError("--figure needs --out (the runs it draws)")
    if args.out is not None and args.out.is_dir():
        raise ValueError(f"--out {args.out} is a folder; give the results file (JSON)")
    for png in (args.figure, args.draw_worlds):
        if png is not None and (png.is_dir() or not png.parent.is_dir()):
            raise ValueError(f"{png}: not a file in an existing folder")
    if any(n < 1 for n in args.particles):
        raise ValueError(f"--particles must be >= 1, got {args.particles}")
    if args.max_laps is not None and args.max_laps < 1:
        raise ValueError(f"--max-laps must be >= 1, got {args.max_laps}")


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        check_args(args)
        seeds = box_family.family_seeds(args.family, args.worlds)
        if args.draw_worlds is not None:
            draw_worlds_figure(args.draw_worlds, box_family.family_seeds(args.family, 12))
            print(f"wrote {args.draw_worlds}")
        if args.out is None:
            return 0
        exp = box_world.load_experiment(args.config)
        unknown = [m for m in args.methods if m not in exp["methods"]]
        if unknown:
            raise ConfigError(f"unknown methods {unknown}; known: {list(exp['methods'])}")
        cells = family_cells(exp, args.methods, args.particles, parse_assignments(args.set))
        world = family_world_settings(exp, args.family, args.max_laps)
        store = ResultStore(args.out, world, key=lambda r: (r["cell"], r["seed"]))
    except (ConfigError, SettingsMismatch, OSError, json.JSONDecodeError, ValueError) as err:
        print(f"box_family.py: {err}", file=sys.stderr)
        return 2
    from tqdm.auto import tqdm

    worlds = store.sections.setdefault("worlds", {})
    for seed in seeds:
        draw = world_draw(seed, args.max_laps)
        worlds[str(seed)] = {"draw": draw.to_json(), "difficulty": box_family.difficulty(draw)}
    stored = store.sections.setdefault("cells", {})
    todo = [(c, seed) for c in cells for seed in seeds if not store.done((box_world.cell_key(c), seed))]
    bar = tqdm(total=len(todo), desc=f"{args.family} family", unit="run", file=sys.stdout)
    for c, seed in todo:  # cell by cell: one compile each, every world after the first reuses it
        key = box_world.cell_key(c)
        stored.setdefault(key, {}).update(c)
        bar.set_description(f"{label(c['method'])} N={c['N']} world {seed}")
        run = run_world(c, seed, world, args.max_laps, args.progress)
        store.add({"cell": key, **run}, cells=stored, worlds=worlds)
        bar.set_postfix(ra=f"{run['ra']:.3f}", s=f"{run['seconds']:.0f}")
        bar.update()
    bar.close()
    rows = summary_rows(cells, [r for r in store.runs if r["seed"] in seeds], world["success_ra"])
    store.write(summary=rows, worlds=worlds)
    print_table(rows)
    if args.figure is not None:
        difficulty_figure(args.figure, cells, [r for r in store.runs if r["seed"] in seeds], worlds,
                          world["success_ra"])
        print(f"wrote {args.figure}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
