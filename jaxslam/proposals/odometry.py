"""The odometry proposal (OP): x_t ~ p(x_t | x_{t-1}, u_t), weight by p(z_t | x_t, m)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxslam import motion
from jaxslam.proposals.base import Proposal, ProposalOutput, StepInputs, step_params
from jaxslam.map_view import MapView
from jaxslam.sensor_model import sensor_model


def propose(key, pose, field, inputs: StepInputs, sensor, params, config, step_motion=None) -> ProposalOutput:
    """Draw from the motion model (``step_motion``, None: ``params.motion``); the increment is the
    sensor model's log-likelihood of z_t there.

    The increment's gradient in the motion noise is the draw's score
    (:func:`jaxslam.motion.sample_with_score`; 0 in value), so the motion terms get gradients
    with either likelihood lookup."""
    params = step_params(params, step_motion)
    new_pose, score_term = motion.sample_with_score(key, pose, inputs.motion, params.motion)
    log_lik = sensor_model(config).log_likelihoods_fn(MapView(config.grid, field), new_pose[None], inputs.ranges,
                                                      sensor, params.likelihood, config.likelihood_lookup)[0]
    return ProposalOutput(new_pose, log_lik + score_term, jnp.bool_(False))


PROPOSAL = Proposal(propose, "odometry: the motion model")
"""The OP's row of :data:`jaxslam.proposals.PROPOSALS`: no settings of its own."""
