"""The particle-filter core shared by SLAM (:mod:`jaxslam.rbpf`) and localization
(:mod:`jaxslam.localization`): weigh, normalise, measure, resample.

A step of every filter in the package ends the same way: multiply the weights by the
step's likelihood increments, normalise them (their sum is the step's evidence), report
the ESS and the weighted pose, and resample selectively. :func:`reweight_and_resample` does
that once for all of them, with the same names for the same quantities (``log_evidence``,
``degenerate``, ``ess``, ``resample_threshold``).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import resampling
from jaxslam.geometry import weighted_mean_and_covariance


class WeightUpdate(NamedTuple):
    """One weight update and its selective resampling."""

    log_weights: Float[Array, "N"]
    """Normalised log-weights after the update, before resampling (uniform when degenerate)."""
    log_evidence: Float[Array, ""]
    """log sum_i w_{t-1,i} exp(increment_i): the filter's estimate of log p(z_t | z_{1:t-1});
    -inf when every particle got weight zero."""
    degenerate: Bool[Array, ""]
    """Every particle got weight zero (-inf or NaN); the weights were reset to uniform."""
    ess: Float[Array, ""]
    """Effective sample size after the update, before resampling."""
    mean_pose: Float[Array, "3"]
    """Weighted mean pose after the update (circular mean in theta)."""
    pose_covariance: Float[Array, "3 3"]
    """Weighted covariance of the poses (theta residuals wrapped)."""
    ancestors: Int[Array, "N"]
    """After resampling, particle i descends from particle ``ancestors[i]`` (identity when the
    ESS was high enough)."""
    resampled: Bool[Array, ""]
    """Whether the particles were resampled."""
    new_log_weights: Float[Array, "N"]
    """Log-weights after resampling (uniform when resampled)."""


def reweight_and_resample(
    key: PRNGKeyArray,
    poses: Float[Array, "N 3"],
    log_weights: Float[Array, "N"],
    log_increments: Float[Array, "N"],
    resample_threshold: Float[Array, ""],
    resampler: str,
) -> WeightUpdate:
    """Multiply the weights by ``exp(log_increments)``, normalise, and resample when
    ESS < ``resample_threshold`` * N with the named scheme (:data:`resampling.RESAMPLERS`), score
    gradients through the resampling (:func:`resampling.resample_if_needed`).

    A NaN weight counts as zero; when every weight is zero the weights become uniform and
    ``degenerate`` says so. ``poses`` only feed the weighted mean and covariance; the caller
    gathers its per-particle state with ``ancestors``.
    """
    updated = log_weights + log_increments
    updated = jnp.where(jnp.isnan(updated), -jnp.inf, updated)
    normalized, log_evidence = resampling.normalize_log_weights(updated)
    mean, cov = weighted_mean_and_covariance(poses, jnp.exp(normalized))
    ancestors, new_log_weights, resampled = resampling.resample_if_needed(
        key, normalized, resample_threshold, resampling.RESAMPLERS[resampler])
    return WeightUpdate(normalized, log_evidence, ~jnp.isfinite(log_evidence), resampling.ess(normalized),
                        mean, cov, ancestors, resampled, new_log_weights)


class FilterOutput(NamedTuple):
    """What a whole-log filter function returns (``rbpf.filter``, ``mcl.filter``, ``doors.filter``)."""

    state: Any
    """The particles after the last step."""
    info: Any
    """Every step's diagnostics, stacked over the steps."""
    marginal_loglik: Float[Array, ""]
    """The filter's estimate of the log-likelihood of the observations given the parameters: the
    sum of the steps' ``log_evidence`` (tempered by the likelihood gain like the weights; -inf
    after a degenerate step). Its gradient is the score estimate of
    :func:`jaxslam.resampling.resample_if_needed`."""


def scan_steps(step_fn: Callable, state, keys: PRNGKeyArray, inputs, checkpoint: bool = False):
    """``step_fn(key, state, inputs_t) -> (state, info)`` over the leading axis of ``keys`` and
    ``inputs`` in one ``lax.scan``: ``(final state, stacked infos)``. The one loop body of every
    filter in the package (:func:`scan_filter`, and :func:`jaxslam.slam.run` chunk by chunk).

    ``checkpoint``: rematerialise each step under reverse-mode differentiation
    (``jax.checkpoint``), so that a gradient over T steps keeps T particle sets, not T steps'
    intermediates (for a localization filter, its N x B x M ray casts); it changes no value but
    for rounding (the compiler may fuse a rematerialised step differently: the door filter's
    beliefs on the corridors scenario differed in the last bit, 6 of 425).
    """
    body = jax.checkpoint(step_fn) if checkpoint else step_fn
    return jax.lax.scan(lambda carry, xs: body(xs[0], carry, xs[1]), state, (keys, inputs))


def scan_filter(step_fn: Callable, key: PRNGKeyArray, state, inputs, log_evidence_fn: Callable,
                checkpoint: bool = True) -> FilterOutput:
    """:func:`scan_steps` with one key per step split from ``key``, and the summed log-evidence
    ``log_evidence_fn(stacked_info)``: a whole-log filter as one pure function."""
    num_steps = jax.tree.leaves(inputs)[0].shape[0]
    final, info = scan_steps(step_fn, state, jax.random.split(key, num_steps), inputs, checkpoint)
    return FilterOutput(final, info, jnp.sum(log_evidence_fn(info)))


def best_particle(log_weights) -> int:
    """Index of the particle with the largest weight (host-side, from any array of log-weights)."""
    return int(np.argmax(np.asarray(log_weights)))
