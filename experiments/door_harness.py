"""The door experiment's harness: one door filter on one scenario log, or on many seeds at once,
scored against the truth (position and heading errors, door-state accuracy). Used by
experiments/doors.py and notebooks/doors.ipynb; the filters themselves are the library's
(:mod:`jaxslam.localization.doors`, :mod:`jaxslam.localization.mcl`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from jaxslam.geometry import pose_errors
from jaxslam.laser import SensorSpec
from jaxslam.localization import doors, mcl
from jaxslam.localization.doors import DoorConfig, DoorMap, DoorParams
from jaxslam.localization.mcl import ScanInputs

FILTERS = ("hybrid", "static", "memoryless")
"""The door filter, static MCL on the map as given, and the door filter without memory."""


class DoorRun(NamedTuple):
    """What one filter did on one scenario log (leading axes: seeds, when batched)."""

    position_error: Float[Array, "T"]
    """|mean position - true position| (m) per step."""
    heading_error: Float[Array, "T"]
    """|mean heading - true heading| (rad, wrapped) per step."""
    door_belief: Float[Array, "T K"]
    """Marginal p(open) per door per step (for static MCL: the map's fixed belief)."""
    door_observed: Float[Array, "T K"]
    """Particle weight that observed door k at step t (0 for static MCL)."""
    ess: Float[Array, "T"]
    """ESS per step."""
    final_poses: Float[Array, "N 3"]
    """Particle poses at the end."""
    final_door_open: Float[Array, "N K"]
    """Particle door beliefs at the end (for static MCL: the map's fixed belief)."""
    final_log_weights: Float[Array, "N"]
    """Log-weights at the end."""


def run_filter(key: PRNGKeyArray, inputs: ScanInputs, true_poses: Float[Array, "T 3"],
               start_regions: Float[Array, "R 4"], door_map: DoorMap, sensor: SensorSpec,
               params: DoorParams, config: DoorConfig, filter_kind: str,
               heading_range: tuple[float, float] = (-np.pi, np.pi)) -> DoorRun:
    """Global initialisation over ``start_regions``, then one filter over the log. Pure and
    vmappable over (key, inputs, true_poses); ``filter_kind`` in :data:`FILTERS` (static).

    The three filters use the same key split, so they see the same initial particles.
    """
    if filter_kind not in FILTERS:
        raise ValueError(f"filter_kind must be one of {FILTERS}, got {filter_kind!r}")
    k_init, k_run = jax.random.split(key)
    init_state = mcl.init_global(k_init, start_regions, config.mcl, heading_range)
    true_poses = jnp.asarray(true_poses, jnp.float32)
    if filter_kind == "static":
        segments, active = doors.static_segments(door_map)
        out = mcl.filter(k_run, init_state, inputs, segments, sensor, params.mcl_params(), config.mcl, active)
        final, info = out.state, out.info
        pos, head = pose_errors(info.mean_pose, true_poses)
        t = inputs.motion.shape[0]
        fixed = (door_map.initial_open >= 0.5).astype(jnp.float32)
        return DoorRun(pos, head, jnp.broadcast_to(fixed, (t, door_map.num_doors)),
                       jnp.zeros((t, door_map.num_doors)), info.ess, final.poses,
                       jnp.broadcast_to(fixed, (final.poses.shape[0], door_map.num_doors)), final.log_weights)
    cfg = config if filter_kind == "hybrid" else dataclasses.replace(config, memory=False)
    out = doors.filter(k_run, doors.init(init_state, door_map), inputs, door_map, sensor, params, cfg)
    final, info = out.state, out.info
    pos, head = pose_errors(info.mcl.mean_pose, true_poses)
    return DoorRun(pos, head, info.door_belief, info.door_observed, info.mcl.ess, final.poses,
                   final.door_open, final.log_weights)


@functools.partial(jax.jit, static_argnames=("config", "filter_kind", "heading_range", "batch_size"))
def run_filter_batch(keys: PRNGKeyArray, inputs: ScanInputs, true_poses: Float[Array, "S T 3"],
                     start_regions, door_map: DoorMap, sensor: SensorSpec, params: DoorParams,
                     config: DoorConfig, filter_kind: str,
                     heading_range: tuple[float, float] = (-np.pi, np.pi), batch_size: int = 8) -> DoorRun:
    """:func:`run_filter` over S seeds: ``lax.map`` in vmapped batches of ``batch_size`` seeds
    (bounds the (batch, N, B, W+K) ray-casting intermediates)."""

    def one(args):
        key, inp, truth = args
        return run_filter(key, inp, truth, start_regions, door_map, sensor, params, config, filter_kind,
                          heading_range)

    return jax.lax.map(one, (keys, inputs, true_poses), batch_size=batch_size)


def door_state_accuracy(final_belief: np.ndarray, true_open: np.ndarray, observed: np.ndarray,
                        open_threshold: float = 0.65, closed_threshold: float = 0.35) -> float:
    """Fraction of observed doors whose belief is on the right side: p(open) > 0.65 for an open
    door, < 0.35 for a closed one. Arrays broadcast ((S, K) over seeds); NaN when nothing was observed."""
    final_belief, true_open, observed = np.broadcast_arrays(np.asarray(final_belief), np.asarray(true_open),
                                                            np.asarray(observed, bool))
    right = np.where(true_open, final_belief > open_threshold, final_belief < closed_threshold)
    n = observed.sum()
    return float(right[observed].sum() / n) if n else float("nan")
