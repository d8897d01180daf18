"""``jaxslam map``'s checkpoints: where one is kept, what identifies a run for ``--resume``,
loading one to resume, and the SIGINT / SIGTERM handlers that stop a run at a chunk boundary."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

from jaxslam.checkpoint import load_checkpoint
from jaxslam.config import ConfigError, config_to_dict, params_to_dict


def checkpoint_path(out) -> Path:
    """Where a run with ``--out OUT`` keeps its checkpoint: ``OUT.checkpoint.npz`` beside the
    output folder (outside it: the folder is swapped in whole when the run ends)."""
    target = Path(os.path.abspath(os.fspath(out)))
    return target.with_name(target.name + ".checkpoint.npz")


def _run_identity(args, log, setup, source: str) -> dict:
    """What identifies a run for ``--resume`` (compared after a JSON round trip)."""
    config, settings, params = setup
    where = os.path.abspath(source) if os.path.exists(source) else source
    identity = {"seed": args.seed, "config": config_to_dict(config), "settings": config_to_dict(settings),
                "params": params_to_dict(params), "log": where, "scans_in_log": log.num_scans,
                "chunk_size": args.chunk_size}
    if getattr(args, "odometry_lead", None) is not None:  # auto is the same lead for the same log
        identity["odometry_lead"] = args.odometry_lead
    return json.loads(json.dumps(identity, sort_keys=True, default=str))


def _load_resume(path: Path, identity: dict):
    """The checkpoint's :class:`~jaxslam.slam.RunProgress` if it is of the run ``identity``, else ``ConfigError``."""
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
