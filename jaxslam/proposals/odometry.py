"""The odometry proposal (OP): x_t ~ p(x_t | x_{t-1}, u_t), weight by p(z_t | x_t, m)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxslam import motion
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.likelihood_field import endpoint_log_likelihood


def propose(key, pose, field, inputs: StepInputs, sensor, params, config) -> ProposalOutput:
    """Draw from the motion model; the increment is the endpoint log-likelihood of z_t there."""
    new_pose = motion.sample(key, pose, inputs.motion, params.motion)
    log_lik = endpoint_log_likelihood(config.grid, field, new_pose, inputs.ranges, sensor,
                                      params.likelihood, config.likelihood_lookup)
    return ProposalOutput(new_pose, log_lik, jnp.bool_(False))
