"""The chain's heading from the filter's and the odometry's by their drift rates
(jaxslam.graph.drift)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.geometry import between_np, chain_np
from jaxslam.graph.drift import heading_drift_rates, odometry_slips, reweighted_chain


def test_heading_drift_rates_recover_two_random_walks():
    """Headings that random-walk at known rates, loops over disjoint spans measuring the truth:
    each rate within 4 standard errors (relative standard error sqrt(2 / loops))."""
    rng = np.random.default_rng(1)
    nodes, span = 20_000, 50
    truth = np.cumsum(rng.normal(0.0, 0.02, nodes))
    filter_rate, odometry_rate = 0.004 ** 2, 0.001 ** 2
    filter_h = truth + np.cumsum(rng.normal(0.0, np.sqrt(filter_rate), nodes))
    odometry_h = truth + 5.0 + np.cumsum(rng.normal(0.0, np.sqrt(odometry_rate), nodes))  # another frame
    first = np.arange(0, nodes - span, span)
    second = first + span
    measured = truth[second] - truth[first]
    got_f, got_o = heading_drift_rates(first, second, measured, filter_h, odometry_h)
    tolerance = 4 * np.sqrt(2 / first.size)
    assert abs(got_f / filter_rate - 1) < tolerance
    assert abs(got_o / odometry_rate - 1) < tolerance


def test_heading_drift_rates_refuse_backward_loops_and_report_none_without_spans():
    with pytest.raises(ValueError, match="second node"):
        heading_drift_rates(np.array([5]), np.array([3]), np.zeros(1), np.zeros(10), np.zeros(10))
    with pytest.raises(ValueError, match="one shape"):
        heading_drift_rates(np.array([1]), np.array([3, 4]), np.zeros(1), np.zeros(10), np.zeros(10))
    assert all(np.isnan(heading_drift_rates(np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(3),
                                            np.zeros(3))))


def test_odometry_slips_flag_the_one_step_the_two_disagree_on():
    rng = np.random.default_rng(2)
    filter_steps = np.zeros((500, 3))
    filter_steps[:, 2] = rng.normal(0.0, 0.01, 500)
    odometry_steps = filter_steps.copy()
    odometry_steps[:, 2] += rng.normal(0.0, 0.005, 500)
    odometry_steps[123, 2] += 0.3  # a slip
    slips = odometry_slips(filter_steps, odometry_steps)
    assert slips[123] and slips.sum() <= 3  # 4 robust stds: a normal tail flags about 0.01 %


def test_reweighted_chain_moves_the_heading_by_the_share_and_keeps_the_slips_and_translation():
    rng = np.random.default_rng(3)
    truth_steps = np.column_stack([np.full(40, 0.5), np.zeros(40), rng.normal(0.0, 0.1, 40)])
    filter_poses = chain_np(np.array([1.0, 2.0, 0.3]), truth_steps + [0.0, 0.0, 0.02])  # a heading bias
    motions = np.vstack([np.zeros(3), truth_steps])  # the odometry: the truth
    slips = np.zeros(40, bool)
    slips[7] = True
    np.testing.assert_allclose(reweighted_chain(filter_poses, motions, 0.0, slips), filter_poses, atol=1e-10)
    for share in (0.25, 1.0):
        poses = reweighted_chain(filter_poses, motions, share, slips)
        steps = between_np(poses[:-1], poses[1:])
        expected = truth_steps[:, 2] + 0.02 * (1 - share)
        expected[7] = truth_steps[7, 2] + 0.02
        np.testing.assert_allclose(steps[:, 2], expected, atol=1e-10)
        np.testing.assert_allclose(steps[:, :2], truth_steps[:, :2], atol=1e-10)


def test_the_passes_loops_merge_each_pair_once_kept_where_any_pass_kept_it():
    from jaxslam.graph.acceptance import Loops, first_kept as _first_kept, merged as _merged

    def loops(query, submap, refused):
        c = len(query)
        return Loops(np.array(query), np.array(submap), np.arange(c * 3.0).reshape(c, 3), np.zeros((c, 3, 3)),
                     np.ones(c), np.zeros(c), np.zeros(c, bool), np.array(refused, object), np.arange(c, dtype=float))

    first_pass = loops([30, 33, 36], [1, 1, 2], ["", "score", ""])
    second_pass = loops([30, 33, 36, 90], [1, 1, 2, 3], ["chi2", "", "", "window"])
    everything = first_pass.extend(second_pass)
    assert _first_kept(everything).tolist() == [0, 2, 4]  # (30, 1) from the first pass, (36, 2) once
    merged = _merged(everything)
    assert list(zip(merged.query.tolist(), merged.submap.tolist(), merged.refused.tolist())) == [
        (30, 1, ""), (36, 2, ""), (33, 1, ""), (90, 3, "window")]
    assert np.all(np.isnan(merged.chi2))
    merged.refused[0] = "chi2"  # the final solve writes into its own copy
    assert everything.refused[0] == ""
