"""The island particle filter (jaxslam.islands): one island is rbpf.filter, the device count
changes no draw, runs reproduce, the islands agree with one island of the same N within Monte
Carlo error, and the island exchange copies whole maps and never draws a zero-weight island."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import islands, rbpf
from jaxslam import maps as paged
from jaxslam.config import ConfigError, RunSettings, SlamConfig, default_params
from jaxslam.sim import office_scenario

REPO_ROOT = Path(__file__).resolve().parents[1]
NUM_SCANS = 40  # 19 steps of the simulated office at the settings below
CONFIG = SlamConfig(num_particles=16, proposal="op", max_insert_range=10.0, beam_stride=2, map_extent=128.0)
SETTINGS = RunSettings(linear_update=0.3, angular_update=0.25)
ISLAND_THRESHOLD = 0.9  # exchanges often, so that the short run exercises them


@pytest.fixture(scope="module")
def prepared():
    log = office_scenario(jax.random.key(3)).log.subset(np.arange(NUM_SCANS))
    return rbpf.prepare(log, CONFIG, SETTINGS)[0]


@pytest.fixture(scope="module")
def four_islands(prepared):
    """4 islands of 4 on one device, jitted in the key."""
    return jax.jit(lambda key: islands.filter(key, prepared, default_params(), CONFIG, 4, 1, ISLAND_THRESHOLD))


@pytest.fixture(scope="module")
def one_island(prepared):
    """One island of 16, jitted in the key."""
    return jax.jit(lambda key: islands.filter(key, prepared, default_params(), CONFIG, 1))


def _leaves(tree) -> dict[str, np.ndarray]:
    flat = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {jax.tree_util.keystr(path): np.asarray(leaf) for path, leaf in flat}


def test_one_island_is_rbpf_filter_bit_for_bit(prepared, one_island):
    ref = jax.jit(lambda key: rbpf.filter(key, prepared, default_params(), CONFIG))(jax.random.key(1))
    out = one_island(jax.random.key(1))
    ref_leaves = _leaves((ref.state, ref.info, ref.marginal_loglik))
    out_leaves = _leaves((jax.tree.map(lambda x: x[0], out.state.islands),
                          jax.tree.map(lambda x: x[:, 0], out.info.islands), out.marginal_loglik))
    assert ref_leaves.keys() == out_leaves.keys()
    for name, value in ref_leaves.items():
        np.testing.assert_array_equal(out_leaves[name], value, err_msg=name)
    np.testing.assert_array_equal(np.asarray(out.info.log_evidence), np.asarray(ref.info.log_evidence))
    assert not np.asarray(out.info.exchanged).any() and float(out.state.log_weights[0]) == 0.0


_MULTI_DEVICE = textwrap.dedent("""
    import os, sys
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=4"
    import jax, numpy as np
    sys.path.insert(0, {root!r})
    from jaxslam import islands, rbpf
    from jaxslam.config import default_params
    from jaxslam.sim import office_scenario
    from tests.test_islands import CONFIG, ISLAND_THRESHOLD, NUM_SCANS, SETTINGS, _leaves
    assert jax.device_count() == 4
    log = office_scenario(jax.random.key(3)).log.subset(np.arange(NUM_SCANS))
    prepared = rbpf.prepare(log, CONFIG, SETTINGS)[0]
    run = jax.jit(lambda key: islands.filter(key, prepared, default_params(), CONFIG, 4, 4, ISLAND_THRESHOLD))
    first, second = _leaves(run(jax.random.key(1))), _leaves(run(jax.random.key(1)))
    np.savez({out!r}, **{{"first" + k: v for k, v in first.items()}}, **{{"second" + k: v for k, v in second.items()}})
""")


@pytest.fixture(scope="module")
def four_devices(tmp_path_factory):
    """4 islands on 4 host devices (a subprocess: the device count is fixed when jax starts),
    run twice with the same key."""
    out = tmp_path_factory.mktemp("islands") / "four_devices.npz"
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    subprocess.run([sys.executable, "-c", _MULTI_DEVICE.format(root=str(REPO_ROOT), out=str(out))], check=True,
                   env=env, cwd=REPO_ROOT, timeout=600)
    data = np.load(out)
    return ({k[len("first"):]: data[k] for k in data.files if k.startswith("first")},
            {k[len("second"):]: data[k] for k in data.files if k.startswith("second")})


def test_four_devices_equal_one_device(four_islands, four_devices):
    one_device = _leaves(four_islands(jax.random.key(1)))
    first, _ = four_devices
    assert one_device.keys() == first.keys()
    assert first[".info.exchanged"].any() and (first[".info.island_ancestors"] != np.arange(4)).any()
    # To the bit: each device runs its islands one at a time, the same program for every island
    # whatever the device count, and the island keys come from the island index.
    for name, value in one_device.items():
        np.testing.assert_array_equal(first[name], value, err_msg=name)


def test_a_fixed_device_count_reproduces_bit_for_bit(four_islands, four_devices):
    first, second = four_devices
    for name, value in first.items():
        np.testing.assert_array_equal(second[name], value, err_msg=name)
    a, b = _leaves(four_islands(jax.random.key(5))), _leaves(four_islands(jax.random.key(5)))
    for name, value in a.items():
        np.testing.assert_array_equal(b[name], value, err_msg=name)


def _posterior_mean_xy(state: islands.IslandState) -> np.ndarray:
    """The final weighted mean position (2,) over all islands' particles."""
    log_weights = np.asarray(state.log_weights)[:, None] + np.asarray(state.islands.log_weights)
    weights = np.exp(log_weights - log_weights.max())
    return (weights[..., None] * np.asarray(state.islands.poses)[..., :2]).sum((0, 1)) / weights.sum()


def test_four_islands_agree_with_one_island_within_monte_carlo_error(four_islands, one_island):
    """24 seeds of 4 islands of 4 against 1 island of 16. The final posterior mean position:
    tolerance 4 SE of the difference of the two across-seed means (SE 3.4 cm in x, 2.5 cm in y on
    2026-11-26; differences 2.1 and 0.3 cm). The likelihood estimate exp(marginal_loglik), unbiased
    for both: the ratio of the two across-seed means, within 4 SE of 1 (0.57, SE 0.38: the
    log-likelihoods spread 2.4 and 2.2 nats over the seeds, so exp is heavy-tailed and this is
    the weaker check)."""
    seeds = 24
    four_runs = [four_islands(jax.random.key(100 + s)) for s in range(seeds)]
    one_runs = [one_island(jax.random.key(100 + s)) for s in range(seeds)]
    four = np.stack([_posterior_mean_xy(out.state) for out in four_runs])
    one = np.stack([_posterior_mean_xy(out.state) for out in one_runs])
    se = np.sqrt(four.var(0, ddof=1) / seeds + one.var(0, ddof=1) / seeds)
    assert np.all(se > 0)
    np.testing.assert_array_less(np.abs(four.mean(0) - one.mean(0)), 4 * se)
    loglik_four = np.array([float(out.marginal_loglik) for out in four_runs], np.float64)
    loglik_one = np.array([float(out.marginal_loglik) for out in one_runs], np.float64)
    shift = max(loglik_four.max(), loglik_one.max())
    lik_four, lik_one = np.exp(loglik_four - shift), np.exp(loglik_one - shift)
    ratio = lik_four.mean() / lik_one.mean()
    # The ratio's SE by the delta method.
    ratio_se = ratio * np.sqrt(lik_four.var(ddof=1) / seeds / lik_four.mean() ** 2
                               + lik_one.var(ddof=1) / seeds / lik_one.mean() ** 2)
    assert abs(ratio - 1.0) < 4 * ratio_se


def test_an_exchange_copies_whole_maps(four_islands):
    """With the islands resampled at the last step, an island replaced holds its source's
    particles: the same poses, and every particle's map reads the same cells."""
    out = four_islands(jax.random.key(1))
    ancestors = np.asarray(out.info.island_ancestors[-1])
    replaced = np.flatnonzero(ancestors != np.arange(4))
    assert bool(out.info.exchanged[-1]) and replaced.size, ancestors
    spec = CONFIG.grid
    state = out.state.islands
    for island in replaced:
        source = ancestors[island]
        np.testing.assert_array_equal(np.asarray(state.poses[island]), np.asarray(state.poses[source]))
        maps, source_maps = (jax.tree.map(lambda x, g=g: x[g], state.maps) for g in (island, source))
        for particle in range(CONFIG.num_particles // 4):
            logodds, field, _ = paged.to_dense(spec, maps, particle)
            source_logodds, source_field, _ = paged.to_dense(spec, source_maps, particle)
            np.testing.assert_array_equal(logodds, source_logodds)
            np.testing.assert_array_equal(field, source_field)
            assert np.abs(logodds).sum() > 0
    assert np.isfinite(float(out.marginal_loglik))


def test_island_weights_carry_over_from_step_to_step(four_islands):
    """After a step without exchange, the next step's island weights are the last ones times the
    islands' evidence, normalised (NumPy, float64): the weights are carried, not reset (a filter
    that reset them every step passed the statistical test above, which exchanges at most steps)."""
    out = four_islands(jax.random.key(1))
    weights = np.asarray(out.info.island_log_weights, np.float64)  # (S, I), after each update
    increments = np.asarray(out.info.islands.log_evidence, np.float64)  # (S, I)
    exchanged = np.asarray(out.info.exchanged)
    carried = np.flatnonzero(~exchanged[:-1])
    assert carried.size >= 2, exchanged  # the run must have steps to check
    for t in carried:
        want = weights[t] + increments[t + 1]
        want -= np.log(np.sum(np.exp(want - want.max()))) + want.max()
        np.testing.assert_allclose(weights[t + 1], want, atol=1e-4)
    # After an exchange the islands start level again.
    for t in np.flatnonzero(exchanged[:-1]):
        want = np.log(0.25) + increments[t + 1]
        want -= np.log(np.sum(np.exp(want - want.max()))) + want.max()
        np.testing.assert_allclose(weights[t + 1], want, atol=1e-4)

def test_a_zero_weight_island_is_never_drawn():
    log_weights = jnp.log(jnp.full((4,), 0.25))
    increments = jnp.array([0.0, -jnp.inf, 3.0, -2.0])
    for resampler in ("systematic", "multinomial"):
        draw = jax.jit(lambda key, r=resampler: islands.resample_islands(key, log_weights, increments, 1.0, r))
        for seed in range(200):
            ancestors, new_log_weights, update = draw(jax.random.key(seed))
            assert bool(update.resampled)
            assert 1 not in np.asarray(ancestors)
            drawn = np.unique(np.asarray(ancestors))
            # Every island drawn keeps its own place; only those not drawn are replaced.
            np.testing.assert_array_equal(np.asarray(ancestors)[drawn], drawn)
            np.testing.assert_allclose(np.asarray(new_log_weights), np.log(0.25), rtol=1e-6)
    # The island weights gain the islands' evidence; the step's evidence is their weighted sum.
    previous = np.log(np.array([0.1, 0.2, 0.3, 0.4]))
    finite = np.array([0.5, -1.0, 2.0, 0.0])
    _, kept, update = islands.resample_islands(jax.random.key(0), jnp.asarray(previous, jnp.float32),
                                               jnp.asarray(finite, jnp.float32), 0.0, "systematic")
    evidence = np.log(np.sum(np.exp(previous + finite)))
    np.testing.assert_allclose(float(update.log_evidence), evidence, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(kept), previous + finite - evidence, rtol=1e-5)
    assert not bool(update.resampled)


def test_bad_island_and_device_counts_are_refused_before_any_work(prepared):
    with pytest.raises(ConfigError, match="num_islands=3 must be a positive divisor of num_particles=16"):
        islands.filter(jax.random.key(0), prepared, default_params(), CONFIG, 3)
    with pytest.raises(ConfigError, match="num_islands=4 is not a multiple of num_devices=3"):
        islands.filter(jax.random.key(0), prepared, default_params(), CONFIG, 4, 3)
    with pytest.raises(ConfigError, match="is more than the 1 devices JAX sees"):
        islands.filter(jax.random.key(0), prepared, default_params(), CONFIG, 4, 4)
    with pytest.raises(ConfigError, match="score_lag"):
        islands.filter(jax.random.key(0), prepared, default_params(), dataclasses.replace(CONFIG, score_lag=2), 4)


def test_the_driver_grows_the_islands_pools_and_draws_the_filters_particles(prepared, four_islands):
    """island_runs.run from pools far too small: the pools grow (a chunk taken again from the
    step that did not fit, by all islands), and the particles, weights, maps and island draws are
    islands.filter's bit for bit. The evidence is summed by another program (chunks, not one
    scan), so it agrees to float32 rounding."""
    from jaxslam import island_runs
    from jaxslam.maps import PoolSize

    ref = four_islands(jax.random.key(1))
    out = island_runs.run(jax.random.key(1), prepared, default_params(), CONFIG, 4, 1, ISLAND_THRESHOLD,
                          chunk_size=8, initial_pool=PoolSize(64, 16, 16, 4))
    assert len(out.growths) >= 2 and out.growths[-1]["capacity"] > 64
    assert np.asarray(out.info.exchanged).any()
    same = _leaves((ref.state.islands.poses, ref.state.islands.log_weights, ref.state.log_weights,
                    ref.info.island_ancestors, ref.info.islands.ancestors, ref.info.best_pose))
    got = _leaves((out.state.islands.poses, out.state.islands.log_weights, out.state.log_weights,
                   out.info.island_ancestors, out.info.islands.ancestors, out.info.best_pose))
    for name, value in same.items():
        np.testing.assert_array_equal(got[name], value, err_msg=name)
    for got_map, ref_map in zip(_dense(out.state), _dense(ref.state), strict=True):
        np.testing.assert_array_equal(got_map, ref_map)
    np.testing.assert_allclose(out.info.log_evidence, ref.info.log_evidence, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out.marginal_loglik, float(ref.marginal_loglik), rtol=1e-5)
    assert not np.asarray(out.state.islands.maps.overflow).any()


def test_an_island_step_is_taken_by_all_islands_or_none(prepared):
    """One island's pools full, the others' not: no island moves, no island weight changes, the
    step adds no evidence, and every island's overflow is set (so the next steps wait too)."""
    state = islands.init(jax.random.key(0), jnp.asarray(prepared.first_ranges), prepared.sensor, default_params(),
                         CONFIG, 4, jnp.asarray(prepared.initial_pose))
    full = state.islands.maps.overflow.at[2].set(True)
    state = state._replace(islands=state.islands._replace(maps=state.islands.maps._replace(overflow=full)))
    inputs = jax.tree.map(lambda a: jnp.asarray(a[0]), prepared.inputs)
    new, info = jax.jit(lambda k, s: islands.step(k, s, inputs, prepared.sensor, default_params(), CONFIG,
                                                  ISLAND_THRESHOLD))(jax.random.key(1), state)
    assert bool(info.pool_overflow) and float(info.log_evidence) == 0.0
    assert np.asarray(new.islands.maps.overflow).all()
    np.testing.assert_array_equal(np.asarray(new.islands.poses), np.asarray(state.islands.poses))
    np.testing.assert_array_equal(np.asarray(new.log_weights), np.asarray(state.log_weights))
    np.testing.assert_array_equal(np.asarray(new.islands.maps.logodds), np.asarray(state.islands.maps.logodds))
    assert not bool(info.exchanged)


def _dense(state: islands.IslandState) -> list[np.ndarray]:
    """Every island's particles' maps as dense log-odds, island by island (whatever the pools'
    sizes and the tiles' slots in them)."""
    maps = jax.tree.map(np.asarray, state.islands.maps)
    return [paged.to_dense(CONFIG.grid, jax.tree.map(lambda a: a[g], maps), n)[0]
            for g in range(maps.directory.shape[0]) for n in range(maps.directory.shape[1])]
