"""The scan-matching proposal (SMP): GMapping's proposal, drawn from the window posterior.

1. Search the window round the odometry prediction x_{t-1} (+) u_t for the modes of
   p(z_t | x, m)^gain p(x | x_{t-1}, u_t) (:func:`jaxslam.window_posterior.window_posterior`:
   coarse to fine, the motion prior inside, every mode refined).
2. Round each mode, a Gaussian fitted on a 3x3x3 stencil with the untempered likelihood (gain
   1, the scan's own sharpness), and the mode's mass (the stencil's Riemann sum at the gain).
3. Draw a mode by its mass, then x_t from its Gaussian: a window with two modes sends particles
   to both in proportion to their mass.
4. The log-weight increment (``config.smp_weight``) estimates
   p(z_t | x_{t-1}, m, u_t) = int p(z | x, m) p(x | x_{t-1}, u) dx, the same quantity the OP's
   increment estimates, so that particles which fall back to the OP (a failed match: the
   heaviest mode's score under ``scan_match.min_score``) stay comparable:

   * "quadrature" (the default): the log of the summed masses. Its gradient goes through the
     draw and the masses (pathwise), which is not a score estimate.
   * "importance": log gamma(x_t) - log q(x_t), gamma = p(z_t | x_t, m)^gain p(x_t | x_{t-1}, u_t)
     and q the mixture drawn from. The draw and q carry no gradient, so the increment's is
     d log gamma(x_t), the score of the drawn pose: the draw's own score d log q and the weight's
     -d log q cancel, as for the LP's localizers (:mod:`jaxslam.proposals.lookahead`).

GMapping (and this library until 2026-11-26) climbed the likelihood alone from the prediction
and fitted one Gaussian round the climb's end; the results of both: docs/results.md.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxslam import window_posterior
from jaxslam.map_view import MapView
from jaxslam.proposals import odometry
from jaxslam.proposals.base import Proposal, ProposalOutput, Setting, StepInputs, step_params
from jaxslam.sensor_model import sensor_model


def propose(key, pose, field, inputs: StepInputs, sensor, params, config, step_motion=None) -> ProposalOutput:
    """One SMP draw for one particle (see the module docstring); ``step_motion``: the motion
    model of this step (None: ``params.motion``; :mod:`jaxslam.proposals.base`)."""
    params = step_params(params, step_motion)
    key_sample, key_fallback = jax.random.split(key)
    importance = config.smp_weight == "importance"
    posterior = window_posterior.window_posterior(pose, field, inputs.motion, inputs.ranges, sensor, params, config,
                                                  fit_gain=1.0)
    if importance:
        posterior = jax.lax.stop_gradient(posterior)
    log_mixture = window_posterior.mixture_log_weights(posterior)
    smp_pose = window_posterior.sample(key_sample, posterior, log_mixture)
    increment = posterior.log_eta
    if importance:  # the drawn pose carries no gradient (the posterior has none): see the docstring
        log_lik = sensor_model(config).log_likelihoods_fn(MapView(config.grid, field), smp_pose[None], inputs.ranges,
                                                          sensor, params.likelihood, config.likelihood_lookup)[0]
        increment = window_posterior.importance_log_weights(smp_pose, log_lik, pose, inputs.motion, params.motion,
                                                            posterior, log_mixture)
    fallback = ~posterior.matched
    op = odometry.propose(key_fallback, pose, field, inputs, sensor, params, config)
    return ProposalOutput(
        jnp.where(fallback, op.pose, smp_pose),
        jnp.where(fallback, op.log_weight_increment, increment),
        fallback,
    )



SMP_WEIGHT = Setting(
    "smp_weight", "quadrature", lambda v: v in ("quadrature", "importance"), "'quadrature' or 'importance'",
    """The SMP's log-weight increment. "quadrature" (the default, the published tables'): the log
    of the window posterior's summed stencil masses, a Rao-Blackwellised estimate of
    p(z_t | x_{t-1}, m, u_t) with little spread between particles, but a Riemann sum on the
    stencil's spacing (``scan_match.linear_step``, ``angular_step``): where the posterior is much
    narrower than that (accurate odometry, every scan an update) it overstates the evidence by
    nats a step, and its gradient is not a score. "importance": the proper importance weight of
    the drawn pose, log p(z_t | x_t, m)^gain + log p(x_t | x_{t-1}, u_t) - log q(x_t) with q the
    window posterior's mixture, an unbiased estimate of the same quantity whose gradient is the
    score of the drawn pose; what ``learning.slam_learning_setup`` sets (the figures:
    docs/design.md, "Motion-noise gradients by the score").""")

PROPOSAL = Proposal(
    propose, "scan matching (GMapping's proposal): a Gaussian round each mode of the window posterior",
    settings=(SMP_WEIGHT,), searches_window_fn=lambda config: True)
"""The SMP's row of :data:`jaxslam.proposals.PROPOSALS`."""
