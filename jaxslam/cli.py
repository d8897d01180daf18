"""The ``jaxslam`` command: ``map``, ``demo``, ``eval`` and ``doors``.

Every field of :class:`~jaxslam.config.SlamConfig` and every parameter of
:class:`~jaxslam.config.SlamParams` can be set with ``--set NAME=VALUE`` (dotted
names for parameters: ``--set motion.srr=0.05 --set linear_update=0.5``) or
from a JSON config file (``--config FILE`` holding ``{"config": {...},
"params": {...}}``); the common ones also have their own flags.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from jaxslam.config import ConfigError


def parse_assignments(items: list[str]) -> dict[str, str]:
    """``["a.b=1", ...]`` (the ``--set`` flags) -> ``{"a.b": "1"}``; a malformed item raises ``ConfigError``."""
    out = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        out[name.strip()] = value.strip()
    return out


def build_config_and_params(args: argparse.Namespace):
    """Merge defaults, the config file, dedicated flags and ``--set`` (later wins)."""
    import dataclasses

    from jaxslam.config import SlamConfig, config_from_dict, params_from_dict

    config_fields = {f.name for f in dataclasses.fields(SlamConfig)}
    config_values: dict = {}
    param_values: dict = {}
    if getattr(args, "config", None):
        path = Path(args.config)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ConfigError(f"{path}: cannot read config file: {err}") from None
        if not isinstance(data, dict) or set(data) - {"config", "params"}:
            raise ConfigError(f"{path}: expected a JSON object with keys 'config' and/or 'params'")
        config_values.update(data.get("config", {}))
        param_values.update(data.get("params", {}))
    flags = {
        "proposal": args.proposal, "num_particles": args.particles,
        "num_localizers": getattr(args, "localizers", None), "horizon": getattr(args, "horizon", None),
    }
    config_values.update({k: v for k, v in flags.items() if v is not None})
    if getattr(args, "alpha", None) is not None:
        param_values["lookahead.alpha"] = args.alpha
    for name, value in parse_assignments(args.set or []).items():
        if name in config_fields:
            config_values[name] = value
        else:
            param_values[name] = value
    return config_from_dict(config_values), params_from_dict(param_values)


def _add_filter_options(p: argparse.ArgumentParser, default_proposal: str, default_particles: int) -> None:
    p.add_argument("--proposal", choices=["op", "smp", "lp"], default=default_proposal,
                   help="proposal distribution: odometry, scan matching (GMapping) or look-ahead")
    p.add_argument("--particles", type=int, default=default_particles, help="number of SLAM particles N")
    p.add_argument("--localizers", type=int, default=None, help="LP: localizer particles L per SLAM particle")
    p.add_argument("--horizon", type=int, default=None, help="LP: look-ahead horizon k (processed scans)")
    p.add_argument("--alpha", type=float, default=None, help="LP: defensive share (0 = the paper's Eq. 10)")
    p.add_argument("--seed", type=int, default=0, help="random seed (runs reproduce bit for bit)")
    p.add_argument("--config", help="JSON file {\"config\": {...}, \"params\": {...}}")
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="set any config field or parameter (dotted), e.g. motion.srr=0.05; repeatable")
    p.add_argument("--chunk-size", type=int, default=32, help="steps per compiled chunk (progress granularity)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--out", default="out", help="output folder")
    p.add_argument("--refine", action="store_true",
                   help="also localise every scan in the final map: trajectory_refined.txt (jaxslam.refine)")


def _cmd_map(args: argparse.Namespace) -> int:
    from jaxslam.io import read_log

    kwargs = {}
    if args.scan_topic:
        kwargs["scan_topic"] = args.scan_topic
    if args.odom_topic:
        kwargs["odom_topic"] = args.odom_topic
    config, params = build_config_and_params(args)
    log = read_log(args.log, **kwargs)
    if args.max_scans is not None:
        import numpy as np

        log = log.subset(np.arange(min(args.max_scans, log.num_scans)))
    return _map_and_write(log, config, params, args, source=str(args.log))


def _map_and_write(log, config, params, args, source: str, world=None) -> int:
    import jax

    from jaxslam.outputs import write_slam_outputs
    from jaxslam.rbpf import run

    result = run(jax.random.key(args.seed), log, config, params, chunk_size=args.chunk_size,
                 progress=not args.no_progress)
    refined, refine_seconds = None, None
    if getattr(args, "refine", False):
        import time

        import numpy as np

        from jaxslam.refine import refine_trajectory

        t0 = time.perf_counter()
        best = int(np.argmax(np.asarray(result.state.log_weights)))
        refined = refine_trajectory(result.config.grid, result.state.maps.hit_dist2[best], result.trajectory,
                                    log.ranges, log.sensor, params, result.config, odometry=log.odometry)
        refine_seconds = time.perf_counter() - t0
    summary = write_slam_outputs(args.out, log, result, params, seed=args.seed, source=source, world=world,
                                 refined=refined, refine_seconds=refine_seconds)
    t = summary["timings"]
    print(f"processed {summary['scans_processed']} of {summary['scans_in_log']} scans in {t['total']:.1f} s "
          f"(compile {t['compile']:.1f} s, real-time factor {t['real_time_factor']:.1f}); "
          f"outputs in {args.out}/")
    for warning in summary["warnings"]:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


DEMO_SETTINGS = ("linear_update=0.25", "angular_update=0.25", "max_insert_range=10.0", "map_padding=5.0",
                 "beam_stride=1")


def _cmd_demo(args: argparse.Namespace) -> int:
    import jax

    from jaxslam.sim import office_scenario

    scenario = office_scenario(jax.random.key(args.seed), num_scans=args.scans)
    # The simulated office is small: process scans more often than GMapping's 1 m / 0.5 rad,
    # and use every beam (its 10 m laser sees little along the 20 m corridor).
    args.set = list(DEMO_SETTINGS) + (args.set or [])
    config, params = build_config_and_params(args)
    return _map_and_write(scenario.log, config, params, args, source="simulated office (jaxslam.sim.office_scenario)",
                          world=scenario.world)


def _cmd_eval(args: argparse.Namespace) -> int:
    from jaxslam.io import read_relations, read_trajectory
    from jaxslam.metrics import relation_error

    timestamps, poses = read_trajectory(args.trajectory)
    relations = read_relations(args.relations)
    err = relation_error(timestamps, poses, relations)
    table = err.to_dict()
    print(f"{'relations':>22}: {table.get('count')}")
    for key, value in table.items():
        if key != "count" and not isinstance(value, (list, dict)):
            print(f"{key:>22}: {value:.6g}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({k: v for k, v in table.items() if not isinstance(v, list)}, indent=2))
        print(f"written to {args.out}")
    return 0


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxslam", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p_map = sub.add_parser("map", help="build a map from a log (ROS 1/2 bag or CARMEN log)")
    p_map.add_argument("log", help="path of the log; the format is read from the file")
    p_map.add_argument("--scan-topic", help="bag topic of sensor_msgs/LaserScan (default /scan)")
    p_map.add_argument("--odom-topic", help="bag topic of nav_msgs/Odometry (default /odom)")
    p_map.add_argument("--max-scans", type=int, help="use only the first N scans of the log")
    _add_filter_options(p_map, "smp", 30)
    p_map.set_defaults(func=_cmd_map)

    p_demo = sub.add_parser("demo", help="map a simulated office (no download needed)")
    p_demo.add_argument("--scans", type=int, default=500, help="scans along the simulated path (88 m)")
    _add_filter_options(p_demo, "smp", 20)
    p_demo.set_defaults(func=_cmd_demo, out="out/demo")

    p_eval = sub.add_parser("eval", help="relation error (Kuemmerle et al. 2009) of a trajectory")
    p_eval.add_argument("trajectory", help="trajectory text file: 'timestamp x y theta' per line")
    p_eval.add_argument("relations", help="relations file: 't1 t2 x y z roll pitch yaw' per line")
    p_eval.add_argument("--out", help="write the table as JSON here")
    p_eval.set_defaults(func=_cmd_eval)

    try:
        from jaxslam.cli_doors import add_parser as add_doors_parser
    except ImportError:  # the doors module is optional at import time of the CLI
        add_doors_parser = None
    if add_doors_parser is not None:
        add_doors_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from jaxslam.laserlog import LogError

    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ConfigError, LogError, FileNotFoundError, ValueError) as err:
        print(f"jaxslam {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
