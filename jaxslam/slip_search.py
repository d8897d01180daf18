"""The slip search: a proposal combinator for steps whose odometry slipped.

The motion model is a mixture: with probability ``scan_match.slip_probability`` a step's odometry
slipped, and the pose is then the odometry's prediction with zero-mean noise of the slip
component's stds, whatever the motion (:func:`slip_motion`). The odometry is common to every
particle, so one particle, the heaviest, tells whether this step slipped
(:func:`slip_log_odds`); where it did, every particle proposes again under the slip component and
draws from the mixture (:func:`slip_mixture`). :func:`with_slip_search` wraps a step's proposal
with this; the RBPF's step applies it where the proposal searches the window posterior
(:func:`searches_window`). docs/design.md, "The slip search".
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import maps as paged
from jaxslam import motion, resampling, window_posterior
from jaxslam.config import SlamConfig, SlamParams
from jaxslam.laser import SensorSpec
from jaxslam.proposals import PROPOSALS
from jaxslam.proposals.base import ProposalOutput, StepInputs


_TAG_SLIP, _TAG_SLIP_CHOICE = 0x511, 0x512  # fold-in tags of the slip search's keys


def searches_window(config: SlamConfig) -> bool:
    """Whether ``config``'s proposal searches the window posterior (the SMP, the LP from the
    match), and so gets the slip search (static; the proposal's row says:
    :attr:`jaxslam.proposals.Proposal.searches_window_fn`)."""
    return PROPOSALS[config.proposal].searches_window_fn(config)


StepProposeFn = Callable[..., tuple[ProposalOutput, Int[Array, ""]]]
"""``(key, state, inputs, sensor, params, config) -> (out, num_slipped)``: a step's proposal of
every particle (:func:`propose`'s arguments, but ``step_motion``) and the number of particles
whose pose came from the slip component."""


def with_slip_search(propose_fn: Callable[..., ProposalOutput]) -> StepProposeFn:
    """``propose_fn`` (:func:`propose`'s signature) with the slip search around it.

    The odometry is common to every particle, so one particle can tell whether this step's
    odometry slipped: the heaviest, whose map is the filter's best (:func:`slip_log_odds`). When
    its posterior puts more than ``scan_match.slip_trigger`` on the slip component,
    ``propose_fn`` runs again under it (:func:`slip_motion`; key ``fold_in(key, _TAG_SLIP)``) and
    every particle draws from the mixture (:func:`slip_mixture`; key
    ``fold_in(key, _TAG_SLIP_CHOICE)``); at other steps the slip component's share is taken as 0
    and the proposal is ``propose_fn``'s alone."""
    def slip_search_fn(key, state, inputs, sensor, params, config):
        out = propose_fn(key, state, inputs, sensor, params, config)
        heaviest = jnp.argmax(state.log_weights)
        slip_odds = jax.lax.stop_gradient(slip_log_odds(
            state.poses[heaviest], paged.particle_field(state.maps, heaviest), inputs, sensor, params, config))

        def with_slip(out):
            slipped = propose_fn(jax.random.fold_in(key, _TAG_SLIP), state, inputs, sensor, params, config,
                                 slip_motion(params))
            return slip_mixture(jax.random.fold_in(key, _TAG_SLIP_CHOICE), out, slipped,
                                params.scan_match.slip_probability)

        def without_slip(out):
            return out, jnp.zeros((config.num_particles,), bool)

        triggered = jax.nn.sigmoid(slip_odds) > params.scan_match.slip_trigger
        out, chose_slip = jax.lax.cond(triggered, with_slip, without_slip, out)
        return out, jnp.sum(chose_slip).astype(jnp.int32)

    return slip_search_fn


def without_slip_search(propose_fn: Callable[..., ProposalOutput]) -> StepProposeFn:
    """``propose_fn`` as a :data:`StepProposeFn` of a proposal that never slips (num_slipped 0)."""
    def no_slip_fn(key, state, inputs, sensor, params, config):
        return propose_fn(key, state, inputs, sensor, params, config), jnp.int32(0)

    return no_slip_fn


def slip_motion(params: SlamParams) -> motion.MotionParams:
    """The motion model's slip component: zero-mean noise of ``scan_match.slip_std_xy`` (x, y) and
    ``slip_std_theta`` (heading) round the odometry's prediction, whatever the motion (the window
    posterior is then sized from these stds)."""
    sm = params.scan_match
    zero = jnp.zeros_like(sm.slip_std_xy)
    return motion.motion_params(zero, zero, zero, zero, sm.slip_std_xy, sm.slip_std_theta)


def slip_log_odds(pose: Float[Array, "3"], field, inputs: StepInputs, sensor: SensorSpec, params: SlamParams,
                  config: SlamConfig) -> Float[Array, ""]:
    """log [epsilon eta_slip / ((1 - epsilon) eta_usual)] for one particle: the posterior log-odds
    that this step's odometry slipped, eta_c the window posterior's evidence (its ``log_eta``)
    under the usual motion model and under its slip component (:func:`slip_motion`), epsilon
    ``scan_match.slip_probability``. ``inputs`` and ``sensor`` beam-subsampled as the proposals'."""
    def log_evidence(step_params):
        return window_posterior.window_posterior(pose, field, inputs.motion, inputs.ranges, sensor, step_params,
                                                 config, fit_gain=1.0).log_eta

    eps = params.scan_match.slip_probability
    slipped = log_evidence(params._replace(motion=slip_motion(params)))
    odds = resampling.safe_log(eps) + slipped - jnp.log1p(-eps) - log_evidence(params)
    return jnp.where(jnp.isnan(odds), -jnp.inf, odds)


def slip_mixture(key: PRNGKeyArray, usual: ProposalOutput, slipped: ProposalOutput,
                 slip_probability: Float[Array, ""]) -> tuple[ProposalOutput, Bool[Array, "N"]]:
    """Each particle's draw under the motion model (1 - epsilon) p_usual + epsilon p_slip, from
    one draw under each component.

    Each proposal's increment estimates its component's evidence eta_c = p(z_t | x_{t-1}, m, u_t)
    under that component. The particle keeps the slip draw with probability
    epsilon eta_slip / ((1 - epsilon) eta_usual + epsilon eta_slip) and its increment is the
    log of that denominator, whichever draw it keeps: the evidence under the mixture (where
    each draw is from its component's posterior, the proposal is then the mixture's posterior
    and this is its exact weight). Increments of -inf under both give -inf and the usual draw.

    Args:
      key: for the choices.
      usual, slipped: (N,)-batched outputs of the proposals under the usual motion model and
        under :func:`slip_motion`.
      slip_probability: epsilon in [0, 1).

    Returns:
      ``(mixed, chose_slip)``: the outputs kept (the increment replaced) and (N,) bool.
    """
    eps = jnp.asarray(slip_probability, usual.log_weight_increment.dtype)
    log_usual = jnp.log1p(-eps) + usual.log_weight_increment
    log_slip = resampling.safe_log(eps) + slipped.log_weight_increment
    # Double where: logaddexp(-inf, -inf) has a NaN gradient, which a sum over particles spreads.
    none = jnp.isneginf(log_usual) & jnp.isneginf(log_slip)
    total = jnp.where(none, -jnp.inf, jnp.logaddexp(jnp.where(none, 0.0, log_usual), jnp.where(none, 0.0, log_slip)))
    finite = jnp.isfinite(total)
    slip_share = jnp.exp(jnp.where(finite, log_slip - jnp.where(finite, total, 0.0), -jnp.inf))
    chose_slip = jax.random.uniform(key, total.shape) < jax.lax.stop_gradient(slip_share)

    def pick(a, b):
        return jnp.where(chose_slip.reshape(chose_slip.shape + (1,) * (a.ndim - 1)), b, a)

    mixed = jax.tree.map(pick, usual, slipped)
    return mixed._replace(log_weight_increment=total), chose_slip
