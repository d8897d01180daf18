"""jaxslam.learning: Adam against a NumPy reference, fitting a linear-Gaussian model's noise with
the particle filter's log-likelihood against the Kalman maximum-likelihood fit, bad inputs."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from linear_gaussian import kalman_log_likelihood, particle_log_likelihood, simulate

from jaxslam.config import default_params
from jaxslam.learning import UNIT_INTERVAL, adam, fit, param_names


class LgParams(NamedTuple):
    a: jax.Array
    q: jax.Array
    r: jax.Array


def _theta(p: LgParams):
    return jnp.stack([p.a, p.q, p.r])


def test_adam_matches_a_numpy_reference():
    grads = [np.array([0.3, -2.0]), np.array([0.1, 1.0]), np.array([-0.5, 0.2])]
    lr, b1, b2, eps = 0.1, 0.9, 0.999, 1e-8
    x, m, v = np.array([1.0, -1.0]), np.zeros(2), np.zeros(2)
    opt = adam(lr)
    coords = {"x": jnp.array([1.0, -1.0])}
    state = opt.init(coords)
    for t, g in enumerate(grads, start=1):
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        x = x + lr * (m / (1 - b1 ** t)) / (np.sqrt(v / (1 - b2 ** t)) + eps)
        coords, state = opt.step(state, coords, {"x": jnp.asarray(g, jnp.float32)})
    np.testing.assert_allclose(np.asarray(coords["x"]), x, rtol=1e-5)
    assert int(state.step) == 3


def test_fit_with_the_particle_filter_finds_the_kalman_maximum():
    """q and r of the linear-Gaussian model (a frozen), started at twice the truth: the fit on
    the particle filter's log-likelihood (N = 200) lands within 15 % of the exact maximum
    likelihood estimate (the same fit on the Kalman log-likelihood); a stays where it was."""
    ys = simulate(jax.random.key(0), jnp.array([0.9, 0.5, 0.3]), 200)
    start = LgParams(jnp.float32(0.9), jnp.float32(1.0), jnp.float32(0.6))
    exact = fit(jax.random.key(1), lambda key, p: kalman_log_likelihood(_theta(p), ys), start, num_steps=300,
                learning_rate=0.05, trainable=["q", "r"], progress=False)
    estimated = fit(jax.random.key(1), lambda key, p: particle_log_likelihood(_theta(p), key, ys, 200, "systematic",
                                                                              0.5),
                    start, num_steps=150, learning_rate=0.05, trainable=["q", "r"], progress=False)
    mle = np.array([float(exact.params.q), float(exact.params.r)])
    assert abs(exact.history["objective"][-1] - exact.history["objective"][-2]) < 1e-3  # converged
    got = np.array([float(estimated.params.q), float(estimated.params.r)])
    np.testing.assert_allclose(got, mle, rtol=0.15)
    assert float(estimated.params.a) == pytest.approx(0.9)
    assert estimated.history["objective"].shape == (150,) and estimated.history["q"][0] == pytest.approx(1.0)
    assert set(estimated.history) == {"objective", "q", "r"}


def test_fit_resumes_from_its_state():
    ys = simulate(jax.random.key(0), jnp.array([0.9, 0.5, 0.3]), 50)
    objective = lambda key, p: kalman_log_likelihood(_theta(p), ys)  # noqa: E731
    start = LgParams(jnp.float32(0.9), jnp.float32(1.0), jnp.float32(0.6))
    whole = fit(jax.random.key(1), objective, start, num_steps=20, trainable=["q"], progress=False)
    first = fit(jax.random.key(1), objective, start, num_steps=10, trainable=["q"], progress=False)
    rest = fit(jax.random.key(2), objective, first.params, num_steps=10, trainable=["q"], progress=False,
               initial_state=first.optimizer_state)
    assert int(rest.optimizer_state.step) == 20
    assert float(rest.params.q) == pytest.approx(float(whole.params.q), rel=1e-5)  # the objective ignores keys


def test_fit_refuses_bad_input_before_any_work():
    def objective(key, params):
        raise AssertionError("the objective was called")

    params = default_params()
    assert param_names(params)[:2] == ["motion.srr", "motion.srt"]
    with pytest.raises(ValueError, match=r"unknown parameter names \['motion.sigma'\]"):
        fit(jax.random.key(0), objective, params, num_steps=5, trainable=["motion.sigma"])
    with pytest.raises(ValueError, match=r"lookahead.alpha = 0.0 is outside its transform's domain \(in \(0, 1\)\)"):
        fit(jax.random.key(0), objective, default_params(**{"lookahead.alpha": 0.0}), num_steps=5,
            trainable=["lookahead.alpha"], transforms={"lookahead.alpha": UNIT_INTERVAL})
    with pytest.raises(ValueError, match=r"insertion.logodds_free = -0.4.* \(> 0\)"):
        fit(jax.random.key(0), objective, params, num_steps=5, trainable=["insertion.logodds_free"])
    with pytest.raises(ValueError, match="num_steps must be a positive integer"):
        fit(jax.random.key(0), objective, params, num_steps=0)



def test_fit_refuses_parameters_the_gradient_cannot_reach():
    """The SLAM filter's map insertion and resampling threshold act through non-differentiable
    steps: fit names them before any work instead of keeping them at their start silently."""
    from jaxslam import rbpf
    from jaxslam.config import RunSettings, SlamConfig
    from jaxslam.learning import structurally_zero
    from jaxslam.sim import office_scenario

    log = office_scenario(jax.random.key(3)).log.subset(np.arange(30))
    config = SlamConfig(num_particles=2, proposal="op", max_insert_range=10.0, beam_stride=8, map_extent=128.0,
                        likelihood_lookup="bilinear")
    prepared, _, _ = rbpf.prepare(log, config, RunSettings(linear_update=0.3, angular_update=0.25))

    def objective(key, params):
        return rbpf.filter(key, prepared, params, config).marginal_loglik

    trainable = ["motion.srr", "likelihood.sigma", "insertion.logodds_occupied", "resample_threshold"]
    with pytest.raises(ValueError, match=r"zero by construction in \['insertion.logodds_occupied', "
                                         r"'resample_threshold'\]"):
        fit(jax.random.key(0), objective, default_params(**{"likelihood.gain": 1.0}), num_steps=1,
            trainable=trainable, progress=False)
    # A gradient that is 0 in value but not by construction is not refused.
    assert structurally_zero(lambda c: c["a"] * 0.0 + jnp.where(c["b"] > 0, 1.0, 0.0), {"a": 1.0, "b": 1.0}) == ["b"]


def test_slam_learning_setup_sets_what_a_fit_needs():
    from jaxslam.learning import LEARNING_SETTINGS, slam_learning_setup

    config, settings, params = slam_learning_setup({"proposal": "op", "motion.min_translation_std": 0.001})
    assert float(params.likelihood.gain) == 1.0 and config.likelihood_lookup == "bilinear"
    assert settings.linear_update == 0.0 and settings.angular_update == 0.0
    assert float(params.motion.min_translation_std) == pytest.approx(0.001) and config.proposal == "op"
    with pytest.warns(UserWarning, match="likelihood.gain"):
        slam_learning_setup({"likelihood.gain": 0.1})
    assert set(LEARNING_SETTINGS) == {"likelihood.gain", "likelihood_lookup", "linear_update", "angular_update",
                                      "smp_weight", "scan_match.linear_step", "scan_match.angular_step"}
    assert config.smp_weight == "importance" and float(params.scan_match.linear_step) == pytest.approx(0.01)
