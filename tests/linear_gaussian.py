"""A 1-D linear-Gaussian state-space model for the gradient and learning tests: its exact
log-likelihood (Kalman filter) and a bootstrap particle filter's estimate of it, built on the
package's ``particle_filter.reweight_and_resample``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.stats import norm

from jaxslam.particle_filter import reweight_and_resample

THETA = jnp.array([0.9, 0.5, 0.3])  # a, q, r: x_t = a x_{t-1} + N(0, q), y_t = x_t + N(0, r), x_0 ~ N(0, 1)


def simulate(key, theta, num_steps):
    a, q, r = theta
    k0, k1 = jax.random.split(key)

    def step(x, k):
        ka, kb = jax.random.split(k)
        x = a * x + jnp.sqrt(q) * jax.random.normal(ka)
        return x, x + jnp.sqrt(r) * jax.random.normal(kb)

    _, ys = jax.lax.scan(step, jax.random.normal(k0), jax.random.split(k1, num_steps))
    return ys


def kalman_log_likelihood(theta, ys):
    """Exact log p(y_1:T | theta) (the slow, obviously right reference)."""
    a, q, r = theta

    def step(carry, y):
        mean, var = carry
        mean, var = a * mean, a * a * var + q
        innovation_var = var + r
        gain = var / innovation_var
        return (mean + gain * (y - mean), (1.0 - gain) * var), norm.logpdf(y, mean, jnp.sqrt(innovation_var))

    _, terms = jax.lax.scan(step, (0.0, 1.0), ys)
    return terms.sum()


def particle_log_likelihood(theta, key, ys, num_particles, resampler, resample_threshold=1.0):
    """The bootstrap filter's estimate of log p(y_1:T | theta) (sum of the steps' log-evidence)."""
    a, q, r = theta
    k0, k1 = jax.random.split(key)
    x = jax.random.normal(k0, (num_particles,))
    log_weights = jnp.full((num_particles,), -jnp.log(num_particles))

    def step(carry, inputs):
        x, log_weights = carry
        k, y = inputs
        k_move, k_resample = jax.random.split(k)
        x = a * x + jnp.sqrt(q) * jax.random.normal(k_move, (num_particles,))  # reparameterised
        poses = jnp.stack([x, jnp.zeros_like(x), jnp.zeros_like(x)], axis=-1)
        update = reweight_and_resample(k_resample, poses, log_weights, norm.logpdf(y, x, jnp.sqrt(r)),
                                       jnp.float32(resample_threshold), resampler)
        return (x[update.ancestors], update.new_log_weights), update.log_evidence

    _, log_evidence = jax.lax.scan(step, (x, log_weights), (jax.random.split(k1, ys.shape[0]), ys))
    return log_evidence.sum()


def adapted_draw(key, theta, x_prev, y):
    """The fully adapted proposal, the analogue of the SMP's importance weight: x_t drawn from its
    exact posterior given x_t-1 and y_t (no gradient), weighed by gamma / q. Returns ``(x,
    increments)``: the increments are log p(y_t | x_t-1) in value (gamma / q is constant) with
    gradient d log gamma(x_t) = d log f(x_t | x_t-1) + d log g(y_t | x_t), the drawn state's score."""
    a, q, r = theta
    var = 1.0 / (1.0 / q + 1.0 / r)
    mean = var * (a * x_prev / q + y / r)
    no_grad = jax.lax.stop_gradient
    x = no_grad(mean + jnp.sqrt(var) * jax.random.normal(key, x_prev.shape))
    log_gamma = norm.logpdf(y, x, jnp.sqrt(r)) + norm.logpdf(x, a * x_prev, jnp.sqrt(q))
    return x, log_gamma - no_grad(norm.logpdf(x, mean, jnp.sqrt(var)))


def score_log_likelihood(theta, key, ys, num_particles, resampler="systematic", resample_threshold=1.0,
                         score_lag=None, proposal="bootstrap"):
    """The bootstrap filter's estimate of log p(y_1:T | theta) in the form the RBPF's OP learns
    by (:func:`jaxslam.motion.sample_with_score`): the states carry no gradient, and each
    particle's increment adds log f(x_t | x_t-1) - stop_gradient(itself), 0 in value, so that the
    gradient is a Fisher-identity score estimate, built by ``particle_filter.scan_filter``:
    the path-space score (``score_lag`` None) or the fixed-lag smoothed one (an int).
    ``proposal="adapted"`` draws from :func:`adapted_draw` instead (the SMP's counterpart)."""
    from jaxslam.particle_filter import scan_filter

    a, q, r = theta
    k0, k1 = jax.random.split(key)
    x0 = jax.random.normal(k0, (num_particles,))
    log_weights = jnp.full((num_particles,), -jnp.log(num_particles))

    def step(k, carry, y):
        x_prev, log_weights = carry
        k_move, k_resample = jax.random.split(k)
        if proposal == "adapted":
            x, increments = adapted_draw(k_move, theta, x_prev, y)
        else:
            x = jax.lax.stop_gradient(a * x_prev + jnp.sqrt(q) * jax.random.normal(k_move, (num_particles,)))
            log_f = norm.logpdf(x, a * x_prev, jnp.sqrt(q))
            increments = norm.logpdf(y, x, jnp.sqrt(r)) + log_f - jax.lax.stop_gradient(log_f)
        poses = jnp.stack([x, jnp.zeros_like(x), jnp.zeros_like(x)], axis=-1)
        update = reweight_and_resample(k_resample, poses, log_weights, increments, jnp.float32(resample_threshold),
                                       resampler)
        return (x[update.ancestors], update.new_log_weights), update.log_evidence, update.score_terms

    out = scan_filter(step, k1, (x0, log_weights), ys, lambda log_evidence: log_evidence, checkpoint=False,
                      score_lag=score_lag)
    return out.marginal_loglik


def kalman_score(theta, ys):
    """The exact score d log p(y_1:T | theta) / d theta."""
    return jax.grad(kalman_log_likelihood)(theta, ys)
