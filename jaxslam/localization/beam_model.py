"""The beam model of a laser in a known map (Thrun, Burgard & Fox, Probabilistic Robotics, 6.3).

Each measured range is scored against the range the map predicts by ray casting
(:mod:`jaxslam.segment_map`): a mixture of a Gaussian hit, an exponential of unexpected
short readings, a point mass at range_max and a uniform floor. MCL and the door filter
(:mod:`jaxslam.localization`) use it; the SLAM filters use the endpoint model of
:mod:`jaxslam.likelihood_field`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax.scipy.special import ndtr as _ndtr
from jaxtyping import Array, Float

from jaxslam.motion import LOG_2PI


class BeamModelParams(NamedTuple):
    """Traced numbers of the beam model (Thrun, Burgard & Fox, Probabilistic Robotics, 6.3).

    The four weights are normalised by their sum inside :func:`beam_model_log_likelihood`.
    """

    z_hit: Float[Array, ""]
    """Weight of the measurement-noise Gaussian around the expected range."""
    z_short: Float[Array, ""]
    """Weight of the exponential of unexpected obstacles (people) in front of the expected one."""
    z_max: Float[Array, ""]
    """Weight of the point mass at range_max (no return)."""
    z_rand: Float[Array, ""]
    """Weight of the uniform density of unexplained readings on [0, range_max)."""
    sigma_hit: Float[Array, ""]
    """Std (m) of the hit Gaussian."""
    lambda_short: Float[Array, ""]
    """Rate (1/m) of the short exponential."""


def make_beam_model_params(z_hit=0.8, z_short=0.1, z_max=0.05, z_rand=0.05, sigma_hit=0.1,
                           lambda_short=0.5) -> BeamModelParams:
    """A :class:`BeamModelParams` of float32 scalars."""
    f = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    return BeamModelParams(f(z_hit), f(z_short), f(z_max), f(z_rand), f(sigma_hit), f(lambda_short))


def beam_model_log_likelihood(
    expected_ranges: Float[Array, "... B"],
    ranges: Float[Array, "... B"],
    range_max: Float[Array, ""],
    params: BeamModelParams,
) -> Float[Array, "... B"]:
    """Per-beam log p(z_b | expected range) of the classic beam model mixture, in nats.

    A reading is a mixed measure: a density (1/m) on [0, range_max) and a point mass at
    range_max (every ``r >= range_max`` is "no return"). With the weights normalised to sum 1:

      hit:   N(r; expected, sigma_hit^2) truncated to [0, range_max]   (density)
      short: lambda e^(-lambda r) / (1 - e^(-lambda expected)) for r <= expected   (density)
      rand:  1 / range_max                                              (density)
      max:   1 at r >= range_max                                        (probability)

    A "no return" reading scores log z_max alone; a return scores
    log(z_hit hit + z_short short + z_rand rand). Computed in log space, finite for any
    finite input (expected ranges are clipped to [0, range_max]).

    Args:
      expected_ranges: (..., B) ranges (m) the map predicts (ray casting), broadcast with ``ranges``.
      ranges: (..., B) measured ranges (m).
      range_max: the sensor's maximum range (m).
      params: mixture weights, sigma_hit (m) and lambda_short (1/m).

    Returns:
      (..., B) float32 log-likelihoods (log of 1/m for returns, log of a probability for
      no-return readings).
    """
    range_max = jnp.asarray(range_max, jnp.float32)
    expected = jnp.clip(jnp.asarray(expected_ranges, jnp.float32), 0.0, range_max)
    r = jnp.asarray(ranges, jnp.float32)
    total = params.z_hit + params.z_short + params.z_max + params.z_rand
    log_w_hit = jnp.log(params.z_hit / total)
    log_w_short = jnp.log(params.z_short / total)
    log_w_max = jnp.log(params.z_max / total)
    log_w_rand = jnp.log(params.z_rand / total)
    sigma = params.sigma_hit
    # Hit: the Gaussian's mass inside [0, range_max] renormalises it .
    upper = _ndtr((range_max - expected) / sigma)
    lower = _ndtr(-expected / sigma)
    log_mass = jnp.log(jnp.maximum(upper - lower, 1e-30))
    z = (r - expected) / sigma
    log_hit = -0.5 * z**2 - jnp.log(sigma) - 0.5 * LOG_2PI - log_mass
    # Short: an exponential truncated to [0, expected]; impossible beyond the expected range
    # and when the expected range is 0 (nothing can stand in front of it).
    lam = params.lambda_short
    norm_short = -jnp.expm1(-lam * expected)  # 1 - e^(-lambda expected), exact for small values
    short_ok = (r <= expected) & (norm_short > 0)
    log_short = jnp.where(
        short_ok, jnp.log(lam) - lam * r - jnp.log(jnp.where(short_ok, norm_short, 1.0)), -jnp.inf)
    log_rand = -jnp.log(range_max)
    log_return = jnp.logaddexp(jnp.logaddexp(log_w_hit + log_hit, log_w_short + log_short),
                               log_w_rand + log_rand)
    return jnp.where(r >= range_max, log_w_max + jnp.zeros_like(log_return), log_return)
