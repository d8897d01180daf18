"""The ``jaxslam`` command: ``map``, ``demo``, ``eval``, ``diagnose`` and ``doors``.

Every field of :class:`~jaxslam.config.SlamConfig` and :class:`~jaxslam.config.RunSettings`
and every parameter of :class:`~jaxslam.config.SlamParams` can be set with
``--set NAME=VALUE`` (dotted names for parameters: ``--set motion.srr=0.05 --set
linear_update=0.5``) or from a JSON config file (``--config FILE`` holding ``{"config":
{...}, "params": {...}}``); the common ones also have their own flags. Precedence, lowest
first: the command's defaults, the config file, the dedicated flags (only when given),
``--set``.

The filter commands keep JAX's compiled code in a persistent cache (:mod:`jaxslam.compile_cache`:
``$JAXSLAM_CACHE_DIR``, by default ``~/.cache/jaxslam/jax``; ``off`` or ``--no-cache`` turns it
off), so that a second run skips most of the compilation.

Every refusal is one line on stderr, ``jaxslam <command>: error: ...``, naming the input, the
value and what would be accepted, with exit code 2 and no traceback; inputs (flags, config
values, parameters, the output folder) are checked before any work, and output folders are
written atomically (:func:`jaxslam.outputs.publish_folder`).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path

from jaxslam.config import ConfigError

SEED_LIMIT = 2**32
"""Seeds are in [0, 2**32): ``jax.random.key`` would wrap larger ones (2**32 runs as 0)."""


class _Parser(argparse.ArgumentParser):
    """argparse with its refusals on one line (``jaxslam map: error: ...``), exit code 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def check_seed(seed: int) -> int:
    """``seed`` if it lies in [0, 2**32), else ``ConfigError`` (jax.random.key would wrap it)."""
    if not 0 <= seed < SEED_LIMIT:
        raise ConfigError(f"--seed must be an integer in [0, 2**32 - 1 = {SEED_LIMIT - 1}], got {seed}")
    return seed


def _check_at_least(flag: str, value, low: int, what: str) -> None:
    if value is not None and value < low:
        raise ConfigError(f"{flag} must be an integer >= {low} ({what}), got {value}")


def _check_filter_args(args: argparse.Namespace) -> None:
    """The flags every filter command shares, before any work."""
    check_seed(args.seed)
    _check_at_least("--chunk-size", args.chunk_size, 1, "steps per compiled chunk")
    _check_at_least("--particles", args.particles, 1, "SLAM particles")
    _check_at_least("--localizers", args.localizers, 1, "localizer particles per SLAM particle")
    _check_at_least("--horizon", args.horizon, 0, "look-ahead scans")
    _check_at_least("--checkpoint-every", getattr(args, "checkpoint_every", None), 1, "chunks between checkpoints")


def _check_out_folder(out) -> None:
    from jaxslam.outputs import OutputError, check_output_folder

    try:
        check_output_folder(out)
    except OutputError as err:
        raise ConfigError(f"--out {err}") from None


def parse_assignments(items: list[str]) -> dict[str, str]:
    """``["a.b=1", ...]`` (the ``--set`` flags) -> ``{"a.b": "1"}``; a malformed item raises ``ConfigError``."""
    out = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        out[name.strip()] = value.strip()
    return out


def read_config_file(path) -> dict:
    """The flat names of a JSON config file ``{"config": {...}, "params": {...}}`` (either key
    optional; ``config`` holds config and run-settings fields, ``params`` dotted parameters)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"{path}: cannot read config file: {err}") from None
    if not isinstance(data, dict) or set(data) - {"config", "params"}:
        got = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{path}: expected a JSON object with keys 'config' and/or 'params', got {got}")
    values = {}
    for part in ("config", "params"):
        if not isinstance(data.get(part, {}), dict):
            raise ConfigError(f"{path}: '{part}' must be a JSON object of names and values, got {data[part]!r}")
        values.update(data.get(part, {}))
    return values


def build_setup_from_args(args: argparse.Namespace, defaults: dict | None = None):
    """``(SlamConfig, RunSettings, SlamParams)`` from ``defaults`` (the command's), the config
    file, the dedicated flags that were given and ``--set`` (later wins)."""
    from jaxslam.config import build_setup

    values = dict(defaults or {})
    if getattr(args, "config", None):
        values.update(read_config_file(args.config))
    flags = {
        "proposal": args.proposal, "num_particles": args.particles,
        "num_localizers": getattr(args, "localizers", None), "horizon": getattr(args, "horizon", None),
        "lookahead.alpha": getattr(args, "alpha", None),
    }
    values.update({k: v for k, v in flags.items() if v is not None})
    values.update(parse_assignments(args.set or []))
    return build_setup(values)


def _add_filter_options(p: argparse.ArgumentParser, command_defaults: dict, proposal_note: str = "") -> None:
    from jaxslam.config import default_values
    from jaxslam.proposals import PROPOSALS

    d = {**default_values(), **command_defaults}
    kinds = "; ".join(f"{name}: {proposal.summary}" for name, proposal in PROPOSALS.items())
    p.add_argument("--proposal", choices=list(PROPOSALS), default=None,
                   help=f"proposal distribution ({kinds}; the look-ahead's localizers start round the scan "
                        f"match, --set lookahead_initial=odometry: the paper's, from the motion model) "
                        f"(default {d['proposal']}{proposal_note})")
    p.add_argument("--particles", type=int, default=None,
                   help=f"number of SLAM particles N (default {d['num_particles']})")
    p.add_argument("--localizers", type=int, default=None,
                   help=f"LP: localizer particles L per SLAM particle (default {d['num_localizers']})")
    p.add_argument("--horizon", type=int, default=None,
                   help=f"LP: look-ahead horizon k, in processed scans (default {d['horizon']})")
    p.add_argument("--alpha", type=float, default=None,
                   help=f"LP: defensive share in [0, 1), 0 = the paper's Eq. 10 (default {d['lookahead.alpha']:g})")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed in [0, 2**32) (runs reproduce bit for bit) (default 0)")
    p.add_argument("--config", help="JSON file {\"config\": {...}, \"params\": {...}}")
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="set any config field or parameter (dotted), e.g. motion.srr=0.05; repeatable")
    p.add_argument("--chunk-size", type=int, default=32,
                   help="steps per compiled chunk (progress granularity), >= 1 (default 32)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--no-cache", action="store_true",
                   help="do not use the persistent compilation cache (as JAXSLAM_CACHE_DIR=off)")
    p.add_argument("--out", default="out",
                   help="output folder (replaced atomically; stale outputs removed) (default %(default)s)")
    p.add_argument("--refine", action="store_true",
                   help="also localise every scan in the final map: trajectory_refined.txt (jaxslam.refine)")
    p.add_argument("--no-close-loops", action="store_true",
                   help="the filter alone: no pose graph, no loop search (by default the loops of the best "
                        "particle's path are closed: trajectory.txt holds the optimised poses, "
                        "trajectory_filter.txt the filter's, graph.npz the graph; jaxslam.graph)")
    p.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                   help="write a checkpoint (OUT.checkpoint.npz, beside the output folder) every N chunks "
                        "(N x --chunk-size processed scans). Without it, Ctrl-C or SIGTERM still writes one "
                        "at the next chunk boundary and exits (130 or 143); a finished run deletes it")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT.checkpoint.npz; it must be of the same log, seed, config, parameters "
                        "and --chunk-size (else refused); the outputs are those of an uninterrupted run")
    p.epilog = (f"Defaults: --proposal {d['proposal']}, {d['num_particles']} particles; a scan is processed after "
                f"{d['linear_update']:g} m or {d['angular_update']:g} rad of odometry (--set linear_update=..., "
                f"--set angular_update=...); the LP's L = {d['num_localizers']} localizers, horizon k = "
                f"{d['horizon']}, alpha = {d['lookahead.alpha']:g}. Compilations are cached in "
                f"$JAXSLAM_CACHE_DIR (default $XDG_CACHE_HOME/jaxslam/jax or ~/.cache/jaxslam/jax; "
                f"JAXSLAM_CACHE_DIR=off or --no-cache: no cache).")


def _cmd_map(args: argparse.Namespace) -> int:
    _log_reader_kwargs(args)  # a bad --laser-pose is refused first
    _check_filter_args(args)
    _check_at_least("--max-scans", args.max_scans, 1, "scans of the log to use")
    setup = build_setup_from_args(args, MAP_DEFAULTS)
    _check_out_folder(args.out)
    return _map_and_write(read_map_log(args), setup, args, source=str(args.log))


def _log_reader_kwargs(args: argparse.Namespace) -> dict:
    """``read_log``'s keyword arguments from ``jaxslam map``'s flags."""
    kwargs = {}
    if args.scan_topic:
        kwargs["scan_topic"] = args.scan_topic
    if args.odom_topic:
        kwargs["odom_topic"] = args.odom_topic
    if args.odometry:
        kwargs["odometry_source"] = args.odometry
    if args.odom_frame:
        kwargs["odom_frame"] = args.odom_frame
    if args.base_frame:
        kwargs["base_frame"] = args.base_frame
    if args.laser_pose is not None:
        kwargs["laser_pose"] = parse_laser_pose(args.laser_pose)
    return kwargs


def read_map_log(args: argparse.Namespace):
    """The log ``jaxslam map`` maps, from its parsed arguments (``make_parser``): read, cut to
    ``--max-scans`` and checked (:func:`jaxslam.laserlog.check_log`)."""
    from jaxslam.io import read_log
    from jaxslam.laserlog import check_log

    kwargs = _log_reader_kwargs(args)
    if not args.no_progress:
        print(f"reading {args.log} ...", file=sys.stderr, flush=True)
    log = read_log(args.log, **kwargs)
    if args.max_scans is not None:
        import numpy as np

        log = log.subset(np.arange(min(args.max_scans, log.num_scans)))
    return check_log(log)  # repeated timestamps (the last kept), dead scans, gaps: log.warnings


def parse_laser_pose(text: str) -> tuple[float, float, float]:
    """``"x,y,theta"`` (``--laser-pose``) -> three floats (:func:`jaxslam.io.rosbag.check_laser_pose`);
    anything else raises ``ConfigError``."""
    from jaxslam.io.rosbag import check_laser_pose

    try:
        return check_laser_pose(text.split(","))
    except ValueError:
        raise ConfigError(f"--laser-pose expects x,y,theta: three finite numbers (m, m, rad) separated by commas, "
                          f"e.g. 0.25,0,0.1 (a negative first one as --laser-pose=-0.25,0,0), got {text!r}") from None


MAP_DEFAULTS = {"proposal": "lp", "num_particles": 30}
"""``jaxslam map``'s defaults beyond the library's: the LP, which failed least in the 10-seed
robustness table (docs/results.md)."""


def checkpoint_path(out) -> Path:
    """Where a run with ``--out OUT`` keeps its checkpoint: ``OUT.checkpoint.npz`` beside the
    output folder (outside it: the folder is swapped in whole when the run ends)."""
    target = Path(os.path.abspath(os.fspath(out)))
    return target.with_name(target.name + ".checkpoint.npz")


def _format_gb(nbytes: float) -> str:
    gb = nbytes / 1e9
    return f"{gb:.0f}" if gb >= 10 else f"{gb:.1f}"


def _check_memory(log, config, settings, params) -> None:
    """Refuse (``ConfigError``) a run whose estimated memory (:func:`jaxslam.resources.estimate_run_bytes`)
    exceeds the machine's available memory; skipped where that cannot be read. The first pools
    grow with the first scan's footprint (:func:`jaxslam.rbpf.pool_size`): where even the widest
    footprint (the insertion's whole window) fits, that is enough; otherwise this log's first scan
    is measured (one particle's insertion), so that a wide first scan at large N is refused here
    rather than running out of memory in the run."""
    from jaxslam.rbpf import first_scan_tiles, prepare
    from jaxslam.resources import available_memory_bytes, estimate_run_bytes

    available = available_memory_bytes()
    if available is None:
        return
    widest = config.grid.window_tiles(config.max_insert_range, config.field_radius) ** 2
    need, how = estimate_run_bytes(config, log.num_beams, widest)
    if need > available:
        prepared, _, _ = prepare(log, config, settings)
        need, how = estimate_run_bytes(config, log.num_beams, first_scan_tiles(prepared, params, config))
    if need > available:
        lp = ", --localizers" if config.lookahead_steps else ""
        raise ConfigError(f"the run needs about {_format_gb(need)} GB ({how}) but {_format_gb(available)} GB are "
                          f"available; lower --particles{lp}, or a smaller --set map_extent=... (m), or a "
                          f"coarser --set resolution=... (m)")


def _check_disk(log, config, settings, out, checkpoints: bool) -> None:
    """Refuse (``ConfigError``) a run whose outputs (and checkpoints) would not fit on the disk."""
    from jaxslam.outputs import OutputError, check_free_space, expected_output_bytes
    from jaxslam.resources import map_cells, state_bytes

    need = expected_output_bytes(map_cells(log.odometry, config), log.num_scans,
                                 state_bytes(config) if checkpoints else 0)
    try:
        check_free_space(out, need)
    except OutputError as err:
        raise ConfigError(f"--out {err}") from None


def _run_identity(args, log, setup, source: str) -> dict:
    """What identifies a run for ``--resume`` (compared after a JSON round trip)."""
    from jaxslam.config import config_to_dict, params_to_dict

    config, settings, params = setup
    where = os.path.abspath(source) if os.path.exists(source) else source
    identity = {"seed": args.seed, "config": config_to_dict(config), "settings": config_to_dict(settings),
                "params": params_to_dict(params), "log": where, "scans_in_log": log.num_scans,
                "chunk_size": args.chunk_size}
    return json.loads(json.dumps(identity, sort_keys=True, default=str))


def _load_resume(path: Path, identity: dict):
    """The checkpoint's :class:`~jaxslam.slam.RunProgress` if it is of the run ``identity``, else ``ConfigError``."""
    from jaxslam.io.checkpoint import load_checkpoint

    if not path.is_file():
        raise ConfigError(f"--resume: no checkpoint at {path} (one is written when a run is interrupted, "
                          f"or with --checkpoint-every)")
    try:
        progress, saved = load_checkpoint(path)
    except (ValueError, OSError) as err:
        raise ConfigError(f"--resume: {err}") from None
    diffs = []
    for key in sorted(set(saved) | set(identity)):
        there, here = saved.get(key), identity.get(key)
        if isinstance(there, dict) and isinstance(here, dict):
            diffs += [f"{key}.{k}: {there.get(k)!r} there, {here.get(k)!r} here"
                      for k in sorted(set(there) | set(here)) if there.get(k) != here.get(k)]
        elif there != here:
            diffs.append(f"{key}: {there!r} there, {here!r} here")
    if diffs:
        raise ConfigError(f"--resume: {path} is the checkpoint of a different run ({'; '.join(diffs[:4])}"
                          f"{'; ...' if len(diffs) > 4 else ''}); rerun with the same settings, or without "
                          f"--resume to start over")
    return progress


class _StopRequest:
    """SIGINT / SIGTERM handlers that only note the signal (the host loop stops at the next chunk
    boundary; no KeyboardInterrupt is raised inside JAX). A second signal restores the default
    handlers, so a third one aborts at once."""

    def __init__(self):
        self.signum = None
        self._old = {}

    def _handle(self, signum, frame):
        if self.signum is not None:
            self.restore()
        self.signum = signum

    def __enter__(self):
        try:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        except ValueError:  # not the main thread: leave the signals alone
            self.restore()
        return self

    def restore(self):
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}

    def __exit__(self, *exc):
        self.restore()
        return False


def _warn_of_the_cache(args) -> None:
    """The compilation cache's warning (:func:`jaxslam.compile_cache.enable`), once the inputs
    have passed their checks (a refusal stays one line)."""
    if getattr(args, "cache_warning", None):
        print(f"jaxslam {args.command}: warning: {args.cache_warning}", file=sys.stderr, flush=True)
        args.cache_warning = None


def _map_and_write(log, setup, args, source: str, world=None) -> int:
    from jaxslam.io.checkpoint import save_checkpoint
    from jaxslam.rbpf import check_config_for_log
    from jaxslam.slam import RunInterrupted, run

    config, settings, params = setup

    check_config_for_log(log, config)
    _check_memory(log, config, settings, params)
    _check_disk(log, config, settings, args.out, bool(getattr(args, "checkpoint_every", None)))
    ckpt = checkpoint_path(args.out)
    identity = _run_identity(args, log, setup, source)
    resume = _load_resume(ckpt, identity) if getattr(args, "resume", False) else None
    every = getattr(args, "checkpoint_every", None)
    _warn_of_the_cache(args)

    import jax

    with _StopRequest() as stop:
        chunks = [0]

        def on_chunk(progress) -> bool:
            chunks[0] += 1
            if stop.signum is not None or (every and chunks[0] % every == 0):
                save_checkpoint(ckpt, progress, identity)
            return stop.signum is not None

        try:
            from jaxslam.graph import ClosureConfig

            close = None if getattr(args, "no_close_loops", False) else ClosureConfig()
            result = run(jax.random.key(args.seed), log, config, params, settings, chunk_size=args.chunk_size,
                         progress=not args.no_progress, on_chunk=on_chunk, resume=resume, close_loops=close)
        except RunInterrupted as err:
            print(f"jaxslam {args.command}: interrupted at step {err.steps_done} of {err.num_steps} "
                  f"(checkpoint {ckpt}); resume with --resume", file=sys.stderr)
            return 128 + int(stop.signum)
        summary = write_map_outputs(args.out, log, result, params, args.seed, source,
                                    refine=getattr(args, "refine", False), world=world)
        if ckpt.exists():
            ckpt.unlink()
    t = summary["timings"]
    print(f"processed {summary['scans_processed']} of {summary['scans_in_log']} scans in {_fmt(t['total'])} s "
          f"(compile {_fmt(t['compile'])} s, real-time factor {_fmt(t['real_time_factor'])}); "
          f"outputs in {args.out}/")
    for warning in summary["warnings"]:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


def write_map_outputs(out, log, result, params, seed: int, source: str, refine: bool = False, world=None) -> dict:
    """``jaxslam map``'s outputs of one finished run (:func:`jaxslam.outputs.write_slam_outputs`);
    with ``refine``, every scan first localised in the final map (``trajectory_refined.txt``,
    :mod:`jaxslam.refine`). Returns the summary as written."""
    from jaxslam.outputs import write_slam_outputs

    refined, refine_seconds = None, None
    if refine:
        import time

        from jaxslam.refine import refine_trajectory

        from jaxslam.rbpf import grid_to_world

        # In the filter's local frame (result.frame_offset subtracted), as the map was built; on
        # the closed map from the closed trajectory where loops were closed.
        closure = result.closure
        if closure is not None and closure.num_loops:
            _, field, grid = result.closed_map(log, params)
            grid, start = grid_to_world(grid, -result.frame_offset), closure.trajectory
        else:
            (_, field, grid), start = result.dense_map(local=True), result.trajectory
        t0 = time.perf_counter()
        refined = refine_trajectory(grid, field, result.to_local(start), log.ranges, log.sensor,
                                    params, result.config, odometry=result.to_local(log.odometry))
        refined = refined._replace(poses=result.to_world(refined.poses),
                                   matched_poses=result.to_world(refined.matched_poses))
        refine_seconds = time.perf_counter() - t0
    return write_slam_outputs(out, log, result, params, seed=seed, source=source, world=world, refined=refined,
                              refine_seconds=refine_seconds)


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.1f}"


DEMO_DEFAULTS = {"proposal": "smp", "num_particles": 20, "linear_update": 0.25, "angular_update": 0.25,
                 "max_insert_range": 10.0, "beam_stride": 1}
"""``jaxslam demo``'s defaults: the simulated office is small, so scans are processed more often
than the library's 0.5 m / 0.25 rad, and every beam is used (its 10 m laser sees little along the
20 m corridor)."""
DEMO_PROPOSAL_NOTE = (", not map's lp: the demo is the first command to run and should take about a minute; "
                      "--proposal lp takes about twice as long on 2 CPU cores")
"""Why the demo keeps the SMP (its ``--help``): measured on the project's 2-core machine with
other jobs running, the demo took 58 s with the SMP and 2 min 15 s with the LP (user CPU time
31 s against 50 s), without the compilation cache."""


def _cmd_demo(args: argparse.Namespace) -> int:
    import jax

    from jaxslam.sim import office_scenario

    _check_filter_args(args)
    _check_at_least("--scans", args.scans, 2, "scans along the simulated path")
    setup = build_setup_from_args(args, DEMO_DEFAULTS)
    _check_out_folder(args.out)
    if not args.no_progress:
        print(f"simulating the office ({args.scans} scans) ...", file=sys.stderr, flush=True)
    scenario = office_scenario(jax.random.key(args.seed), num_scans=args.scans)
    status = _map_and_write(scenario.log, setup, args, source="simulated office (jaxslam.sim.office_scenario)",
                            world=scenario.world)
    if status == 0:
        summary = json.loads((Path(args.out) / "summary.json").read_text())
        print(_ground_truth_error_line(summary["ground_truth_error"]))
        closure = summary.get("closure")
        if closure is not None:
            print(f"loop closure: {closure['loops_kept']} loops kept of {closure['candidates']} candidates; closed path "
                  f"mean {closure['ground_truth_mean_m']:.3f} m (summary.json: closure; graph.npz)")
    return status


def _ground_truth_error_line(error: dict) -> str:
    """The demo's line on its ``summary.json`` ``ground_truth_error`` (position errors, m)."""
    return (f"ground truth error at the {error['scans']} processed scans: best path mean "
            f"{error['best_path_mean_m']:.3f} m, max {error['best_path_max_m']:.3f} m; odometry mean "
            f"{error['odometry_mean_m']:.3f} m, max {error['odometry_max_m']:.3f} m (summary.json: ground_truth_error)")


def _cmd_eval(args: argparse.Namespace) -> int:
    from jaxslam.io import read_relations, read_trajectory
    from jaxslam.metrics import relation_error
    from jaxslam.outputs import OutputError, check_output_file, strict_json_values, write_file_atomic

    if args.out:
        try:
            check_output_file(args.out)
        except OutputError as err:
            raise ConfigError(f"--out {err}") from None
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        timestamps, poses = read_trajectory(args.trajectory)  # repeated timestamps: the last kept, warned
    found = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    relations = read_relations(args.relations)
    err = relation_error(timestamps, poses, relations)
    table = err.to_dict()
    for warning in found:
        print(f"warning: {warning}", file=sys.stderr)
    print(f"{'relations':>22}: {table.get('count')}")
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


def _cmd_diagnose(args: argparse.Namespace) -> int:
    """Per-step diagnosis of a ``jaxslam map`` run: diagnosis.json and diagnosis.png."""
    from jaxslam.diagnose import diagnose, plot_diagnosis, read_step_record
    from jaxslam.io import read_relations, read_trajectory
    from jaxslam.outputs import strict_json_values, write_file_atomic

    run = Path(args.run_dir)
    out = Path(args.out) if args.out else run
    record = read_step_record(run)  # before any work: a clear error for a folder without it
    relations = read_relations(args.relations) if args.relations else None
    # The particles' record is the filter's: compare it with the filter's own trajectory.
    filter_trajectory = run / ("trajectory_filter.txt" if (run / "trajectory_filter.txt").exists() else "trajectory.txt")
    trajectory = read_trajectory(filter_trajectory) if relations is not None else None
    result = diagnose(record, trajectory, relations)
    out.mkdir(parents=True, exist_ok=True)
    values, nulled = strict_json_values(result)
    if nulled:
        values["null_reasons"] = nulled
    write_file_atomic(out / "diagnosis.json", json.dumps(values, allow_nan=False))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plot_diagnosis(result, record, title=str(run))
    try:
        fig.savefig(out / "diagnosis.png", dpi=120)
    finally:
        plt.close(fig)
    written = [out / "diagnosis.json", out / "diagnosis.png"]
    if (run / "graph.npz").exists():
        written.append(_draw_graph(run, out))
    summary = result["summary"]
    for key, value in summary.items():
        print(f"{key:>40}: {value}")
    for name, events in result["events"].items():
        print(name.replace("_", " ") + ":")
        for event in events:
            print("   " + ", ".join(f"{k} {v:.4g}" for k, v in event.items()))
    print("written to " + ", ".join(str(path) for path in written))
    return 0


def _draw_graph(run: Path, out: Path) -> Path:
    """graph.png: a run's pose graph (graph.npz) drawn over its map."""
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxslam.graph import load_graph, plot_graph
    from jaxslam.io.maps import read_map
    from jaxslam.plotting import plot_map

    graph = load_graph(run / "graph.npz")
    fig, ax = plt.subplots(figsize=(9, 9))
    try:
        if (run / "map.yaml").exists():
            occupancy, spec = read_map(run / "map.yaml")
            occupancy = np.clip(occupancy, 1e-3, 1 - 1e-3)
            plot_map(ax, np.log(occupancy / (1 - occupancy)), spec)  # plot_map draws log-odds
        plot_graph(ax, graph)
        kept = int((graph["loop_refused"] == "").sum())
        ax.set_title(f"{run}: {kept} loops kept of {graph['loop_refused'].size} candidates")
        fig.savefig(out / "graph.png", dpi=120)
    finally:
        plt.close(fig)
    return out / "graph.png"


def _cmd_doors(args: argparse.Namespace) -> int:
    """One door scenario, one filter: figures and a JSON summary."""
    import dataclasses
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxslam.geometry import pose_errors
    from jaxslam.localization import doors, mcl
    from jaxslam.localization.plotting import figure_run, plot_door_map, plot_position_errors, save_figures
    from jaxslam.sim.door_worlds import SCENARIOS, filter_settings

    if args.particles < 1:
        raise ConfigError(f"--particles must be >= 1, got {args.particles}")
    check_seed(args.seed)
    _check_out_folder(args.out)
    _warn_of_the_cache(args)
    t0 = time.time()
    scenario = SCENARIOS[args.scenario](jax.random.key(args.seed))
    config, params = filter_settings(scenario, args.particles)
    key = jax.random.key((10_000 + args.seed) % SEED_LIMIT)
    k_init, k_run = jax.random.split(key)  # as experiments/door_harness.py: the same start for every filter
    start = mcl.init_global(k_init, jnp.asarray(scenario.start_regions), config.mcl, tuple(scenario.heading_range))
    inputs, door_map, sensor = mcl.log_inputs(scenario.log), scenario.door_map, scenario.log.sensor
    if args.filter_kind == "static":  # MCL on the map as given
        segments, active = doors.static_segments(door_map)
        mean_pose = mcl.filter(k_run, start, inputs, segments, sensor, params.mcl_params(), config.mcl,
                               active).info.mean_pose
        final_belief = np.asarray(door_map.initial_open >= 0.5, np.float32)
    else:  # the door filter (memoryless: every door 50% open before every update)
        info = doors.filter(k_run, doors.init(start, door_map), inputs, door_map, sensor, params,
                            dataclasses.replace(config, memory=args.filter_kind == "hybrid")).info
        mean_pose = info.mcl.mean_pose
        final_belief = np.asarray(info.door_belief[-1])
    position_error, heading_error = (np.asarray(e) for e in
                                     pose_errors(mean_pose, jnp.asarray(scenario.true_poses, jnp.float32)))
    result = {"scenario": args.scenario, "filter": args.filter_kind, "seed": args.seed, "particles": args.particles,
              "final_position_error_m": float(position_error[-1]),
              "final_heading_error_deg": float(np.rad2deg(heading_error[-1])),
              "final_door_belief": dict(zip(scenario.door_names, np.round(final_belief, 4).tolist())),
              "true_door_open_final": dict(zip(scenario.door_names, scenario.true_door_open[-1].tolist()))}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    errors = {args.filter_kind: position_error[None]}
    if args.filter_kind == "static":
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(13, 4))
        plot_door_map(axes[0], scenario, final_belief, "static MCL: the map as given", path=scenario.true_poses)
        plot_position_errors(axes[1], errors)
        fig.tight_layout()
        fig.savefig(out / "static.png", dpi=110)
        plt.close(fig)
        figures = [str(out / "static.png")]
    else:
        infos, history = figure_run(key, scenario, config, params, memory=args.filter_kind == "hybrid")
        figures = save_figures(out, scenario, infos, history, params, errors)
    result["figures"] = figures
    result["seconds"] = round(time.time() - t0, 1)
    (out / "summary.json").write_text(json.dumps(result, indent=2))
    print(f"{args.scenario} / {args.filter_kind}: final position error {result['final_position_error_m']:.3f} m, "
          f"heading error {result['final_heading_error_deg']:.2f} deg; wrote {out / 'summary.json'}")
    return 0


def make_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="jaxslam", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p_map = sub.add_parser("map", help="build a map from a log (ROS 1/2 bag or CARMEN log)")
    p_map.add_argument("log", help="path of the log; the format is read from the file")
    p_map.add_argument("--scan-topic", help="bag topic of sensor_msgs/LaserScan (default /scan)")
    p_map.add_argument("--odom-topic", help="bag topic of nav_msgs/Odometry, or of transforms read as /tf is "
                                            "(default /odom); where the bag has none, the odometry is the "
                                            "--odom-frame -> --base-frame transform in /tf")
    p_map.add_argument("--odom-frame", help="bags: the odometry's frame in /tf, used where the bag has no odometry "
                                            "topic (default odom)")
    p_map.add_argument("--base-frame", help="bags: the robot's frame (default base_link): its pose in --odom-frame "
                                            "is the /tf odometry, and the laser's mounting is read from the "
                                            "transform base frame -> the scans' frame in /tf_static")
    p_map.add_argument("--laser-pose", metavar="X,Y,THETA",
                       help="the laser's mounting on the robot (m, m, rad), instead of the log's (bags: /tf_static; "
                            "CARMEN: ROBOTLASER1 lines), e.g. 0.25,0,0.1; a negative first value as "
                            "--laser-pose=-0.25,0,0")
    p_map.add_argument("--odometry", choices=("laser", "odom"),
                       help="CARMEN logs: the odometry inside the laser lines (default) or the ODOM lines "
                            "(interpolated at the laser timestamps); the two are compared and a disagreement warned of")
    p_map.add_argument("--max-scans", type=int, help="use only the first N scans of the log")
    _add_filter_options(p_map, MAP_DEFAULTS)
    p_map.set_defaults(func=_cmd_map)

    p_demo = sub.add_parser("demo", help="map a simulated office (no download needed)")
    p_demo.add_argument("--scans", type=int, default=500, help="scans along the simulated path (88 m)")
    _add_filter_options(p_demo, DEMO_DEFAULTS, DEMO_PROPOSAL_NOTE)
    p_demo.set_defaults(func=_cmd_demo, out="out/demo")

    p_eval = sub.add_parser("eval", help="relation error (Kuemmerle et al. 2009) of a trajectory")
    p_eval.add_argument("trajectory", help="trajectory text file: 'timestamp x y theta' per line")
    p_eval.add_argument("relations", help="relations file: 't1 t2 x y z roll pitch yaw' per line")
    p_eval.add_argument("--out", help="write the table as JSON to this file (not a folder)")
    p_eval.set_defaults(func=_cmd_eval)

    p_diag = sub.add_parser("diagnose", help="what happened in a map run, step by step (ESS, lineages, "
                                             "corrections, relation error over time)")
    p_diag.add_argument("run_dir", help="the output folder of `jaxslam map` (it holds steps.npz)")
    p_diag.add_argument("relations", nargs="?", help="relations file of the log, for the error over time")
    p_diag.add_argument("--out", help="folder for diagnosis.json and diagnosis.png (default: RUN_DIR)")
    p_diag.set_defaults(func=_cmd_diagnose)

    p_doors = sub.add_parser("doors", help="localization with door-state estimation (Avots et al. 2002)")
    p_doors.add_argument("--scenario", choices=("corridors", "office", "patrol"), default="corridors",
                         help="corridors: two corridors told apart only by their doors (Fig. 2); "
                              "office: doors closed on the way out, opened, then the return pass (Fig. 1); "
                              "patrol: ten round trips while the doors open and close at random")
    p_doors.add_argument("--particles", type=int, default=1000)
    p_doors.add_argument("--seed", type=int, default=0, help="seed of the simulated log and of the filter")
    p_doors.add_argument("--filter", dest="filter_kind", choices=("hybrid", "static", "memoryless"),
                         default="hybrid")
    p_doors.add_argument("--out", default="out/doors", help="folder for summary.json and the figures")
    p_doors.add_argument("--no-cache", action="store_true",
                         help="do not use the persistent compilation cache (as JAXSLAM_CACHE_DIR=off)")
    p_doors.set_defaults(func=_cmd_doors)
    return parser


def main(argv: list[str] | None = None) -> int:
    from jaxslam.laserlog import LogError

    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        if hasattr(args, "no_cache"):  # the commands that compile: the cache on before the first compilation
            from jaxslam import compile_cache

            _, args.cache_warning = compile_cache.enable(disabled=args.no_cache)
        return args.func(args)
    except KeyboardInterrupt:  # Ctrl-C outside a filter run (which stops at a chunk boundary instead)
        print(f"jaxslam {args.command}: interrupted", file=sys.stderr)
        return 130
    except (ConfigError, LogError, ValueError, OSError) as err:  # OSError: FileNotFoundError, PermissionError, ...
        message = " ".join(str(err).split()) or type(err).__name__
        print(f"jaxslam {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
