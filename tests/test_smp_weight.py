"""The SMP's two log-weight increments (``SlamConfig.smp_weight``) against a brute-force integral.

One step in the test room with the learning settings (gain 1, bilinear lookup, 1 mm and 1 mrad
minimum stds): the evidence p(z_t | x_{t-1}, m, u_t) = int p(z | x, m) p(x | x_{t-1}, u) dx as a
Riemann sum over a fine lattice of poses round the posterior (summed in NumPy float64; the
slow reference), and its gradient in log coordinates by autodiff of that sum and by central finite
differences. "importance" must reproduce both from its draws; "quadrature" (the default) is shown
to miss them where the posterior is narrower than its stencil, which is why learning does not use
it (docs/design.md, "Motion-noise gradients by the score").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from rooms import ROOM_EXTENT, SENSOR, build_room_map, paged_field, room_path, scan_at

from jaxslam import motion
from jaxslam import window_posterior as W
from jaxslam.config import ConfigError, SlamConfig, default_params
from jaxslam.geometry import between, compose
from jaxslam.learning import slam_learning_setup
from jaxslam.likelihood_field import endpoint_log_likelihoods
from jaxslam.proposals import scan_match
from jaxslam.proposals.base import StepInputs

NAMES = ("motion.srr", "motion.srt", "motion.str", "motion.stt", "likelihood.sigma")
BASE = default_params(**{"likelihood.gain": 1.0, "motion.min_translation_std": 0.001,
                         "motion.min_rotation_std": 0.001})
NUM_DRAWS = 8000
LATTICE = 61  # per axis, +-5 cm and +-0.05 rad round the heaviest mode: ~1.7 mm, 1.7 mrad apart


def _config(smp_weight):
    return SlamConfig(num_particles=1, proposal="smp", map_extent=ROOM_EXTENT, max_insert_range=10.0,
                      likelihood_lookup="bilinear", smp_weight=smp_weight)


def _at(log_scales):
    """BASE with each of NAMES multiplied by exp(log_scales[i]) (traceable)."""
    params = BASE
    for i, name in enumerate(NAMES):
        group, field = name.split(".")
        part = getattr(params, group)
        params = params._replace(**{group: part._replace(**{field: jnp.exp(log_scales[i]) * getattr(part, field)})})
    return params


@pytest.fixture(scope="module")
def step():
    config = _config("importance")
    field = paged_field(build_room_map(3), config)
    path = room_path(6)
    pose, motion_step, ranges = jnp.asarray(path[1]), jnp.asarray(between(path[1], path[2])), scan_at(path[2])
    inputs = StepInputs(motion_step, ranges, jnp.zeros((0, 3)), jnp.zeros((0, ranges.shape[0])), jnp.zeros((0,), bool))
    return field, pose, inputs


def _reference(field, pose, inputs, config):
    """(log evidence, its gradient by autodiff, by central differences) of the lattice's Riemann sum."""
    post = W.window_posterior(pose, field, inputs.motion, inputs.ranges, SENSOR, BASE, config, fit_gain=1.0)
    centre = np.asarray(between(compose(pose, inputs.motion), post.means[int(np.argmax(np.asarray(post.log_masses)))]))
    axes = [c + np.linspace(-0.05, 0.05, LATTICE) for c in centre]
    offsets = jnp.asarray(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(LATTICE, -1, 3), jnp.float32)
    log_volume = float(np.sum(np.log([a[1] - a[0] for a in axes])))

    def log_gamma(log_scales):
        params = _at(log_scales)

        def chunk(delta):
            poses = compose(pose, inputs.motion + delta)
            return (endpoint_log_likelihoods(config.grid, field, poses, inputs.ranges, SENSOR, params.likelihood,
                                             "bilinear") + motion.log_density(poses, pose, inputs.motion, params.motion))
        return jax.lax.map(chunk, offsets).reshape(-1)

    values = np.asarray(jax.jit(log_gamma)(jnp.zeros(len(NAMES))), np.float64)
    evidence = float(values.max() + np.log(np.sum(np.exp(values - values.max())))) + log_volume
    autodiff = np.asarray(jax.jit(jax.grad(lambda s: jax.scipy.special.logsumexp(log_gamma(s))))(jnp.zeros(len(NAMES))))
    h = 1e-2
    total = jax.jit(lambda s: jax.scipy.special.logsumexp(log_gamma(s)))
    central = np.array([(float(total(jnp.zeros(len(NAMES)).at[i].set(h))) - float(total(jnp.zeros(len(NAMES)).at[i].set(-h))))
                        / (2 * h) for i in range(len(NAMES))])
    return evidence, autodiff, central


def _draws(field, pose, inputs, config):
    """The SMP's increments and their gradients (log coordinates) over NUM_DRAWS keys."""
    def increment(log_scales, key):
        return scan_match.propose(key, pose, field, inputs, SENSOR, _at(log_scales), config).log_weight_increment
    keys = jax.random.split(jax.random.key(0), NUM_DRAWS)
    values, grads = jax.jit(jax.vmap(jax.value_and_grad(increment), in_axes=(None, 0)))(jnp.zeros(len(NAMES)), keys)
    return np.asarray(values, np.float64), np.asarray(grads, np.float64)


def test_the_importance_weight_estimates_the_evidence_and_its_score(step):
    """"importance": the mean of the weights is the lattice's evidence (within 0.25 nats: the
    log of a mean of heavy-tailed weights falls a little short) and the self-normalised mean of
    the increments' gradients (d log gamma at each draw: Fisher's identity) is the evidence's
    gradient within 3 % and 5 delta-method standard errors, every term. The lattice's autodiff
    and finite differences agree first (the reference is smooth). "quadrature", the default, is
    off by nats in value and by more than half in srr's and srt's gradient: its stencil (5 cm, 0.05
    rad apart) is far wider than this posterior."""
    field, pose, inputs = step
    evidence, autodiff, central = _reference(field, pose, inputs, _config("importance"))
    np.testing.assert_allclose(autodiff, central, rtol=0.02, atol=1e-3)

    values, grads = _draws(field, pose, inputs, _config("importance"))
    assert np.all(np.isfinite(values)) and np.all(np.isfinite(grads))
    weights = np.exp(values - values.max())
    estimate = np.log(weights.mean()) + values.max()
    assert abs(estimate - evidence) < 0.25, (estimate, evidence)
    normalised = weights / weights.sum()
    score = normalised @ grads
    standard_error = np.sqrt(np.sum(normalised[:, None] ** 2 * (grads - score) ** 2, axis=0))
    assert np.all(np.abs(score - autodiff) <= 0.03 * np.abs(autodiff) + 5 * standard_error), (score, autodiff)

    quadrature, quadrature_grads = _draws(field, pose, inputs, _config("quadrature"))
    assert quadrature[0] > evidence + 2.0  # deterministic: the summed stencil masses
    off = np.abs(quadrature_grads[0] - autodiff) / np.abs(autodiff)
    assert off[0] > 0.5 and off[1] > 0.5, off


def test_smp_weight_is_checked_and_learning_sets_importance():
    with pytest.raises(ConfigError, match="smp_weight"):
        SlamConfig(smp_weight="exact")
    config, _, _ = slam_learning_setup()
    assert config.smp_weight == "importance"
    assert SlamConfig().smp_weight == "quadrature"


def test_the_filter_with_the_learning_setup_has_finite_score_gradients():
    """The whole filter, SMP with ``slam_learning_setup`` (the importance weight), 30 office scans:
    the value and every parameter's gradient are finite and each motion term's is nonzero (the
    drawn poses' scores)."""
    from jaxslam import rbpf
    from jaxslam.sim import office_scenario

    log = office_scenario(jax.random.key(0)).log.subset(np.arange(30))
    config, settings, params = slam_learning_setup({"proposal": "smp", "num_particles": 4, "max_insert_range": 10.0,
                                                    "beam_stride": 2, "map_extent": 128.0})
    prepared, _, _ = rbpf.prepare(log, config, settings)
    value, grads = jax.jit(jax.value_and_grad(
        lambda p: rbpf.filter(jax.random.key(1), prepared, p, config).marginal_loglik))(params)
    assert np.isfinite(float(value))
    bad = [jax.tree_util.keystr(path) for path, g in jax.tree_util.tree_flatten_with_path(grads)[0]
           if not np.isfinite(float(g))]
    assert not bad, bad
    assert all(float(getattr(grads.motion, name)) != 0.0 for name in ("srr", "srt", "str", "stt"))


def test_the_linear_gaussian_counterpart_weighs_by_the_predictive_with_the_drawn_states_score():
    """tests/linear_gaussian.adapted_draw, the SMP's importance weight where q is the exact local
    posterior (experiments/score_bias.py measures its score's bias): the increment is
    log N(y; a x_prev, q + r) in value for every draw, and its gradient is d log gamma at the drawn
    state, gamma = N(x; a x_prev, q) N(y; x, r), computed by hand."""
    from linear_gaussian import THETA, adapted_draw

    x_prev, y = jnp.linspace(-1.0, 1.0, 7), jnp.float32(0.4)
    x, increments = adapted_draw(jax.random.key(3), THETA, x_prev, y)
    a, q, r = (float(v) for v in THETA)
    xp, xs = np.asarray(x_prev, np.float64), np.asarray(x, np.float64)
    predictive = -0.5 * np.log(2 * np.pi * (q + r)) - 0.5 * (float(y) - a * xp) ** 2 / (q + r)
    np.testing.assert_allclose(np.asarray(increments), predictive, rtol=1e-5, atol=1e-5)
    grads = np.asarray(jax.jacrev(lambda th: adapted_draw(jax.random.key(3), th, x_prev, y)[1])(THETA))
    by_hand = np.stack([(xs - a * xp) * xp / q,                                   # d/da of log f
                        -0.5 / q + 0.5 * (xs - a * xp) ** 2 / q**2,               # d/dq of log f
                        -0.5 / r + 0.5 * (float(y) - xs) ** 2 / r**2], axis=-1)   # d/dr of log g
    np.testing.assert_allclose(grads, by_hand, rtol=1e-4, atol=1e-5)


if __name__ == "__main__":  # python3 tests/test_smp_weight.py: the note's table, 20,000 draws
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    NUM_DRAWS = 20_000
    field, pose, inputs = step.__wrapped__()
    evidence, autodiff, central = _reference(field, pose, inputs, _config("importance"))
    print(f"lattice: log evidence {evidence:.2f}, gradient {np.round(autodiff, 3)} (central differences "
          f"{np.round(central, 3)})")
    for smp_weight in ("quadrature", "importance"):
        values, grads = _draws(field, pose, inputs, _config(smp_weight))
        weights = np.exp(values - values.max())
        normalised = weights / weights.sum()
        score = normalised @ grads
        se = np.sqrt(np.sum(normalised[:, None] ** 2 * (grads - score) ** 2, axis=0))
        print(f"{smp_weight}: log evidence {np.log(weights.mean()) + values.max():.2f}, gradient {np.round(score, 3)} "
              f"± {np.round(se, 3)}")
