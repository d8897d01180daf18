"""Gradients through resampling (issue: differentiable filtering).

A bootstrap particle filter on a 1-D linear-Gaussian model, built on the package's
``particle_filter.reweight_and_resample``, against the Kalman filter's exact gradient of
log p(y_1:T | theta): with the score gradient through resampling (Scibior & Wood's
stop-gradient construction) the gradient of the log-likelihood estimate, averaged over runs,
matches it for every resampling scheme.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from linear_gaussian import THETA, kalman_log_likelihood, particle_log_likelihood, simulate

from jaxslam import rbpf, slam
from jaxslam.config import RunSettings, SlamConfig, default_params
from jaxslam.resampling import RESAMPLERS, resample_if_needed
from jaxslam.sim import office_scenario

def _gradients(resampler, num_runs=400, num_particles=100, num_steps=10):
    ys = simulate(jax.random.key(0), THETA, num_steps)
    keys = jax.random.split(jax.random.key(1), num_runs)
    fn = jax.jit(jax.vmap(jax.value_and_grad(particle_log_likelihood), in_axes=(None, 0, None, None, None)),
                 static_argnums=(3, 4))
    values, grads = fn(THETA, keys, ys, num_particles, resampler)
    exact = np.asarray(jax.grad(kalman_log_likelihood)(THETA, ys))
    grads = np.asarray(grads)
    z = (grads.mean(0) - exact) / (grads.std(0, ddof=1) / np.sqrt(num_runs))
    return np.asarray(values), grads, z


@pytest.mark.slow  # Monte Carlo check (python3 -m pytest -m slow)
@pytest.mark.parametrize("resampler", sorted(RESAMPLERS))
def test_score_gradient_matches_the_kalman_gradient(resampler):
    """Resampling every step (threshold 1), 400 runs of N = 100 over 10 steps: the mean gradient
    in (a, q, r) is within 3 Monte Carlo standard errors of the exact one (the estimator's bias,
    O(1/N), is below that)."""
    _, _, z = _gradients(resampler)
    assert np.all(np.abs(z) < 3.0), z


def test_without_resampling_autodiff_is_the_derivative_of_the_estimate():
    """No resampling (threshold 0): for a fixed key the estimate is smooth in theta, and its
    autodiff gradient equals a central finite difference of it."""
    ys = simulate(jax.random.key(0), THETA, 10)
    f = jax.jit(lambda th: particle_log_likelihood(th, jax.random.key(5), ys, 50, "systematic", 0.0))
    grad = np.asarray(jax.grad(f)(THETA))
    eps = 1e-3
    fd = [(float(f(THETA.at[i].add(eps))) - float(f(THETA.at[i].add(-eps)))) / (2 * eps) for i in range(3)]
    np.testing.assert_allclose(grad, fd, rtol=1e-2)


def test_score_resampling_gradient_is_finite_with_zero_weights():
    """The package's resamplers never draw a particle of weight zero; a resampler that does
    (here one that always draws particle 1, of weight zero) must not turn its -inf - -inf into
    NaN weights or gradients."""
    def f(shift, resample_fn):
        log_w = jnp.array([0.0, -jnp.inf, shift, -jnp.inf, 0.5 * shift])
        _, new_log_weights, resampled = resample_if_needed(jax.random.key(0), log_w, jnp.float32(1.0), resample_fn)
        return jax.scipy.special.logsumexp(new_log_weights + jnp.arange(5.0)), (resampled, new_log_weights)

    def draws_a_dead_particle(key, log_weights, num_samples):
        return jnp.ones((num_samples,), jnp.int32)

    for resample_fn in (RESAMPLERS["systematic"], draws_a_dead_particle):
        (value, (resampled, weights)), grad = jax.value_and_grad(f, has_aux=True)(jnp.float32(0.3), resample_fn)
        assert bool(resampled) and np.isfinite(float(value)) and np.isfinite(float(grad))
        np.testing.assert_array_equal(np.asarray(weights), np.full(5, -np.log(5.0), np.float32))


def test_selection_mixture_derivative_is_exact_and_finite_at_the_ends():
    """The LP's selection probabilities log[(1 - alpha) a + alpha b]: autodiff equals the
    derivative written out (checked by central differences inside (0, 1)) and stays finite
    at alpha = 0, the paper's Eq. 10, where log(alpha) is -inf."""
    from jaxslam.proposals.lookahead import _log_mixture

    log_a = jnp.log(jnp.array([0.5, 0.3, 0.2, 0.0]))
    log_b = jnp.log(jnp.array([0.1, 0.2, 0.3, 0.4]))

    def f(alpha, log_a, log_b):
        return jnp.sum(jnp.sin(jnp.arange(1.0, 5.0)) * _log_mixture(alpha, log_a, log_b))

    for alpha in (0.3, 0.7):
        grads = jax.grad(f, argnums=(0, 1, 2))(jnp.float32(alpha), log_a, log_b)
        eps = 1e-3
        fd_alpha = (f(alpha + eps, log_a, log_b) - f(alpha - eps, log_a, log_b)) / (2 * eps)
        np.testing.assert_allclose(grads[0], fd_alpha, rtol=2e-3)
        i = 1
        fd_a = (f(alpha, log_a.at[i].add(eps), log_b) - f(alpha, log_a.at[i].add(-eps), log_b)) / (2 * eps)
        np.testing.assert_allclose(grads[1][i], fd_a, rtol=2e-3)
    grads = jax.grad(f, argnums=(0, 1, 2))(jnp.float32(0.0), log_a, log_b)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)
    # At alpha = 0 the mixture is a alone: d/dalpha log p_i = b_i / a_i - 1 where a_i > 0.
    expected = jnp.sum(jnp.sin(jnp.arange(1.0, 4.0)) * (jnp.exp(log_b[:3] - log_a[:3]) - 1.0))
    np.testing.assert_allclose(grads[0], expected, rtol=1e-5)


@pytest.mark.parametrize("learning,alpha", [(False, 0.0), (True, 0.0), (True, 0.5)],
                         ids=["mapping", "learning", "learning-alpha0.5"])
def test_lookahead_at_alpha_zero_has_finite_gradients(learning, alpha):
    """The paper's Eq. 10 (lookahead.alpha = 0): the log-likelihood estimate of a short LP run
    and its gradient in every parameter are finite. With the mapping settings they were NaN for
    the sensor, alpha and the localizer gain; with the learning settings (gain 1, every scan,
    bilinear lookup, the paper's localizers), 100 localizers over 5 scans leave samples of the
    time-t cloud whose selection probability is 0 in float32, and the derivative in alpha of
    such a sample's log p (b / p, infinite) times its zero cotangent was NaN in 11 parameters.
    Since issue 35 log p_J enters the increment without gradient, so the derivative in alpha is
    0 (E[exp(increment)] does not depend on alpha); the learning settings also with alpha = 0.5."""
    if learning:
        from jaxslam.learning import slam_learning_setup

        log = office_scenario(jax.random.key(0)).log.subset(np.arange(60))
        config, settings, _ = slam_learning_setup({"proposal": "lp", "num_particles": 10, "num_localizers": 100,
                                                   "horizon": 5, "lookahead_initial": "odometry"})
        prepared, _, _ = rbpf.prepare(log, config, settings)
        params = default_params(**{"lookahead.alpha": alpha, "likelihood.gain": 1.0})
    else:
        log = office_scenario(jax.random.key(3)).log.subset(np.arange(30))
        config = SlamConfig(num_particles=3, proposal="lp", num_localizers=8, horizon=2, max_insert_range=10.0,
                            beam_stride=4, map_extent=128.0)
        prepared, _, _ = rbpf.prepare(log, config, RunSettings(linear_update=0.3, angular_update=0.25))
        params = default_params(**{"lookahead.alpha": 0.0})

    def log_likelihood(params):
        return rbpf.filter(jax.random.key(1), prepared, params, config).marginal_loglik

    value, grads = jax.jit(jax.value_and_grad(log_likelihood))(params)
    assert np.isfinite(float(value))
    bad = [jax.tree_util.keystr(path) for path, g in jax.tree_util.tree_flatten_with_path(grads)[0]
           if not np.isfinite(float(g))]
    assert not bad, bad
    assert float(grads.lookahead.alpha) == 0.0


def test_the_pure_filter_is_run_bit_for_bit_compiles_once_and_vmaps():
    """``rbpf.filter`` (init + lax.scan of the step, one jitted function) gives ``slam.run``'s
    particles bit for bit, compiles once for new parameter values and keys, and vmaps over keys."""
    import chex

    log = office_scenario(jax.random.key(3)).log.subset(np.arange(60))
    settings = RunSettings(linear_update=0.3, angular_update=0.25)
    config = SlamConfig(num_particles=6, proposal="smp", max_insert_range=10.0, beam_stride=1, map_extent=128.0)
    params = default_params()
    result = slam.run(jax.random.key(1), log, config, params, settings, progress=False)
    prepared, selection, _ = rbpf.prepare(log, config, settings)
    np.testing.assert_array_equal(selection.indices, result.selection.indices)

    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def filter_fn(key, params):
        return rbpf.filter(key, prepared, params, config)

    out = filter_fn(jax.random.key(1), params)
    np.testing.assert_array_equal(np.asarray(out.info.proposed_poses), np.asarray(result.info.proposed_poses))
    np.testing.assert_array_equal(np.asarray(out.state.log_weights), np.asarray(result.state.log_weights))
    # The same steps' evidence; only the order of the float32 sum may differ (XLA's against NumPy's).
    np.testing.assert_allclose(float(out.marginal_loglik), np.sum(np.asarray(result.info.log_evidence, np.float64)),
                               rtol=1e-6)
    assert not bool(out.state.maps.overflow)
    other = filter_fn(jax.random.key(2), default_params(**{"motion.srr": 0.2}))  # no retrace
    assert np.isfinite(float(other.marginal_loglik))

    keys = jax.random.split(jax.random.key(7), 2)
    batched = jax.jit(jax.vmap(lambda k: rbpf.filter(k, prepared, params, config).marginal_loglik))(keys)
    singles = [float(filter_fn(k, params).marginal_loglik) for k in keys]
    # vmap compiles another program (other fusions, so other float32 summation orders over the
    # window posterior's hundreds of poses a particle): 1.02e-5 apart on 2026-11-26, no draw changed.
    np.testing.assert_allclose(np.asarray(batched), singles, rtol=1e-4)


@pytest.mark.slow  # whole-filter gradients of four configurations, eight compilations (python3 -m pytest -m slow)
@pytest.mark.parametrize("proposal,initial", [("op", "odometry"), ("smp", "odometry"), ("lp", "odometry"),
                                              ("lp", "scan_match")])
def test_which_configurations_give_motion_gradients(proposal, initial):
    """The OP's and the LP's motion-noise gradients are the scores of their draws (the LP's
    time-t localizers: issue 35), finite and nonzero with either likelihood lookup. The SMP's goes
    through the step's own draw: with the nearest-cell likelihood the weights are piecewise
    constant in the pose, but its matched Gaussian carries the motion prior, so it is nonzero too;
    with likelihood_lookup="bilinear" all are finite and nonzero. Before issue 35 the paper's LP's
    was pathwise and exactly 0 with the nearest cell. Reverse-mode autodiff goes through the whole
    filter (the maps' computed-once loops included)."""
    log = office_scenario(jax.random.key(3)).log.subset(np.arange(40))
    grads = {}
    for lookup in ("nearest", "bilinear"):
        config = SlamConfig(num_particles=4, proposal=proposal, num_localizers=8, horizon=2, max_insert_range=10.0,
                            beam_stride=4, map_extent=128.0, likelihood_lookup=lookup, lookahead_initial=initial)
        prepared, _, _ = rbpf.prepare(log, config, RunSettings(linear_update=0.3, angular_update=0.25))
        grads[lookup] = jax.jit(jax.grad(
            lambda p: rbpf.filter(jax.random.key(1), prepared, p, config).marginal_loglik))(default_params())
    nearest, bilinear = (np.array([float(getattr(grads[k].motion, n)) for n in ("srr", "srt", "str", "stt")])
                         for k in ("nearest", "bilinear"))
    assert np.all(np.isfinite(bilinear)) and np.all(bilinear[[0, 3]] != 0.0)
    assert np.all(np.isfinite(nearest)) and np.all(nearest[[0, 3]] != 0.0)


def test_the_log_likelihood_has_a_maximum_in_sigma():
    """``known_path_loglik_fn`` on the true path of the simulated office, 1 cm cells: the
    normalised log-likelihood peaks at a finite sigma (below the 2 cm range noise: the field
    measures the distance to the nearest earlier endpoint) and is bounded as sigma falls below a
    cell. Two normalisers that fail, shown: none (the weights' terms alone rise with sigma at
    every value) and a half-normal's per beam, sqrt(2/pi)/sigma, which ignores that the distance is
    known only to the cell: every endpoint in a registered cell is then worth log(1/sigma), and
    the log-likelihood rises without bound as sigma falls."""
    log = office_scenario(jax.random.key(0)).log.subset(np.arange(80))
    true_log = dataclasses.replace(log, odometry=np.asarray(log.ground_truth, log.odometry.dtype))
    cell = 0.01
    config = SlamConfig(num_particles=1, proposal="op", max_insert_range=10.0, beam_stride=1, map_extent=64.0,
                        resolution=cell, field_radius=11, likelihood_lookup="bilinear")
    every_scan = RunSettings(linear_update=0.0, angular_update=0.0)
    known_path_loglik = rbpf.known_path_loglik_fn(true_log, config, every_scan)
    ranges = log.ranges[1:]  # every scan after the first is scored
    counted = np.sum((ranges >= log.sensor.range_min) & (ranges < log.sensor.range_max))
    sigmas = [0.0005, 0.002, 0.012, 0.04]
    normalised, shape_only, half_normal = [], [], []
    for sigma in sigmas:
        value = float(known_path_loglik(default_params(**{"likelihood.sigma": sigma, "likelihood.gain": 1.0})))
        log_z = np.log(cell * np.sum(np.exp(-0.5 * (np.arange(1000) * cell / sigma) ** 2)))
        normalised.append(value)
        shape_only.append(value + counted * log_z)
        half_normal.append(shape_only[-1] + counted * (0.5 * np.log(2 / np.pi) - np.log(sigma)))
    assert normalised[2] > max(normalised[0], normalised[1], normalised[3])
    assert normalised[0] == pytest.approx(normalised[1], rel=1e-3)  # flat below a cell, not rising
    assert half_normal[0] > half_normal[1] > half_normal[2]
    assert shape_only[0] < shape_only[1] < shape_only[2] < shape_only[3]
    # The poses are known: the motion noise plays no part.
    wide = default_params(**{"likelihood.sigma": sigmas[2], "likelihood.gain": 1.0, "motion.srr": 0.3, "motion.stt": 0.4})
    assert float(known_path_loglik(wide)) == normalised[2]
    # A pool too small for the path's tiles gives -inf, not a log-likelihood of a partial map.
    tiny = rbpf.pool_size(config)._replace(capacity=64)  # the path needs hundreds of tiles
    assert float(rbpf.known_path_loglik_fn(true_log, config, every_scan, pool=tiny)(wide)) == -np.inf
