"""The ``jaxslam`` command: ``map``, ``demo``, ``eval``, ``diagnose``, ``doors`` and ``localize``.

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
written atomically (:func:`jaxslam.io.files.publish_folder`).
"""

from __future__ import annotations

import argparse
import sys

from jaxslam import compile_cache
from jaxslam.cli.checkpoints import checkpoint_path
from jaxslam.cli.common import (SEED_LIMIT, _add_filter_options, _Parser, build_setup_from_args, check_seed,
                                parse_assignments, read_config_file)
from jaxslam.cli.demo import DEMO_DEFAULTS, DEMO_PROPOSAL_NOTE, _cmd_demo
from jaxslam.cli.doors import _cmd_doors
from jaxslam.cli.evaluate import _cmd_diagnose, _cmd_eval
from jaxslam.cli.localize import add_localize_options
from jaxslam.cli.map import MAP_DEFAULTS, _cmd_map, parse_laser_pose, read_map_log, write_map_outputs
from jaxslam.config import ConfigError
from jaxslam.laserlog import LogError

__all__ = [
    "DEMO_DEFAULTS", "DEMO_PROPOSAL_NOTE", "MAP_DEFAULTS", "SEED_LIMIT", "build_setup_from_args", "check_seed",
    "checkpoint_path", "main", "make_parser", "parse_assignments", "parse_laser_pose", "read_config_file",
    "read_map_log", "write_map_outputs",
]


LOG_CLOCK_HELP = ("the log the trajectory came from, for relations written on another clock (a converter rewrote "
                  "the log's timestamps, as MIT Killian's bag): each relation timestamp is found among its scans by "
                  "the time gaps and the odometry")


COMMAND_SUMMARIES = {
    "map": "build a map from a log (ROS 1/2 bag or CARMEN log)",
    "demo": "map a simulated office (no download needed) and report the error against its ground truth",
    "eval": "relation error (Kuemmerle et al. 2009) of a trajectory",
    "diagnose": "what happened in a map run, step by step (ESS, lineages, corrections, relation error over time); "
                "in a closed run, the returns the closure missed and why",
    "doors": "localization with door-state estimation (Avots et al. 2002) in a simulated world",
    "localize": "Monte Carlo localization of a log in a saved map (map.yaml), tracked from a pose or global",
}
"""Each command's one line: its entry in ``jaxslam --help`` and the description of its own ``--help``."""

DESCRIPTION = ("Particle filters for robot SLAM and localization in JAX: map a log (map) or a simulated office "
               "(demo), score a trajectory against relations (eval), look into a map run (diagnose), localize "
               "with door-state estimation (doors), localize a log in a saved map (localize).")
"""``jaxslam --help``'s description, in plain words: the module docstring above is RST, which a
terminal would print with its markup."""

EPILOG = ("map and demo set every config field, run setting and parameter by name: --set NAME=VALUE (dotted names "
          "for parameters, e.g. --set motion.srr=0.05 --set linear_update=0.5) or a JSON file, --config FILE "
          "holding {\"config\": {...}, \"params\": {...}}. Later wins: the command's defaults, the config file, "
          "the dedicated flags (when given), --set. The filter commands cache their compiled code in "
          "$JAXSLAM_CACHE_DIR (default $XDG_CACHE_HOME/jaxslam/jax or ~/.cache/jaxslam/jax; off or --no-cache: "
          "no cache). A refused input is one line on stderr, jaxslam COMMAND: error: ..., with exit code 2, "
          "before any work.")
"""``jaxslam --help``'s epilog: the module docstring's precedence, cache and refusals, without markup."""


def make_parser() -> argparse.ArgumentParser:
    """The ``jaxslam`` parser and its subcommands (each command's function under ``func``)."""
    parser = _Parser(prog="jaxslam", description=DESCRIPTION, epilog=EPILOG)
    sub = parser.add_subparsers(title="commands", dest="command", required=True, metavar="COMMAND",
                                help="jaxslam COMMAND --help lists the command's options")

    def add_command(name: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=COMMAND_SUMMARIES[name], description=COMMAND_SUMMARIES[name])

    p_map = add_command("map")
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
    p_map.add_argument("--odometry-lead", metavar="auto|SECONDS",
                       help="read the odometry this many seconds earlier at every scan: where it runs ahead of the "
                            "laser (MIT Killian's bag: 0.14 s); auto measures it from the log's own scans at turns. "
                            "Default: the odometry as recorded")
    _add_filter_options(p_map, MAP_DEFAULTS)
    p_map.set_defaults(func=_cmd_map)

    p_demo = add_command("demo")
    p_demo.add_argument("--scans", type=int, default=500,
                        help="scans along the simulated path (88 m) (default %(default)s)")
    _add_filter_options(p_demo, DEMO_DEFAULTS, DEMO_PROPOSAL_NOTE)
    p_demo.set_defaults(func=_cmd_demo, out="out/demo")

    p_eval = add_command("eval")
    p_eval.add_argument("trajectory", help="trajectory text file: 'timestamp x y theta' per line")
    p_eval.add_argument("relations", help="relations file: 't1 t2 x y z roll pitch yaw' per line")
    p_eval.add_argument("--out", help="write the table as JSON to this file (not a folder)")
    p_eval.add_argument("--log", help=LOG_CLOCK_HELP)
    p_eval.add_argument("--scans", metavar="LOG",
                        help="the log whose scans say whose error it is: for each relation at most 60 s long on "
                             "which the trajectory is more than 0.1 m off, which motion (the relation's or the "
                             "trajectory's) lays its two scans over each other better")
    p_eval.set_defaults(func=_cmd_eval)

    p_diag = add_command("diagnose")
    p_diag.add_argument("run_dir", help="the output folder of jaxslam map (it holds steps.npz)")
    p_diag.add_argument("relations", nargs="?", help="relations file of the log, for the error over time")
    p_diag.add_argument("--log", help=LOG_CLOCK_HELP)
    p_diag.add_argument("--out", help="folder for diagnosis.json and diagnosis.png (default: RUN_DIR)")
    p_diag.set_defaults(func=_cmd_diagnose)

    _add_doors_options(add_command("doors"))
    add_localize_options(add_command("localize"))
    return parser


def _add_doors_options(p_doors: argparse.ArgumentParser) -> None:
    """``jaxslam doors``' options: the scenario, the filter and their sizes."""
    p_doors.add_argument("--scenario", choices=("corridors", "office", "patrol"), default="corridors",
                         help="corridors: two corridors told apart only by their doors (Fig. 2); "
                              "office: doors closed on the way out, opened, then the return pass (Fig. 1); "
                              "patrol: ten round trips while the doors open and close at random "
                              "(default %(default)s)")
    p_doors.add_argument("--particles", type=int, default=1000,
                         help="number of MCL particles, >= 1 (default %(default)s)")
    p_doors.add_argument("--seed", type=int, default=0,
                         help="seed of the simulated log and of the filter (default %(default)s)")
    p_doors.add_argument("--filter", dest="filter_kind", choices=("hybrid", "static", "memoryless"),
                         default="hybrid",
                         help="hybrid: the door filter, each particle's door beliefs kept from scan to scan; "
                              "memoryless: every door 50%% open again before each update; static: MCL on the map "
                              "as given, each door fixed open or closed as the map has it (default %(default)s)")
    p_doors.add_argument("--out", default="out/doors",
                         help="folder for summary.json and the figures (default %(default)s)")
    p_doors.add_argument("--no-cache", action="store_true",
                         help="do not use the persistent compilation cache (as JAXSLAM_CACHE_DIR=off)")
    p_doors.set_defaults(func=_cmd_doors)


def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        if hasattr(args, "no_cache"):  # the commands that compile: the cache on before the first compilation
            _, args.cache_warning = compile_cache.enable(disabled=args.no_cache)
        return args.func(args)
    except KeyboardInterrupt:  # Ctrl-C outside a filter run (which stops at a chunk boundary instead)
        print(f"jaxslam {args.command}: interrupted", file=sys.stderr)
        return 130
    except (ConfigError, LogError, ValueError, OSError) as err:  # OSError: FileNotFoundError, PermissionError, ...
        message = " ".join(str(err).split()) or type(err).__name__
        print(f"jaxslam {args.command}: error: {message}", file=sys.stderr)
        return 2
