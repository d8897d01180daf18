"""``jaxslam map``: the log read and checked, the memory and disk checks, the run (checkpointed,
resumable, stopped at a chunk boundary by Ctrl-C or SIGTERM) and its outputs
(:func:`write_map_outputs`)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import jax
import numpy as np

from jaxslam.checkpoint import save_checkpoint
from jaxslam.cli.checkpoints import _load_resume, _run_identity, _StopRequest, checkpoint_path
from jaxslam.cli.common import (_check_at_least, _check_filter_args, _check_out_folder, _warn_of_the_cache,
                                build_setup_from_args)
from jaxslam.config import ConfigError
from jaxslam.io import read_log
from jaxslam.io.files import OutputError, check_free_space
from jaxslam.io.rosbag import check_laser_pose
from jaxslam.laserlog import check_log, estimate_odometry_lead, with_odometry_lead
from jaxslam.proposals import PROPOSALS
from jaxslam.outputs import expected_output_bytes, write_slam_outputs
from jaxslam.rbpf import check_config_for_log, first_scan_tiles, prepare
from jaxslam.pipeline import finish_mapping, map_log
from jaxslam.resources import available_memory_bytes, estimate_run_bytes, map_cells, state_bytes
from jaxslam.slam import RunInterrupted, SlamResult


def _cmd_map(args: argparse.Namespace) -> int:
    _log_reader_kwargs(args)  # a bad --laser-pose is refused first
    args.odometry_lead = parse_odometry_lead(getattr(args, "odometry_lead", None))  # ... and a bad lead
    _check_filter_args(args)
    _check_at_least("--max-scans", args.max_scans, 1, "scans of the log to use")
    setup = build_setup_from_args(args, MAP_DEFAULTS)
    _check_out_folder(args.out)
    started = time.perf_counter()  # the user's wait: from the log's reading to the last output
    log = read_map_log(args)
    return _map_and_write(log, setup, args, source=str(args.log), started=started,
                          stages={"read": time.perf_counter() - started})


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
    kwargs = _log_reader_kwargs(args)
    if not args.no_progress:
        print(f"reading {args.log} ...", file=sys.stderr, flush=True)
    log = read_log(args.log, **kwargs)
    if args.max_scans is not None:
        log = log.subset(np.arange(min(args.max_scans, log.num_scans)))
    log = check_log(log)  # repeated timestamps (the last kept), dead scans, gaps: log.warnings
    lead = getattr(args, "odometry_lead", None)
    if lead == "auto":
        measured = estimate_odometry_lead(log)
        lead = measured.lead
        print(f"odometry lead: {lead:.3f} s, measured on {measured.num_pairs} turning pairs of scans",
              file=sys.stderr, flush=True)
    return with_odometry_lead(log, float(lead)) if lead is not None else log


def parse_odometry_lead(text: str | None) -> str | float | None:
    """``--odometry-lead``: ``auto``, a finite number of seconds, or None; anything else is a
    :class:`ConfigError` before the log is read."""
    if text is None or text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value):
        raise ConfigError(f"--odometry-lead {text!r}: give auto or a number of seconds, e.g. 0.14")
    return value


def parse_laser_pose(text: str) -> tuple[float, float, float]:
    """``"x,y,theta"`` (``--laser-pose``) -> three floats (:func:`jaxslam.io.rosbag.check_laser_pose`);
    anything else raises ``ConfigError``."""
    try:
        return check_laser_pose(text.split(","))
    except ValueError:
        raise ConfigError(f"--laser-pose expects x,y,theta: three finite numbers (m, m, rad) separated by commas, "
                          f"e.g. 0.25,0,0.1 (a negative first one as --laser-pose=-0.25,0,0), got {text!r}") from None


MAP_DEFAULTS: dict = {}
"""``jaxslam map``'s defaults beyond the library's: none. The command runs
:class:`~jaxslam.config.SlamConfig`'s defaults, one set for the library and the command: the SMP
with 30 particles, the proposal every headline figure in the README was measured with (issue 84:
on Intel the SMP and the LP both refine to 0.029 m, the SMP in 237 s of wall time against 338 s;
on a log kept back from tuning the SMP refines to 0.29-0.32 m against the LP's 0.35-0.37 m).
``--proposal lp`` runs the look-ahead proposal, with its own settings' defaults (100 localizers,
a horizon of 5: ``--localizers``, ``--horizon``)."""


def _format_gb(nbytes: float) -> str:
    gb = nbytes / 1e9
    return f"{gb:.0f}" if gb >= 10 else f"{gb:.1f}"


def _check_memory(log, config, settings, params):
    """Refuse (``ConfigError``) a run whose estimated memory (:func:`jaxslam.resources.estimate_run_bytes`)
    exceeds the machine's available memory; skipped where that cannot be read. The first pools
    grow with the first scan's footprint (:func:`jaxslam.rbpf.pool_size`). Where even the
    smallest footprint (one tile) does not fit, the run is refused at once (no preparation, no
    compilation: a huge ``max_insert_range`` is refused on the estimate alone); where the widest (the insertion's whole
    window) fits, that is enough; otherwise this log's first scan is measured (one particle's
    insertion), so that a wide first scan at large N is refused here rather than running out of
    memory in the run. Returns :func:`jaxslam.rbpf.prepare`'s output where it prepared the log (the
    run then takes it, so the log is prepared once), else None."""
    available = available_memory_bytes()
    if available is None:
        return None
    prepared = None
    need, how = estimate_run_bytes(config, log.num_beams, 1)
    if need <= available:
        widest = config.grid.window_tiles(config.max_insert_range, config.field_radius) ** 2
        need, how = estimate_run_bytes(config, log.num_beams, widest)
        if need > available:
            prepared = prepare(log, config, settings)
            need, how = estimate_run_bytes(config, log.num_beams, first_scan_tiles(prepared[0], params, config))
    if need > available:
        lp = "".join(f", {flag.flag}" for flag in _memory_flags(config, log.num_beams))
        raise ConfigError(f"the run needs about {_format_gb(need)} GB ({how}) but {_format_gb(available)} GB are "
                          f"available; lower --particles{lp}, or a smaller --set map_extent=... (m), or a "
                          f"coarser --set resolution=... (m)")
    return prepared


def _memory_flags(config, num_beams: int) -> list:
    """The proposal's int flags whose setting, halved, lowers the memory its row estimates."""
    proposal = PROPOSALS[config.proposal]
    need, _ = proposal.memory_fn(config, num_beams)
    out = []
    for flag in proposal.flags:
        if flag.type is int and "." not in flag.name:
            halved = dataclasses.replace(config, **{flag.name: max(getattr(config, flag.name) // 2, flag.minimum or 0)})
            if proposal.memory_fn(halved, num_beams)[0] < need:
                out.append(flag)
    return out


def _check_disk(log, config, settings, out, checkpoints: bool) -> None:
    """Refuse (``ConfigError``) a run whose outputs (and checkpoints) would not fit on the disk."""
    need = expected_output_bytes(map_cells(log.odometry, config), log.num_scans,
                                 state_bytes(config) if checkpoints else 0)
    try:
        check_free_space(out, need)
    except OutputError as err:
        raise ConfigError(f"--out {err}") from None


def _map_and_write(log, setup, args, source: str, world=None, started: float | None = None,
                   stages: dict | None = None) -> int:
    """Check, map (:func:`jaxslam.pipeline.map_log`, checkpointed and resumable) and write one
    log's outputs. ``started``: ``time.perf_counter()`` when the user's wait began; ``stages``:
    the seconds of what came before (``read``), for ``summary.json``'s ``timings``."""
    config, settings, params = setup
    started = time.perf_counter() if started is None else started
    t_checks = time.perf_counter()
    check_config_for_log(log, config)
    prepared = _check_memory(log, config, settings, params)
    _check_disk(log, config, settings, args.out, bool(getattr(args, "checkpoint_every", None)))
    ckpt = checkpoint_path(args.out)
    identity = _run_identity(args, log, setup, source)
    resume = _load_resume(ckpt, identity) if getattr(args, "resume", False) else None
    every = getattr(args, "checkpoint_every", None)
    _warn_of_the_cache(args)
    stages = dict(stages or {}, checks=time.perf_counter() - t_checks)

    with _StopRequest() as stop:
        chunks = [0]

        def on_chunk(progress) -> bool:
            chunks[0] += 1
            if stop.signum is not None or (every and chunks[0] % every == 0):
                save_checkpoint(ckpt, progress, identity)
            return stop.signum is not None

        try:
            mapped = map_log(jax.random.key(args.seed), log, config, params, settings,
                             close_loops=not getattr(args, "no_close_loops", False),
                             refine=getattr(args, "refine", True), progress=not args.no_progress,
                             chunk_size=args.chunk_size, on_chunk=on_chunk, resume=resume, prepared=prepared)
        except RunInterrupted as err:
            print(f"jaxslam {args.command}: interrupted at step {err.steps_done} of {err.num_steps} "
                  f"(checkpoint {ckpt}); resume with --resume", file=sys.stderr)
            return 128 + int(stop.signum)
        summary = write_map_outputs(args.out, log, mapped, params, args.seed, source, world=world,
                                    timings=stages, started=started)
        if ckpt.exists():
            ckpt.unlink()
    t = summary["timings"]
    print(f"processed {summary['scans_processed']} of {summary['scans_in_log']} scans in {_fmt(t['total'])} s "
          f"(compile {_fmt(t['compile'])} s, real-time factor {_fmt(t['real_time_factor'])}); "
          f"{_fmt(t.get('total_wall'))} s in all; outputs in {args.out}/")
    for warning in summary["warnings"]:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


def write_map_outputs(out, log, mapped, params, seed: int, source: str, refine: bool = False, world=None,
                      timings: dict | None = None, started: float | None = None) -> dict:
    """``jaxslam map``'s outputs of one finished run: :func:`jaxslam.outputs.write_slam_outputs` of
    ``mapped``, what :func:`jaxslam.pipeline.map_log` returned (``timings``, ``started``: as
    there). A :class:`~jaxslam.slam.SlamResult` (a filter run elsewhere, with its closure if any) is
    first finished by :func:`jaxslam.pipeline.finish_mapping` (the map drawn again; with
    ``refine``, the refinement). Returns the summary as written."""
    if isinstance(mapped, SlamResult):
        mapped = finish_mapping(log, mapped, params, refine=refine)
    return write_slam_outputs(out, log, mapped, params, seed=seed, source=source, world=world, timings=timings,
                              started=started)


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.1f}"
