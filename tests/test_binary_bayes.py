"""The binary Bayes filter (jaxslam.binary_bayes): log-odds to probability, transitions, measurement update."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxslam import binary_bayes as BB

prob = st.floats(0.0, 1.0, width=32)
predict_n = jax.jit(BB.predict_n)
update = jax.jit(BB.update)


def test_probability_inverts_the_logodds():
    p = np.linspace(0.001, 0.999, 101, dtype=np.float32)
    logodds = np.log(p / (1 - p))
    np.testing.assert_allclose(np.asarray(BB.probability(jnp.asarray(logodds))), p, rtol=1e-5)
    # A host map (NumPy) gives float64 NumPy, as the outputs and figures use it.
    host = BB.probability(logodds)
    assert isinstance(host, np.ndarray) and host.dtype == np.float64
    np.testing.assert_allclose(host, p, rtol=1e-5)


def test_predict_formula():
    p = jnp.array([0.0, 0.3, 1.0])
    np.testing.assert_allclose(np.asarray(BB.predict(p, 0.9, 0.2)), [0.2, 0.9 * 0.3 + 0.2 * 0.7, 0.9], rtol=1e-6)
    # Avots et al.'s memoryless baseline: p(open|open) = p(open|closed) = 0.5 forgets at once.
    np.testing.assert_allclose(np.asarray(BB.predict(p, 0.5, 0.5)), 0.5)


@settings(max_examples=80, deadline=None)
@given(prob, prob, prob, st.integers(0, 40))
def test_predict_n_equals_iterated_predict(p, p_stay, p_enter, steps):
    if 1.0 - p_stay + p_enter < 1e-6:
        return  # the static model p_stay = 1, p_enter = 0: see the dedicated test below
    loop = np.float32(p)
    for _ in range(steps):
        loop = np.float32(BB.predict(loop, np.float32(p_stay), np.float32(p_enter)))
    closed = float(predict_n(jnp.float32(p), jnp.float32(p_stay), jnp.float32(p_enter), jnp.int32(steps)))
    # Each float32 step rounds by ~6e-8; 40 steps accumulate well under 1e-5.
    assert closed == pytest.approx(float(loop), abs=1e-5)
    assert 0.0 - 1e-6 <= closed <= 1.0 + 1e-6


@pytest.mark.parametrize("steps", [0, 1, 7])
def test_predict_n_python_int_and_float_steps(steps):
    loop = 0.3
    for _ in range(steps):
        loop = 0.15 * loop + 0.8 * (1 - loop)  # p_stay = 0.15, p_enter = 0.8: oscillates (negative factor)
    assert float(BB.predict_n(jnp.float32(0.3), 0.15, 0.8, steps)) == pytest.approx(loop, abs=1e-6)
    assert float(BB.predict_n(jnp.float32(0.3), 0.15, 0.8, jnp.float32(steps))) == pytest.approx(loop, abs=1e-6)


def test_predict_n_vectorised_over_doors():
    p = jnp.array([0.1, 0.5, 0.9])
    ps = jnp.array([0.9, 0.6, 0.2])
    pe = jnp.array([0.05, 0.3, 0.7])
    want = np.asarray(p)
    for _ in range(5):
        want = np.asarray(ps) * want + np.asarray(pe) * (1 - want)
    np.testing.assert_allclose(np.asarray(predict_n(p, ps, pe, 5)), want, atol=1e-6)


@pytest.mark.parametrize("p_stay,p_enter", [(0.9, 0.05), (0.2, 0.7), (0.5, 0.5), (0.999, 0.001)])
def test_predict_converges_to_stationary(p_stay, p_enter):
    s = float(BB.stationary(jnp.float32(p_stay), jnp.float32(p_enter)))
    assert s == pytest.approx(p_enter / (1 - p_stay + p_enter), rel=1e-5)
    # The stationary value is a fixed point of predict.
    assert float(BB.predict(jnp.float32(s), p_stay, p_enter)) == pytest.approx(s, abs=1e-6)
    # |p_stay - p_enter| < 1: the distance to it shrinks geometrically from any start.
    for p0 in (0.0, 0.37, 1.0):
        assert float(predict_n(jnp.float32(p0), jnp.float32(p_stay), jnp.float32(p_enter), jnp.int32(20000))) \
            == pytest.approx(s, abs=1e-5)
        loop = p0
        for _ in range(200):
            loop = p_stay * loop + p_enter * (1 - loop)
        s64 = p_enter / (1 - p_stay + p_enter)
        assert abs(loop - s64) == pytest.approx(abs(p0 - s64) * abs(p_stay - p_enter) ** 200, abs=1e-9)


def test_predict_n_static_model_keeps_the_probability():
    p = jnp.array([0.0, 0.3, 1.0])
    np.testing.assert_allclose(np.asarray(BB.predict(p, 1.0, 0.0)), np.asarray(p))
    got = np.asarray(predict_n(p, jnp.float32(1.0), jnp.float32(0.0), jnp.int32(5)))
    np.testing.assert_allclose(got, np.asarray(p))


def direct_update(p, l1, l0):
    """posterior = L1 p / (L1 p + L0 (1 - p)), in float64 with a shared scale against underflow."""
    m = max(l1, l0)
    a, b = np.exp(l1 - m) * p, np.exp(l0 - m) * (1 - p)
    return a / (a + b), m + np.log(a + b)


def test_update_against_direct_formula():
    rng = np.random.default_rng(1)
    p = rng.uniform(0.01, 0.99, 200)
    l1 = rng.uniform(-20, 5, 200)
    l0 = rng.uniform(-20, 5, 200)
    l1[:20] -= 1000.0  # tiny likelihoods: would underflow in probability space
    l0[:20] -= 1000.0
    post, ev = update(jnp.asarray(p, jnp.float32), jnp.asarray(l1, jnp.float32), jnp.asarray(l0, jnp.float32))
    want = [direct_update(*args) for args in zip(p, l1, l0)]
    np.testing.assert_allclose(np.asarray(post), [w[0] for w in want], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(ev), [w[1] for w in want], rtol=1e-5, atol=1e-4)


def test_update_with_minus_inf_likelihoods():
    ninf = -jnp.inf
    p = jnp.array([0.3, 0.3, 0.3, 0.0, 1.0, 0.0, 1.0])
    l1 = jnp.array([ninf, -1.0, ninf, -1.0, -1.0, ninf, ninf])
    l0 = jnp.array([-2.0, ninf, ninf, -2.0, -2.0, -2.0, -2.0])
    post, ev = update(p, l1, l0)
    post, ev = np.asarray(post), np.asarray(ev)
    assert not np.isnan(post).any() and not np.isnan(ev).any()
    np.testing.assert_allclose(post, [0.0, 1.0, 0.3, 0.0, 1.0, 0.0, 1.0])  # both impossible: keep the prior
    np.testing.assert_allclose(ev[:2], [-2.0 + np.log(0.7), -1.0 + np.log(0.3)], rtol=1e-6)
    assert ev[2] == -np.inf  # reported, not hidden
    np.testing.assert_allclose(ev[3:5], [-2.0, -1.0], rtol=1e-6)
    assert ev[5] == pytest.approx(-2.0) and ev[6] == -np.inf


def test_update_is_the_door_weight_of_eq_33():
    """exp(log_evidence) = L1 p+ + L0 (1 - p+) after predict: the per-door factor of the particle weight."""
    p_plus = float(BB.predict(jnp.float32(0.4), 0.8, 0.1))
    post, ev = update(jnp.float32(p_plus), jnp.float32(np.log(0.6)), jnp.float32(np.log(0.15)))
    assert float(jnp.exp(ev)) == pytest.approx(0.6 * p_plus + 0.15 * (1 - p_plus), rel=1e-6)
    assert float(post) == pytest.approx(0.6 * p_plus / (0.6 * p_plus + 0.15 * (1 - p_plus)), rel=1e-6)


@pytest.mark.parametrize("p", [0.0, 1.0, 0.3])
def test_update_derivatives_are_finite_and_right_at_saturated_beliefs(p):
    """A belief of exactly 0 or 1 (a door known not to move) has finite derivatives: checked
    against central differences of the update written in NumPy (one-sided at the ends)."""
    l1, l0, h = -1.0, -2.0, 1e-6

    def reference(x):
        ev = np.exp(x[1]) * x[0] + np.exp(x[2]) * (1.0 - x[0])
        return np.array([np.exp(x[1]) * x[0] / ev, np.log(ev)])

    for k in (0, 1):
        grad = jax.grad(lambda *a: BB.update(*a)[k], argnums=(0, 1, 2))(
            jnp.float32(p), jnp.float32(l1), jnp.float32(l0))
        for i in range(3):
            hi, lo = np.array([p, l1, l0]), np.array([p, l1, l0])
            hi[i] = min(1.0, p + h) if i == 0 else hi[i] + h
            lo[i] = max(0.0, p - h) if i == 0 else lo[i] - h
            expected = (reference(hi)[k] - reference(lo)[k]) / (hi[i] - lo[i])
            assert np.isfinite(float(grad[i]))
            assert float(grad[i]) == pytest.approx(expected, abs=1e-4)
