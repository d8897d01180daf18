"""The filter runs in a local frame: a log far from the origin maps as well as the same log near it.

``slam.run`` subtracts the first odometry pose's translation (rounded to a multiple of 64 m) on
the host in float64 before anything reaches float32, and adds it back to the paths and the
maps' placement. So the simulated office shifted by 5,000 km (a multiple of 64 m) runs bit for
bit as the unshifted one, and only the offset separates the outputs.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from jaxslam import rbpf, slam
from jaxslam.config import RunSettings, SlamConfig, default_params
from jaxslam.io.maps import read_map
from jaxslam.outputs import write_slam_outputs
from jaxslam.sim import office_scenario

SHIFT = 5_000_000.0  # 5,000 km: float32 resolves 0.5 m there
SETTINGS = RunSettings(linear_update=0.3, angular_update=0.25)
CONFIG = SlamConfig(num_particles=4, proposal="smp", max_insert_range=10.0, beam_stride=1, map_extent=128.0)


def _shifted(log, shift):
    """``log`` with ``shift`` added to the x and y of the odometry and the ground truth."""
    odometry, truth = log.odometry.copy(), log.ground_truth.copy()
    odometry[:, :2] += shift
    truth[:, :2] += shift
    return dataclasses.replace(log, odometry=odometry, ground_truth=truth)


@pytest.fixture(scope="module")
def office_log():
    """The simulated office's first 60 scans, odometry on a 1/64 m grid (so that adding 5,000 km
    and writing it with 6 decimals are exact, and both runs see the same numbers)."""
    log = office_scenario(jax.random.key(3), num_scans=150, num_beams=181).log.subset(np.arange(60))
    odometry = log.odometry.copy()
    odometry[:, :2] = np.round(odometry[:, :2] * 64.0) / 64.0
    return dataclasses.replace(log, odometry=odometry)


@pytest.fixture(scope="module")
def runs(office_log):
    far = _shifted(office_log, SHIFT)
    near_result = slam.run(jax.random.key(0), office_log, CONFIG, default_params(), SETTINGS, progress=False)
    far_result = slam.run(jax.random.key(0), far, CONFIG, default_params(), SETTINGS, progress=False)
    return office_log, far, near_result, far_result


def test_a_log_near_the_origin_is_not_shifted(runs):
    _, _, near, _ = runs
    np.testing.assert_array_equal(near.frame_offset, [0.0, 0.0])  # the office starts at (1.2, 7.5)
    assert near.best_path.dtype == np.float64 and near.frame_offset.dtype == np.float64


def test_a_log_5000_km_away_maps_as_the_same_log_near_the_origin(runs):
    _, _, near, far = runs
    np.testing.assert_array_equal(far.frame_offset, [SHIFT, SHIFT])
    # The filter saw the same numbers: its state and diagnostics (local frame) are bit for bit equal.
    np.testing.assert_array_equal(np.asarray(far.state.poses), np.asarray(near.state.poses))
    np.testing.assert_array_equal(np.asarray(far.state.log_weights), np.asarray(near.state.log_weights))
    np.testing.assert_array_equal(far.info.proposed_poses, near.info.proposed_poses)
    for far_part, near_part in zip(far.state.maps, near.state.maps):
        np.testing.assert_array_equal(np.asarray(far_part), np.asarray(near_part))
    # Paths in the world frame: the shift added back in float64 (its ulp at 5,000 km is 1e-9 m).
    back = far.best_path.copy()
    back[:, :2] -= SHIFT
    np.testing.assert_allclose(back, near.best_path, rtol=0, atol=1e-6)
    traj = far.trajectory.copy()
    traj[:, :2] -= SHIFT
    np.testing.assert_allclose(traj, near.trajectory, rtol=0, atol=1e-6)
    np.testing.assert_allclose(far.to_world(np.asarray(far.state.poses))[:, :2] - SHIFT,
                               np.asarray(near.state.poses)[:, :2], rtol=0, atol=1e-6)
    # One virtual grid, centred on the local origin; placed in the world by the offset.
    assert far.config.grid == near.config.grid
    np.testing.assert_allclose(np.subtract(far.world_grid.origin, near.world_grid.origin), [SHIFT, SHIFT],
                               rtol=0, atol=1e-8)
    far_map, _, far_box = far.dense_map()
    near_map, _, near_box = near.dense_map()
    np.testing.assert_array_equal(far_map, near_map)
    np.testing.assert_allclose(np.subtract(far_box.origin, near_box.origin), [SHIFT, SHIFT], rtol=0, atol=1e-8)


def test_the_outputs_differ_by_the_offset_only(runs, tmp_path):
    near_log, far_log, near, far = runs
    params = default_params()
    write_slam_outputs(tmp_path / "near", near_log, near, params, seed=0, source="near")
    write_slam_outputs(tmp_path / "far", far_log, far, params, seed=0, source="far")
    _, near_spec = read_map(tmp_path / "near" / "map.yaml")
    _, far_spec = read_map(tmp_path / "far" / "map.yaml")
    assert far_spec.shape == near_spec.shape
    np.testing.assert_allclose(np.subtract(far_spec.origin, near_spec.origin), [SHIFT, SHIFT], rtol=0, atol=1e-8)
    assert (tmp_path / "near" / "map.pgm").read_bytes() == (tmp_path / "far" / "map.pgm").read_bytes()
    near_traj = np.loadtxt(tmp_path / "near" / "trajectory.txt")
    far_traj = np.loadtxt(tmp_path / "far" / "trajectory.txt")
    far_traj[:, 1:3] -= SHIFT
    np.testing.assert_allclose(far_traj, near_traj, rtol=0, atol=2e-6)  # 9 decimals written
    summary = json.loads((tmp_path / "far" / "summary.json").read_text())
    assert summary["config"]["map_extent"] == CONFIG.map_extent


def test_every_output_of_a_far_log_is_the_near_ones_shifted(office_log, tmp_path):
    """End to end: the filter, the loop closure over 35 m of path, the map drawn again and the
    refinement, with scans skipped by the update rule so that the per-scan trajectories
    interpolate between processed scans. At 5,000 km (a multiple of 64 m) the filter sees the
    same bits, so every output is the near one's, shifted: the closure and the per-scan
    trajectories work in the local frame too (in the log's frame float32 resolves 0.5 m there)."""
    from jaxslam.cli import main
    from logs import write_flaser_log

    far_log = _shifted(office_log, SHIFT)
    for name, log in (("near", office_log), ("far", far_log)):
        write_flaser_log(tmp_path / f"{name}.clf", log)
        assert main(["map", str(tmp_path / f"{name}.clf"), "--particles", "3", "--proposal", "smp", "--no-progress",
                     "--set", "linear_update=1.0", "--set", "max_insert_range=8", "--out", str(tmp_path / name)]) == 0
    near_graph, far_graph = np.load(tmp_path / "near" / "graph.npz"), np.load(tmp_path / "far" / "graph.npz")
    assert near_graph["node_scans"].size < office_log.num_scans  # scans were skipped: interpolated
    for key in ("filter_poses", "poses", "chain_poses"):
        moved = far_graph[key].copy()
        moved[:, :2] -= SHIFT
        np.testing.assert_allclose(moved, near_graph[key], rtol=0, atol=1e-6, err_msg=key)
    for file in ("trajectory.txt", "trajectory_filter.txt", "trajectory_refined.txt"):
        near_traj, far_traj = np.loadtxt(tmp_path / "near" / file), np.loadtxt(tmp_path / "far" / file)
        far_traj[:, 1:3] -= SHIFT
        np.testing.assert_allclose(far_traj, near_traj, rtol=0, atol=2e-6, err_msg=file)  # 9 decimals written
    _, near_spec = read_map(tmp_path / "near" / "map.yaml")
    _, far_spec = read_map(tmp_path / "far" / "map.yaml")
    assert far_spec.shape == near_spec.shape
    np.testing.assert_allclose(np.subtract(far_spec.origin, near_spec.origin), [SHIFT, SHIFT], rtol=0, atol=1e-6)
    assert (tmp_path / "near" / "map.pgm").read_bytes() == (tmp_path / "far" / "map.pgm").read_bytes()


def test_the_closure_of_a_path_in_another_local_frame_is_the_same(runs):
    """The closure alone, of one filter path given 500,012.25 m away (not a multiple of 64 m, so
    its local frame lies 19.75 m from the near one's; on the 1/64 m grid, so the shifted numbers are
    exact): the same graph, shifted, and every scan's pose (float32 resolves 3 cm at 500 km)."""
    from jaxslam.graph import ClosureConfig, close_trajectory_loops
    from jaxslam.laserlog import local_frame_offset

    near_log, _, near, _ = runs
    shift = 500_012.25
    far_log = _shifted(near_log, shift)
    params = default_params()
    closures = []
    for log, offset in ((near_log, 0.0), (far_log, shift)):
        poses = near.best_path.copy()
        poses[:, :2] += offset
        closures.append(close_trajectory_loops(log, near.selection.indices, poses, near.selection.motions, params,
                                               near.config, local_frame_offset(log), ClosureConfig()))
    near_closure, far_closure = closures
    assert np.any(local_frame_offset(far_log) != shift)  # another local frame
    for key in ("poses", "trajectory", "chain_poses"):
        moved = getattr(far_closure, key).copy()
        moved[:, :2] -= shift
        np.testing.assert_allclose(moved, getattr(near_closure, key), rtol=0, atol=1e-6, err_msg=key)


def test_the_readers_interpolation_and_the_update_rule_read_a_far_log_as_the_near_one(office_log):
    """``poses_at`` (the bag readers' odometry at the scans' times) and ``select_updates`` work in
    float32 in a local frame: 5,000 km away (float32 resolves 0.5 m there) they give the near
    log's poses, shifted, and its motions bit for bit."""
    from jaxslam.laserlog import poses_at, select_updates

    far = _shifted(office_log, SHIFT)
    halfway = 0.5 * (office_log.timestamps[:-1] + office_log.timestamps[1:])
    near_read = poses_at(halfway, office_log.timestamps, office_log.odometry).poses
    far_read = poses_at(halfway, far.timestamps, far.odometry).poses
    far_read[:, :2] -= SHIFT
    np.testing.assert_allclose(far_read, near_read, rtol=0, atol=1e-8)
    assert np.max(np.abs(near_read[:, :2] - office_log.odometry[:-1, :2])) > 0.1  # between messages: interpolated
    near_selection, far_selection = select_updates(office_log, 1.0, 0.25), select_updates(far, 1.0, 0.25)
    np.testing.assert_array_equal(far_selection.indices, near_selection.indices)
    np.testing.assert_array_equal(far_selection.motions, near_selection.motions)
