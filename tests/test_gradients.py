"""Gradients through resampling (issue: differentiable filtering).

A bootstrap particle filter on a 1-D linear-Gaussian model, built on the package's
``particle_filter.reweight_and_resample``, against the Kalman filter's exact gradient of
log p(y_1:T | theta): with ``resampling_gradient="score"`` (Scibior & Wood's stop-gradient
construction) the gradient of the log-likelihood estimate, averaged over runs, matches it for
every resampling scheme; with ``"none"`` (resampling as an implicit stop-gradient on the
weights) it does not. Both give the same forward values bit for bit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import norm

from jaxslam import rbpf
from jaxslam.config import RunSettings, SlamConfig, default_params
from jaxslam.particle_filter import reweight_and_resample
from jaxslam.resampling import RESAMPLERS, resample_if_needed
from jaxslam.sim import office_scenario

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


def particle_log_likelihood(theta, key, ys, num_particles, resampler, gradient, resample_threshold=1.0):
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
                                       jnp.float32(resample_threshold), resampler, gradient)
        return (x[update.ancestors], update.new_log_weights), update.log_evidence

    _, log_evidence = jax.lax.scan(step, (x, log_weights), (jax.random.split(k1, ys.shape[0]), ys))
    return log_evidence.sum()


def _gradients(resampler, gradient, num_runs=400, num_particles=100, num_steps=10):
    ys = simulate(jax.random.key(0), THETA, num_steps)
    keys = jax.random.split(jax.random.key(1), num_runs)
    fn = jax.jit(jax.vmap(jax.value_and_grad(particle_log_likelihood), in_axes=(None, 0, None, None, None, None)),
                 static_argnums=(3, 4, 5))
    values, grads = fn(THETA, keys, ys, num_particles, resampler, gradient)
    exact = np.asarray(jax.grad(kalman_log_likelihood)(THETA, ys))
    grads = np.asarray(grads)
    z = (grads.mean(0) - exact) / (grads.std(0, ddof=1) / np.sqrt(num_runs))
    return np.asarray(values), grads, z


@pytest.mark.slow  # Monte Carlo check (python3 -m pytest -m slow)
@pytest.mark.parametrize("resampler", sorted(RESAMPLERS))
def test_score_gradient_matches_the_kalman_gradient(resampler):
    """Resampling every step (threshold 1), 400 runs of N = 100 over 10 steps: the mean gradient
    in (a, q, r) is within 3 Monte Carlo standard errors of the exact one (the estimator's bias,
    O(1/N), is below that); the implicit stop-gradient misses by more than 20."""
    _, _, z = _gradients(resampler, "score")
    assert np.all(np.abs(z) < 3.0), z
    _, _, z_none = _gradients(resampler, "none")
    assert np.all(np.abs(z_none) > 20.0), z_none


def test_resampling_gradient_keeps_the_forward_values():
    values_score, _, _ = _gradients("systematic", "score", num_runs=8)
    values_none, _, _ = _gradients("systematic", "none", num_runs=8)
    np.testing.assert_array_equal(values_score, values_none)


def test_without_resampling_autodiff_is_the_derivative_of_the_estimate():
    """No resampling (threshold 0): for a fixed key the estimate is smooth in theta, and its
    autodiff gradient equals a central finite difference of it."""
    ys = simulate(jax.random.key(0), THETA, 10)
    f = jax.jit(lambda th: particle_log_likelihood(th, jax.random.key(5), ys, 50, "systematic", "score", 0.0))
    grad = np.asarray(jax.grad(f)(THETA))
    eps = 1e-3
    fd = [(float(f(THETA.at[i].add(eps))) - float(f(THETA.at[i].add(-eps)))) / (2 * eps) for i in range(3)]
    np.testing.assert_allclose(grad, fd, rtol=1e-2)


def test_score_resampling_gradient_is_finite_with_zero_weights():
    """A particle of weight zero is never drawn: no -inf - -inf NaN reaches the gradient."""
    def f(shift):
        log_w = jnp.array([0.0, -jnp.inf, shift, -jnp.inf, 0.5 * shift])
        _, new_log_weights, resampled = resample_if_needed(jax.random.key(0), log_w, jnp.float32(1.0))
        return jax.scipy.special.logsumexp(new_log_weights + jnp.arange(5.0)), resampled

    (value, resampled), grad = jax.value_and_grad(f, has_aux=True)(jnp.float32(0.3))
    assert bool(resampled) and np.isfinite(float(value)) and np.isfinite(float(grad))


def test_rbpf_forward_is_the_same_for_either_resampling_gradient():
    log = office_scenario(jax.random.key(3)).log.subset(np.arange(60))
    settings = RunSettings(linear_update=0.3, angular_update=0.25)
    results = []
    for gradient in ("score", "none"):
        config = SlamConfig(num_particles=6, proposal="smp", max_insert_range=10.0, beam_stride=1, map_extent=128.0,
                            resampling_gradient=gradient)
        results.append(rbpf.run(jax.random.key(1), log, config, default_params(**{"resample_threshold": 0.9}),
                                settings, progress=False))
    a, b = results
    assert int(np.asarray(a.info.resampled).sum()) > 0  # the comparison covers resampling steps
    np.testing.assert_array_equal(np.asarray(a.trajectory), np.asarray(b.trajectory))
    np.testing.assert_array_equal(np.asarray(a.info.log_evidence), np.asarray(b.info.log_evidence))
    np.testing.assert_array_equal(np.asarray(a.state.log_weights), np.asarray(b.state.log_weights))
