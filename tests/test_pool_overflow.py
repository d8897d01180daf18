"""A step the maps' pools cannot hold: it is not taken, nothing after it is, and the filter says so.

``rbpf.filter`` cannot grow its pools (``slam.run`` can). A pool whose per-step allowance
(``PoolSize.max_new_tiles``) is below what some step asks for makes that step's insertion fail;
later steps that would fit must not quietly carry on from a state that lost a step, and the
log-likelihood must not count a step whose motion was dropped.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from jaxslam import learning, rbpf
from jaxslam.config import RunSettings, SlamConfig, default_params
from jaxslam.sim import office_scenario

CONFIG = SlamConfig(num_particles=8, proposal="op", max_insert_range=10.0, beam_stride=4, map_extent=128.0,
                    tile_size=16)
SETTINGS = RunSettings(linear_update=0.3, angular_update=0.25)
PARAMS = default_params(**{"resample_threshold": 0.9})
filter_jit = jax.jit(rbpf.filter, static_argnames=("config", "pool"))


@pytest.fixture(scope="module")
def office():
    log = office_scenario(jax.random.key(3)).log.subset(np.arange(60))
    prepared, _, _ = rbpf.prepare(log, CONFIG, SETTINGS)
    big = filter_jit(jax.random.key(1), prepared, PARAMS, CONFIG, pool=rbpf.pool_size(CONFIG))
    assert not bool(big.state.maps.overflow)
    # Room for three quarters of the largest request: the steps that ask for more do not fit,
    # and later steps that ask for less would (the flag of one insertion alone clears then).
    small = rbpf.pool_size(CONFIG)._replace(max_new_tiles=int(big.state.maps.peak_request) * 3 // 4)
    return log, prepared, big, small


def test_a_step_that_does_not_fit_stops_the_filter_and_its_likelihood_is_minus_inf(office):
    _, prepared, big, small = office
    out = filter_jit(jax.random.key(1), prepared, PARAMS, CONFIG, pool=small)
    stalled = np.asarray(out.info.pool_overflow)
    first = int(np.argmax(stalled))
    assert stalled.any() and 0 < first < stalled.size - 1
    assert np.all(stalled[first:]), "the overflow flag must stay set"
    assert bool(out.state.maps.overflow)
    assert float(out.marginal_loglik) == -np.inf
    # The steps before the stall are the big pool's, bit for bit; from it on none is taken.
    np.testing.assert_array_equal(np.asarray(out.info.log_evidence[:first]), np.asarray(big.info.log_evidence[:first]))
    np.testing.assert_array_equal(np.asarray(out.info.proposed_poses[:first]),
                                  np.asarray(big.info.proposed_poses[:first]))
    np.testing.assert_array_equal(np.asarray(out.info.log_evidence[first:]), 0.0)
    assert int(out.state.step) == first
    # A step not taken keeps every particle where it was.
    np.testing.assert_array_equal(np.asarray(out.info.ancestors[first:]),
                                  np.broadcast_to(np.arange(CONFIG.num_particles),
                                                  (stalled.size - first, CONFIG.num_particles)))


def test_known_path_loglik_is_minus_inf_when_a_step_of_the_path_does_not_fit(office):
    log, _, _, small = office
    true_log = dataclasses.replace(log, odometry=np.asarray(log.ground_truth, log.odometry.dtype))
    one = dataclasses.replace(CONFIG, num_particles=1)
    fits = rbpf.known_path_loglik_fn(true_log, one, SETTINGS)
    value = float(fits(PARAMS))
    assert np.isfinite(value)
    # One particle asks for a few tiles a step: allow fewer than the most it asks for.
    probe = rbpf.filter(jax.random.key(0), rbpf.prepare(true_log, one, SETTINGS)[0],
                        PARAMS._replace(motion=jax.tree.map(np.zeros_like, PARAMS.motion)), one)
    tight = rbpf.pool_size(one)._replace(max_new_tiles=int(probe.state.maps.peak_request) - 1)
    assert float(rbpf.known_path_loglik_fn(true_log, one, SETTINGS, pool=tight)(PARAMS)) == -np.inf


def test_fit_stops_with_a_clear_error_on_a_filter_whose_pools_overflow(office):
    _, prepared, _, small = office

    def objective(key, params):
        return rbpf.filter(key, prepared, params, CONFIG, pool=small).marginal_loglik

    with pytest.raises(learning.FitError, match="pools overflowed") as err:
        learning.fit(jax.random.key(0), objective, PARAMS, num_steps=2, trainable=["motion.srr"], progress=False)
    assert len(err.value.result.history["objective"]) == 0  # the first step failed: nothing was fitted
