"""LaserLog validation and GMapping-style update selection (jaxslam.laserlog)."""

from __future__ import annotations

import re

import jax
import numpy as np
import pytest

from jaxslam.geometry import between_np, chain_np, compose_np, wrap_angle_np
from jaxslam.laserlog import (LaserLog, LogError, estimate_odometry_lead, poses_at, select_updates,
                              with_odometry_lead)
from jaxslam.laser import make_sensor
from jaxslam.sim import simulate_scans
from logs import cluttered_world

SENSOR = make_sensor([-0.5, 0.0, 0.5], range_min=0.1, range_max=10.0)


def make_log(num_scans=6, **overrides):
    t = np.arange(num_scans) * 0.1
    odom = np.stack([np.arange(num_scans) * 0.1, np.zeros(num_scans), np.zeros(num_scans)], axis=-1)
    ranges = np.full((num_scans, 3), 2.0)
    kwargs = dict(timestamps=t, odometry=odom, ranges=ranges, sensor=SENSOR, source="lab.log")
    kwargs.update(overrides)
    return LaserLog(**kwargs)


def error_of(**overrides):
    with pytest.raises(LogError) as info:
        make_log(**overrides)
    assert isinstance(info.value, ValueError)
    msg = str(info.value)
    assert msg.startswith("lab.log"), msg  # names the source
    return msg


def scan_named(msg, i):
    return re.search(rf"\bscan {i}\b", msg) is not None


def test_valid_log_and_dtypes():
    log = make_log()
    assert log.num_scans == 6 and log.num_beams == 3
    assert log.timestamps.dtype == np.float64 and log.odometry.dtype == np.float64
    assert log.ranges.dtype == np.float32
    assert log.duration == pytest.approx(0.5)
    sub = log.subset([1, 3])
    np.testing.assert_array_equal(sub.odometry, log.odometry[[1, 3]])
    # Equal timestamps are allowed (non-decreasing), and so are no-return ranges >= range_max.
    make_log(timestamps=np.array([0.0, 0.1, 0.1, 0.2, 0.3, 0.3]), ranges=np.full((6, 3), 50.0))


def test_empty_log():
    msg = error_of(num_scans=0)
    assert "empty" in msg


def test_timestamps_wrong_shape_is_not_called_empty():
    msg = error_of(timestamps=np.zeros((6, 1)))
    assert "timestamps" in msg and "(6, 1)" in msg and "empty" not in msg


def test_mismatched_ranges_shape():
    msg = error_of(ranges=np.ones((6, 4)))
    assert "ranges" in msg and "(6, 4)" in msg and "(6, 3)" in msg


def test_mismatched_ranges_scan_count():
    msg = error_of(ranges=np.ones((5, 3)))
    assert "ranges" in msg and "(5, 3)" in msg


def test_mismatched_odometry_shape():
    msg = error_of(odometry=np.zeros((5, 3)))
    assert "odometry" in msg and "(5, 3)" in msg
    msg = error_of(odometry=np.zeros((6, 2)))
    assert "odometry" in msg and "(6, 2)" in msg


def test_nan_range_names_scan_and_beam():
    r = np.full((6, 3), 2.0)
    r[3, 1] = np.nan
    msg = error_of(ranges=r)
    assert scan_named(msg, 3) and "beam 1" in msg and "nan" in msg.lower()


def test_infinite_range_is_rejected():
    r = np.full((6, 3), 2.0)
    r[4, 2] = np.inf
    msg = error_of(ranges=r)
    assert scan_named(msg, 4) and "beam 2" in msg and "inf" in msg.lower()


def test_negative_range_names_scan():
    r = np.full((6, 3), 2.0)
    r[2, 0] = -0.5
    msg = error_of(ranges=r)
    assert scan_named(msg, 2) and "beam 0" in msg and "-0.5" in msg and "non-negative" in msg


def test_timestamps_backwards_names_scan():
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.25, 0.5])
    msg = error_of(timestamps=t)
    assert scan_named(msg, 4) and "backwards" in msg


def test_nan_timestamp_names_scan():
    t = np.array([0.0, 0.1, np.nan, 0.3, 0.4, 0.5])
    msg = error_of(timestamps=t)
    assert scan_named(msg, 2) and "timestamp" in msg


def test_nan_odometry_names_scan():
    odom = np.zeros((6, 3))
    odom[1, 2] = np.nan
    msg = error_of(odometry=odom)
    assert scan_named(msg, 1) and "odometry" in msg


def test_ground_truth_validated():
    msg = error_of(ground_truth=np.zeros((4, 3)))
    assert "ground truth" in msg and "(4, 3)" in msg
    gt = np.zeros((6, 3))
    gt[5, 0] = np.inf
    msg = error_of(ground_truth=gt)
    assert scan_named(msg, 5) and "ground truth" in msg


def np_between(a, b):
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    dth = (b[..., 2] - a[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dth], axis=-1)


def forward(pose, dist, turn=0.0):
    """Drive ``dist`` metres along the heading, then turn ``turn`` radians."""
    x, y, th = pose
    return np.array([x + dist * np.cos(th), y + dist * np.sin(th), th + turn])


def hand_odometry():
    p = [np.zeros(3)]
    p.append(forward(p[-1], 0.3))        # 1: lin 0.3
    p.append(forward(p[-1], 0.3))        # 2: lin 0.6 >= 0.5           -> selected
    p.append(forward(p[-1], 0.0, 0.2))   # 3: ang 0.2
    p.append(forward(p[-1], 0.0, 0.2))   # 4: ang 0.4 >= 0.35          -> selected
    p.append(forward(p[-1], 0.2))        # 5: lin 0.2
    p.append(forward(p[-1], 0.2, -0.1))  # 6: lin 0.4, ang 0.1
    p.append(forward(p[-1], 0.0, 0.3))   # 7: ang 0.4 (|-0.1| + 0.3)   -> selected
    p.append(forward(p[-1], 0.3))        # 8: lin 0.3
    p.append(forward(p[-1], -0.3))       # 9: back where 7 was: path 0.6 -> selected
    p.append(forward(p[-1], 0.1))        # 10: lin 0.1, never selected
    return np.array(p)


def test_select_updates_hand_computed():
    odom = hand_odometry()
    log = make_log(num_scans=len(odom), odometry=odom)
    sel = select_updates(log, linear_update=0.5, angular_update=0.35)
    np.testing.assert_array_equal(sel.indices, [0, 2, 4, 7, 9])
    assert sel.motions.dtype == np.float32 and sel.motions.shape == (5, 3)
    np.testing.assert_array_equal(sel.motions[0], 0.0)
    want = np_between(odom[sel.indices[:-1]], odom[sel.indices[1:]])
    np.testing.assert_allclose(sel.motions[1:], want, rtol=0, atol=1e-6)
    # Hand values: 0.6 m straight; a 0.4 rad turn on the spot; then 0.4 m at heading 0.4 - 0.1 ...
    np.testing.assert_allclose(sel.motions[1], [0.6, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(sel.motions[2], [0.0, 0.0, 0.4], atol=1e-6)
    np.testing.assert_allclose(sel.motions[3, 2], 0.2, atol=1e-6)
    # ... and a back-and-forth with no net motion.
    np.testing.assert_allclose(sel.motions[4], [0.0, 0.0, 0.0], atol=1e-6)


def test_select_updates_motions_compose_back_to_odometry():
    """Composing the selected motions from the first odometry pose reproduces the odometry
    at the selected scans (the motions are between() of consecutive selected poses)."""
    rng = np.random.default_rng(0)
    steps = np.stack([rng.uniform(0, 0.2, 60), np.zeros(60), rng.normal(0, 0.15, 60)], axis=-1)
    odom = [np.array([5.0, -3.0, 2.5])]
    for s in steps:
        odom.append(forward(odom[-1], s[0], s[2]))
    odom = np.array(odom)
    odom[:, 2] = (odom[:, 2] + np.pi) % (2 * np.pi) - np.pi
    sel = select_updates(make_log(num_scans=len(odom), odometry=odom), 0.5, 0.4)
    assert sel.indices[0] == 0 and np.all(np.diff(sel.indices) > 0) and 3 < len(sel.indices) < 40
    pose = odom[0]
    for k in range(1, len(sel.indices)):
        m = sel.motions[k].astype(np.float64)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        pose = np.array([pose[0] + c * m[0] - s * m[1], pose[1] + s * m[0] + c * m[1], pose[2] + m[2]])
        want = odom[sel.indices[k]]
        np.testing.assert_allclose(pose[:2], want[:2], atol=1e-4)
        assert abs((pose[2] - want[2] + np.pi) % (2 * np.pi) - np.pi) < 1e-4
    # The accumulated path (not the net displacement) since the last selected scan triggers selection.
    lin = np.hypot(*np_between(odom[:-1], odom[1:])[:, :2].T)
    ang = np.abs(np_between(odom[:-1], odom[1:])[:, 2])
    for a, b in zip(sel.indices[:-1], sel.indices[1:]):
        assert lin[a:b].sum() >= 0.5 or ang[a:b].sum() >= 0.4
        assert lin[a:b - 1].sum() < 0.5 and ang[a:b - 1].sum() < 0.4


def test_select_updates_angles_wrap_across_pi():
    th = 3.0 + 0.05 * np.arange(12)
    odom = np.stack([np.zeros(12), np.zeros(12), (th + np.pi) % (2 * np.pi) - np.pi], axis=-1)
    sel = select_updates(make_log(num_scans=12, odometry=odom), 1.0, 0.12)
    # 0.05 rad per scan, also across +-pi: selected every third scan.
    np.testing.assert_array_equal(sel.indices, [0, 3, 6, 9])
    np.testing.assert_allclose(sel.motions[1:, 2], 0.15, atol=1e-5)


@pytest.mark.parametrize("lin,ang", [(0.0, 0.0), (-1.0, -1.0)])
def test_nonpositive_thresholds_select_every_scan(lin, ang):
    odom = hand_odometry()
    odom[5] = odom[4]  # a scan without motion is still processed
    log = make_log(num_scans=len(odom), odometry=odom)
    sel = select_updates(log, lin, ang)
    np.testing.assert_array_equal(sel.indices, np.arange(len(odom)))
    np.testing.assert_allclose(sel.motions[1:], np_between(odom[:-1], odom[1:]), atol=1e-6)


def test_first_scan_always_selected_even_without_motion():
    odom = np.zeros((5, 3))
    sel = select_updates(make_log(num_scans=5, odometry=odom), 0.5, 0.5)
    np.testing.assert_array_equal(sel.indices, [0])
    assert sel.motions.shape == (1, 3) and not sel.motions.any()


def test_select_updates_far_from_the_origin():
    """Odometry in large world coordinates (10 km away) gives the same selection and motions:
    the relative motion must be computed before any float32 rounding."""
    odom = hand_odometry()
    far = odom.copy()
    far[:, 0] += 10_000.0
    far[:, 1] -= 7_000.0
    near_sel = select_updates(make_log(num_scans=len(odom), odometry=odom), 0.5, 0.35)
    far_sel = select_updates(make_log(num_scans=len(odom), odometry=far), 0.5, 0.35)
    np.testing.assert_array_equal(far_sel.indices, near_sel.indices)
    np.testing.assert_allclose(far_sel.motions, near_sel.motions, atol=1e-5)


def _log_with_odometry_ahead(lead: float, seed: int = 0, num_scans: int = 400):
    """A robot weaving through a cluttered world, a scan every 0.1 s taken at the true pose, and
    odometry (with a little drift) read where the robot was ``lead`` seconds later."""
    rng = np.random.default_rng(seed)
    times = 0.1 * np.arange(num_scans)
    turn = 0.12 * np.sin(np.arange(num_scans) / 6.0)  # turns of up to 1.2 rad/s, both ways
    steps = np.stack([np.full(num_scans, 0.08), np.zeros(num_scans), turn], axis=1)
    truth = chain_np(np.zeros(3), steps[1:])
    world = cluttered_world(rng, truth[:, :2].min(0) - 5.0, truth[:, :2].max(0) + 5.0, 300)
    sensor = make_sensor(np.linspace(-np.pi / 2, np.pi / 2, 91), range_max=8.0)
    ranges = simulate_scans(jax.random.PRNGKey(seed), world, truth, sensor, range_noise_std=0.01)
    ahead = poses_at(np.clip(times + lead, times[0], times[-1]), times, truth).poses
    drift = chain_np(np.zeros(3), rng.normal(0.0, [0.002, 0.001, 0.001], size=(num_scans - 1, 3)))
    odometry = np.asarray([compose_np(a, d) for a, d in zip(ahead, drift)])
    return LaserLog(times, odometry, ranges, sensor, ground_truth=truth), truth


@pytest.mark.parametrize("lead", [0.0, 0.15])
def test_the_odometry_lead_is_measured_from_the_scans_and_taken_back(lead):
    log, truth = _log_with_odometry_ahead(lead)
    measured = estimate_odometry_lead(log)
    assert measured.num_pairs >= 100 and measured.leads.size == measured.misfit.size == 17
    # The quarter-scan grid and its parabola: within a fifth of a scan interval (0.02 s).
    assert measured.lead == pytest.approx(lead, abs=0.02)
    read_back = with_odometry_lead(log, measured.lead)
    if lead == 0.0:
        assert measured.lead == 0.0 and read_back is log  # bit for bit: nothing to take back
    else:
        def heading_error(odometry):
            moved = between_np(odometry[:-2], odometry[2:])[:, 2] - between_np(truth[:-2], truth[2:])[:, 2]
            return np.abs(wrap_angle_np(moved)).mean()
        assert heading_error(read_back.odometry) < 0.3 * heading_error(log.odometry)
        assert "leads the laser" in read_back.notes[-1]


def test_a_log_without_turns_measures_no_lead():
    log, _ = _log_with_odometry_ahead(0.15, num_scans=60)
    straight = LaserLog(log.timestamps, np.column_stack([0.08 * np.arange(60), np.zeros(60), np.zeros(60)]),
                        log.ranges, log.sensor)
    measured = estimate_odometry_lead(straight)
    assert measured.lead == 0.0 and measured.num_pairs == 0 and np.isnan(measured.misfit).all()
    with pytest.raises(ValueError, match="gap and max_pairs must be >= 1"):
        estimate_odometry_lead(straight, gap=0)
