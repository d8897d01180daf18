"""Resampling and weight bookkeeping in log space.

Every resampler has the signature ``resample_fn(key, log_weights, num_samples) ->
indices`` and accepts unnormalised log-weights. Inverse-CDF lookups use
``searchsorted(side="right")`` on a CDF whose last entry is exactly 1, clamped
to the last index, so that a zero-weight particle is never drawn, even when the
float32 cumulative sum ends below 1.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

ResampleFn = Callable[[PRNGKeyArray, Float[Array, "N"], int], Int[Array, "M"]]


def normalize_log_weights(log_weights: Float[Array, "N"]) -> tuple[Float[Array, "N"], Float[Array, ""]]:
    """``(log_weights - logsumexp, logsumexp)``. When every weight is -inf the result is
    uniform (log 1/N each) and the returned logsumexp is -inf, for the caller to report."""
    total = jax.scipy.special.logsumexp(log_weights)
    finite = jnp.isfinite(total)
    uniform = jnp.full_like(log_weights, -jnp.log(log_weights.shape[0]))
    return jnp.where(finite, log_weights - jnp.where(finite, total, 0.0), uniform), total


def ess(log_weights: Float[Array, "N"]) -> Float[Array, ""]:
    """Effective sample size 1 / sum(w^2) of normalised weights, from unnormalised log-weights."""
    normalized, _ = normalize_log_weights(log_weights)
    return jnp.exp(-jax.scipy.special.logsumexp(2.0 * normalized))


def _cdf(log_weights: Float[Array, "N"]) -> Float[Array, "N"]:
    normalized, _ = normalize_log_weights(log_weights)
    cdf = jnp.cumsum(jnp.exp(normalized))
    return cdf / cdf[-1]  # exactly 1 at the end; monotone since the divisor is positive


def _inverse_cdf(cdf: Float[Array, "N"], u: Float[Array, "M"]) -> Int[Array, "M"]:
    # (u + M - 1) / M can round to exactly 1.0 in float32; keep u below 1 so that the
    # clamp below never lands on a zero-weight last particle.
    u = jnp.minimum(u, jnp.nextafter(jnp.float32(1.0), jnp.float32(0.0)))
    idx = jnp.searchsorted(cdf, u, side="right")
    return jnp.minimum(idx, cdf.shape[0] - 1).astype(jnp.int32)


def systematic(key: PRNGKeyArray, log_weights: Float[Array, "N"], num_samples: int) -> Int[Array, "M"]:
    """Systematic resampling: one uniform offset, evenly spaced points."""
    u = (jax.random.uniform(key, ()) + jnp.arange(num_samples)) / num_samples
    return _inverse_cdf(_cdf(log_weights), u)


def stratified(key: PRNGKeyArray, log_weights: Float[Array, "N"], num_samples: int) -> Int[Array, "M"]:
    """Stratified resampling: one uniform point in each of ``num_samples`` equal strata."""
    u = (jax.random.uniform(key, (num_samples,)) + jnp.arange(num_samples)) / num_samples
    return _inverse_cdf(_cdf(log_weights), u)


def multinomial(key: PRNGKeyArray, log_weights: Float[Array, "N"], num_samples: int) -> Int[Array, "M"]:
    """Multinomial resampling: independent draws from the weights."""
    u = jax.random.uniform(key, (num_samples,))
    return _inverse_cdf(_cdf(log_weights), u)


def residual(key: PRNGKeyArray, log_weights: Float[Array, "N"], num_samples: int) -> Int[Array, "M"]:
    """Residual resampling: floor(M w_i) copies of each particle, the rest multinomial on the residues."""
    normalized, _ = normalize_log_weights(log_weights)
    weights = jnp.exp(normalized)
    n = log_weights.shape[0]
    copies = jnp.floor(num_samples * weights).astype(jnp.int32)
    # Deterministic part: particle i fills slots [start_i, start_i + copies_i).
    starts = jnp.cumsum(copies) - copies
    slots = jnp.arange(num_samples)
    deterministic = jnp.minimum(jnp.searchsorted(starts + copies, slots, side="right"), n - 1)
    num_det = jnp.sum(copies)
    residues = num_samples * weights - copies
    log_res = safe_log(residues)
    random_part = multinomial(key, log_res, num_samples)
    # If every residue is zero (num_det == num_samples) the random part is never used.
    return jnp.where(slots < num_det, deterministic, random_part).astype(jnp.int32)


def safe_log(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """log(x) for x >= 0: -inf where x is 0, with no NaN in the gradient there (double where)."""
    positive = x > 0
    return jnp.where(positive, jnp.log(jnp.where(positive, x, 1.0)), -jnp.inf)


RESAMPLERS: dict[str, ResampleFn] = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
    "residual": residual,
}


def resample_if_needed(
    key: PRNGKeyArray,
    log_weights: Float[Array, "N"],
    resample_threshold: Float[Array, ""],
    resample_fn: ResampleFn = systematic,
) -> tuple[Int[Array, "N"], Float[Array, "N"], Bool[Array, ""]]:
    """Selective resampling: resample when ESS < ``resample_threshold`` * N.

    Returns ``(ancestors, new_log_weights, resampled)``: identity ancestors and the
    normalised weights when no resampling happens, uniform weights after it.

    What autodiff sees of a resampling (the score gradient): the weights after it are
    ``1/N * w[a] / stop_gradient(w[a])`` (Scibior & Wood 2021, "Differentiable particle filtering
    without modifying the forward pass"): 1/N in value, but their derivative carries the
    resampling's dependence on the parameters, so that the gradient of the filter's
    log-likelihood estimate is the particle estimate of the score (Fisher's identity over the
    surviving paths, as Poyiadjis, Doucet and Singh 2011), consistent as N grows.
    """
    n = log_weights.shape[0]
    normalized, _ = normalize_log_weights(log_weights)
    do = ess(normalized) < resample_threshold * n
    drawn = resample_fn(key, normalized, n)
    ancestors = jnp.where(do, drawn, jnp.arange(n, dtype=jnp.int32))
    uniform = jnp.full_like(normalized, -jnp.log(n))
    # x - stop_gradient(x) is exactly 0 for finite x, so the value stays 1/N bit for bit. A
    # drawn particle never has weight zero; the where keeps an impossible -inf from making NaN.
    picked = normalized[drawn]
    uniform = uniform + jnp.where(jnp.isfinite(picked), picked - jax.lax.stop_gradient(picked), 0.0)
    new_log_weights = jnp.where(do, uniform, normalized)
    return ancestors, new_log_weights, do


def keep_in_place(ancestors: Int[Array, "N"]) -> tuple[Int[Array, "N"], Int[Array, "N"]]:
    """The same draw with every drawn index in its own slot: ``(arranged, order)``, ``arranged =
    ancestors[order]``, ``arranged[i] = i`` wherever ``i`` was drawn, and the extra copies of
    the indices drawn more than once fill the slots of those never drawn (in increasing order).

    A resampling's outcome is the multiset of ancestors, not their order: arranged so, the only
    slots that change are those whose own occupant was not drawn, and no slot that is copied
    from is itself overwritten (:mod:`jaxslam.islands` moves a whole island's maps only for the
    islands replaced). ``order`` permutes whatever goes with the ancestors (the new log-weights
    of :func:`resample_if_needed`, with their score terms)."""
    n = ancestors.shape[0]
    order = jnp.argsort(ancestors, stable=True)
    drawn = ancestors[order]  # sorted
    first = jnp.concatenate([jnp.ones((1,), bool), drawn[1:] != drawn[:-1]])
    never_drawn = jnp.ones((n,), bool).at[ancestors].set(False)
    empty_slots = jnp.nonzero(never_drawn, size=n, fill_value=n - 1)[0]
    extra_rank = jnp.cumsum(~first) - 1  # the k-th extra copy goes to the k-th empty slot
    slot = jnp.where(first, drawn, empty_slots[jnp.maximum(extra_rank, 0)])
    arranged = jnp.zeros_like(ancestors).at[slot].set(drawn)
    return arranged, jnp.zeros_like(order).at[slot].set(order).astype(jnp.int32)
