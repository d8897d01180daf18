"""Scan matching against a grid map: the hill climber, its score, and the Gaussian fitted round a match.

* :func:`match`: from an initial pose, each iteration tries the six moves +-dx, +-dy (world
  frame) and +-dtheta at the current step sizes, moves to the best one if it improves the
  log-likelihood, and otherwise halves the steps. The number of iterations is static, so the
  matcher vmaps over particles and compiles to one loop (no value-dependent Python control
  flow). Unlike GMapping's matcher, every move is scored with the same likelihood that weighs
  the particles, and the best pose found is always the one returned.
* :func:`matched_gaussian`: the SMP's steps 1-3 (match, 27-pose stencil round the mode,
  a Gaussian fitted to it) and its weight increment; the look-ahead proposal
  (:mod:`jaxslam.proposals.lookahead`) starts its localizers from the same fit.

Scans are scored by the sensor model (:mod:`jaxslam.sensor_model`; the endpoint model unless
told otherwise), whose match score decides whether a match counts.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, UInt8

from jaxslam import motion
from jaxslam.geometry import compose, wrap_angle
from jaxslam.grid import GridSpec
from jaxslam.laser import SensorSpec, within_usable_range
from jaxslam.likelihood_field import LikelihoodParams
from jaxslam.map_view import MapView
from jaxslam.motion import LOG_2PI
from jaxslam.paged_map import PagedField, PagedGridSpec
from jaxslam.sensor_model import ENDPOINT, SensorModel, sensor_model

# NumPy, not jnp: module-level jnp values created while a trace is active would leak tracers.
_MOVES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float32)
_STENCIL = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.float32)  # (27, 3)


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


def stencil_poses(center: Float[Array, "3"], scan_match_params) -> tuple[Float[Array, "27 3"], Float[Array, "27 3"],
                                                                         Float[Array, "3"]]:
    """The 3x3x3 stencil round a matched pose, spaced by the matcher's initial steps.

    Returns:
      ``(poses, offsets, spacing)``: (27, 3) poses (angles wrapped), their (27, 3) offsets
      from ``center`` and the (3,) spacing (m, m, rad).
    """
    sm = scan_match_params
    spacing = jnp.stack([sm.linear_step, sm.linear_step, sm.angular_step])
    offsets = _STENCIL * spacing
    poses = center + offsets
    return poses.at[:, 2].set(wrap_angle(poses[:, 2])), offsets, spacing


class MatchedGaussian(NamedTuple):
    """A Gaussian over x_t fitted around the scan-matched pose (steps 1-3 of the SMP)."""

    mean: Float[Array, "3"]
    """Mean pose (m, m, rad)."""
    chol: Float[Array, "3 3"]
    """Lower Cholesky factor of the covariance."""
    log_eta: Float[Array, ""]
    """log sum_j p(z | x_j, m)^gain p(x_j | x_{t-1}, u) + log(cell volume): the SMP's weight increment."""
    matched: Bool[Array, ""]
    """The match succeeded (score >= ``scan_match.min_score``, finite weight)."""


def matched_gaussian(pose, field, inputs, sensor, params, config, fit_gain,
                     start_key=None) -> MatchedGaussian:
    """Scan-match z_t from the odometry prediction and fit a Gaussian on the 27-pose stencil.

    The stencil weights are p(z | x_j, m)^fit_gain p(x_j | x_{t-1}, u): the SMP fits with
    fit_gain = 1 (the scan's own sharpness; tempering the fit too would widen the draws to
    the stencil's size and bend the maps, for nothing: the likelihood gain only exists to
    keep the weights of correlated beams from collapsing, and GMapping likewise moves to the
    matched pose and tempers only the weights); the scan-matched look-ahead fits with
    ``lookahead.localizer_gain``.

    With ``start_key`` the hill climber starts from a motion-model draw whose stds are scaled
    by ``scan_match.start_noise`` (0: the prediction itself, as without a key).
    """
    spec = config.grid
    sm = params.scan_match
    predicted = compose(pose, inputs.motion)
    if start_key is not None:
        start_std = motion.noise_std(inputs.motion, params.motion) * sm.start_noise
        predicted = compose(pose, inputs.motion + jax.random.normal(start_key, (3,), pose.dtype) * start_std)
    model = sensor_model(config)
    result = match(spec, field, predicted, inputs.ranges, sensor, params.likelihood,
                   sm.linear_step, sm.angular_step, config.match_iterations, config.match_lookup,
                   usable_range=config.max_insert_range, model=model)
    candidates, offsets, spacing = stencil_poses(result.pose, sm)
    untempered = params.likelihood._replace(gain=jnp.float32(1.0))
    raw_log_lik = model.log_likelihoods_fn(MapView(spec, field), candidates, inputs.ranges, sensor, untempered,
                                           config.likelihood_lookup)
    log_motion = motion.log_density(candidates, pose, inputs.motion, params.motion)
    log_eta = jax.scipy.special.logsumexp(params.likelihood.gain * raw_log_lik + log_motion) + jnp.sum(jnp.log(spacing))

    w = jax.nn.softmax(fit_gain * raw_log_lik + log_motion)
    mean_offset = w @ offsets
    centred = offsets - mean_offset
    cov = (centred * w[:, None]).T @ centred + jnp.diag((sm.min_std_fraction * spacing) ** 2)
    mean = result.pose + mean_offset
    mean = mean.at[2].set(wrap_angle(mean[2]))
    matched = (result.score >= sm.min_score) & jnp.isfinite(log_eta)
    return MatchedGaussian(mean, jnp.linalg.cholesky(cov), log_eta, matched)


def gaussian_log_density(poses: Float[Array, "... 3"], gaussian: MatchedGaussian) -> Float[Array, "..."]:
    """log N(poses; mean, L L^T) with the angle residual wrapped (density in m^-2 rad^-1)."""
    residual = poses - gaussian.mean
    residual = residual.at[..., 2].set(wrap_angle(residual[..., 2]))
    z = jax.scipy.linalg.solve_triangular(gaussian.chol, residual[..., None], lower=True)[..., 0]
    log_det = jnp.sum(jnp.log(jnp.diag(gaussian.chol)))
    return -0.5 * jnp.sum(z**2, axis=-1) - log_det - 1.5 * LOG_2PI


def sample_gaussian(key, gaussian: MatchedGaussian, shape=()) -> Float[Array, "... 3"]:
    """Draws from a :class:`MatchedGaussian` (angles wrapped)."""
    draw = gaussian.mean + jax.random.normal(key, shape + (3,)) @ gaussian.chol.T
    return draw.at[..., 2].set(wrap_angle(draw[..., 2]))
