"""``jaxslam eval`` (a trajectory's relation error) and ``jaxslam diagnose`` (a map run, step by
step, with its pose graph drawn over its map)."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from jaxslam.config import ConfigError
from jaxslam.diagnose import NUM_EVENTS, diagnose, read_step_record, relations_within
from jaxslam.io import read_log, read_relations, read_trajectory, sideways_relations
from jaxslam.io.relation_clock import align_relations_clock
from jaxslam.io.files import OutputError, check_output_file, write_file_atomic
from jaxslam.io.maps import read_map
from jaxslam.metrics import relation_error, scan_support
from jaxslam.outputs import strict_json_values
from jaxslam.plotting import plot_diagnosis, plot_map


def _cmd_eval(args: argparse.Namespace) -> int:
    if args.out:
        try:
            check_output_file(args.out)
        except OutputError as err:
            raise ConfigError(f"--out {err}") from None

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        timestamps, poses = read_trajectory(args.trajectory)  # repeated timestamps: the last kept, warned
    found = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    relations, alignment = _read_relations(args.relations, args.log)
    scans_log = None
    if args.scans:
        with warnings.catch_warnings(record=True) as caught_log:
            warnings.simplefilter("always")
            scans_log = read_log(args.scans)
        found += [f"--scans: {w.message}" for w in caught_log if issubclass(w.category, UserWarning)]
    try:
        err = relation_error(timestamps, poses, relations)
    except ValueError as missing:
        if alignment is not None:
            raise
        raise ConfigError(f"{missing}; relations written on another clock than the log's (a converted log, as "
                          f"MIT Killian's bag) need --log LOG") from None
    table = err.to_dict()
    # Kept in the mean, as the benchmark keeps them; their count and the mean without them beside it.
    sideways = sideways_relations(relations)
    table["sideways_count"] = int(sideways.sum())
    table["trans_mean_no_sideways"] = float(np.mean(err.trans[~sideways])) if not sideways.all() else float("nan")
    if scans_log is not None:
        try:
            support = scan_support(relations, timestamps, poses, err.trans, scans_log.timestamps, scans_log.ranges,
                                   scans_log.sensor)
        except ValueError as missing:
            raise ConfigError(f"--scans {args.scans}: {missing}") from None
        table["scan_support"] = support.summary(err.trans)
    for warning in found:
        print(f"warning: {warning}", file=sys.stderr)
    if alignment is not None:
        table["clock_alignment"] = _alignment_summary(alignment)
        print(f"{'clock':>22}: {alignment.times.size} relation timestamps found among the log's scans "
              f"(scan period {alignment.scan_period:.4f} s); {table['clock_alignment']['unpinned']} not pinned to "
              f"one scan (margin < 1); neighbour relations against the odometry: median "
              f"{table['clock_alignment']['residual_median_m']:.3f} m, largest "
              f"{table['clock_alignment']['residual_max_m']:.3f} m; the laser's scans "
              f"{alignment.laser_shift:+d} scans from the odometry's")
    print(f"{'relations':>22}: {table.get('count')}")
    if "scan_support" in table:
        support = table["scan_support"]
        print(f"{'scans':>22}: of {support['checked']} relations at most 60 s long and more than 0.1 m off, the two "
              f"scans favour the trajectory's motion in {support['favour_trajectory']} "
              f"({support['favour_trajectory_error_share']:.0%} of the summed error), the relation's in "
              f"{support['favour_relation']} ({support['favour_relation_error_share']:.0%})")
    for key, value in table.items():
        if key != "count" and not isinstance(value, (list, dict)):
            print(f"{key:>22}: {value:.6g}")
    if args.out:
        values, nulled = strict_json_values({k: v for k, v in table.items() if not isinstance(v, list)})
        if nulled:
            values["null_reasons"] = nulled
        values["warnings"] = found
        write_file_atomic(args.out, json.dumps(values, indent=2, allow_nan=False))
        print(f"written to {args.out}")
    return 0


def _read_relations(path, log_path):
    """The relations file, and with ``--log`` its timestamps found among that log's scans
    (:func:`jaxslam.io.relation_clock.align_relations_clock`): ``(relations, alignment or None)``."""
    relations = read_relations(path)
    if not log_path:
        return relations, None
    log = read_log(log_path)
    alignment = align_relations_clock(relations, log.timestamps, log.odometry, ranges=log.ranges, sensor=log.sensor)
    return alignment.relations, alignment


def _alignment_summary(alignment) -> dict:
    """What ``jaxslam eval --log`` records of the clock's alignment."""
    return {"timestamps": int(alignment.times.size), "scan_period_s": float(alignment.scan_period),
            "unpinned": int(np.sum(alignment.margin < 1.0)),
            "residual_median_m": float(np.nanmedian(alignment.residual)),
            "residual_max_m": float(np.nanmax(alignment.residual)),
            "laser_shift_scans": int(alignment.laser_shift),
            # Each shift's mean scan misfit from -max_shift on; None where the shift leaves the log.
            "shift_misfit_m2": [float(v) if np.isfinite(v) else None for v in alignment.shift_misfit]}


def _cmd_diagnose(args: argparse.Namespace) -> int:
    """Per-step diagnosis of a ``jaxslam map`` run: diagnosis.json and diagnosis.png."""
    run = Path(args.run_dir)
    out = Path(args.out) if args.out else run
    record = read_step_record(run)  # before any work: a clear error for a folder without it
    relations = _read_relations(args.relations, args.log)[0] if args.relations else None
    # The particles' record is the filter's: compare it with the filter's own trajectory.
    filter_trajectory = run / ("trajectory_filter.txt" if (run / "trajectory_filter.txt").exists() else "trajectory.txt")
    trajectory = read_trajectory(filter_trajectory) if relations is not None else None
    result = diagnose(record, trajectory, relations)
    # A closed run: the returns its closure missed, and why (jaxslam.graph.missed).
    missed = _missed_returns(run, relations) if relations is not None and (run / "graph.npz").exists() else None
    if missed is not None:
        result["closure"] = {"missed_returns": missed}
        result["summary"]["missed_returns"] = len(missed)
    out.mkdir(parents=True, exist_ok=True)
    values, nulled = strict_json_values(result)
    if nulled:
        values["null_reasons"] = nulled
    write_file_atomic(out / "diagnosis.json", json.dumps(values, allow_nan=False))
    import matplotlib  # lazy: matplotlib.pyplot adds 0.7 s to every command's start (measured)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plot_diagnosis(result, record, title=str(run))
    try:
        fig.savefig(out / "diagnosis.png", dpi=120)
    finally:
        plt.close(fig)
    written = [out / "diagnosis.json", out / "diagnosis.png"]
    if (run / "graph.npz").exists():
        written.append(_draw_graph(run, out, missed))
    summary = result["summary"]
    for key, value in summary.items():
        print(f"{key:>40}: {value}")
    for name, events in result["events"].items():
        print(name.replace("_", " ") + ":")
        for event in events:
            print("   " + ", ".join(f"{k} {v:.4g}" for k, v in event.items()))
    if missed is not None:
        print(f"returns the closure missed ({len(missed)}; the worst {min(len(missed), NUM_EVENTS)}):")
        for m in missed[:NUM_EVENTS]:
            print("   " + _missed_line(m))
    print("written to " + ", ".join(str(path) for path in written))
    return 0


def _missed_line(m: dict) -> str:
    """One missed return (:func:`jaxslam.graph.missed.missed_returns`) as a line."""
    searched = m["searched"]
    looked = "" if searched is None else f"; searched {searched['pairs']} pairs there"
    if searched is not None and searched["pairs"]:
        looked += (f", best {searched['best_score']:.2f}, windows {searched['window_m'][0]:.1f}-"
                   f"{searched['window_m'][1]:.1f} m centred {searched['guess_off_m'][0]:.1f} m or more off the "
                   f"relations' pose, {searched['reached']} holding it")
    if searched is not None:
        looked += f" ({searched['pairs_elsewhere']} elsewhere)"
    return (f"nodes {m['later_nodes'][0]}-{m['later_nodes'][1]} back to {m['earlier_nodes'][0]}-"
            f"{m['earlier_nodes'][1]} ({m['path_between_m']:.0f} m of path): {m['relations']} relations, closed "
            f"{m['closed_error_m']:.2f} m, filter {m['filter_error_m']:.2f} m; candidates {m['candidates'] or 'none'}"
            f"{looked}: {m['cause']}")


def _missed_returns(run: Path, relations) -> list[dict]:
    """:func:`jaxslam.graph.missed.missed_returns` of a closed run's folder."""
    from jaxslam.graph import load_graph, missed_returns  # lazy: scipy.sparse adds 0.7 s to every start (measured)

    times, closed = read_trajectory(run / "trajectory.txt")
    filter_times, filtered = read_trajectory(run / "trajectory_filter.txt")
    if not np.array_equal(times, filter_times):
        raise ValueError(f"diagnose: {run}'s trajectory.txt and trajectory_filter.txt hold other scans")
    return missed_returns(load_graph(run / "graph.npz"), times, closed, filtered, relations_within(relations, times)[0])


def _draw_graph(run: Path, out: Path, missed: list[dict] | None) -> Path:
    """graph.png: a run's pose graph (graph.npz) drawn over its map, with the returns it missed."""
    # lazy: matplotlib.pyplot and jaxslam.graph (scipy.sparse) add 0.7 s each to every command's start (measured)
    import matplotlib.pyplot as plt

    from jaxslam.graph import load_graph, plot_graph

    graph = load_graph(run / "graph.npz")
    fig, ax = plt.subplots(figsize=(9, 9))
    try:
        if (run / "map.yaml").exists():
            occupancy, spec = read_map(run / "map.yaml")
            occupancy = np.clip(occupancy, 1e-3, 1 - 1e-3)
            plot_map(ax, np.log(occupancy / (1 - occupancy)), spec)  # plot_map draws log-odds
        plot_graph(ax, graph, missed=missed)
        kept = int((graph["loop_refused"] == "").sum())
        title = f"{run}: {kept} loops kept of {graph['loop_refused'].size} candidates"
        if "drift_rates" in graph and np.all(np.isfinite(graph["drift_rates"])):
            # Whose heading drifts, as the loops measured it: the reason a far loop was or was not reached.
            filter_rate, odometry_rate = np.degrees(np.sqrt(graph["drift_rates"]))
            title += (f"\nheading drift per sqrt(step): filter {filter_rate:.3f}, odometry {odometry_rate:.3f} deg; "
                      f"{int(graph['passes'])} passes, odometry's share {float(graph['odometry_share']):.2f}")
            print(title.replace("\n", "; "))
        ax.set_title(title, fontsize=9)
        fig.savefig(out / "graph.png", dpi=120)
    finally:
        plt.close(fig)
    return out / "graph.png"
