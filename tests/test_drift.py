"""The chain's heading from the filter's and the odometry's by their drift rates
(jaxslam.graph.drift)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.geometry import between_np, chain_np
from jaxslam.graph.acceptance import Loops
from jaxslam.graph.drift import fused_chain, heading_drift_rates, parting, smoothed_headings, step_noise
from jaxslam.graph.jumps import heading_jumps, loops_across, loops_side_with, spanned_nodes, undo_jump, unspanned_jumps
from jaxslam.graph.submaps import submap_ranges


def test_heading_drift_rates_recover_two_random_walks_whatever_the_submaps_first_node_jitters():
    """Headings that random-walk at known rates, the filter's with white jitter and a 3-degree
    jump at every submap's first node (FR-clinic's), loops over disjoint spans measuring the
    truth in the submap's frame: each rate within 4 standard errors (relative standard error
    sqrt(2 / loops)) plus the 5 % by which the filter's span shrinks to the ends' means."""
    rng = np.random.default_rng(1)
    nodes, span, submap = 100_000, 200, 20
    truth = np.cumsum(rng.normal(0.0, 0.02, nodes))
    filter_rate, odometry_rate = 0.004 ** 2, 0.001 ** 2
    first = np.arange(0, nodes - span - submap, span)
    last, second = first + submap - 1, first + span
    jitter = rng.normal(0.0, 0.005, nodes)
    jitter[first] += np.radians(3.0) * rng.choice([-1.0, 1.0], first.size)
    filter_h = truth + np.cumsum(rng.normal(0.0, np.sqrt(filter_rate), nodes)) + jitter
    odometry_h = truth + 5.0 + np.cumsum(rng.normal(0.0, np.sqrt(odometry_rate), nodes))  # another frame
    # the submap's frame is its first node's filter pose; its scans lie where the filter put all
    # of them, turned from the truth by the filter's mean error over them
    content = np.array([np.mean(filter_h[a:b + 1] - truth[a:b + 1]) for a, b in zip(first, last)])
    measured = truth[second] - filter_h[first] + content
    got_f, got_o = heading_drift_rates(first, last, second, measured, filter_h, odometry_h)
    tolerance = 4 * np.sqrt(2 / first.size)
    assert abs(got_f / filter_rate - 1) < tolerance + 0.05
    assert abs(got_o / odometry_rate - 1) < tolerance
    # a one-node "submap" takes the loop's ends at the first node and the query: the jumps then
    # enter every loop of both chains, and the odometry's rate comes out over ten times too fast
    _, from_first_node = heading_drift_rates(first, first, second, measured, filter_h, odometry_h)
    assert from_first_node > 10 * odometry_rate


def test_heading_drift_rates_refuse_backward_loops_and_report_none_without_spans():
    with pytest.raises(ValueError, match="before its query"):
        heading_drift_rates(np.array([2]), np.array([4]), np.array([3]), np.zeros(1), np.zeros(10), np.zeros(10))
    with pytest.raises(ValueError, match="one shape"):
        heading_drift_rates(np.array([1]), np.array([2]), np.array([3, 4]), np.zeros(1), np.zeros(10), np.zeros(10))
    empty = np.zeros(0, int)
    assert all(np.isnan(heading_drift_rates(empty, empty, empty, np.zeros(0), np.zeros(3), np.zeros(3))))


@pytest.mark.parametrize("slip_share", [0.0, 0.01])
def test_step_noise_separates_the_random_walk_from_the_filters_jitter(slip_share):
    """Disagreements made of two random walks' increments and the filter's white jitter's
    differences, 0 or 1 % of them slips of 0.3 rad. Over 60 seeds the estimates' relative
    errors had std 0.071 (q) and 0.055 (r), and the slips biased q by +0.10: within 4 stds of
    that."""
    rng = np.random.default_rng(4)
    steps, walk, jitter = 20_000, 0.005 ** 2, 0.005 ** 2
    odometry_steps = np.zeros((steps, 3))
    odometry_steps[:, 2] = rng.normal(0.0, 0.1, steps)
    filter_heading = np.cumsum(np.concatenate([[0.0], odometry_steps[:, 2] + rng.normal(0, np.sqrt(walk), steps)]))
    filter_heading += rng.normal(0.0, np.sqrt(jitter), steps + 1)
    slips = rng.random(steps) < slip_share
    odometry_steps[slips, 2] += rng.choice([-0.3, 0.3], slips.sum())
    filter_steps = np.zeros((steps, 3))
    filter_steps[:, 2] = np.diff(filter_heading)
    got_walk, got_jitter = step_noise(filter_steps, odometry_steps)
    assert abs(got_walk / walk - 1 - 10 * slip_share) < 4 * 0.077
    assert abs(got_jitter / jitter - 1) < 4 * 0.057


def _dense_smoothed(headings, turns, filter_rate, odometry_rate, jitter):
    """The smoother's first (unweighted) least squares, dense: unknowns (x_0.., b_0..)."""
    size = headings.size
    rows, rhs, sigma = [], [], []
    for t in range(size - 1):
        row = np.zeros(2 * size)
        row[t + 1], row[t] = 1.0, -1.0
        rows.append(row), rhs.append(turns[t]), sigma.append(np.sqrt(odometry_rate))
        row = np.zeros(2 * size)
        row[size + t + 1], row[size + t] = 1.0, -1.0
        rows.append(row), rhs.append(0.0), sigma.append(np.sqrt(filter_rate))
    for t in range(size):
        row = np.zeros(2 * size)
        row[t] = row[size + t] = 1.0
        rows.append(row), rhs.append(headings[t]), sigma.append(np.sqrt(jitter))
    row = np.zeros(2 * size)
    row[size] = 1.0
    rows.append(row), rhs.append(0.0), sigma.append(np.sqrt(jitter))
    a = np.array(rows) / np.array(sigma)[:, None]
    return np.linalg.lstsq(a, np.array(rhs) / np.array(sigma), rcond=None)[0][:size]


def test_smoothed_headings_banded_solve_matches_the_dense_least_squares():
    rng = np.random.default_rng(5)
    headings = np.cumsum(rng.normal(0.0, 0.1, 30))
    turns = np.diff(headings) + rng.normal(0.0, 0.01, 29)
    got = smoothed_headings(headings, turns, 1e-4, 4e-5, 2e-4, iterations=1)
    np.testing.assert_allclose(got, _dense_smoothed(headings, turns, 1e-4, 4e-5, 2e-4), atol=1e-9)


def test_smoothed_headings_give_a_jump_the_map_takes_back_to_the_filter_and_a_step_that_stays_to_the_odometry():
    """The disagreement's size alone cannot say who is at fault: the same 3 degrees at two steps;
    the filter's jump returns two steps later (its jitter), the odometry's slip stays."""
    rng = np.random.default_rng(6)
    truth = np.cumsum(rng.normal(0.0, 0.05, 400))
    turns = np.diff(truth) + rng.normal(0.0, 0.0005, 399)
    filter_h = truth + rng.normal(0.0, 0.002, 400)
    jump = np.radians(3.0)
    filter_h[100:102] += jump  # the filter jumps, its map takes it back
    turns[299] += jump  # the wheels slip: the odometry turns 3 degrees the robot did not
    got = smoothed_headings(filter_h, turns, 1e-8, 0.0005 ** 2, 0.002 ** 2)  # the model the data were drawn from
    error = np.degrees(np.abs(got - got[0] - (truth - truth[0])))
    assert error[95:110].max() < 0.5  # not the filter's 3 degrees
    assert error[300:].max() < 0.5  # not the odometry's 3 degrees


def test_fused_chain_keeps_each_submap_rigid_and_turns_it_by_its_mean_correction():
    rng = np.random.default_rng(3)
    steps = np.column_stack([np.full(49, 0.5), np.zeros(49), rng.normal(0.0, 0.1, 49)])
    filter_poses = chain_np(np.array([1.0, 2.0, 0.3]), steps)
    first, last = np.array([0, 20, 40]), np.array([19, 39, 49])
    headings = np.unwrap(filter_poses[:, 2]) + np.linspace(0.0, 0.2, 50) + rng.normal(0.0, 0.01, 50)
    poses = fused_chain(filter_poses, headings, first, last)
    for a, b in zip(first, last):
        np.testing.assert_allclose(between_np(poses[a], poses[a:b + 1]), between_np(filter_poses[a], filter_poses[a:b + 1]),
                                   atol=1e-9)  # rigid
        turned = np.mean(np.unwrap(poses[a:b + 1, 2]) - np.unwrap(filter_poses[a:b + 1, 2]))
        np.testing.assert_allclose(turned, np.mean(headings[a:b + 1] - np.unwrap(filter_poses[a:b + 1, 2])), atol=1e-9)
    np.testing.assert_allclose(np.hypot(*np.diff(poses[:, :2], axis=0).T), 0.5, atol=1e-9)  # the filter's translation
    with pytest.raises(ValueError, match="cover"):
        fused_chain(filter_poses, headings, np.array([0, 20]), np.array([19, 39]))


def test_the_passes_loops_merge_each_pair_once_kept_where_any_pass_kept_it():
    from jaxslam.graph.acceptance import first_kept as _first_kept, merged as _merged

    def loops(query, submap, refused):
        c = len(query)
        return Loops(np.array(query), np.array(submap), np.arange(c * 3.0).reshape(c, 3), np.zeros((c, 3, 3)),
                     np.ones(c), np.zeros(c), np.zeros(c, bool), np.array(refused, object), np.arange(c, dtype=float),
                     np.zeros(c, bool))

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


def test_parting_is_a_standard_normal_where_the_rates_hold_and_large_after_a_turn_they_do_not():
    """Headings that random-walk at the rates, the filter's with white jitter: |parting| over
    many draws exceeds 2 as often as a standard normal does (4.55 %), within 4 binomial standard
    errors; a 15-degree turn of the filter alone (7 standard deviations) after node ``since`` parts it by far more than 3."""
    rng = np.random.default_rng(3)
    draws, nodes, since = 4000, 400, 150
    filter_rate, odometry_rate, jitter = 0.002 ** 2, 0.001 ** 2, 0.004 ** 2
    rates = (filter_rate, odometry_rate)
    values, turned = [], []
    for _ in range(draws):
        odometry_h = 2.0 + np.cumsum(rng.normal(0.0, np.sqrt(odometry_rate), nodes))
        filter_h = np.cumsum(rng.normal(0.0, np.sqrt(filter_rate), nodes)) + rng.normal(0.0, np.sqrt(jitter), nodes)
        values.append(parting(filter_h, odometry_h, since, rates, jitter))
        filter_h[300:] += np.radians(15.0)
        turned.append(parting(filter_h, odometry_h, since, rates, jitter))
    share = np.mean(np.asarray(values) > 2.0)
    assert abs(share - 0.0455) < 4 * np.sqrt(0.0455 * 0.9545 / draws)
    assert np.mean(np.asarray(turned) > 3.0) > 0.99


def _slow_jump_statistic(headings, turns, half_width):
    """The jump statistic by a loop over the nodes: the mean filter-minus-odometry heading over
    the ``half_width`` nodes from ``c`` less its mean over the ``half_width`` nodes before."""
    parted = np.unwrap(headings) - np.concatenate([[0.0], np.cumsum(turns)])
    return {c: parted[c:c + half_width].mean() - parted[c - half_width:c].mean()
            for c in range(half_width, headings.size - half_width + 1)}


def test_unspanned_jumps_find_the_filters_jumps_where_no_loop_spans_them():
    """A filter that tracks the odometry with white jitter and drift, and jumps 0.4 rad at node
    137 and -0.25 rad at node 240: found there, largest first, each to 0.02 rad (the jitter's
    standard error over 2 x 5 nodes is about 0.006), far beyond 4 robust standard deviations;
    the third largest is a noise draw at least two half widths from both. A steady drift of the
    filter's heading changes nothing. Spanned at 137, the largest open jump is 240's; everything
    spanned, none. The statistic matches a loop over the nodes."""
    rng = np.random.default_rng(11)
    nodes, half_width = 400, 5
    turns = rng.normal(0.0, 0.05, nodes - 1)
    headings = 0.3 + np.concatenate([[0.0], np.cumsum(turns + rng.normal(0.0, 0.002, nodes - 1))])
    headings += rng.normal(0.0, 0.01, nodes)
    headings[137:] += 0.4
    headings[240:] -= 0.25
    spanned = np.zeros(nodes, bool)
    spanned[300:] = True
    node, jump, sds = unspanned_jumps(headings, turns, spanned, half_width, 3)
    assert node[:2].tolist() == [137, 240] and np.allclose(jump[:2], [0.4, -0.25], atol=0.02) and np.all(sds[:2] > 10)
    slow = _slow_jump_statistic(headings, turns, half_width)
    np.testing.assert_allclose(jump, [slow[c] for c in node], atol=1e-12)
    far = [c for c in slow if not spanned[c] and abs(c - 137) > 2 * half_width and abs(c - 240) > 2 * half_width]
    assert node[2] == max(far, key=lambda c: abs(slow[c])) and sds[2] < 6
    drifting = unspanned_jumps(headings + 0.015 * np.arange(nodes), turns, spanned, half_width, 3)  # a steady drift
    np.testing.assert_array_equal(drifting[0], node)  # moves every node's statistic alike: no jump
    np.testing.assert_allclose(drifting[2], sds, rtol=1e-6)
    spanned[120:160] = True
    assert unspanned_jumps(headings, turns, spanned, half_width, 1)[0].tolist() == [240]
    assert unspanned_jumps(headings, turns, np.ones(nodes, bool), half_width, 3)[0].size == 0
    assert unspanned_jumps(headings[:9], turns[:8], np.zeros(9, bool), half_width, 3)[0].size == 0


def test_heading_jumps_are_every_large_jump_spanned_or_not_and_begin_a_submap():
    """The filter of the test above: its two jumps (44 and 28 robust standard deviations) are
    found whether loops span them or not, and the next largest values of the statistic (2.4) are
    not; a steady drift changes nothing. The submaps begin a run at each jump; a piece shorter
    than half a run joins the run on its side of the jump, so no submap holds nodes on both
    sides; without jumps the runs are the regular ones."""
    rng = np.random.default_rng(11)
    nodes = 400
    turns = rng.normal(0.0, 0.05, nodes - 1)
    headings = 0.3 + np.concatenate([[0.0], np.cumsum(turns + rng.normal(0.0, 0.002, nodes - 1))])
    headings += rng.normal(0.0, 0.01, nodes)
    headings[137:] += 0.4
    headings[240:] -= 0.25
    cuts = heading_jumps(headings, turns, 5, 4.0)
    assert cuts.tolist() == [137, 240]
    np.testing.assert_array_equal(heading_jumps(headings + 0.015 * np.arange(nodes), turns, 5, 4.0), cuts)
    assert heading_jumps(headings, turns, 5, 50.0).size == 0
    first, last = submap_ranges(nodes, 20, cuts)
    assert list(zip(first, last))[6:13] == [(120, 136), (137, 159), (160, 179), (180, 199), (200, 219),
                                            (220, 239), (240, 259)]  # 240 begins the regular run
    np.testing.assert_array_equal(first[1:], last[:-1] + 1)
    for c in cuts:
        assert c in first  # no submap holds both c - 1 and c
    regular = submap_ranges(101, 20)
    np.testing.assert_array_equal(regular[0], [0, 20, 40, 60, 80, 100])
    np.testing.assert_array_equal(regular[1], [19, 39, 59, 79, 99, 100])
    cases = {(61,): [0, 20, 40, 61, 80, 100],  # [60, 61) joins 40's run
             (78,): [0, 20, 40, 60, 78, 100],  # [78, 80) joins 80's run
             (61, 78): [0, 20, 40, 61, 78, 100],
             (65,): [0, 20, 40, 65, 80, 100],  # [60, 65) joins 40's run: 25 nodes
             (70,): [0, 20, 40, 60, 70, 80, 100],  # both pieces half a run
             (40, 0, 101, 150): [0, 20, 40, 60, 80, 100]}  # a regular start, the ends, beyond them
    for given, firsts in cases.items():
        got_first, got_last = submap_ranges(101, 20, given)
        assert got_first.tolist() == firsts, given
        np.testing.assert_array_equal(got_last, np.append(got_first[1:] - 1, 100))


def test_undo_jump_takes_the_odometrys_turns_near_the_node_and_keeps_every_other_step():
    rng = np.random.default_rng(2)
    steps = np.column_stack([rng.uniform(0.2, 0.5, 59), rng.normal(0.0, 0.02, 59), rng.normal(0.0, 0.1, 59)])
    filter_poses = chain_np(np.array([3.0, -1.0, 0.5]), steps)
    turns = rng.normal(0.0, 0.1, 59)
    undone = undo_jump(filter_poses, turns, 30, 4)
    got = between_np(undone[:-1], undone[1:])
    near = np.arange(59)
    near = (near >= 26) & (near < 34)
    np.testing.assert_allclose(got[near, 2], turns[near], atol=1e-9)
    np.testing.assert_allclose(got[~near], steps[~near], atol=1e-9)
    np.testing.assert_allclose(got[:, :2], steps[:, :2], atol=1e-9)
    np.testing.assert_allclose(undone[0], filter_poses[0])


def _loops(query, submap, refused, heading=None):
    count = len(query)
    measurement = np.zeros((count, 3))
    if heading is not None:
        measurement[:, 2] = heading
    return Loops(np.array(query), np.array(submap), measurement, np.zeros((count, 3, 3)), np.ones(count),
                 np.zeros(count), np.zeros(count, bool), np.array(refused, object), np.zeros(count), np.zeros(count, bool))


def test_spanned_nodes_and_loops_across_count_the_kept_loops_as_a_loop_over_the_nodes_does():
    rng = np.random.default_rng(5)
    nodes, first_node = 200, np.arange(0, 200, 20)
    submap = rng.integers(0, 8, 60)
    query = np.minimum(first_node[submap] + 20 + rng.integers(0, 120, 60), nodes - 1)
    refused = rng.choice(["", "", "score", "consistency"], 60)
    loops = _loops(query, submap, refused).extend(_loops(query[:5], submap[:5], [""] * 5))  # a pair kept twice
    loops = loops._replace(appearance=np.arange(65) % 7 == 3)  # found by appearance: no span counts
    kept = {(q, m) for q, m, r in zip(loops.query, loops.submap, loops.refused) if r == ""}
    first_rows = {}  # each kept pair once, by its first kept row; counted unless that row came by appearance
    for q, m, r, a in zip(loops.query, loops.submap, loops.refused, loops.appearance):
        if r == "":
            first_rows.setdefault((q, m), a)
    windowed = {pair for pair, by_appearance in first_rows.items() if not by_appearance}
    count = np.array([sum(first_node[m] + 20 <= c <= q for q, m in windowed) for c in range(nodes)])
    for min_loops in (1, 3):
        spanned = spanned_nodes(loops, first_node, nodes, min_loops)
        np.testing.assert_array_equal(spanned[20:], count[20:] >= min_loops)
        assert spanned[:20].all()  # the first submap: no loop can span it
    for node in (25, 90, 170):
        across = loops_across(loops, first_node, node)
        assert {(int(loops.query[k]), int(loops.submap[k])) for k in across} == {
            (q, m) for q, m in kept if first_node[m] + 20 <= node <= q}


def test_loops_side_with_the_chain_whose_heading_they_measure():
    """Two chains that part by 0.3 rad at node 50: loops into the first submap measured on either
    side with it, whatever the jitter of 0.02 rad; no loop sides with neither."""
    rng = np.random.default_rng(8)
    steps = np.column_stack([np.full(99, 0.4), np.zeros(99), rng.normal(0.0, 0.05, 99)])
    right = chain_np(np.zeros(3), steps)
    steps[49, 2] += 0.3
    jumped = chain_np(np.zeros(3), steps)
    first_node, query = np.arange(0, 100, 20), np.arange(60, 100, 5)
    for chain, other in ((right, jumped), (jumped, right)):
        loops = _loops(query, np.zeros(query.size, int), [""] * query.size,
                       chain[query, 2] - chain[0, 2] + rng.normal(0.0, 0.02, query.size))
        across = loops_across(loops, first_node, 50)
        assert across.size == query.size
        assert loops_side_with(loops, across, first_node, chain, other)
        assert not loops_side_with(loops, across, first_node, other, chain)
        assert not loops_side_with(loops, across[:0], first_node, chain, other)


def test_a_turn_lets_the_loops_after_it_set_the_heading_where_the_straight_steps_hold_it():
    """FR-clinic's last corner: the chain turned 90 degrees 2.8 degrees too far, and the loops
    after the corner measured it, but the chain's heading variance was the loops' drift rate alone
    (0.05 degrees a root step), so the graph held the chain's turn against them. The motion
    model's share of a turn (``stt`` times it) frees the turn and not the straight steps: the
    solved heading after the corner is the loops', and without it stays off by over 1 degree."""
    from jaxslam.config import default_params
    from jaxslam.graph import pose_graph
    from jaxslam.graph.drift import sequential_edges
    from jaxslam.graph.pose_graph import LOOP, Edges, PoseGraph

    steps = np.zeros((81, 3))
    steps[1:, 0] = 0.7  # 0.7 m a step, the corner's 90 degrees over steps 40 and 41
    steps[40:42, 2] = np.pi / 4
    truth = chain_np(np.zeros(3), steps[1:])
    odometry = steps.copy()
    odometry[40:42, 2] *= 1 + np.radians(2.8) / (np.pi / 2)  # the odometry's turn 2.8 degrees too far
    chain = chain_np(np.zeros(3), odometry[1:])
    pairs = np.array([(20, 60), (25, 65), (30, 70)])  # loops across the corner, as the scans measured them
    information = np.broadcast_to(np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.01**2]), (3, 3, 3))
    loops = Edges(pairs[:, 0], pairs[:, 1], between_np(truth[pairs[:, 0]], truth[pairs[:, 1]]), information,
                  np.full(3, LOOP))
    params = default_params().motion
    after = slice(45, 81)

    def solved_with(motion):
        sequential = sequential_edges(chain, odometry, motion, np.radians(0.05) ** 2)
        return pose_graph.optimize(PoseGraph(chain, pose_graph.concat_edges(sequential, loops)), loop_phi=None,
                                   max_iterations=100, tolerance=1e-12).poses

    freed, held = solved_with(params), solved_with(params._replace(stt=0.0))
    assert np.degrees(np.abs(freed[after, 2] - truth[after, 2]).max()) < 0.3
    assert np.degrees(np.abs(np.diff(freed[:40, 2])).max()) < 0.05  # the straight steps keep their stiffness
    assert np.degrees(np.abs(held[after, 2] - truth[after, 2]).max()) > 1.0
