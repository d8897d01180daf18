"""Monte Carlo localization and the beam model."""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import particle_filter
from jaxslam.localization import mcl
from jaxslam.localization.beam_model import beam_model_log_likelihood, make_beam_model_params
from jaxslam.sim.door_worlds import corridors_scenario, office_doors_scenario


def _beam_model_reference(expected, r, range_max, z_hit, z_short, z_max, z_rand, sigma, lam):
    """Plain-Python beam model (Probabilistic Robotics, Table 6.1), weights normalised."""
    total = z_hit + z_short + z_max + z_rand
    z_hit, z_short, z_max, z_rand = (w / total for w in (z_hit, z_short, z_max, z_rand))
    if r >= range_max:
        return math.log(z_max)
    cdf = lambda v: 0.5 * (1.0 + math.erf(v / math.sqrt(2.0)))  # noqa: E731
    eta = cdf((range_max - expected) / sigma) - cdf(-expected / sigma)
    hit = math.exp(-0.5 * ((r - expected) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi)) / eta
    short = lam * math.exp(-lam * r) / (1 - math.exp(-lam * expected)) if (r <= expected and expected > 0) else 0.0
    return math.log(z_hit * hit + z_short * short + z_rand / range_max)


def test_beam_model_matches_reference():
    rng = np.random.default_rng(0)
    weights = dict(z_hit=0.7, z_short=0.15, z_max=0.05, z_rand=0.1)
    params = make_beam_model_params(**weights, sigma_hit=0.15, lambda_short=0.8)
    range_max = 8.0
    expected = rng.uniform(0.0, 9.0, 200).astype(np.float32)
    measured = np.concatenate([rng.uniform(0, 8.5, 150), expected[150:] + rng.normal(0, 0.1, 50)]).astype(np.float32)
    measured = np.clip(measured, 0.0, None)
    got = np.asarray(beam_model_log_likelihood(expected, measured, range_max, params))
    want = np.array([_beam_model_reference(min(e, range_max), r, range_max, **weights, sigma=0.15, lam=0.8)
                     for e, r in zip(expected.astype(float), measured.astype(float))])
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_beam_model_is_normalised():
    """Density on [0, range_max) plus the point mass at range_max integrates to 1."""
    params = make_beam_model_params(0.6, 0.2, 0.1, 0.1, sigma_hit=0.2, lambda_short=0.7)
    range_max = 6.0
    grid = np.linspace(0.0, range_max, 600001, dtype=np.float64)[:-1]
    for expected in (0.05, 2.0, 5.9):
        dens = np.exp(np.asarray(beam_model_log_likelihood(jnp.full(grid.shape, expected), grid, range_max, params),
                                 np.float64))
        mass = np.sum(dens) * (grid[1] - grid[0])
        point = float(jnp.exp(beam_model_log_likelihood(expected, range_max, range_max, params)))
        assert abs(mass + point - 1.0) < 2e-3, (expected, mass, point)


def test_beam_model_finite_at_extremes():
    params = make_beam_model_params()
    e = jnp.array([0.0, 0.0, 10.0, 50.0, 3.0])
    r = jnp.array([0.0, 10.0, 10.0, 0.0, 1e-6])
    out = beam_model_log_likelihood(e, r, 10.0, params)
    assert np.all(np.isfinite(np.asarray(out)))


@pytest.fixture(scope="module")
def office():
    return office_doors_scenario(jax.random.key(3))


def _outbound(scenario, steps):
    """The first ``steps`` scans (every door closed: a static world)."""
    inputs = mcl.log_inputs(scenario.log)
    return mcl.ScanInputs(inputs.motion[:steps], inputs.ranges[:steps])


@pytest.mark.slow  # Monte Carlo or whole-scenario check (python3 -m pytest -m slow)
def test_mcl_tracks_a_simulated_run(office):
    steps = 60
    segments = jnp.asarray(office.world.segments)  # doors present: they are closed on the way out
    config = mcl.MclConfig(num_particles=300, beam_stride=3)
    params = mcl.make_params(beam=make_beam_model_params(sigma_hit=0.2), likelihood_gain=0.2)
    start = jnp.asarray(office.true_poses[0], jnp.float32) + jnp.array([0.15, -0.1, 0.05])
    state = mcl.init_tracked(jax.random.key(0), start, jnp.array([0.2, 0.2, 0.1]), config)
    out = mcl.filter(jax.random.key(1), state, _outbound(office, steps), segments, office.log.sensor, params, config)
    final, info = out.state, out.info
    err = np.hypot(*(np.asarray(info.mean_pose[:, :2]) - office.true_poses[:steps, :2]).T)
    assert err[-20:].max() < 0.15, err
    assert np.all(np.isfinite(np.asarray(info.ess))) and not np.any(np.asarray(info.degenerate))
    assert final.poses.shape == (300, 3)


@pytest.mark.slow  # Monte Carlo or whole-scenario check (python3 -m pytest -m slow)
def test_mcl_global_in_region_converges():
    """Uniform over the first 3.5 m of corridor A of the door scenario, on its true map (D2, D3 closed):
    the open door D1 pins the position down."""
    scenario = corridors_scenario(jax.random.key(5))
    steps = 30
    segments = jnp.asarray(scenario.world.segments)
    num_walls = scenario.door_map.num_walls
    active = jnp.concatenate([jnp.ones(num_walls, bool), jnp.asarray(~scenario.true_door_open[0])])
    config = mcl.MclConfig(num_particles=1000, beam_stride=3)
    params = mcl.make_params(beam=make_beam_model_params(sigma_hit=0.2), likelihood_gain=0.1)
    region = jnp.array([[0.5, 0.3, 4.0, 1.7]])
    state = mcl.init_global(jax.random.key(2), region, config, (-0.5, 0.5))
    info = mcl.filter(jax.random.key(3), state, _outbound(scenario, steps), segments, scenario.log.sensor, params,
                      config, active).info
    err = np.hypot(*(np.asarray(info.mean_pose[-1, :2]) - scenario.true_poses[steps - 1, :2]))
    assert err < 0.2
    assert np.hypot(*(np.asarray(info.mean_pose[0, :2]) - scenario.true_poses[0, :2])) > err


def test_init_global_stays_in_regions():
    regions = jnp.array([[0.0, 0.0, 1.0, 1.0], [5.0, 5.0, 8.0, 6.0]])
    state = mcl.init_global(jax.random.key(0), regions, mcl.MclConfig(num_particles=4000), (-0.2, 0.3))
    p = np.asarray(state.poses)
    in_a = (p[:, 0] >= 0) & (p[:, 0] <= 1) & (p[:, 1] >= 0) & (p[:, 1] <= 1)
    in_b = (p[:, 0] >= 5) & (p[:, 0] <= 8) & (p[:, 1] >= 5) & (p[:, 1] <= 6)
    assert np.all(in_a | in_b)
    assert abs(in_b.mean() - 0.75) < 0.03  # area-proportional: 3 of the 4 m^2
    assert p[:, 2].min() >= -0.2 and p[:, 2].max() <= 0.3


def test_degenerate_step_is_reported_not_nan():
    config = mcl.MclConfig(num_particles=8)
    state = mcl.init_tracked(jax.random.key(0), jnp.zeros(3), jnp.full(3, 0.1), config)
    update = particle_filter.reweight_and_resample(jax.random.key(1), state.poses, state.log_weights,
                                                   jnp.full(8, -jnp.inf).at[3].set(jnp.nan), jnp.float32(0.5),
                                                   "systematic")
    assert bool(update.degenerate) and bool(mcl.MclInfo.of(update).degenerate)
    assert np.all(np.isfinite(np.asarray(update.new_log_weights)))
    assert np.all(np.isfinite(np.asarray(update.mean_pose)))


def test_mcl_step_compiles_once(office):
    segments = jnp.asarray(office.world.segments)
    config = mcl.MclConfig(num_particles=16, beam_stride=4)
    inputs = _outbound(office, 3)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def stepper(key, state, inp, params):
        return mcl.step(key, state, inp, segments, office.log.sensor, params, config)

    state = mcl.init_tracked(jax.random.key(0), jnp.asarray(office.true_poses[0], jnp.float32), jnp.full(3, 0.1),
                             config)
    for t in range(3):
        params = mcl.make_params(likelihood_gain=0.1 + 0.1 * t, resample_threshold=0.3 + 0.1 * t)
        state, _ = stepper(jax.random.key(t), state, mcl.ScanInputs(inputs.motion[t], inputs.ranges[t]), params)
    chex.clear_trace_counter()


def test_filter_is_the_stepwise_loop_and_sums_the_evidence(office):
    """``mcl.filter`` (one scan, each step rematerialised) gives the particles of a Python loop
    of ``step_jit`` and the sum of its log-evidence increments; ``run`` is the filter without it."""
    segments = jnp.asarray(office.world.segments)
    config = mcl.MclConfig(num_particles=32, beam_stride=4)
    params = mcl.make_params(likelihood_gain=0.3, resample_threshold=0.9)  # resamples often
    inputs = _outbound(office, 6)
    state = mcl.init_tracked(jax.random.key(0), jnp.asarray(office.true_poses[0], jnp.float32), jnp.full(3, 0.1),
                             config)
    out = mcl.filter(jax.random.key(4), state, inputs, segments, office.log.sensor, params, config)
    loop, total, resampled = state, 0.0, []
    for t, step_key in enumerate(jax.random.split(jax.random.key(4), 6)):
        loop, info = mcl.step_jit(step_key, loop, mcl.ScanInputs(inputs.motion[t], inputs.ranges[t]), segments,
                                  office.log.sensor, params, config)
        total += float(info.log_evidence)
        resampled.append(bool(info.resampled))
    assert any(resampled)  # the resampling path is part of the comparison
    np.testing.assert_allclose(np.asarray(out.state.poses), np.asarray(loop.poses), atol=1e-5)
    np.testing.assert_allclose(float(out.marginal_loglik), total, rtol=1e-5)
    np.testing.assert_allclose(float(out.marginal_loglik), float(np.sum(np.asarray(out.info.log_evidence))), rtol=1e-6)
