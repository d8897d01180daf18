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
    score_terms: "ScoreTerms"
    """What :func:`fixed_lag_score` needs of this step."""


class ScoreTerms(NamedTuple):
    """One step's share of the filter's score, per particle (stacked over the steps by
    :func:`scan_filter`, for :func:`fixed_lag_score`)."""

    log_weights: Float[Array, "N"]
    """Normalised log-weights after the update, before resampling (no gradient needed)."""
    increments: Float[Array, "N"]
    """0 in value; gradient: the gradient of each particle's log-weight increment (with any
    score term in it, as :func:`jaxslam.motion.sample_with_score`'s); 0 where the increment is
    not finite."""
    ancestors: Int[Array, "N"]
    """After the step's resampling, particle i descends from particle ``ancestors[i]``."""


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
    finite = jnp.isfinite(log_increments)
    score_increments = jnp.where(finite, log_increments - jax.lax.stop_gradient(log_increments), 0.0)
    return WeightUpdate(normalized, log_evidence, ~jnp.isfinite(log_evidence), resampling.ess(normalized),
                        mean, cov, ancestors, resampled, new_log_weights,
                        ScoreTerms(normalized, score_increments, ancestors))


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


def even_block_size(count: int, most: int) -> int:
    """The block size that cuts ``count`` items into as few blocks of at most ``most`` as possible,
    as even as possible (1,000 particles in blocks of at most 128: 8 of 125), so that a
    blocked map over them has no remainder block, or a small one, to compile and run apart."""
    if count < 1 or most < 1:
        raise ValueError(f"even_block_size needs a positive count and block size, got {count} and {most}")
    num_blocks = -(-count // most)
    return -(-count // num_blocks)


def map_in_blocks(fn: Callable, xs, most: int | None):
    """``jax.vmap(fn)(xs)``, computed ``most`` particles (leading items) at a time at most: a
    ``lax.map`` over blocks of :func:`even_block_size`, each block vmapped. The same values as
    the one vmap; its intermediates cost a block's worth of memory, not all items'. ``most``
    None: one vmap."""
    count = jax.tree.leaves(xs)[0].shape[0]
    if most is None or most >= count:
        return jax.vmap(fn)(xs)
    return jax.lax.map(fn, xs, batch_size=even_block_size(count, most))


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
                checkpoint: bool = True, score_lag: int | None = None) -> FilterOutput:
    """:func:`scan_steps` with one key per step split from ``key``, and the summed log-evidence
    ``log_evidence_fn(stacked_info)``: a whole-log filter as one pure function.

    ``step_fn(key, state, inputs_t)`` returns ``(state, info)`` or ``(state, info, ScoreTerms)``
    (its :class:`WeightUpdate`'s ``score_terms``). ``score_lag`` (static; needs the second form):
    None, or at least the number of steps, leaves the gradient of ``marginal_loglik`` the
    path-space score (:func:`jaxslam.resampling.resample_if_needed`); an int L makes it the
    fixed-lag smoothed score (:func:`fixed_lag_score`). The value is the same bit for bit.
    """
    num_steps = jax.tree.leaves(inputs)[0].shape[0]
    smoothed = score_lag is not None and score_lag < num_steps

    def body(k, s, inp):
        out = step_fn(k, s, inp)
        # The terms leave the scan only when used: the program is then the same as without them.
        return out[0], (out[1], out[2] if smoothed and len(out) == 3 else None)

    final, (info, terms) = scan_steps(body, state, jax.random.split(key, num_steps), inputs, checkpoint)
    marginal_loglik = jnp.sum(log_evidence_fn(info))
    if smoothed:
        if terms is None:
            raise ValueError("scan_filter: score_lag needs a step_fn that returns (state, info, ScoreTerms)")
        marginal_loglik = marginal_loglik + fixed_lag_score(terms, score_lag)
    return FilterOutput(final, info, marginal_loglik)


def fixed_lag_score(terms: ScoreTerms, lag: int) -> Float[Array, ""]:
    """0 in value; added to a filter's log-likelihood estimate, it turns the estimate's gradient
    from the path-space score into the fixed-lag smoothed score (Olsson, Cappe, Douc & Moulines
    2008; Kantas et al. 2015, section 5).

    The path-space score (what autodiff of the summed log-evidence gives, through
    :func:`jaxslam.resampling.resample_if_needed`) is sum_i W_{T,i} sum_t g_t(ancestor of i at t),
    g_t the gradient of step t's log-weight increment: every step's term averaged over the final
    particles' ancestral paths, which after many resamplings share a few ancestors (path
    degeneracy), so the early terms are averaged over a handful of paths. The fixed-lag score
    averages step t's term over the particles ``lag`` steps later instead, sum_t sum_i
    W_{t+lag,i} g_t(ancestor of i at t) (the last ``lag`` steps' terms with the final weights): it
    ignores what the observations after t + lag say about x_t (a bias that falls as the lag
    grows, since the model forgets), and keeps ~N distinct ancestors per term. ``lag`` = 0 is the
    filtering weights' estimate, ``lag`` >= T - 1 the path-space score (to rounding).

    Each particle carries a ring buffer of its last ``lag`` + 1 terms, permuted with its
    ancestors at every step, as the accumulated path sums are; the returned scalar is the
    difference of the two estimators built from 0-valued terms (so exactly 0), T (N ``lag`` + 1)
    floats of work.

    Args:
      terms: the (T, ...) stacked :class:`ScoreTerms` of the filter's steps.
      lag: L >= 0 (static).
    """
    if lag < 0:
        raise ValueError(f"fixed_lag_score: lag must be >= 0 (or None for the path-space score), got {lag}")
    num_steps, n = terms.log_weights.shape
    if num_steps == 0:
        return jnp.zeros((), terms.increments.dtype)
    slots = lag + 1

    def body(carry, xs):
        buffer, path, matured = carry  # (N, L+1), (N,), ()
        log_weights, increments, ancestors, s = xs
        weights = jax.lax.stop_gradient(jnp.exp(log_weights))
        buffer = buffer.at[:, s % slots].set(increments)
        path = path + increments
        due = (s + 1) % slots  # the slot written L steps ago (this one when L = 0)
        matured = matured + weights @ buffer[:, due]
        buffer = buffer.at[:, due].set(0.0)
        # If the log ended here: the terms not yet matured with these weights, as the path sums.
        difference = matured + weights @ jnp.sum(buffer, axis=1) - weights @ path
        return (buffer[ancestors], path[ancestors], matured), difference

    zero = jnp.zeros((), terms.increments.dtype)
    init = (jnp.zeros((n, slots), terms.increments.dtype), jnp.zeros((n,), terms.increments.dtype), zero)
    _, differences = jax.lax.scan(body, init, (terms.log_weights, terms.increments, terms.ancestors,
                                               jnp.arange(num_steps)))
    return differences[-1]
