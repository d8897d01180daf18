"""The scan-matching proposal (SMP): GMapping's proposal, drawn from the window posterior.

1. Search the window round the odometry prediction x_{t-1} (+) u_t for the modes of
   p(z_t | x, m)^gain p(x | x_{t-1}, u_t) (:func:`jaxslam.window_posterior.window_posterior`:
   coarse to fine, the motion prior inside, every mode refined).
2. Round each mode, a Gaussian fitted on a 3x3x3 stencil with the untempered likelihood (gain
   1, the scan's own sharpness), and the mode's mass (the stencil's Riemann sum at the gain).
3. Draw a mode by its mass, then x_t from its Gaussian: a window with two modes sends particles
   to both in proportion to their mass.
4. The log-weight increment is the log of the summed masses, the quadrature of
   p(z_t | x_{t-1}, m, u_t) = int p(z | x, m) p(x | x_{t-1}, u) dx, the same quantity the OP's
   increment estimates, so that particles which fall back to the OP (a failed match: the
   heaviest mode's score under ``scan_match.min_score``) stay comparable.

GMapping (and this library until 2026-11-26) climbed the likelihood alone from the prediction
and fitted one Gaussian round the climb's end; the results of both: docs/results.md.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxslam import window_posterior
from jaxslam.proposals import odometry
from jaxslam.proposals.base import ProposalOutput, StepInputs


def propose(key, pose, field, inputs: StepInputs, sensor, params, config) -> ProposalOutput:
    """One SMP draw for one particle (see the module docstring)."""
    key_sample, key_fallback = jax.random.split(key)
    posterior = window_posterior.window_posterior(pose, field, inputs.motion, inputs.ranges, sensor, params, config,
                                                  fit_gain=1.0)
    smp_pose = window_posterior.sample(key_sample, posterior, window_posterior.mixture_log_weights(posterior))
    fallback = ~posterior.matched
    op = odometry.propose(key_fallback, pose, field, inputs, sensor, params, config)
    return ProposalOutput(
        jnp.where(fallback, op.pose, smp_pose),
        jnp.where(fallback, op.log_weight_increment, posterior.log_eta),
        fallback,
    )
