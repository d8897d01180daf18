"""What the ``jaxslam`` commands share: the one-line parser, the checks of the flags and of the
output folder, config files and ``--set``, the setup from the parsed arguments and the filter
options of ``map`` and ``demo``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from jaxslam.config import ConfigError, build_setup, default_values
from jaxslam.io.files import OutputError, check_output_folder
from jaxslam.proposals import PROPOSALS, proposal_flags


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
    for flag in proposal_flags().values():
        if flag.minimum is not None:
            _check_at_least(flag.flag, getattr(args, _dest(flag)), flag.minimum, flag.help)
    _check_at_least("--checkpoint-every", getattr(args, "checkpoint_every", None), 1, "chunks between checkpoints")


def _dest(flag) -> str:
    """The argparse attribute of a proposal's flag (``--localizers`` -> ``localizers``)."""
    return flag.flag.lstrip("-").replace("-", "_")


def _check_out_folder(out) -> None:
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
    values = dict(defaults or {})
    if getattr(args, "config", None):
        values.update(read_config_file(args.config))
    flags = {"proposal": args.proposal, "num_particles": args.particles,
             **{flag.name: getattr(args, _dest(flag), None) for flag in proposal_flags().values()}}
    values.update({k: v for k, v in flags.items() if v is not None})
    values.update(parse_assignments(args.set or []))
    return build_setup(values)


def _add_filter_options(p: argparse.ArgumentParser, command_defaults: dict, proposal_note: str = "") -> None:
    d = {**default_values(), **command_defaults}
    kinds = "; ".join(f"{name}: {proposal.summary}" for name, proposal in PROPOSALS.items())
    p.add_argument("--proposal", choices=list(PROPOSALS), default=None,
                   help=f"proposal distribution ({kinds}) (default {d['proposal']}{proposal_note})")
    p.add_argument("--particles", type=int, default=None,
                   help=f"number of SLAM particles N (default {d['num_particles']})")
    owners = {flag.flag: name for name, proposal in PROPOSALS.items() for flag in proposal.flags}
    for flag in proposal_flags().values():  # each proposal's own flags, from its row
        p.add_argument(flag.flag, type=flag.type, default=None,
                       help=f"{owners[flag.flag].upper()}: {flag.help} (default {d[flag.name]:g})")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed, 0 to 2^32 - 1 (runs reproduce bit for bit) (default %(default)s)")
    p.add_argument("--config", help="JSON file {\"config\": {...}, \"params\": {...}}")
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="set any config field or parameter (dotted), e.g. motion.srr=0.05; repeatable")
    p.add_argument("--chunk-size", type=int, default=32,
                   help="steps per compiled chunk (progress granularity), >= 1 (default %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--no-cache", action="store_true",
                   help="do not use the persistent compilation cache (as JAXSLAM_CACHE_DIR=off)")
    p.add_argument("--out", default="out",
                   help="output folder (replaced atomically; stale outputs removed) (default %(default)s)")
    p.add_argument("--refine", action=argparse.BooleanOptionalAction, default=True,
                   help="the last step: every scan localised in the final map (the closed one where loops were "
                        "closed) and fused with the odometry: trajectory_refined.txt (jaxslam.refine); "
                        "--no-refine skips it (default: refine)")
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
    own = "; ".join(f"{name.upper()}: " + ", ".join(f"{s.name} = {s.default}" for s in proposal.settings)
                    for name, proposal in PROPOSALS.items() if proposal.settings)
    p.epilog = (f"Defaults: --proposal {d['proposal']}, {d['num_particles']} particles; a scan is processed after "
                f"{d['linear_update']:g} m or {d['angular_update']:g} rad of odometry (--set linear_update=..., "
                f"--set angular_update=...); the proposals' own settings (--set NAME=VALUE): {own}. "
                f"Compilations are cached in "
                f"$JAXSLAM_CACHE_DIR (default $XDG_CACHE_HOME/jaxslam/jax or ~/.cache/jaxslam/jax; "
                f"JAXSLAM_CACHE_DIR=off or --no-cache: no cache).")


def _warn_of_the_cache(args) -> None:
    """The compilation cache's warning (:func:`jaxslam.compile_cache.enable`), once the inputs
    have passed their checks (a refusal stays one line)."""
    if getattr(args, "cache_warning", None):
        print(f"jaxslam {args.command}: warning: {args.cache_warning}", file=sys.stderr, flush=True)
        args.cache_warning = None
