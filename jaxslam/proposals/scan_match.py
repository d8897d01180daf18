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

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import motion
from jaxslam.geometry import compose, wrap_angle
from jaxslam.proposals import odometry
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.scan_matching import match
from jaxslam.sensor import endpoint_log_likelihoods

_STENCIL = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.float32)  # (27, 3), NumPy: see scan_matching
_REGULARIZER = 0.1  # floor of the fitted std, as a fraction of the stencil spacing


def propose(key, pose, grid_map, inputs: StepInputs, sensor, params, config) -> ProposalOutput:
    """One SMP draw for one particle (see the module docstring)."""
    spec = config.grid
    sm = params.scan_match
    key_sample, key_fallback = jax.random.split(key)
    predicted = compose(pose, inputs.motion)
    result = match(spec, grid_map.hit_dist2, predicted, inputs.ranges, sensor, params.likelihood,
                   sm.linear_step, sm.angular_step, config.match_iterations)

    spacing = jnp.stack([sm.linear_step, sm.linear_step, sm.angular_step])
    offsets = _STENCIL * spacing
    candidates = result.pose + offsets
    candidates = candidates.at[:, 2].set(wrap_angle(candidates[:, 2]))
    # The Gaussian is fitted to the untempered likelihood (gain 1: the scan's own sharpness);
    # the weight uses the tempered one. Tempering the fit too would widen the draw to the
    # stencil's size and bend the maps, for nothing: the gain only exists to keep weights
    # of correlated beams from collapsing (GMapping likewise moves to the matched pose and
    # tempers only the weights).
    untempered = params.likelihood._replace(gain=jnp.float32(1.0))
    raw_log_lik = endpoint_log_likelihoods(spec, grid_map.hit_dist2, candidates, inputs.ranges, sensor, untempered)
    log_motion = motion.log_density(candidates, pose, inputs.motion, params.motion)
    log_terms = params.likelihood.gain * raw_log_lik + log_motion
    log_eta = jax.scipy.special.logsumexp(log_terms) + jnp.sum(jnp.log(spacing))

    w = jax.nn.softmax(raw_log_lik + log_motion)
    mean_offset = w @ offsets
    centred = offsets - mean_offset
    cov = (centred * w[:, None]).T @ centred + jnp.diag((_REGULARIZER * spacing) ** 2)
    draw = mean_offset + jnp.linalg.cholesky(cov) @ jax.random.normal(key_sample, (3,))
    smp_pose = result.pose + draw
    smp_pose = smp_pose.at[2].set(wrap_angle(smp_pose[2]))

    fallback = ~(result.score >= sm.min_score) | ~jnp.isfinite(log_eta)
    op = odometry.propose(key_fallback, pose, grid_map, inputs, sensor, params, config)
    return ProposalOutput(
        jnp.where(fallback, op.pose, smp_pose),
        jnp.where(fallback, op.log_weight_increment, log_eta),
        fallback,
    )
