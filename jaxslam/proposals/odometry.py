"""The odometry proposal (OP): x_t ~ p(x_t | x_{t-1}, u_t), weight by p(z_t | x_t, m)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxslam import motion
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.likelihood_field import endpoint_log_likelihood


def propose(key, pose, field, inputs: StepInputs, sensor, params, config) -> ProposalOutput:
    """Draw from the motion model; the increment is the endpoint log-likelihood of z_t there.

    The increment's gradient in the motion noise is the draw's score
    (:func:`jaxslam.motion.sample_with_score`; 0 in value), so the motion terms get gradients
    with either likelihood lookup."""
    new_pose, score_term = motion.sample_with_score(key, pose, inputs.motion, params.motion)
    log_lik = endpoint_log_likelihood(config.grid, field, new_pose, inputs.ranges, sensor,
                                      params.likelihood, config.likelihood_lookup)
    return ProposalOutput(new_pose, log_lik + score_term, jnp.bool_(False))
