"""The hybrid door filter (Avots et al.): math pinned against brute force and closed forms."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import binary_bayes
from jaxslam.localization import doors, mcl
from jaxslam.geometry import between
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.localization.beam_model import beam_model_log_likelihood, make_beam_model_params
from jaxslam.motion import motion_params
from jaxslam.segment_map import raycast

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import door_harness  # noqa: E402  (experiments/door_harness.py)

ZERO_MOTION = motion_params(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def _room_with_three_doors():
    """A 10 m x 6 m room; doors in three different walls, each opening onto a closet, so that no
    beam from inside the room crosses two doors (the factorisation is then exact)."""
    walls = [
        [0, 0, 10, 0], [10, 0, 10, 2], [10, 3, 10, 6],  # east wall, door 0 at y in [2, 3]
        [10, 6, 6, 6], [5, 6, 0, 6],  # north wall, door 1 at x in [5, 6]
        [0, 6, 0, 4], [0, 3, 0, 0],  # west wall, door 2 at y in [3, 4]
        [10, 2, 12, 2], [12, 2, 12, 3], [12, 3, 10, 3],  # closet behind door 0
        [5, 6, 5, 8], [5, 8, 6, 8], [6, 8, 6, 6],  # closet behind door 1
        [0, 3, -3, 3], [-3, 3, -3, 4], [-3, 4, 0, 4],  # closet behind door 2
    ]
    door_segments = [[10, 2, 10, 3], [5, 6, 6, 6], [0, 3, 0, 4]]
    return np.asarray(walls, np.float32), np.asarray(door_segments, np.float32)


def _brute_force(walls, door_segments, poses, scans, sensor, beam, gain, initial, p_oo, p_oc):
    """Forward filter over all 2^K joint door states (float64), with the product transition model.

    Returns (T, K) marginals p(open) after each scan and the total log-evidence log p(z_1:T).
    """
    k = door_segments.shape[0]
    states = np.array(list(itertools.product([0, 1], repeat=k)), bool)  # (2^K, K), True = open
    segments = np.concatenate([walls, door_segments])
    # Product transition: T[s, s'] = prod_k p(s'_k | s_k).
    p_open_given = np.where(states, p_oo, p_oc)  # (S, K): p(open_t | s_{t-1})
    trans = np.prod(np.where(states[None, :, :], p_open_given[:, None, :], 1 - p_open_given[:, None, :]), axis=-1)
    prior = np.prod(np.where(states, initial, 1 - initial), axis=-1)
    marginals, log_evidence = [], 0.0
    for pose, z in zip(poses, scans):
        lik = []
        for s in states:
            active = np.concatenate([np.ones(walls.shape[0], bool), ~s])
            expected, _ = raycast(segments, pose[:2], pose[2] + sensor.beam_angles, sensor.range_max, active)
            lik.append(gain * float(np.sum(np.asarray(beam_model_log_likelihood(expected, z, sensor.range_max, beam),
                                                      np.float64))))
        lik = np.asarray(lik)
        predicted = prior @ trans
        joint = np.log(predicted) + lik
        norm = np.logaddexp.reduce(joint)
        log_evidence += norm
        prior = np.exp(joint - norm)
        marginals.append(prior @ states)
    return np.asarray(marginals), log_evidence


class _Changing(NamedTuple):
    """A fixed path in the three-door room, scans from a world whose doors change (door 0 closed
    then open, 1 open, 2 closed), and the exact answers of :func:`_brute_force`."""

    walls: np.ndarray
    door_segments: np.ndarray
    sensor: object
    beam: object
    gain: float
    initial: np.ndarray
    p_oo: np.ndarray
    p_oc: np.ndarray
    poses: np.ndarray
    scans: list


def _changing_doors() -> _Changing:
    walls, door_segments = _room_with_three_doors()
    sensor = make_sensor(uniform_beams(90, 2 * np.pi * 89 / 90), 0.0, 15.0)
    beam = make_beam_model_params(0.8, 0.1, 0.05, 0.05, sigma_hit=0.3, lambda_short=0.5)
    gain, initial = 0.3, np.array([0.3, 0.5, 0.8])
    p_oo, p_oc = np.array([0.9, 0.8, 0.95]), np.array([0.1, 0.3, 0.02])
    poses = np.array([[3, 2, 0.3], [5, 2.5, 0.0], [7, 3, 0.5], [7.5, 3.5, 1.2], [6, 4, 2.5], [3, 4, 3.0]], np.float32)
    truth_open = np.array([[0, 1, 0]] * 3 + [[1, 1, 0]] * 3, bool)
    segments = np.concatenate([walls, door_segments])
    rng = np.random.default_rng(0)
    scans = []
    for pose, open_now in zip(poses, truth_open):
        active = np.concatenate([np.ones(walls.shape[0], bool), ~open_now])
        r, _ = raycast(segments, pose[:2], pose[2] + sensor.beam_angles, sensor.range_max, active)
        scans.append(np.clip(np.asarray(r) + rng.normal(0, 0.05, r.shape), 0, 15).astype(np.float32))
    return _Changing(walls, door_segments, sensor, beam, gain, initial, p_oo, p_oc, poses, scans)


def _single_particle_filter(case: _Changing):
    """Door map, params, config (one particle, no motion noise, no resampling), initial state and
    stacked inputs of :func:`_changing_doors`: the filter then is the exact forward filter."""
    door_map = doors.make_door_map(case.walls, case.door_segments, case.initial, case.p_oo, case.p_oc)
    params = doors.make_params(door_map, motion=ZERO_MOTION, beam=case.beam, likelihood_gain=case.gain,
                               resample_threshold=0.0)
    config = doors.DoorConfig(mcl.MclConfig(num_particles=1))
    state = doors.init(mcl.MclState(jnp.asarray(case.poses[:1]), jnp.zeros(1), jnp.zeros((), jnp.int32)), door_map)
    motions = np.concatenate([np.zeros((1, 3)), np.asarray(between(case.poses[:-1], case.poses[1:]))])
    inputs = mcl.ScanInputs(jnp.asarray(motions, jnp.float32), jnp.asarray(np.stack(case.scans)))
    return door_map, params, config, state, inputs


def test_factored_posterior_matches_brute_force_enumeration():
    case = _changing_doors()
    want_marginals, want_evidence = _brute_force(case.walls, case.door_segments, case.poses, case.scans, case.sensor,
                                                 case.beam, case.gain, case.initial, case.p_oo, case.p_oc)
    door_map, params, config, state, inputs = _single_particle_filter(case)
    evidence = 0.0
    for t in range(len(case.poses)):
        state, info = doors.step_jit(jax.random.key(t), state, mcl.ScanInputs(inputs.motion[t], inputs.ranges[t]),
                                     door_map, case.sensor, params, config)
        np.testing.assert_allclose(np.asarray(state.poses[0]), case.poses[t], atol=1e-5)
        np.testing.assert_allclose(np.asarray(state.door_open[0]), want_marginals[t], atol=2e-4)
        evidence += float(info.mcl.log_evidence)
    np.testing.assert_allclose(evidence, want_evidence, rtol=1e-5, atol=1e-3)
    # The test has teeth: each door was seen, and changed its belief.
    assert np.all(np.abs(want_marginals[-1] - case.initial) > 0.1)


def test_filter_loglik_and_transition_gradient_match_brute_force():
    """``doors.filter``'s log-likelihood is the exact log-evidence, and its gradient in the
    transition probabilities is the exact one (central differences of the float64 enumeration)."""
    case = _changing_doors()
    door_map, params, config, state, inputs = _single_particle_filter(case)

    def loglik(p_oo, p_oc):
        return doors.filter(jax.random.key(0), state, inputs, door_map, case.sensor,
                            params._replace(p_open_open=p_oo, p_open_closed=p_oc), config).marginal_loglik

    value, (grad_oo, grad_oc) = jax.value_and_grad(loglik, argnums=(0, 1))(params.p_open_open, params.p_open_closed)
    _, want = _brute_force(case.walls, case.door_segments, case.poses, case.scans, case.sensor, case.beam, case.gain,
                           case.initial, case.p_oo, case.p_oc)
    np.testing.assert_allclose(float(value), want, rtol=1e-5, atol=1e-3)
    h = 1e-5
    for name, got in (("p_oo", grad_oo), ("p_oc", grad_oc)):
        for k in range(3):
            plus, minus = {"p_oo": case.p_oo.copy(), "p_oc": case.p_oc.copy()}, {"p_oo": case.p_oo.copy(),
                                                                                 "p_oc": case.p_oc.copy()}
            plus[name][k] += h
            minus[name][k] -= h
            f = lambda p: _brute_force(case.walls, case.door_segments, case.poses, case.scans, case.sensor,  # noqa: E731
                                       case.beam, case.gain, case.initial, p["p_oo"], p["p_oc"])[1]
            numeric = (f(plus) - f(minus)) / (2 * h)
            np.testing.assert_allclose(float(got[k]), numeric, rtol=2e-3, atol=2e-2, err_msg=f"{name}[{k}]")
    # Teeth: the transitions matter to this log (door 0 changed while the robot watched).
    assert np.max(np.abs(np.asarray(grad_oc))) > 1.0
    # filter_history is the filter, with every step's particles in its info.
    out = doors.filter(jax.random.key(0), state, inputs, door_map, case.sensor, params, config)
    kept = doors.filter_history(jax.random.key(0), state, inputs, door_map, case.sensor, params, config)
    infos, history = kept.info
    chex.assert_trees_all_equal((out.state, out.info, out.marginal_loglik), (kept.state, infos, kept.marginal_loglik))
    np.testing.assert_allclose(float(out.marginal_loglik), float(np.sum(np.asarray(out.info.mcl.log_evidence))),
                               rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(history.door_open[-1]), np.asarray(out.state.door_open))
    assert history.poses.shape == (len(case.poses), 1, 3)


def test_unobserved_door_decays_to_closed_form():
    walls, door_segments = _room_with_three_doors()
    sensor = make_sensor(uniform_beams(31, np.pi / 2), 0.0, 4.0)  # sees the south-east corner only
    p_oo, p_oc, initial = np.array([0.97, 0.9, 0.99]), np.array([0.05, 0.2, 0.001]), np.array([0.95, 0.1, 0.5])
    door_map = doors.make_door_map(walls, door_segments, initial, p_oo, p_oc)
    params = doors.make_params(door_map, motion=ZERO_MOTION, resample_threshold=0.0)
    config = doors.DoorConfig(mcl.MclConfig(num_particles=2))
    pose = jnp.array([8.0, 1.0, -0.5])
    state = doors.init(mcl.MclState(jnp.stack([pose, pose]), jnp.log(jnp.full(2, 0.5)), jnp.zeros((), jnp.int32)),
                       door_map)
    steps = 40
    inputs = mcl.ScanInputs(jnp.zeros((steps, 3)), jnp.full((steps, 31), 2.0))
    out = doors.filter(jax.random.key(0), state, inputs, door_map, sensor, params, config)
    final, info = out.state, out.info
    assert np.all(np.asarray(info.door_observed) == 0)
    for n in (1, 10, 40):
        want = binary_bayes.predict_n(initial, p_oo, p_oc, n)
        np.testing.assert_allclose(np.asarray(info.door_belief[n - 1]), want, rtol=1e-5, atol=1e-6)
    stationary = binary_bayes.stationary(p_oo, p_oc)
    far = binary_bayes.predict_n(initial, p_oo, p_oc, 10_000)
    np.testing.assert_allclose(far, stationary, atol=1e-6)
    # ...and the filter moved toward the stationary value, never past it.
    start_gap, end_gap = initial - stationary, np.asarray(final.door_open[0]) - stationary
    assert np.all(np.sign(start_gap) == np.sign(end_gap)) and np.all(np.abs(end_gap) < np.abs(start_gap))


def _small_run_setup(num_particles=64):
    walls, door_segments = _room_with_three_doors()
    sensor = make_sensor(uniform_beams(45, np.pi), 0.0, 12.0)
    door_map = doors.make_door_map(walls, door_segments, [0.2, 0.7, 0.5], [0.9, 0.95, 0.99], [0.05, 0.1, 0.01])
    poses = np.array([[2 + 0.4 * t, 2 + 0.1 * t, 0.2 * t - 0.5] for t in range(8)], np.float32)
    segments = np.concatenate([walls, door_segments])
    active = np.concatenate([np.ones(walls.shape[0], bool), [True, False, True]])
    ranges = np.stack([np.asarray(raycast(segments, p[:2], p[2] + sensor.beam_angles, 12.0, active)[0]) for p in poses])
    motions = np.concatenate([np.zeros((1, 3)), np.asarray(between(poses[:-1], poses[1:]))]).astype(np.float32)
    inputs = mcl.ScanInputs(jnp.asarray(motions), jnp.asarray(ranges))
    state = doors.init(mcl.init_tracked(jax.random.key(7), poses[0], jnp.array([0.1, 0.1, 0.05]),
                                        mcl.MclConfig(num_particles)), door_map)
    return door_map, sensor, inputs, state


def test_memoryless_baseline_equals_hybrid_with_half_transitions():
    door_map, sensor, inputs, state = _small_run_setup()
    params = doors.make_params(door_map, likelihood_gain=0.3, resample_threshold=0.7)
    key = jax.random.key(11)
    a, info_a, _ = doors.filter(key, state, inputs, door_map, sensor, params,
                                doors.DoorConfig(mcl.MclConfig(64), memory=False))
    b, info_b, _ = doors.filter(key, state, inputs, door_map, sensor, doors.memoryless_params(params),
                                doors.DoorConfig(mcl.MclConfig(64), memory=True))
    chex.assert_trees_all_close(a, b, atol=1e-5)
    chex.assert_trees_all_close(info_a, info_b, atol=1e-4)
    assert np.any(np.asarray(info_a.mcl.resampled))  # the resampling path was exercised
    # With memory and the map's transitions, the result differs (the test can fail).
    c = doors.filter(key, state, inputs, door_map, sensor, params, doors.DoorConfig(mcl.MclConfig(64))).state
    assert not np.allclose(np.asarray(c.door_open), np.asarray(a.door_open), atol=1e-3)


def test_beam_to_door_attribution_on_hand_made_geometry():
    # A wall x = 5 (gap y in [-0.5, 0.5] holding door 0), door 1 at x = 8 behind it, a wall x = 10,
    # and door 2 at y = 3 beyond the wall x = 5 (reachable only through a wall: never attributed).
    walls = np.array([[5, -5, 5, -0.5], [5, 0.5, 5, 5], [10, -5, 10, 5]], np.float32)
    door_segments = np.array([[5, -0.5, 5, 0.5], [8, -1, 8, 1], [6, 3, 9, 3]], np.float32)
    door_map = doors.make_door_map(walls, door_segments)
    angles = jnp.array([0.0, np.arctan2(3.0, 5.0), np.arctan2(0.4, 5.0), np.pi, np.arctan2(0.9, 8.0)])
    att = jax.jit(doors.attribute_beams)(door_map, jnp.zeros(2), angles, jnp.float32(20.0))
    np.testing.assert_array_equal(np.asarray(att.door), [0, -1, 0, -1, -1])
    # Beam 0: door 0 at 5 m; with door 0 open it meets door 1 (closed) at 8 m, not the wall at 10 m.
    np.testing.assert_allclose(np.asarray(att.range_closed[0]), 5.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(att.range_open[0]), 8.0, atol=1e-5)
    # Beam 1 hits the wall x = 5 (door 2 lies behind it); no door, both ranges the same.
    np.testing.assert_allclose(np.asarray(att.range_closed[1]), np.hypot(5, 3), atol=1e-4)
    np.testing.assert_allclose(np.asarray(att.range_open[1]), np.asarray(att.range_closed[1]))
    # Beam 3 (west) hits nothing: max range, no door.
    np.testing.assert_allclose(np.asarray(att.range_closed[3]), 20.0)
    # Beam 4 would reach door 1 through the gap at y = 0.5625 > 0.5: blocked by the wall.
    np.testing.assert_allclose(np.asarray(att.range_closed[4]), 5.0 / np.cos(np.arctan2(0.9, 8.0)), rtol=1e-5)
    # The per-door split of a scan: beams 0 and 2 go to door 0, the rest to the static part.
    sensor = make_sensor(angles, 0.0, 20.0)
    params = doors.make_params(door_map, likelihood_gain=1.0)
    z = jnp.array([5.0, 5.8, 5.0, 20.0, 5.0])
    lik = jax.jit(doors.scan_door_likelihoods)(door_map, jnp.zeros(3), z, sensor, params)
    np.testing.assert_array_equal(np.asarray(lik.num_beams), [2, 0, 0])
    per_beam_closed = beam_model_log_likelihood(att.range_closed, z, 20.0, params.beam)
    np.testing.assert_allclose(float(lik.log_closed[0]), float(per_beam_closed[0] + per_beam_closed[2]), rtol=1e-5)
    np.testing.assert_allclose(float(lik.static), float(per_beam_closed[1] + per_beam_closed[3] + per_beam_closed[4]),
                               rtol=1e-5)
    assert float(lik.log_closed[0]) > float(lik.log_open[0])  # the door is seen closed


def test_door_step_compiles_once():
    door_map, sensor, inputs, state = _small_run_setup(32)
    config = doors.DoorConfig(mcl.MclConfig(32))

    @jax.jit
    @chex.assert_max_traces(n=1)
    def stepper(key, st, inp, dmap, params):
        return doors.step(key, st, inp, dmap, sensor, params, config)

    for t in range(4):
        params = doors.make_params(door_map, likelihood_gain=0.2 + 0.1 * t)._replace(
            p_open_open=jnp.full(3, 0.9 - 0.1 * t))
        dmap = door_map._replace(initial_open=door_map.initial_open * 0.5)
        state, _ = stepper(jax.random.key(t), state, mcl.ScanInputs(inputs.motion[t], inputs.ranges[t]), dmap, params)
    chex.clear_trace_counter()


def test_door_state_accuracy():
    belief = np.array([[0.9, 0.2, 0.5], [0.6, 0.1, 0.9]])
    truth = np.array([True, False, True])
    observed = np.array([[True, True, False], [True, True, True]])
    # Seed 0: 2 of 2 right; seed 1: 0.6 is not > 0.65 (wrong), 0.1 right, 0.9 right -> 4 of 5.
    assert door_harness.door_state_accuracy(belief, truth, observed) == pytest.approx(0.8)


def test_door_config_holds_the_mcl_config():
    config = doors.DoorConfig(mcl.MclConfig(num_particles=7, beam_stride=3), memory=False)
    assert config.mcl.num_particles == 7 and config.mcl.beam_stride == 3 and not config.memory
    assert doors.DoorConfig().mcl == mcl.MclConfig()
    hash(config)  # static under jit
    with pytest.raises(TypeError, match="MclConfig"):
        doors.DoorConfig(64)
    with pytest.raises(ValueError, match="num_particles"):  # checked once, by MclConfig
        doors.DoorConfig(mcl.MclConfig(num_particles=0))


def test_the_experiment_harness_composes_the_library_filters():
    """experiments/door_harness.py: ``run_filter`` is ``mcl.init_global`` then ``doors.filter`` (or
    ``mcl.filter`` on the map as given), scored against the truth; a batch of seeds is the same runs."""
    door_map, sensor, inputs, _ = _small_run_setup()
    params = doors.make_params(door_map, likelihood_gain=0.3)
    config = doors.DoorConfig(mcl.MclConfig(16))
    regions = jnp.array([[1.8, 1.8, 2.2, 2.2]])
    truth = jnp.asarray(np.cumsum(np.asarray(inputs.motion), axis=0) + [2.0, 2.0, -0.5], jnp.float32)
    key = jax.random.key(3)
    run = jax.jit(door_harness.run_filter, static_argnames=("config", "filter_kind", "heading_range"))
    k_init, k_run = jax.random.split(key)
    start = mcl.init_global(k_init, regions, config.mcl)
    hybrid = run(key, inputs, truth, regions, door_map, sensor, params, config, "hybrid")
    out = doors.filter(k_run, doors.init(start, door_map), inputs, door_map, sensor, params, config)
    np.testing.assert_array_equal(np.asarray(hybrid.final_door_open), np.asarray(out.state.door_open))
    np.testing.assert_array_equal(np.asarray(hybrid.door_belief), np.asarray(out.info.door_belief))
    want = np.hypot(*(np.asarray(out.info.mcl.mean_pose[:, :2]) - np.asarray(truth[:, :2])).T)
    np.testing.assert_allclose(np.asarray(hybrid.position_error), want, rtol=1e-6, atol=1e-6)
    static = run(key, inputs, truth, regions, door_map, sensor, params, config, "static")
    segments, active = doors.static_segments(door_map)
    out = mcl.filter(k_run, start, inputs, segments, sensor, params.mcl_params(), config.mcl, active)
    np.testing.assert_array_equal(np.asarray(static.final_poses), np.asarray(out.state.poses))
    np.testing.assert_array_equal(np.asarray(static.door_belief[-1]), [0.0, 1.0, 1.0])  # the map as given
    batch = door_harness.run_filter_batch(jax.random.split(key, 2), jax.tree.map(lambda x: jnp.stack([x, x]), inputs),
                                          jnp.stack([truth, truth]), regions, door_map, sensor, params, config,
                                          "hybrid", batch_size=2)
    assert batch.position_error.shape == (2, inputs.motion.shape[0])
    with pytest.raises(ValueError, match="filter_kind"):
        door_harness.run_filter(key, inputs, truth, regions, door_map, sensor, params, config, "nope")


def test_static_doors_have_finite_gradients():
    """Doors known not to move (p(open|open) = 1, p(open|closed) = 0) saturate the beliefs at 0
    or 1; the filter's value and every gradient stay finite (the update's derivatives are written
    out, binary_bayes.update), with the untempered likelihood a fit uses."""
    from jaxslam.sim.door_worlds import corridors_scenario, filter_settings

    scenario = corridors_scenario(jax.random.key(0))
    config, params = filter_settings(scenario, num_particles=64)
    k = params.p_open_open.shape[0]
    params = params._replace(p_open_open=jnp.ones(k), p_open_closed=jnp.zeros(k), likelihood_gain=jnp.float32(1.0))
    inputs = jax.tree.map(lambda a: a[:30], mcl.log_inputs(scenario.log))
    start = mcl.init_global(jax.random.key(1), scenario.start_regions, config.mcl, scenario.heading_range)
    state = doors.init(start, scenario.door_map)
    value, grads = jax.value_and_grad(lambda p: doors.filter(jax.random.key(2), state, inputs, scenario.door_map,
                                                             scenario.log.sensor, p, config).marginal_loglik)(params)
    assert np.isfinite(float(value))
    for name, leaf in zip(("motion", "beam", "gain", "threshold", "p_open_open", "p_open_closed"), grads):
        assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(leaf)), name
