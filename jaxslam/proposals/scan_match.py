"""The scan-matching proposal (SMP) of Grisetti, Stachniss and Burgard (2005/2007), as in GMapping.

1. Scan-match z_t in m_{t-1} starting from the odometry prediction x_{t-1} (+) u_t.
2. Around the mode, evaluate the 27 poses of a 3x3x3 stencil (spacing: the matcher's
   initial steps) weighted by p(z | x_j, m) p(x_j | x_{t-1}, u).
3. Fit a Gaussian to them (with the untempered likelihood, gain 1) and draw x_t from it.
4. The log-weight increment is log sum_j p(z | x_j, m) p(x_j | x_{t-1}, u) + log(cell volume):
   the Riemann sum of p(z_t | x_{t-1}, m, u) = int p(z | x, m) p(x | x_{t-1}, u) dx, the
   same quantity the OP's increment estimates, so that particles which fall back to the
   OP (a failed match: score under ``scan_match.min_score``) stay comparable.

Steps 1-3 are :func:`jaxslam.scan_matching.matched_gaussian`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxslam.proposals import odometry
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.scan_matching import matched_gaussian, sample_gaussian


def propose(key, pose, field, inputs: StepInputs, sensor, params, config) -> ProposalOutput:
    """One SMP draw for one particle (see the module docstring)."""
    key_sample, key_fallback = jax.random.split(key)
    key_start = jax.random.fold_in(key, 1)  # a separate stream: the other two draws stay as they were
    gaussian = matched_gaussian(pose, field, inputs, sensor, params, config, fit_gain=1.0, start_key=key_start)
    smp_pose = sample_gaussian(key_sample, gaussian)
    fallback = ~gaussian.matched
    op = odometry.propose(key_fallback, pose, field, inputs, sensor, params, config)
    return ProposalOutput(
        jnp.where(fallback, op.pose, smp_pose),
        jnp.where(fallback, op.log_weight_increment, gaussian.log_eta),
        fallback,
    )
