"""The proposal seam: a proposal defined here, in the test, with a setting, numbers and a flag of
its own, is one row registered at run time (:func:`jaxslam.config.register_proposal`). No
library file names it: ``SlamConfig``, ``build_setup``, the command line and the filter find
everything in its row.

"Best of M": M draws from the motion model (its noise scaled by ``best_of.spread``), one of them
kept by its likelihood, the increment log (1/M) sum_i p(z_t | x_i) (sampling importance
resampling inside the proposal: the look-ahead at horizon 0). With one draw and spread 1 it is
the odometry proposal, bit for bit.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array, Float

from jaxslam import motion, slam
from jaxslam.config import ConfigError, RunSettings, SlamConfig, build_setup, default_params, register_proposal
from jaxslam.map_view import MapView
from jaxslam.proposals import PROPOSALS, Flag, ParamGroup, Proposal, ProposalOutput, Setting
from jaxslam.proposals.base import step_params
from jaxslam.sensor_model import sensor_model
from jaxslam.sim import office_scenario


class BestOfParams(NamedTuple):
    spread: Float[Array, ""]
    """The draws' noise, as a multiple of the motion model's."""


def best_of_propose(key, pose, field, inputs, sensor, params, config, step_motion=None) -> ProposalOutput:
    params = step_params(params, step_motion)
    draws = config.best_of_draws
    noise = jax.tree.map(lambda v: v * params.best_of.spread, params.motion)
    poses, score = motion.sample_with_score(key, jnp.broadcast_to(pose, (draws, 3)), inputs.motion, noise)
    log_lik = sensor_model(config).log_likelihoods_fn(MapView(config.grid, field), poses, inputs.ranges, sensor,
                                                      params.likelihood, config.likelihood_lookup) + score
    pick = jax.random.categorical(jax.random.fold_in(key, 1), jax.lax.stop_gradient(log_lik))
    return ProposalOutput(poses[pick], jax.nn.logsumexp(log_lik) - jnp.log(draws), jnp.bool_(False))


BEST_OF = Proposal(
    best_of_propose, "best of M motion-model draws, kept by their likelihood",
    settings=(Setting("best_of_draws", 8, lambda v: v >= 1, ">= 1 (draws)", "M, the draws a particle makes."),),
    params=ParamGroup("best_of", BestOfParams, {"spread": 1.0}, {"spread": (lambda v: v > 0, "> 0")}),
    flags=(Flag("--draws", "best_of_draws", int, "motion-model draws M per particle", minimum=1),))


@pytest.fixture
def best_of():
    register_proposal("best_of", BEST_OF)
    yield BEST_OF
    del PROPOSALS["best_of"]  # other tests see the library's table


def test_its_setting_numbers_and_flag_come_from_its_row(best_of):
    config = SlamConfig(proposal="best_of", best_of_draws=3)
    assert (config.best_of_draws, SlamConfig().best_of_draws, config.lookahead_steps) == (3, 8, 0)
    with pytest.raises(ConfigError, match="best_of_draws must be >= 1"):
        SlamConfig(best_of_draws=0)
    config, _, params = build_setup({"proposal": "best_of", "best_of_draws": "4", "best_of.spread": "0.5"})
    assert config.best_of_draws == 4 and float(params.best_of.spread) == 0.5
    with pytest.raises(ConfigError, match="best_of.spread must be > 0"):
        build_setup({"best_of.spread": 0.0})
    from jaxslam.cli import make_parser
    from jaxslam.cli.common import build_setup_from_args

    help_text = make_parser()._subparsers._group_actions[0].choices["map"].format_help()
    assert "--draws" in help_text and "best of M motion-model draws" in help_text
    args = make_parser().parse_args(["map", "LOG", "--proposal", "best_of", "--draws", "5"])
    assert build_setup_from_args(args)[0].best_of_draws == 5


def test_a_row_that_takes_a_name_already_owned_is_refused(best_of):
    register_proposal("best_of", BEST_OF)  # the same row again: a no-op
    with pytest.raises(ValueError, match="taken by another proposal"):
        register_proposal("best_of", BEST_OF._replace(summary="another"))
    with pytest.raises(ValueError, match="names of SlamConfig or SlamParams"):
        register_proposal("clash", BEST_OF._replace(settings=(Setting("num_particles", 1, bool, "", ""),)))
    other_draws = Setting("best_of_draws", 2, lambda v: v >= 1, ">= 1", "another proposal's draws")
    with pytest.raises(ValueError, match="taken by another proposal"):  # best_of_draws is best_of's
        register_proposal("clash", BEST_OF._replace(settings=(other_draws,), flags=(), params=None))
    assert "clash" not in PROPOSALS


def test_the_filter_draws_with_it_and_one_draw_is_the_odometry_proposal(best_of):
    """The filter finds the proposal, its setting and its numbers in the row: one draw at spread 1
    is the OP's run bit for bit (a wrong key, draw count or noise would change it)."""
    log = office_scenario(jax.random.key(3)).log.subset(np.arange(40))
    settings = RunSettings(linear_update=0.3, angular_update=0.25)
    base = dict(num_particles=4, max_insert_range=8.0, map_extent=64.0)
    params = default_params()
    op = slam.run(jax.random.key(0), log, SlamConfig(proposal="op", **base), params, settings, progress=False)
    one = slam.run(jax.random.key(0), log, SlamConfig(proposal="best_of", best_of_draws=1, **base), params,
                   settings, progress=False)
    np.testing.assert_array_equal(one.best_path, op.best_path)
    np.testing.assert_array_equal(one.info.log_evidence, op.info.log_evidence)
