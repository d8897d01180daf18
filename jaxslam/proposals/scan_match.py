"""The scan-matching proposal (SMP) of Grisetti, Stachniss and Burgard (2005/2007), as in GMapping.

1. Scan-match z_t in m_{t-1} starting from the odometry prediction x_{t-1} (+) u_t.
2. Around the mode, evaluate the 27 poses of a 3x3x3 stencil (spacing: the matcher's
   initial steps) weighted by p(z | x_j, m) p(x_j | x_{t-1}, u).
3. Fit a Gaussian to them (with the untempered likelihood, gain 1) and draw x_t from it.
4. The log-weight increment is log sum_j p(z | x_j, m) p(x_j | x_{t-1}, u) + log(cell volume):
   the Riemann sum of p(z_t | x_{t-1}, m, u) = int p(z | x, m) p(x | x_{t-1}, u) dx, the
   same quantity the OP's increment estimates, so that particles which fall back to the
   OP (a failed match: score under ``scan_match.min_score``) stay comparable.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxslam import motion
from jaxslam.motion import _LOG_2PI
from jaxslam.geometry import compose, wrap_angle
from jaxslam.proposals import odometry
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.scan_matching import match
from jaxslam.sensor import endpoint_log_likelihoods

_STENCIL = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.float32)  # (27, 3), NumPy: see scan_matching


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


def matched_gaussian(pose, grid_map, inputs: StepInputs, sensor, params, config, fit_gain,
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
    result = match(spec, grid_map.hit_dist2, predicted, inputs.ranges, sensor, params.likelihood,
                   sm.linear_step, sm.angular_step, config.match_iterations, config.match_lookup)
    candidates, offsets, spacing = stencil_poses(result.pose, sm)
    untempered = params.likelihood._replace(gain=jnp.float32(1.0))
    raw_log_lik = endpoint_log_likelihoods(spec, grid_map.hit_dist2, candidates, inputs.ranges, sensor, untempered,
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
    return -0.5 * jnp.sum(z**2, axis=-1) - log_det - 1.5 * _LOG_2PI


def sample_gaussian(key, gaussian: MatchedGaussian, shape=()) -> Float[Array, "... 3"]:
    """Draws from a :class:`MatchedGaussian` (angles wrapped)."""
    draw = gaussian.mean + jax.random.normal(key, shape + (3,)) @ gaussian.chol.T
    return draw.at[..., 2].set(wrap_angle(draw[..., 2]))


def propose(key, pose, grid_map, inputs: StepInputs, sensor, params, config) -> ProposalOutput:
    """One SMP draw for one particle (see the module docstring)."""
    key_sample, key_fallback = jax.random.split(key)
    key_start = jax.random.fold_in(key, 1)  # a separate stream: the other two draws stay as they were
    gaussian = matched_gaussian(pose, grid_map, inputs, sensor, params, config, fit_gain=1.0, start_key=key_start)
    smp_pose = sample_gaussian(key_sample, gaussian)
    fallback = ~gaussian.matched
    op = odometry.propose(key_fallback, pose, grid_map, inputs, sensor, params, config)
    return ProposalOutput(
        jnp.where(fallback, op.pose, smp_pose),
        jnp.where(fallback, op.log_weight_increment, gaussian.log_eta),
        fallback,
    )
