"""The hill-climbing scan matcher of the trajectory refinement (:mod:`jaxslam.refine`).

:func:`match`: from an initial pose, each iteration tries the six moves +-dx, +-dy (world
frame) and +-dtheta at the current step sizes, moves to the best one if it improves the
log-likelihood, and otherwise halves the steps. The number of iterations is static, so the
matcher vmaps over scans and compiles to one loop (no value-dependent Python control flow).
Unlike GMapping's matcher, every move is scored with the same likelihood that weighs the
particles, and the best pose found is always the one returned.

The proposals do not climb: they search the whole window (:mod:`jaxslam.window_posterior`);
what the climb did there, and why it went: docs/design.md, "The window posterior".

Scans are scored by the sensor model (:mod:`jaxslam.sensor_model`; the endpoint model unless
told otherwise), whose match score decides whether a match counts.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt8

from jaxslam.geometry import wrap_angle
from jaxslam.grid import GridSpec
from jaxslam.laser import SensorSpec, within_usable_range
from jaxslam.likelihood_field import LikelihoodParams
from jaxslam.map_view import MapView
from jaxslam.maps import PagedField, PagedGridSpec
from jaxslam.sensor_model import ENDPOINT, SensorModel

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
    spec: GridSpec | PagedGridSpec,
    hit_dist2: UInt8[Array, "H W"] | PagedField,
    initial_pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    likelihood: LikelihoodParams,
    linear_step: Float[Array, ""],
    angular_step: Float[Array, ""],
    iterations: int,
    lookup: str = "nearest",
    usable_range: float | None = None,
    model: SensorModel = ENDPOINT,
) -> MatchResult:
    """Hill-climb from ``initial_pose`` for ``iterations`` (static) rounds of six moves, on the
    sensor model's likelihood (``model``, static; ``lookup`` as :data:`jaxslam.likelihood_field.FIELD_LOOKUPS`).
    The match's ``score`` counts only beams shorter than ``usable_range`` (m; static; None: all),
    the range up to which the map registers endpoints (``SlamConfig.max_insert_range``)."""
    view = MapView(spec, hit_dist2)
    log_liks = lambda poses: model.log_likelihoods_fn(view, poses, ranges, sensor, likelihood, lookup)
    step_scale = jnp.stack([linear_step, linear_step, angular_step])

    def body(carry, _):
        pose, best, scale = carry
        candidates = pose + _MOVES * (step_scale * scale)
        candidates = candidates.at[:, 2].set(wrap_angle(candidates[:, 2]))
        values = log_liks(candidates)
        j = jnp.argmax(values)
        better = values[j] > best
        pose = jnp.where(better, candidates[j], pose)
        best = jnp.where(better, values[j], best)
        scale = jnp.where(better, scale, 0.5 * scale)
        return (pose, best, scale), None

    (pose, best, _), _ = jax.lax.scan(body, (initial_pose, log_liks(initial_pose[None])[0], jnp.float32(1.0)),
                                      None, length=iterations)
    scored = ranges if usable_range is None else within_usable_range(ranges, usable_range)
    score = model.match_score_fn(view, pose, scored, sensor, likelihood)
    return MatchResult(pose, best, score)
