"""Resamplers, ESS and log-weight normalisation (jaxslam.resampling).

Every Monte Carlo check uses fixed keys; its tolerance is a stated number of standard
errors of the multinomial scheme, whose count variance M w (1 - w) bounds the others'.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import resampling as R

NAMES = ["systematic", "stratified", "multinomial", "residual"]
K = 4000  # keys per Monte Carlo check (one batch size, so that each resampler compiles once per M)
N_BIG = 1000  # particle count of the large-N checks
K_BIG = 16  # keys of the large-N checks

# Jitted once per shape: eager JAX compiles every primitive separately, which is slow.
ess = jax.jit(R.ess)
normalize = jax.jit(R.normalize_log_weights)
resample_if_needed = jax.jit(R.resample_if_needed, static_argnums=3)


@functools.lru_cache(maxsize=None)
def _batched(name: str, num_samples: int):
    """jit(vmap over keys) of one resampler with a static sample count."""
    fn = R.RESAMPLERS[name]
    return jax.jit(jax.vmap(lambda k, lw: fn(k, lw, num_samples), in_axes=(0, None)))


def draw_keys(name, log_weights, num_samples, keys):
    idx = np.asarray(_batched(name, num_samples)(keys, jnp.asarray(log_weights, jnp.float32)))
    assert idx.shape == (keys.shape[0], num_samples)
    assert idx.dtype == np.int32
    return idx


def draw_many(name, log_weights, num_samples, num_keys, seed):
    return draw_keys(name, log_weights, num_samples, jax.random.split(jax.random.key(seed), num_keys))


def counts_of(idx, n):
    return np.stack([np.bincount(row, minlength=n) for row in idx])


def log(w):
    w = np.asarray(w, np.float64)
    with np.errstate(divide="ignore"):
        return np.log(w).astype(np.float32)


# First and last particle (and one in the middle) have zero weight.
W = np.array([0.0, 0.05, 0.3, 0.0, 0.15, 0.23, 0.27, 0.0])
# M w at M = 20: 1.4, 4.2, 2.6, 3.2, 1.8, 2.4, 0.6, 3.8 (no integer to round across).
W_VAR = np.array([0.07, 0.21, 0.13, 0.16, 0.09, 0.12, 0.03, 0.19])


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("num_samples", [8, 20])
def test_expected_counts_equal_m_times_w(name, num_samples):
    n = W.size
    idx = draw_many(name, log(W) + 3.7, num_samples, K, seed=1)  # unnormalised on purpose
    c = counts_of(idx, n)
    assert np.all(c.sum(axis=1) == num_samples)
    assert np.all(c[:, W == 0] == 0)  # zero weight (first, middle, last): never drawn
    want = num_samples * W
    # Per key, a count has variance at most the multinomial M w (1 - w) (the other three
    # schemes only lower it), so the mean over K keys has a standard error of at most
    # sqrt(M w (1 - w) / K); allow 5 of them.
    tol = 5 * np.sqrt(num_samples * W * (1 - W) / K)
    assert np.all(np.abs(c.mean(axis=0) - want) <= tol)


@pytest.mark.parametrize("name", NAMES)
def test_zero_weight_never_drawn_with_many_tiny_weights(name):
    # One heavy particle and hundreds of tiny ones: the float32 cumulative sum of the
    # normalised weights ends away from 1 (checked below); zero weights at both ends and inside.
    n = N_BIG
    lw = np.full(n, np.log(1e-6), np.float32)
    lw[1] = 0.0
    lw[[0, n - 2, n - 1]] = -np.inf
    lw[500:510] = -np.inf
    norm = np.asarray(normalize(jnp.asarray(lw))[0])
    assert np.cumsum(np.exp(norm), dtype=np.float32)[-1] != np.float32(1.0)  # the case is real
    idx = draw_many(name, lw, n, K_BIG, seed=4)
    assert not np.isin(idx, [0, n - 2, n - 1]).any()
    assert not ((idx >= 500) & (idx < 510)).any()
    assert idx.max() < n


def test_systematic_never_draws_zero_weight_last_particle_for_real_keys():
    """Systematic points are (u0 + j) / M with u0 uniform in [0, 1). For u0 close to 1 the
    last point rounds to exactly 1.0 in float32 (about 1 key in 10,000 at M = 1000); no
    CDF entry exceeds it, and a zero-weight last particle must still not be drawn."""
    n = N_BIG
    keys = jax.random.split(jax.random.key(5), 200_000)
    u0 = np.asarray(jax.jit(jax.vmap(lambda k: jax.random.uniform(k, ())))(keys))
    last_point = (u0 + np.float32(n - 1)) / np.float32(n)  # float32 arithmetic, as in the resampler
    hits = np.nonzero(last_point >= np.float32(1.0))[0]
    assert hits.size > 0  # these keys do trigger the rounding
    lw = jnp.zeros(n).at[-1].set(-jnp.inf)
    idx = draw_keys("systematic", lw, n, keys[np.resize(hits, K_BIG)])
    assert not (idx == n - 1).any(), f"zero-weight particle drawn for key(s) {hits}"


U_MAX = np.float32(1.0) - np.float32(2.0**-23)  # the largest value jax.random.uniform returns


@pytest.mark.parametrize("name,value", [
    ("systematic", U_MAX),
    ("stratified", U_MAX),
    ("multinomial", U_MAX),
    ("residual", U_MAX),
] + [(name, np.float32(0.0)) for name in NAMES])
def test_zero_weight_end_particles_with_extreme_uniforms(name, value, monkeypatch):
    """Every uniform at an extreme legal output of jax.random.uniform: 0, or 1 - 2^-23, for
    which the last systematic/stratified point rounds to 1.0."""

    def extreme_uniform(key, shape=(), dtype=jnp.float32, *args, **kwargs):
        return jnp.full(shape, value, dtype)

    monkeypatch.setattr(jax.random, "uniform", extreme_uniform)
    n = N_BIG
    fn = R.RESAMPLERS[name]
    # A fresh lambda: no jit cache from another test can serve a trace without the patch.
    idx = np.asarray(jax.jit(lambda k, lw: fn(k, lw, n))(jax.random.key(0),
                                                         jnp.zeros(n).at[-1].set(-jnp.inf).at[0].set(-jnp.inf)))
    assert not (idx == n - 1).any()
    assert not (idx == 0).any()


@pytest.mark.parametrize("name", NAMES)
def test_minus_inf_log_weights(name):
    lw = np.array([-np.inf, -np.inf, 0.0, -np.inf, np.log(3.0), -np.inf, -np.inf, -np.inf], np.float32)
    idx = draw_many(name, lw, 8, K, seed=6)
    assert np.isin(idx, [2, 4]).all()
    frac = (idx == 4).mean()
    # 8 K draws, p = 0.75: a multinomial standard error of sqrt(p (1 - p) / (8 K)) = 0.0024
    # (the other schemes are more accurate); allow 5 of them.
    assert abs(frac - 0.75) < 5 * np.sqrt(0.75 * 0.25 / (8 * K))


@pytest.mark.parametrize("name", NAMES)
def test_all_minus_inf_weights_resample_uniformly(name):
    n = 8
    idx = draw_many(name, np.full(n, -np.inf, np.float32), n, K, seed=7)
    assert idx.min() >= 0 and idx.max() < n
    c = counts_of(idx, n).mean(axis=0)
    # Uniform: mean count 1 per particle, standard error <= sqrt((1 - 1/n) / K) = 0.015; 5 of them.
    np.testing.assert_allclose(c, 1.0, rtol=0, atol=5 * np.sqrt((1 - 1 / n) / K))


@pytest.mark.parametrize("name", NAMES)
def test_same_key_same_draw(name):
    a = draw_many(name, log(W), 8, K, seed=13)
    b = draw_many(name, log(W), 8, K, seed=13)
    c = draw_many(name, log(W), 8, K, seed=14)
    np.testing.assert_array_equal(a, b)
    assert (a != c).any()


def test_normalize_log_weights_against_numpy():
    rng = np.random.default_rng(8)
    lw = rng.normal(0, 30, N_BIG).astype(np.float32)
    lw[[3, 9]] = -np.inf
    norm, total = normalize(jnp.asarray(lw))
    fin = np.isfinite(lw)
    m = lw[fin].max()
    want_total = m + np.log(np.sum(np.exp(lw[fin].astype(np.float64) - m)))
    np.testing.assert_allclose(float(total), want_total, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(norm)[fin], (lw - want_total)[fin], rtol=0, atol=1e-4)
    assert np.all(np.asarray(norm)[[3, 9]] == -np.inf)
    np.testing.assert_allclose(np.exp(np.asarray(norm, np.float64)).sum(), 1.0, rtol=1e-5)


def test_normalize_all_minus_inf_is_uniform_without_nan():
    norm, total = normalize(jnp.full(8, -jnp.inf))
    assert float(total) == -np.inf
    np.testing.assert_allclose(np.asarray(norm), -np.log(8.0), rtol=1e-6)
    assert float(ess(jnp.full(8, -jnp.inf))) == pytest.approx(8.0, rel=1e-5)


@pytest.mark.parametrize("n", [1, 8, N_BIG])
def test_ess_uniform_and_one_hot(n):
    assert float(ess(jnp.zeros(n) - 12.3)) == pytest.approx(n, rel=1e-4)
    one_hot = jnp.full(n, -jnp.inf).at[n // 2].set(5.0)
    assert float(ess(one_hot)) == pytest.approx(1.0, rel=1e-6)


def test_ess_against_numpy():
    rng = np.random.default_rng(9)
    lw = rng.normal(0, 2, N_BIG).astype(np.float32) + 50.0
    w = np.exp(lw.astype(np.float64) - lw.max())
    w /= w.sum()
    assert float(ess(jnp.asarray(lw))) == pytest.approx(1.0 / np.sum(w**2), rel=1e-4)


def test_resample_if_needed_keeps_particles_above_threshold():
    lw = jnp.log(jnp.array([0.2, 0.3, 0.1, 0.25, 0.15])) + 4.0
    e = float(ess(lw))  # about 4.26 of 5
    anc, new_lw, did = resample_if_needed(jax.random.key(0), lw, jnp.float32(0.8))
    assert not bool(did)
    np.testing.assert_array_equal(np.asarray(anc), np.arange(5))
    assert np.asarray(anc).dtype == np.int32
    np.testing.assert_allclose(np.exp(np.asarray(new_lw)), [0.2, 0.3, 0.1, 0.25, 0.15], rtol=1e-5)
    # Just above and just below the ESS: the decision flips at ess_threshold * N.
    assert bool(resample_if_needed(jax.random.key(0), lw, jnp.float32(e / 5 + 1e-3))[2])
    assert not bool(resample_if_needed(jax.random.key(0), lw, jnp.float32(e / 5 - 1e-3))[2])


def test_resample_if_needed_resamples_below_threshold():
    lw = jnp.log(jnp.array([0.9, 0.05, 0.05, 0.0, 0.0]))
    marker = jnp.array([4, 3, 2, 1, 0], jnp.int32)
    calls = []

    def fake(key, log_weights, num):
        calls.append(num)
        return marker

    anc, new_lw, did = resample_if_needed(jax.random.key(0), lw, jnp.float32(0.5), fake)
    assert bool(did) and calls == [5]
    np.testing.assert_array_equal(np.asarray(anc), np.asarray(marker))
    np.testing.assert_allclose(np.asarray(new_lw), -np.log(5.0), rtol=1e-6)
    # With the real resampler: only positive-weight particles survive.
    anc, _, did = resample_if_needed(jax.random.key(1), lw, jnp.float32(0.5))
    assert bool(did) and not np.isin(np.asarray(anc), [3, 4]).any()


def test_resample_if_needed_all_minus_inf_no_nan():
    anc, new_lw, did = resample_if_needed(jax.random.key(0), jnp.full(5, -jnp.inf), jnp.float32(0.5))
    assert not bool(did)  # the uniform fallback has ESS = N
    np.testing.assert_allclose(np.asarray(new_lw), -np.log(5.0), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(anc), np.arange(5))


def test_low_variance_schemes_beat_multinomial():
    w, n = W_VAR, 20
    var = {name: counts_of(draw_many(name, log(w), n, K, seed=10), w.size).var(axis=0) for name in NAMES}
    mult = n * w * (1 - w)  # 0.58 .. 3.3, summing to 17
    # The empirical multinomial variance matches M w (1 - w): its relative standard error is
    # about sqrt(2 / K) = 2.2%; allow 15%.
    np.testing.assert_allclose(var["multinomial"], mult, rtol=0.15)
    # A systematic count is floor(M w) or ceil(M w): variance <= 1/4. A stratified count
    # varies only through the (at most two) strata that straddle the particle's CDF edges:
    # <= 1/2 (+0.05 = 4 standard errors of an empirical variance of 0.5 over K keys).
    assert np.all(var["systematic"] <= 0.25)
    assert np.all(var["stratified"] <= 0.5 + 0.05)
    # Summed over particles: multinomial 17, systematic <= 2, stratified <= 4.
    assert var["systematic"].sum() < 0.2 * mult.sum()
    assert var["stratified"].sum() < 0.3 * mult.sum()
    assert var["residual"].sum() < 0.8 * mult.sum()


def test_systematic_counts_are_floor_or_ceil():
    w, n = W_VAR, 20
    c = counts_of(draw_many("systematic", log(w), n, K, seed=11), w.size)
    assert np.all(c >= np.floor(n * w)) and np.all(c <= np.ceil(n * w))


def test_residual_keeps_deterministic_copies():
    w, n = W_VAR, 20
    c = counts_of(draw_many("residual", log(w), n, K, seed=12), w.size)
    assert np.all(c >= np.floor(n * w))
    # The random part draws the remaining M - sum(floor(M w)) = 6 slots from the residues.
    assert np.all((c - np.floor(n * w)).sum(axis=1) == n - np.floor(n * w).sum())


def test_keep_in_place_moves_only_the_slots_not_drawn():
    """Every drawn index in its own slot, the extra copies in the slots never drawn, the same
    multiset, ``order`` the permutation that arranges it; checked on random draws."""
    rng = np.random.default_rng(0)
    for n in (1, 2, 5, 16):
        for _ in range(50):
            ancestors = rng.integers(0, n, n).astype(np.int32)
            arranged, order = (np.asarray(a) for a in R.keep_in_place(jnp.asarray(ancestors)))
            np.testing.assert_array_equal(arranged, ancestors[order])
            np.testing.assert_array_equal(np.sort(order), np.arange(n))
            drawn = np.unique(ancestors)
            np.testing.assert_array_equal(arranged[drawn], drawn)
            moved = np.flatnonzero(arranged != np.arange(n))
            assert not np.isin(moved, drawn).any()  # no source is overwritten
    np.testing.assert_array_equal(np.asarray(R.keep_in_place(jnp.array([3, 3, 0, 1]))[0]), [0, 1, 3, 3])
