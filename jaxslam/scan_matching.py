"""A vmappable scan matcher: hill climbing on the endpoint likelihood with a fixed budget.

From an initial pose, each iteration tries the six moves +-dx, +-dy (world frame)
and +-dtheta at the current step sizes, moves to the best one if it improves the
log-likelihood, and otherwise halves the steps. The number of iterations is
static, so that the matcher vmaps over particles and compiles to one loop (no
value-dependent Python control flow). Unlike GMapping's matcher, every move is
scored with the same likelihood that weighs the particles, and the best pose
found is always the one returned.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt8

from jaxslam.geometry import wrap_angle
from jaxslam.grid import GridSpec
from jaxslam.sensor import (LikelihoodParams, SensorSpec, endpoint_log_likelihood, endpoint_log_likelihoods,
                            match_score)

# NumPy, not jnp: module-level jnp values created while a trace is active would leak tracers.
_MOVES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float32)


class MatchResult(NamedTuple):
    """The outcome of matching one scan against one map."""

    pose: Float[Array, "3"]
    """Best pose found (m, m, rad)."""
    log_likelihood: Float[Array, ""]
    """Endpoint log-likelihood at ``pose``."""
    score: Float[Array, ""]
    """Mean per-beam fit (0..1) at ``pose``: the match quality."""


def match(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    initial_pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    likelihood: LikelihoodParams,
    linear_step: Float[Array, ""],
    angular_step: Float[Array, ""],
    iterations: int,
    lookup: str = "nearest",
) -> MatchResult:
    """Hill-climb from ``initial_pose`` for ``iterations`` (static) rounds of six moves, on the
    endpoint likelihood read from the field by ``lookup`` (static, ``sensor.FIELD_LOOKUPS``)."""
    log_lik = lambda pose: endpoint_log_likelihood(spec, hit_dist2, pose, ranges, sensor, likelihood, lookup)
    step_scale = jnp.stack([linear_step, linear_step, angular_step])

    def body(carry, _):
        pose, best, scale = carry
        candidates = pose + _MOVES * (step_scale * scale)
        candidates = candidates.at[:, 2].set(wrap_angle(candidates[:, 2]))
        values = endpoint_log_likelihoods(spec, hit_dist2, candidates, ranges, sensor, likelihood, lookup)
        j = jnp.argmax(values)
        better = values[j] > best
        pose = jnp.where(better, candidates[j], pose)
        best = jnp.where(better, values[j], best)
        scale = jnp.where(better, scale, 0.5 * scale)
        return (pose, best, scale), None

    (pose, best, _), _ = jax.lax.scan(body, (initial_pose, log_lik(initial_pose), jnp.float32(1.0)),
                                      None, length=iterations)
    score = match_score(spec, hit_dist2, pose, ranges, sensor, likelihood.sigma)
    return MatchResult(pose, best, score)
