"""The loop closure (jaxslam.graph) on simulated worlds with ground truth: precision and recall
of its loops, and the path error before and after.

Worlds: the twin rooms and the twin corridors built to alias (``jaxslam.sim.aliasing``: two
identical rooms 10 m apart; two identical 36 m corridors 8 m apart, joined into a ring) and the
demo's office. Inputs: the filter itself (``slam.run``, the SMP with the demo's
settings, ``close_loops``), and, to test the back end alone, the true path drifted as a filter
drifts (a heading bias and a scale error per processed scan, drawn per seed). The ``wide``
window variant searches 12 m either side from the start: wide enough to reach the twin.

A loop is correct when its measurement is within 0.3 m and 0.05 rad of the true relative pose.
Precision: correct kept loops over kept loops. Recall: of the queries that revisit (the true
position within 1 m of a node of a submap that ends at least ``min_separation`` of path before
it), the share with a correct kept loop.

    python experiments/loop_closure.py --out OUT/loop_closure.json --seeds 3 --figure OUT/twin_rooms.png

Runs are stored as they finish; a rerun into the same file skips them (experiments/_runs.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
from _runs import ResultStore, closure_settings  # experiments/_runs.py: the shared resume helper

WORLDS = ("twin_rooms", "twin_corridors", "office")
INPUTS = ("filter", "drift")
WINDOWS = {"default": {}, "wide": {"window_min_xy": 12.0, "window_max_xy": 12.0, "max_node_distance": 15.0}}
VARIANT = {}
"""ClosureConfig fields every run of this invocation sets (``--set NAME=VALUE``), recorded in the settings."""
FILTER = {"proposal": "smp", "num_particles": 20, "linear_update": 0.25, "angular_update": 0.25}
"""The filter's settings (the demo's)."""
CORRECT_XY, CORRECT_THETA = 0.3, 0.05


def scenario_of(world: str, seed: int):
    import jax

    from jaxslam.sim import office_scenario
    from jaxslam.sim.aliasing import twin_corridors_scenario, twin_rooms_scenario

    key = jax.random.key(seed)
    return {"twin_rooms": twin_rooms_scenario, "twin_corridors": twin_corridors_scenario,
            "office": office_scenario}[world](key)


def drifted(truth: np.ndarray, seed: int) -> np.ndarray:
    """The true node poses drifted as a filter drifts: each step's heading off by a bias of
    0.0005-0.0015 rad (either sign) and its length by a scale error of 0.5-1.5 %, drawn per seed."""
    from jaxslam.geometry import between_np, compose_np

    rng = np.random.default_rng(1000 + seed)
    bias = rng.uniform(0.0005, 0.0015) * rng.choice([-1, 1])
    scale = 1 + rng.uniform(0.005, 0.015) * rng.choice([-1, 1])
    steps = between_np(truth[:-1], truth[1:])
    steps[:, 2] += bias
    steps[:, :2] *= scale
    out = [truth[0]]
    for step in steps:
        out.append(compose_np(out[-1], step))
    return np.array(out)


def judge(closure, truth: np.ndarray, config) -> dict:
    """Precision, recall and path errors of one closure against the true node poses."""
    from jaxslam.geometry import between_np
    from jaxslam.graph.closure import path_distances

    loops = closure.loops
    origin = closure.submap_first_node[loops.submap] if loops.submap.size else np.zeros(0, int)
    diff = between_np(between_np(truth[origin], truth[loops.query]), loops.measurement)
    correct = (np.hypot(diff[:, 0], diff[:, 1]) < CORRECT_XY) & (np.abs(diff[:, 2]) < CORRECT_THETA)
    kept = loops.refused == ""
    travelled = path_distances(truth)
    first = closure.submap_first_node
    last = np.append(first[1:] - 1, truth.shape[0] - 1)
    queries = np.arange(0, truth.shape[0], config.query_stride)
    revisits = []
    for q in queries:
        eligible = last[(last < q) & (travelled[q] - travelled[last] >= config.min_separation)]
        if eligible.size and np.min(np.hypot(*(truth[:eligible.max() + 1, :2] - truth[q, :2]).T)) < 1.0:
            revisits.append(q)
    found = set(loops.query[kept & correct].tolist())
    error = lambda poses: float(np.mean(np.hypot(*(poses[:, :2] - truth[:, :2]).T)))
    return {"pairs": closure.pairs_searched, "candidates": int(loops.query.size), "kept": int(kept.sum()),
            "kept_correct": int((kept & correct).sum()), "kept_false": int((kept & ~correct).sum()),
            "false_candidates": int((~correct).sum()),
            "precision": float((kept & correct).sum() / kept.sum()) if kept.any() else None,
            "revisits": len(revisits), "recall": len(found & set(revisits)) / len(revisits) if revisits else None,
            "error_before_m": error(closure.filter_poses), "error_after_m": error(closure.poses),
            "refused": {str(r): int(n) for r, n in zip(*np.unique(loops.refused[~kept], return_counts=True))},
            "closure_s": closure.timings["total"]}


def run_one(world: str, source: str, window: str, seed: int) -> tuple[dict, object, object]:
    import jax

    from jaxslam import slam
    from jaxslam.config import build_setup
    from jaxslam.graph import ClosureConfig, close_trajectory_loops
    from jaxslam.laserlog import select_updates
    from jaxslam.laserlog import local_frame_offset

    scenario = scenario_of(world, seed)
    closure_config = dataclasses.replace(ClosureConfig(), **{**WINDOWS[window], **VARIANT})  # --set wins
    config, settings, params = build_setup(dict(FILTER))
    t0 = time.perf_counter()
    if source == "filter":
        result = slam.run(jax.random.key(seed), scenario.log, config, params, settings, progress=False,
                          close_loops=closure_config)
        closure, selection = result.closure, result.selection
    else:
        selection = select_updates(scenario.log, settings.linear_update, settings.angular_update)
        poses = drifted(scenario.true_poses[selection.indices], seed)
        closure = close_trajectory_loops(scenario.log, selection.indices, poses, selection.motions, params, config,
                                         local_frame_offset(scenario.log), closure_config)
    record = {"world": world, "input": source, "window": window, "seed": seed, "wall_s": time.perf_counter() - t0,
              **judge(closure, scenario.true_poses[selection.indices], closure_config)}
    return record, closure, scenario


def draw(path: Path, closure, scenario, title: str) -> None:
    from matplotlib.figure import Figure

    from jaxslam.graph import load_graph, plot_graph, save_graph

    tmp = path.with_suffix(".npz")
    save_graph(tmp, closure)
    graph = load_graph(tmp)
    tmp.unlink()
    fig = Figure(figsize=(11, 4.5))
    ax = fig.subplots()
    for seg in scenario.world.segments:
        ax.plot(seg[[0, 2]], seg[[1, 3]], color="k", lw=0.8)
    plot_graph(ax, graph, truth=scenario.true_poses[closure.node_scans])
    ax.set_title(title, fontsize=9)
    fig.savefig(path, dpi=130, bbox_inches="tight")


def table(runs: list[dict]) -> str:
    lines = ["| world | input | window | runs | kept (false) | precision | recall | path error before -> after [m] |",
             "|---|---|---|---|---|---|---|---|"]
    cells: dict = {}
    for r in runs:
        cells.setdefault((r["world"], r["input"], r["window"]), []).append(r)
    for (world, source, window), rs in sorted(cells.items()):
        kept, false = sum(r["kept"] for r in rs), sum(r["kept_false"] for r in rs)
        precision = (kept - false) / kept if kept else float("nan")
        recall = np.mean([r["recall"] for r in rs if r["recall"] is not None])
        lines.append(f"| {world} | {source} | {window} | {len(rs)} | {kept} ({false}) | {precision:.3f} | {recall:.2f} "
                     f"| {np.mean([r['error_before_m'] for r in rs]):.3f} -> {np.mean([r['error_after_m'] for r in rs]):.3f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="results JSON (runs already in it are skipped)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per cell (default 3)")
    parser.add_argument("--worlds", nargs="+", choices=WORLDS, default=list(WORLDS))
    parser.add_argument("--inputs", nargs="+", choices=INPUTS, default=list(INPUTS))
    parser.add_argument("--windows", nargs="+", choices=tuple(WINDOWS), default=list(WINDOWS),
                        help="window variants to run (the wide one on the twin worlds only; default: both)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="a ClosureConfig field for every run (e.g. min_score=0.5), recorded in the settings")
    parser.add_argument("--figure", help="PNG of the twin rooms' first filter run (or drift run): the loops kept and refused")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be at least 1, got {args.seeds}")
    if args.figure and Path(args.figure).is_dir():
        parser.error(f"--figure must be a PNG file, got the folder {args.figure}")
    from tqdm import tqdm

    try:
        VARIANT.update(closure_settings(args.set))
    except ValueError as err:
        parser.error(str(err))
    store = ResultStore(args.out, {"filter": FILTER, "windows": WINDOWS, "set": dict(VARIANT)},
                        key=lambda r: (r["world"], r["input"], r["window"], r["seed"]))
    cells = [(w, i, win, s) for w in args.worlds for i in args.inputs for win in args.windows for s in range(args.seeds)
             if win == "default" or w.startswith("twin_")]
    drawn = False
    for cell in tqdm(cells, desc="loop closure runs", unit="run"):
        if store.done(cell) and not (args.figure and not drawn and cell[0] == "twin_rooms" and cell[2] == "default"):
            continue
        record, closure, scenario = run_one(*cell)
        if args.figure and not drawn and cell[0] == "twin_rooms" and cell[2] == "default":
            draw(Path(args.figure), closure, scenario,
                 f"twin rooms, {cell[1]} input, seed {cell[3]}: {record['kept']} loops kept "
                 f"({record['kept_false']} false), path error {record['error_before_m']:.2f} -> "
                 f"{record['error_after_m']:.2f} m")
            drawn = True
        store.add(record)
    text = table(store.runs)
    store.write(table=text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
