"""Monte Carlo localization in a saved grid map (jaxslam.localization.grid_mcl) and ``jaxslam localize``."""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chi2

from jaxslam.cli import main
from jaxslam.config import default_params
from jaxslam.geometry import between_np, compose_np, wrap_angle_np
from jaxslam.io.maps import crop_to_known, read_map, write_map
from jaxslam.io.trajectory import read_trajectory
from jaxslam.laser import make_sensor, uniform_beams
from jaxslam.laserlog import to_local, to_world
from jaxslam.localization import grid_mcl, mcl
from jaxslam.motion import motion_params
from jaxslam.occupancy import FAR, map_from_scans
from jaxslam.sim import make_world
from jaxslam.sim.simulate import simulate_log, simulate_scans
from logs import write_flaser_log
from rooms import ROOM

WORLD = make_world(ROOM)  # a 6 x 4 m room with a box and a slanted panel: no two poses look alike
SHIFT = np.array([1280.0, -640.0])
"""The map and the log are moved here (a multiple of 64 m), so that the local frame is exercised."""
CONFIG = grid_mcl.GridMclConfig(max_particles=3000, min_particles=50)
"""One config for every filter test below: one compilation."""
NUM_SCANS = 60
KIDNAP_AT = 25


def room_loop(num: int) -> np.ndarray:
    """An ellipse round the room's middle, clear of the box and the panel by about 0.2 m: (num, 3)
    poses facing along it."""
    s = np.linspace(0.0, 2 * np.pi, num, endpoint=False)
    x, y = 3.0 + 1.8 * np.cos(s), 2.0 + 1.0 * np.sin(s)
    return np.stack([x, y, np.arctan2(np.gradient(y), np.gradient(x))], axis=-1)


def shifted(poses) -> np.ndarray:
    out = np.array(poses, np.float64)
    out[..., :2] += SHIFT
    return out


@pytest.fixture(scope="module")
def room_map(tmp_path_factory):
    """The room's map, drawn from 16 all-round scans at the true poses, written as map_server
    files and read back: ``(yaml path, probability, spec)`` in the shifted frame."""
    sensor = make_sensor(uniform_beams(360, 2 * np.pi * 359 / 360), range_min=0.05, range_max=10.0)
    poses = room_loop(16)
    ranges = simulate_scans(jax.random.key(1), WORLD, poses, sensor, 0.0, None, None)
    grid_map, spec = map_from_scans(poses, np.asarray(ranges), sensor, default_params().insertion, 0.05, 10.0, 4)
    logodds, cropped = crop_to_known(np.asarray(grid_map.logodds, np.float32), spec)
    cropped = dataclasses.replace(cropped, origin=tuple(np.asarray(cropped.origin) + SHIFT))
    stem = tmp_path_factory.mktemp("map") / "map"
    write_map(stem, logodds, cropped)
    probability, read_spec = read_map(f"{stem}.yaml")
    return f"{stem}.yaml", probability, read_spec


@pytest.fixture(scope="module")
def prepared(room_map):
    return grid_mcl.prepare_map(room_map[1], room_map[2])


@pytest.fixture(scope="module")
def room_log():
    """60 scans round the loop (91 beams over 180 degrees, 2 cm range noise, noisy odometry), shifted."""
    sensor = make_sensor(uniform_beams(91, np.pi), range_min=0.05, range_max=8.0)
    log = simulate_log(jax.random.key(0), WORLD, room_loop(NUM_SCANS), sensor,
                       motion_params(0.05, 0.02, 0.05, 0.05, 0.001, 0.001), 0.02)
    return dataclasses.replace(log, odometry=shifted(log.odometry), ground_truth=shifted(log.ground_truth))


def kidnapped(log, at: int, jump=(1.5, -0.8, np.pi / 2)):
    """``log`` with its odometry teleported by ``jump`` (robot frame) between scans at - 1 and at:
    the robot did not move, the filter is told it did."""
    odom = log.odometry
    base = compose_np(odom[at - 1], np.asarray(jump, np.float64))
    new = odom.copy()
    new[at:] = [compose_np(base, between_np(odom[at - 1], o)) for o in odom[at:]]
    return dataclasses.replace(log, odometry=new)


def run(key, state, log, grid, **params):
    return grid_mcl.filter(key, state, mcl.log_inputs(log), grid, log.sensor, grid_mcl.make_params(**params), CONFIG)


def position_errors(info, offset, truth) -> np.ndarray:
    poses = to_world(np.asarray(info.mcl.mean_pose, np.float64), offset)
    return np.hypot(*(poses[:, :2] - truth[:, :2]).T)


def tracked(log, offset, std=(0.1, 0.1, 0.05)):
    pose = jnp.asarray(to_local(log.ground_truth[0], offset), jnp.float32)
    return grid_mcl.init_tracked(jax.random.key(0), pose, jnp.asarray(std, jnp.float32), CONFIG)


# ------------------------------------------------------------------------------- the likelihood


def _field_reference(probability, radius):
    """The squared cell distance to the nearest occupied cell, by brute force (FAR beyond ``radius``)."""
    occupied = np.argwhere(probability > grid_mcl.OCCUPIED_PROBABILITY)
    rows, cols = np.indices(probability.shape)
    d2 = np.full(probability.shape, np.inf)
    for r, c in occupied:
        d2 = np.minimum(d2, (rows - r) ** 2 + (cols - c) ** 2)
    return np.where(d2 <= radius**2, d2, FAR)


def _log_likelihood_reference(field, spec, pose, ranges, sensor, sigma, z_hit, z_rand, gain, stride):
    """One pose's endpoint log-likelihood in NumPy, beam by beam."""
    total = 0.0
    angles = np.asarray(sensor.beam_angles, np.float64)
    lx, ly, lth = np.asarray(sensor.laser_pose, np.float64)
    x, y, th = pose
    ox, oy = x + math.cos(th) * lx - math.sin(th) * ly, y + math.sin(th) * lx + math.cos(th) * ly
    for b in range(0, len(ranges), stride):
        r = float(ranges[b])
        if not float(sensor.range_min) <= r < float(sensor.range_max):
            continue
        ex, ey = ox + r * math.cos(th + lth + angles[b]), oy + r * math.sin(th + lth + angles[b])
        col = math.floor((ex - spec.origin[0]) / spec.resolution)
        row = math.floor((ey - spec.origin[1]) / spec.resolution)
        inside = 0 <= row < spec.shape[0] and 0 <= col < spec.shape[1]
        d2 = field[row, col] if inside else FAR
        fit = 0.0 if d2 == FAR else math.exp(-0.5 * d2 * spec.resolution**2 / sigma**2)
        total += math.log(z_hit * fit + z_rand)
    return gain * total


def test_the_field_and_the_scan_log_likelihoods_match_a_numpy_reference(room_map, room_log):
    probability, spec = room_map[1][40:120, 50:150], room_map[2]  # a corner of the room: a small brute force
    spec = dataclasses.replace(spec, shape=probability.shape,
                               origin=(spec.origin[0] + 50 * spec.resolution, spec.origin[1] + 40 * spec.resolution))
    grid, offset = grid_mcl.prepare_map(probability, spec, field_radius=6)
    field = _field_reference(probability, 6)
    np.testing.assert_array_equal(np.asarray(grid.field.values), field)
    free = probability < grid_mcl.FREE_PROBABILITY
    assert grid.free_xy.shape[0] == free.sum()
    rng = np.random.default_rng(0)
    x0, x1, y0, y1 = spec.extent
    poses = np.stack([rng.uniform(x0, x1, 16), rng.uniform(y0, y1, 16), rng.uniform(-np.pi, np.pi, 16)], -1)
    poses[0] = room_log.ground_truth[0]
    config = grid_mcl.GridMclConfig(max_particles=16, min_particles=1, beam_stride=3)
    params = grid_mcl.make_params()
    ranges = room_log.ranges[7]
    got = grid_mcl.scan_log_likelihoods(grid, jnp.asarray(to_local(poses, offset), jnp.float32), jnp.asarray(ranges),
                                        room_log.sensor, params, config)
    lik = params.likelihood
    want = [_log_likelihood_reference(field, spec, p, ranges, room_log.sensor, float(lik.sigma), float(lik.z_hit),
                                      float(lik.z_rand), float(lik.gain), 3) for p in poses]
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-3)
    assert np.ptp(want) > 1.0  # the poses score differently: the comparison says something


def test_prepare_map_refuses_a_map_without_free_or_occupied_cells(room_map):
    spec = room_map[2]
    with pytest.raises(ValueError, match="occupied"):
        grid_mcl.prepare_map(np.zeros(spec.shape, np.float32), spec)
    with pytest.raises(ValueError, match="field_radius"):
        grid_mcl.prepare_map(room_map[1], spec, field_radius=16)


# ------------------------------------------------------------------------------- KLD sampling


def test_kld_bound_is_foxs_chi_square_quantile():
    k = np.array([2, 5, 10, 50, 200])
    got = np.asarray(grid_mcl.kld_bound(jnp.asarray(k), jnp.float32(0.05), jnp.float32(2.326)))
    want = chi2.ppf(0.99, k - 1) / (2 * 0.05)
    np.testing.assert_allclose(got, want, rtol=0.03)
    assert float(grid_mcl.kld_bound(jnp.asarray(1), jnp.float32(0.05), jnp.float32(2.326))) == 1.0


def test_occupied_bins_counts_the_distinct_bins_of_every_prefix(room_map):
    spec = room_map[2]
    rng = np.random.default_rng(1)
    x0, x1, y0, y1 = spec.extent
    poses = np.stack([rng.uniform(x0, x0 + 2, 300), rng.uniform(y0, y0 + 1.5, 300), rng.uniform(-3.1, 3.1, 300)], -1)
    config = grid_mcl.GridMclConfig(max_particles=300, min_particles=1)
    got = np.asarray(grid_mcl.occupied_bins(jnp.asarray(poses, jnp.float32), spec, config))
    bins = set()
    want = []
    for p in poses:
        bins.add((math.floor((p[0] - x0) / 0.5), math.floor((p[1] - y0) / 0.5),
                  math.floor((wrap_angle_np(p[2]) + math.pi) / config.bin_theta)))
        want.append(len(bins))
    np.testing.assert_array_equal(got, want)
    assert want[-1] > 50


def test_the_kld_count_is_large_for_a_wide_cloud_and_small_for_a_tight_one(prepared):
    grid, _ = prepared
    params = grid_mcl.make_params()
    key = jax.random.key(3)
    wide = grid_mcl.uniform_free_poses(key, grid, CONFIG.max_particles)
    spec = grid.field.spec
    centre = np.asarray(spec.origin) + 0.25 + 0.5 * np.array([7, 5])  # the middle of a bin, in the room
    tight = jnp.asarray(centre, jnp.float32) + 0.02 * jax.random.normal(key, (CONFIG.max_particles, 2))
    tight = jnp.concatenate([tight, jnp.full((CONFIG.max_particles, 1), -math.pi + 18.5 * CONFIG.bin_theta)], axis=1)
    assert int(grid_mcl.kld_count(wide, spec, params, CONFIG)) == CONFIG.max_particles
    assert int(grid_mcl.kld_count(tight, spec, params, CONFIG)) == CONFIG.min_particles


def test_the_filter_count_shrinks_as_the_spread_shrinks(room_log, prepared):
    grid, offset = prepared
    weak = grid_mcl.LikelihoodParams(*(jnp.float32(v) for v in (0.2, 0.9, 0.1, 0.03)))  # a slow convergence
    out = run(jax.random.key(1), tracked(room_log, offset, std=(0.7, 0.7, 0.7)), room_log, grid, likelihood=weak)
    count, spread = np.asarray(out.info.num_active), np.asarray(out.info.spread)
    assert count[0] == CONFIG.max_particles and spread[0] > 0.5
    assert count[-10:].max() < CONFIG.max_particles / 5 and spread[-10:].max() < 0.15
    assert np.corrcoef(count, spread)[0, 1] > 0.5
    # The inactive slots weigh nothing; the active ones are normalised.
    weights, n = np.asarray(out.state.log_weights), int(out.state.num_active)
    assert np.all(np.isneginf(weights[n:])) and abs(np.logaddexp.reduce(weights[:n])) < 1e-4


# ------------------------------------------------------------------------------- the filter


def test_tracking_from_the_true_first_pose_stays_on_the_true_path(room_log, prepared):
    grid, offset = prepared
    assert np.all(offset == SHIFT)  # the map's local frame
    out = run(jax.random.key(1), tracked(room_log, offset), room_log, grid)
    errors = position_errors(out.info, offset, room_log.ground_truth)
    assert errors.max() < 0.2, errors.round(2)
    heading = wrap_angle_np(np.asarray(out.info.mcl.mean_pose)[:, 2] - room_log.ground_truth[:, 2])
    assert np.abs(heading).max() < 0.1
    assert np.all(np.asarray(out.info.redrawn_share) == 0)  # never lost, never redrawn
    assert np.isfinite(float(out.marginal_loglik))


def test_global_localisation_converges_in_a_distinctive_world(room_log, prepared):
    grid, offset = prepared
    start = grid_mcl.init_global(jax.random.key(0), grid, CONFIG)
    assert np.std(np.asarray(start.poses)[:, 0]) > 1.0  # spread over the room
    out = run(jax.random.key(1), start, room_log, grid)
    errors = position_errors(out.info, offset, room_log.ground_truth)
    assert errors[10:].max() < 0.2, errors.round(2)
    assert np.asarray(out.info.spread)[-1] < 0.2


def test_recovery_relocalises_after_a_kidnap_where_plain_mcl_does_not(room_log, prepared):
    grid, offset = prepared
    log = kidnapped(room_log, KIDNAP_AT)
    start = tracked(log, offset)
    with_recovery = run(jax.random.key(1), start, log, grid)
    without = run(jax.random.key(1), start, log, grid, alpha_slow=0.0, alpha_fast=0.0)
    found = position_errors(with_recovery.info, offset, log.ground_truth)
    lost = position_errors(without.info, offset, log.ground_truth)
    assert found[:KIDNAP_AT].max() < 0.2 and found[KIDNAP_AT] > 1.0  # on track, then kidnapped
    assert found[-15:].max() < 0.2, found.round(2)
    assert lost[-15:].min() > 1.0, lost.round(2)
    assert np.asarray(with_recovery.info.redrawn_share)[KIDNAP_AT:].max() > 0.1
    assert np.all(np.asarray(without.info.redrawn_share) == 0)


# ------------------------------------------------------------------------------- the command


def test_localize_writes_its_three_outputs(tmp_path, room_map, room_log, capsys):
    log_path = tmp_path / "room.clf"
    write_flaser_log(log_path, room_log, stop=30)
    out = tmp_path / "out"
    x, y, theta = room_log.ground_truth[0]
    code = main(["localize", room_map[0], str(log_path), f"--initial-pose={x},{y},{theta}", "--particles", "1000",
                 "--seed", "3", "--max-scans", "20", "--out", str(out)])
    assert code == 0
    for name in ("trajectory.txt", "summary.json", "localize.png"):
        assert (out / name).is_file(), name
    timestamps, poses = read_trajectory(out / "trajectory.txt")
    assert poses.shape == (20, 3)
    np.testing.assert_allclose(timestamps, 1000.0 + room_log.timestamps[:20], atol=1e-6)
    assert np.hypot(*(poses[:, :2] - room_log.ground_truth[:20, :2]).T).max() < 0.25
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "tracking" and summary["scans"] == 20 and summary["seed"] == 3
    assert summary["config"]["max_particles"] == 1000
    assert summary["time_to_converge_s"] == 0.0 and summary["mean_spread_m"] < 0.2
    assert "localized 20 scans" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--initial-pose", "1,2"], "--initial-pose expects three finite numbers"),
    (["--initial-pose", "1,2,x"], "--initial-pose expects three finite numbers"),
    (["--initial-pose=-50,2,0"], "lies outside the map"),
    (["--particles", "0"], "--particles must be an integer >= 1"),
])
def test_bad_inputs_are_refused_before_any_work(tmp_path, room_map, capsys, args, message):
    log_path = tmp_path / "never_read.clf"  # the log is read last: a missing one shows nothing was done
    out = tmp_path / "out"
    assert main(["localize", room_map[0], str(log_path), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxslam localize: error: ") and message in err, err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_a_missing_map_file_is_a_clear_error(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["localize", str(tmp_path / "nowhere.yaml"), str(tmp_path / "log.clf"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "nowhere.yaml" in err and "no such map YAML file" in err and not out.exists()
