"""The binary Bayes filter in closed form, shared by occupancy-grid cells and doors.

A binary state y (cell occupied / door open) is tracked either as log-odds
``l = log p(y) / (1 - p(y))`` (grid cells: the static-state update is an addition, done by
:mod:`jaxslam.occupancy`; :func:`probability` reads a map back) or as a probability ``p`` (doors: a transition model mixes the states between
steps, which is linear in p).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def probability(logodds_value: Float[Array, "..."]) -> Float[Array, "..."]:
    """Probability of a log-odds value. A NumPy array (a map on the host, for outputs and
    figures) gives a float64 NumPy array; anything else a JAX array of its float type."""
    if isinstance(logodds_value, np.ndarray):
        return 1.0 / (1.0 + np.exp(-logodds_value.astype(np.float64)))
    return jax.nn.sigmoid(logodds_value)


def predict(p, p_stay, p_enter):
    """One step of the transition model (Avots et al., Eq. 24).

    Args:
      p: p(y_{t-1} = 1), any shape.
      p_stay: p(y_t = 1 | y_{t-1} = 1), e.g. p(open | open).
      p_enter: p(y_t = 1 | y_{t-1} = 0), e.g. p(open | closed).

    Returns:
      p(y_t = 1) before the measurement.
    """
    return p_stay * p + p_enter * (1.0 - p)


def stationary(p_stay, p_enter):
    """The stationary probability of y = 1 under the transition model: p_enter / (1 - p_stay + p_enter)."""
    return p_enter / (1.0 - p_stay + p_enter)


def predict_n(p, p_stay, p_enter, steps):
    """``steps`` transition steps in closed form: the distance to the stationary value shrinks
    by (p_stay - p_enter) per step."""
    lam = p_stay - p_enter
    static = lam >= 1.0  # p_stay = 1, p_enter = 0: the state never changes (no stationary mix)
    s = jnp.where(static, p, p_enter / jnp.where(static, 1.0, 1.0 - lam))
    return s + (p - s) * lam**steps


@jax.custom_jvp
def update(p_prior, log_lik_true, log_lik_false):
    """Measurement update in probability space, from log-likelihoods of the two states.

    Returns ``(posterior, log_evidence)`` with posterior = L1 p / (L1 p + L0 (1 - p)) and
    log_evidence = log(L1 p + L0 (1 - p)) (Avots et al., Eqs. 27-28 and 33). Computed in
    log space, so that tiny likelihoods neither underflow nor produce NaN. The derivatives are
    written out (:func:`_update_jvp`): through ``log(p)`` autodiff would give NaN at a belief of
    exactly 0 or 1 (a door known not to move), where the update's derivatives are finite.
    """
    a = log_lik_true + jnp.log(p_prior)
    b = log_lik_false + jnp.log1p(-p_prior)
    log_evidence = jnp.logaddexp(a, b)
    posterior = jnp.exp(a - jnp.where(jnp.isfinite(log_evidence), log_evidence, 0.0))
    posterior = jnp.where(jnp.isfinite(log_evidence), posterior, p_prior)
    return posterior, log_evidence


@update.defjvp
def _update_jvp(primals, tangents):
    p, l1, l0 = primals
    dp, dl1, dl0 = tangents
    posterior, log_evidence = update(p, l1, l0)
    finite = jnp.isfinite(log_evidence)
    ev = jnp.where(finite, log_evidence, 0.0)
    # L1 / ev and L0 / ev, finite whenever the evidence is (p at 0 or 1 included).
    r1 = jnp.where(finite, jnp.exp(jnp.where(finite, l1 - ev, 0.0)), 0.0)
    r0 = jnp.where(finite, jnp.exp(jnp.where(finite, l0 - ev, 0.0)), 0.0)
    spread = posterior * (1.0 - posterior)
    d_log_evidence = (r1 - r0) * dp + posterior * dl1 + (1.0 - posterior) * dl0
    d_posterior = jnp.where(finite, r1 * r0 * dp + spread * (dl1 - dl0), dp)
    return (posterior, log_evidence), (d_posterior, jnp.where(finite, d_log_evidence, 0.0))
