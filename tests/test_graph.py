"""The loop closure (jaxslam.graph): the SE(2) pose graph's Jacobians and solve, the branch and
bound against an exhaustive NumPy search, and the closure on the twin-rooms world built to alias."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.config import SlamConfig, default_params
from jaxslam.geometry import between_np, chain_np, compose_np, wrap_angle_np
from jaxslam.graph import ClosureConfig, close_trajectory_loops, load_graph, plot_graph, save_graph
from jaxslam.graph import pose_graph
from jaxslam.graph.loop_search import SearchWindow, class_shape, search_batch
from jaxslam.graph.pose_graph import LOOP, ODOMETRY, SEQUENTIAL, Edges, PoseGraph
from jaxslam.graph.submaps import square_bounds
from jaxslam.laserlog import select_updates
from jaxslam.sim.aliasing import TWIN_OFFSET, twin_rooms_scenario
from jaxslam.sim.scenarios import office_scenario

# ---------------------------------------------------------------------------------------------
# The pose graph.


def _random_edges(rng, poses, pairs, kind):
    first, second = np.array(pairs).T
    measurement = between_np(poses[first], poses[second])
    info = np.zeros((len(first), 3, 3))
    info[:, [0, 1, 2], [0, 1, 2]] = rng.uniform(1.0, 100.0, (len(first), 3))
    return Edges(first, second, measurement, info, np.full(len(first), kind))


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    poses = rng.normal(size=(6, 3)) * [3.0, 3.0, 1.0]
    edges = _random_edges(rng, poses, [(0, 1), (1, 2), (4, 2), (5, 0)], LOOP)
    edges = edges._replace(measurement=edges.measurement + rng.normal(scale=0.1, size=edges.measurement.shape))
    error, jac_a, jac_b = pose_graph._jacobians(poses, edges)
    np.testing.assert_allclose(error, pose_graph.edge_errors(poses, edges), atol=1e-12)
    eps = 1e-6
    for e in range(edges.count):
        one = Edges(*(field[e:e + 1] for field in edges))
        for node, jac in ((edges.first[e], jac_a), (edges.second[e], jac_b)):
            for k in range(3):
                bumped = poses.copy()
                bumped[node, k] += eps
                numeric = (pose_graph.edge_errors(bumped, one)[0] - error[e]) / eps
                np.testing.assert_allclose(numeric, jac[e, :, k], atol=1e-4)


def _square_walk(rng, laps=2, side=8, noise=(0.03, 0.03, 0.01)):
    """True poses of a walk round a square, and a chain of noisy relative measurements."""
    steps = []
    for _ in range(laps * 4):
        steps += [[1.0, 0.0, 0.0]] * (side - 1) + [[1.0, 0.0, np.pi / 2]]
    truth = [np.zeros(3)]
    for step in steps:
        truth.append(compose_np(truth[-1], step))
    truth = np.array(truth)
    measured = between_np(truth[:-1], truth[1:]) + rng.normal(scale=noise, size=(len(steps), 3))
    return truth, measured


def test_optimize_closes_a_square_and_a_robust_kernel_refuses_a_false_loop():
    rng = np.random.default_rng(1)
    truth, measured = _square_walk(rng)
    num, lap = truth.shape[0], 32
    dead_reckoned = [truth[0]]
    for step in measured:
        dead_reckoned.append(compose_np(dead_reckoned[-1], step))
    dead_reckoned = np.array(dead_reckoned)
    info = np.zeros((num - 1, 3, 3))
    info[:, [0, 1, 2], [0, 1, 2]] = 1.0 / np.array([0.03, 0.03, 0.01]) ** 2
    chain = Edges(np.arange(num - 1), np.arange(1, num), measured, info, np.full(num - 1, SEQUENTIAL))
    # True loops: every other node of the first lap is seen again from its twin of the second.
    true_loops = _random_edges(rng, truth, [(i, i + lap) for i in range(0, lap, 2)], LOOP)
    edges = pose_graph.concat_edges(chain, true_loops)
    solved = pose_graph.optimize(PoseGraph(dead_reckoned, edges), loop_phi=None)

    def err(p):  # how far lap 2 lies from lap 1 against the truth (the loops' business), m
        first = np.arange(lap)
        diff = between_np(between_np(truth[first], truth[first + lap]), between_np(p[first], p[first + lap]))
        return np.mean(np.hypot(diff[:, 0], diff[:, 1]))

    before, after = err(dead_reckoned), err(solved.poses)
    assert before > 0.2 and after < 0.25 * before
    np.testing.assert_array_equal(solved.poses[0], dead_reckoned[0])  # the gauge
    # A false loop 3 m off, strongly weighted: least squares bends; the kernel keeps the map.
    false = Edges(np.array([5]), np.array([45]), np.array([[3.0, 0.0, 0.0]]), np.eye(3)[None] * 1e4,
                  np.array([LOOP]))
    with_false = pose_graph.concat_edges(edges, false)
    plain = pose_graph.optimize(PoseGraph(solved.poses, with_false), loop_phi=None)
    robust = pose_graph.optimize(PoseGraph(solved.poses, with_false), loop_phi=1.0)
    assert err(plain.poses) > 2 * err(robust.poses)
    assert robust.loop_scales[-1] < 0.05 and np.all(robust.loop_scales[chain.count:-1] > 0.5)


def test_normal_equations_match_a_dense_sum_over_the_edges():
    # Repeated pairs, an edge into node 0 (the gauge) and weights: the sparse assembly against
    # J^T W Omega J and J^T W Omega e summed edge by edge into dense arrays.
    rng = np.random.default_rng(2)
    poses = rng.normal(size=(7, 3)) * [3.0, 3.0, 1.0]
    edges = _random_edges(rng, poses, [(0, 1), (1, 2), (2, 3), (4, 2), (4, 2), (6, 0), (3, 5), (5, 6)], LOOP)
    edges = edges._replace(measurement=edges.measurement + rng.normal(scale=0.1, size=edges.measurement.shape),
                           information=edges.information + 0.3 * np.eye(3)[[1, 0, 2]][None])
    weights = rng.uniform(0.1, 1.0, edges.count)
    h, g, _ = pose_graph._normal_equations(poses, edges, weights, pose_graph._sparsity(edges, poses.shape[0]))
    error, jac_a, jac_b = pose_graph._jacobians(poses, edges)
    dense_h, dense_g = np.zeros((21, 21)), np.zeros(21)
    for e in range(edges.count):
        jac = np.zeros((3, 21))
        jac[:, 3 * edges.first[e]:3 * edges.first[e] + 3] += jac_a[e]
        jac[:, 3 * edges.second[e]:3 * edges.second[e] + 3] += jac_b[e]
        dense_h += weights[e] * jac.T @ edges.information[e] @ jac
        dense_g += weights[e] * jac.T @ edges.information[e] @ error[e]
    np.testing.assert_allclose(h.toarray(), dense_h[3:, 3:], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(g, dense_g[3:], rtol=1e-12, atol=1e-9)


def test_a_tail_of_sequential_edges_leaves_the_solution_before_it():
    # Why the closure solves only the searched nodes: nodes that hang off the last one by
    # sequential edges alone are free to satisfy them, so the rest is solved as without them.
    rng = np.random.default_rng(3)
    truth, measured = _square_walk(rng)
    num, lap, solved_until = truth.shape[0], 32, 48
    dead_reckoned = chain_np(truth[0], measured)
    info = np.zeros((num - 1, 3, 3))
    info[:, [0, 1, 2], [0, 1, 2]] = 1.0 / np.array([0.03, 0.03, 0.01]) ** 2
    chain = Edges(np.arange(num - 1), np.arange(1, num), measured, info, np.full(num - 1, SEQUENTIAL))
    loops = _random_edges(rng, truth, [(i, i + lap) for i in range(0, solved_until - lap, 2)], LOOP)
    whole = pose_graph.optimize(PoseGraph(dead_reckoned, pose_graph.concat_edges(chain, loops)), loop_phi=None,
                                max_iterations=100, tolerance=1e-12)
    head = Edges(*(field[:solved_until - 1] for field in chain))
    part = pose_graph.optimize(PoseGraph(dead_reckoned[:solved_until], pose_graph.concat_edges(head, loops)),
                               loop_phi=None, max_iterations=100, tolerance=1e-12)
    assert np.abs(whole.poses[:solved_until] - dead_reckoned[:solved_until]).max() > 0.1
    np.testing.assert_allclose(part.poses, whole.poses[:solved_until], atol=1e-6)
    np.testing.assert_allclose(whole.chi2[solved_until - 1:num - 1], 0.0, atol=1e-8)


def test_optimize_refuses_bad_input():
    poses = np.zeros((3, 3))
    edges = Edges(np.array([0]), np.array([3]), np.zeros((1, 3)), np.eye(3)[None], np.array([LOOP]))
    with pytest.raises(ValueError, match="second indices must lie in"):
        pose_graph.optimize(PoseGraph(poses, edges))
    with pytest.raises(ValueError, match="poses must be"):
        pose_graph.optimize(PoseGraph(np.zeros((1, 3)), edges))


# ---------------------------------------------------------------------------------------------
# The branch and bound against an exhaustive search.


def _brute_force(fit, points, valid, guess, half_cells, half_angles, angular_step, resolution):
    """The best (score, row offset, col offset, angle step) over the whole window, in NumPy."""
    best = (-1.0, 0, 0, 0)
    n = max(valid.sum(), 1)
    for k in range(-half_angles, half_angles + 1):
        a = guess[2] + k * angular_step
        c, s = np.cos(a), np.sin(a)
        x = guess[0] + c * points[:, 0] - s * points[:, 1]
        y = guess[1] + s * points[:, 0] + c * points[:, 1]
        rows = np.floor(y / resolution).astype(np.float32).astype(int)
        cols = np.floor(x / resolution).astype(np.float32).astype(int)
        for dr in range(-half_cells, half_cells + 1):
            for dc in range(-half_cells, half_cells + 1):
                r, q = rows + dr, cols + dc
                inside = (r >= 0) & (r < fit.shape[0]) & (q >= 0) & (q < fit.shape[1]) & valid
                score = fit[r[inside], q[inside]].astype(float).sum() / (255.0 * n)
                if score > best[0]:
                    best = (score, dr, dc, k)
    return best


def test_square_bounds_bound_every_shift():
    rng = np.random.default_rng(2)
    fit = rng.integers(0, 256, size=(1, 16, 20)).astype(np.uint8)
    for level, bound in enumerate(square_bounds(fit, 3), start=1):
        side = 2**level
        padded = np.pad(fit[0], ((0, side), (0, side)))
        for r in range(16):
            for c in range(20):
                assert bound[0, r, c] == padded[r:r + side, c:c + side].max()


def test_class_shape_deepens_only_windows_wider_than_the_top_squares():
    window = SearchWindow(half_cells=400, half_angles=3, angular_step=0.01, levels=5, keep=8, ambiguity_cells=1,
                          ambiguity_angles=1, top_squares=9)
    # Spans 65, 257, 513, 801 cells: 3, 9, 17 and 26 squares of 32 cells a side.
    shapes = [class_shape(h, window) for h in (32, 128, 256, 400)]
    assert [(s.half_cells, s.levels, s.keep) for s in shapes] == [(32, 5, 8), (128, 5, 8), (256, 6, 16), (400, 7, 32)]
    assert [class_shape(h, window._replace(top_squares=0)).levels for h in (32, 400)] == [5, 5]
    assert class_shape(400, window._replace(levels=8)).levels == 8  # never fewer than levels


def _walls_and_scan(resolution=0.1):
    """A submap's (64, 64) fit of a few walls and posts, and 40 of its wall cells seen as a scan
    from a true pose: (fit, points (40, 2), valid (40,), true_pose (3,))."""
    rng = np.random.default_rng(3)
    # A submap of a few walls and posts; the scan is the walls seen from a pose, shifted.
    fit = np.zeros((64, 64), np.uint8)
    fit[10, 5:60] = 255
    fit[5:50, 50] = 255
    fit[30:34, 20:22] = 200
    fit[45, 10:30] = 255
    fit = np.maximum.reduce([np.roll(np.roll(fit, dr, 0), dc, 1) * (0.6 if dr or dc else 1.0)
                             for dr in (-1, 0, 1) for dc in (-1, 0, 1)]).astype(np.uint8)
    cells = np.argwhere(fit == 255)
    pick = cells[rng.choice(len(cells), 40, replace=False)]
    true_pose = np.array([3.0, 2.8, 0.05])
    world = (pick[:, ::-1] + 0.5) * resolution  # (x, y) of the cells' centres
    c, s = np.cos(true_pose[2]), np.sin(true_pose[2])
    rel = world - true_pose[:2]
    points = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], -1).astype(np.float32)
    return fit, points, np.ones(len(points), bool), true_pose


@pytest.mark.parametrize("levels", [2, 4])
def test_branch_and_bound_finds_the_exhaustive_optimum_where_it_certifies(levels):
    resolution = 0.1
    fit, points, valid, true_pose = _walls_and_scan(resolution)
    # Four levels: the top node is the whole 17-cell window's square, as a deepened class's is.
    window = SearchWindow(half_cells=8, half_angles=3, angular_step=0.025, levels=levels, keep=16, ambiguity_cells=3,
                          ambiguity_angles=2)
    bounds = tuple(jnp.asarray(b) for b in square_bounds(fit[None], window.levels))
    guesses = np.array([true_pose + [0.3, -0.2, 0.05], true_pose + [-0.5, 0.4, -0.05], true_pose])
    result = search_batch(jnp.asarray(fit[None]), bounds, jnp.zeros(3, jnp.int32), jnp.asarray(points[None].repeat(3, 0)),
                          jnp.asarray(valid[None].repeat(3, 0)), jnp.asarray(guesses, jnp.float32),
                          jnp.full(3, 8, jnp.int32), jnp.full(3, 0.08, jnp.float32), resolution, window)
    for p in range(3):
        score, dr, dc, k = _brute_force(fit, points, valid, guesses[p].astype(np.float32), 8, 3, 0.025, resolution)
        if bool(result.certified[p]):
            assert float(result.score[p]) == pytest.approx(score, abs=1e-6)
        else:  # uncertified: never better than the optimum, and the optimum lies under the dropped bound
            assert float(result.score[p]) <= score + 1e-6 and score <= float(result.dropped_bound[p]) + 1e-6
    assert np.any(np.asarray(result.certified))
    best = int(np.argmax(np.asarray(result.score)))
    np.testing.assert_allclose(np.asarray(result.pose[best])[:2], true_pose[:2], atol=2 * resolution)


def test_a_deepened_class_screens_and_its_candidates_are_searched_again_at_the_base_levels():
    from jaxslam.graph.loop_search import search_pairs
    from jaxslam.graph.submaps import Submaps
    from jaxslam.grid import GridSpec

    resolution = 0.1
    fit, points, valid, true_pose = _walls_and_scan(resolution)
    base = SearchWindow(half_cells=8, half_angles=3, angular_step=0.025, levels=2, keep=4, ambiguity_cells=3,
                        ambiguity_angles=2, top_squares=2, recheck_score=0.5)
    deep = class_shape(8, base)
    assert (deep.levels, deep.keep) == (4, 16)  # 17 cells: 5 squares of 4, 3 of 8, 2 of 16
    bounds = tuple(jnp.asarray(b) for b in square_bounds(fit[None], deep.levels))
    submaps = Submaps(np.zeros(1, int), np.zeros(1, int), np.zeros((1, 2)), GridSpec((64, 64), resolution, (0.0, 0.0)),
                      None, jnp.asarray(fit[None]), bounds)
    rng = np.random.default_rng(5)
    num = 12
    guess = (true_pose + rng.uniform(-1, 1, (num, 3)) * [1.6, 1.6, 0.07]).astype(np.float32)  # some windows miss it
    args = (np.zeros(num, np.int32), np.repeat(points[None], num, 0), np.repeat(valid[None], num, 0), guess,
            np.full(num, 8, np.int32), np.full(num, 0.08, np.float32))
    found = search_pairs(submaps, *args, base, batch=5)

    def alone(shape):
        return search_batch(submaps.fit, bounds, *(jnp.asarray(a) for a in args), resolution, shape)

    screened, searched_again = alone(deep), alone(base)
    again = np.asarray(screened.score) >= base.recheck_score
    assert 0 < again.sum() < num  # both kinds of pair occur
    # The two searches differ where the pairs are searched again, so skipping it would show.
    assert not np.array_equal(np.asarray(screened.dropped_bound)[again], np.asarray(searched_again.dropped_bound)[again])
    for field, first, second in zip(found, screened, searched_again):
        np.testing.assert_array_equal(field, np.where(again.reshape((-1,) + (1,) * (field.ndim - 1)), second, first))


# ---------------------------------------------------------------------------------------------
# The closure on the world built to alias.


@pytest.fixture(scope="module")
def twin_rooms():
    """The twin-rooms tour and a drifted copy of its true path (a filter's heading bias of
    0.001 rad and a 1 % scale error per processed scan): the closure's input, without a filter."""
    scenario = twin_rooms_scenario(jax.random.key(0))
    selection = select_updates(scenario.log, 0.5, 0.25)
    truth = scenario.true_poses[selection.indices]
    steps = between_np(truth[:-1], truth[1:])
    steps[:, 2] += 0.001
    steps[:, :2] *= 1.01
    drifted = [truth[0]]
    for step in steps:
        drifted.append(compose_np(drifted[-1], step))
    return scenario, selection, truth, np.array(drifted)


def _loop_errors(closure, truth):
    """(C,) how far each candidate loop's measurement is from the truth (m)."""
    loops = closure.loops
    origin = closure.submap_first_node[loops.submap]
    diff = between_np(between_np(truth[origin], truth[loops.query]), loops.measurement)
    return np.hypot(diff[:, 0], diff[:, 1])


def test_twin_rooms_no_false_loop_is_kept_and_the_path_comes_closer(twin_rooms, tmp_path):
    scenario, selection, truth, drifted = twin_rooms
    closure = close_trajectory_loops(scenario.log, selection.indices, drifted, selection.motions, default_params(),
                                     SlamConfig(), np.zeros(2))
    kept = closure.loops.refused == ""
    errors = _loop_errors(closure, truth)
    assert kept.sum() >= 10  # the true loop (room A twice) is closed ...
    assert np.all(errors[kept] < 0.3)  # ... and no kept loop is off by a room
    before = np.mean(np.hypot(*(drifted - truth)[:, :2].T))
    after = np.mean(np.hypot(*(closure.poses - truth)[:, :2].T))
    assert after < 0.4 * before
    # The trajectory holds a pose per scan, the processed ones the graph's.
    np.testing.assert_allclose(closure.trajectory[selection.indices], closure.poses, atol=1e-9)
    save_graph(tmp_path / "graph.npz", closure)
    graph = load_graph(tmp_path / "graph.npz")
    assert graph["loop_refused"].shape == kept.shape and int((graph["loop_refused"] == "").sum()) == kept.sum()
    np.testing.assert_array_equal(graph["loop_appearance"], closure.loops.appearance)
    kinds = np.bincount(graph["edge_kind"], minlength=3)
    # one edge per kept loop; the chain's and the odometry's over every step (lengths.py)
    assert kinds[LOOP] == kept.sum() and kinds[SEQUENTIAL] == kinds[ODOMETRY] == closure.node_scans.size - 1
    # The search's record holds every windowed pair (the widened and appearance pairs aside), each
    # kept loop's among them at a candidate's score, and travels in graph.npz.
    record = closure.searched
    assert 0 < record.query.size <= closure.pairs_searched and set(record.chain_pass) <= set(range(1, closure.passes + 1))
    rows = {}
    for q, j, score in zip(record.query, record.submap, record.score):  # a pair's best over the passes
        rows[(int(q), int(j))] = max(rows.get((int(q), int(j)), 0.0), float(score))
    windowed = kept & ~closure.loops.appearance
    assert all(rows[(int(q), int(j))] >= ClosureConfig().candidate_score
               for q, j in zip(closure.loops.query[windowed], closure.loops.submap[windowed]))
    np.testing.assert_array_equal(graph["searched_score"], record.score)
    np.testing.assert_array_equal(graph["searched_half_xy"], record.half_xy)


def test_twin_rooms_turned_inside_a_submap_keep_no_loop_into_it(twin_rooms):
    """The true path turned 0.5 rad between nodes 60 and 61, against an odometry that did not
    turn. A submap of nodes 60-79 would hold node 60 in one frame and the rest in another, and
    loops measured in node 60's frame carry the turn: with no jump counted large enough to begin
    a submap, two are kept 2.0-2.6 m off the truth, both into it. At the defaults a submap
    begins at node 61 (the piece before joins nodes 40-59), and no kept loop is off."""
    scenario, selection, truth, _ = twin_rooms
    steps = between_np(truth[:-1], truth[1:])
    steps[60, 2] += 0.5
    turned = chain_np(truth[0], steps)

    def close(**changes):
        return close_trajectory_loops(scenario.log, selection.indices, turned, selection.motions, default_params(),
                                      SlamConfig(), np.zeros(2), dataclasses.replace(ClosureConfig(), **changes))

    uncut, cut = close(jump_min_sds=1e9), close()
    assert 60 in uncut.submap_first_node and 61 not in uncut.submap_first_node
    off = (uncut.loops.refused == "") & (_loop_errors(uncut, truth) > 0.3)
    assert off.sum() >= 1 and np.all(uncut.submap_first_node[uncut.loops.submap[off]] == 60)
    assert 61 in cut.submap_first_node and 60 not in cut.submap_first_node and 40 in cut.submap_first_node
    kept = cut.loops.refused == ""
    assert kept.sum() >= 10 and np.all(_loop_errors(cut, truth)[kept] < 0.3)


def test_twin_rooms_the_loops_measure_whose_heading_drifts(twin_rooms):
    """The input path's heading drifts by 0.001 rad a step; the odometry here is the truth's
    steps with a tenth of that in noise. The first pass's loops measure the input's drift as the
    faster, the next passes search from a chain that takes most of its heading from the odometry,
    and that chain ends nearer the truth in heading than the input. The simulator's own odometry
    drifts faster than the input (about 0.03 rad a square-root step): the share stays small. With
    one pass the closure is the input's chain alone (share 0)."""
    scenario, selection, truth, drifted = twin_rooms
    rng = np.random.default_rng(0)
    motions = np.zeros_like(truth)
    motions[1:] = between_np(truth[:-1], truth[1:])
    motions[1:, 2] += rng.normal(0.0, 1e-4, truth.shape[0] - 1)
    closure = close_trajectory_loops(scenario.log, selection.indices, drifted, motions, default_params(),
                                     SlamConfig(), np.zeros(2))
    filter_rate, odometry_rate = closure.drift_rates
    assert filter_rate > 4 * odometry_rate
    assert closure.passes >= 2 and closure.odometry_share > 0.5
    heading_error = lambda poses: np.abs(wrap_angle_np(poses[-1, 2] - truth[-1, 2]))
    assert heading_error(closure.chain_poses) < 0.5 * heading_error(drifted)
    summary = closure.summary()
    assert summary["passes"] == closure.passes and summary["odometry_heading_share"] == closure.odometry_share
    honest = close_trajectory_loops(scenario.log, selection.indices, drifted, selection.motions, default_params(),
                                    SlamConfig(), np.zeros(2), dataclasses.replace(ClosureConfig(), max_passes=1))
    assert honest.passes == 1 and honest.odometry_share == 0.0
    np.testing.assert_array_equal(honest.chain_poses, drifted)
    assert honest.drift_rates[1] > honest.drift_rates[0]


def test_twin_rooms_no_loop_from_the_filter_then_one_pass_from_the_odometry(twin_rooms):
    """An input whose heading drifts 0.012 rad a step is out of every window at the revisit: the
    first pass keeps no loop; the second searches from the odometry's chain (the truth's steps
    and a little noise) and keeps loops, none into the twin room, which measure the input's drift
    as the faster. At 0.015 rad a step neither pass keeps one, and the result is the first pass's:
    nothing says the odometry is better."""
    scenario, selection, truth, _ = twin_rooms
    motions = np.zeros_like(truth)
    motions[1:] = between_np(truth[:-1], truth[1:])
    motions[1:, 2] += np.random.default_rng(1).normal(0.0, 1e-3, truth.shape[0] - 1)  # steps differ, as in a log
    one_pass = dataclasses.replace(ClosureConfig(), max_passes=1)
    for bias, finds in ((0.012, True), (0.015, False)):
        steps = between_np(truth[:-1], truth[1:])
        steps[:, 2] += bias
        drifted = chain_np(truth[0], steps)
        first = close_trajectory_loops(scenario.log, selection.indices, drifted, motions, default_params(),
                                       SlamConfig(), np.zeros(2), one_pass)
        closure = close_trajectory_loops(scenario.log, selection.indices, drifted, motions, default_params(),
                                         SlamConfig(), np.zeros(2))
        kept = closure.loops.refused == ""
        assert first.num_loops == 0 and closure.passes == 2
        if finds:
            assert kept.sum() >= 3 and np.all(_loop_errors(closure, truth)[kept] < 0.5)
            assert closure.drift_rates[0] > 4 * closure.drift_rates[1] and closure.odometry_share > 0.5
        else:
            assert kept.sum() == 0 and closure.odometry_share == 0.0
            np.testing.assert_array_equal(closure.poses, first.poses)


def test_twin_rooms_a_window_wider_than_the_drift_aliases(twin_rooms):
    """The window is the defence: one wide enough to reach the twin room (12 m) finds the
    perfect matches 10 m off, and they pass every test (the twin is the same to the centimetre)."""
    scenario, selection, truth, drifted = twin_rooms
    wide = dataclasses.replace(ClosureConfig(), window_min_xy=12.0, window_max_xy=12.0, max_node_distance=15.0)
    closure = close_trajectory_loops(scenario.log, selection.indices, drifted, selection.motions, default_params(),
                                     SlamConfig(), np.zeros(2), wide)
    errors = _loop_errors(closure, truth)
    kept = closure.loops.refused == ""
    aliased = np.abs(errors - np.hypot(*TWIN_OFFSET[:2])) < 3.0
    assert np.any(kept & (errors > 1.0)) and np.any(aliased)


def test_twin_rooms_a_peak_on_the_window_edge_is_searched_again_wider(twin_rooms):
    """Windows too narrow for the drift (0.3 m, no growth) put the true matches on their edge,
    where the window test refuses them; searched again in windows twice and four times as wide,
    they are found and kept, each within 0.3 m of the truth (22 refused on the edge without;
    24 loops kept with against 10)."""
    scenario, selection, truth, drifted = twin_rooms
    narrow = dataclasses.replace(ClosureConfig(), window_min_xy=0.3, window_xy_per_metre=0.0, max_passes=1)
    closures = {}
    for widenings in (0, 2):
        closures[widenings] = close_trajectory_loops(
            scenario.log, selection.indices, drifted, selection.motions, default_params(), SlamConfig(), np.zeros(2),
            dataclasses.replace(narrow, max_widenings=widenings))
    fixed, widened = closures[0], closures[2]
    on_edge = (fixed.loops.refused == "window") & (fixed.loops.score >= narrow.min_score)
    assert on_edge.sum() >= 5
    kept = widened.loops.refused == ""
    assert kept.sum() >= fixed.num_loops + 5
    assert np.all(_loop_errors(widened, truth)[kept] < 0.3)
    assert widened.pairs_searched > fixed.pairs_searched
    with pytest.raises(ValueError, match="max_widenings"):
        dataclasses.replace(ClosureConfig(), max_widenings=-1)


def test_twin_rooms_a_loop_beyond_the_window_is_found_by_appearance_and_the_bound_is_the_defence(twin_rooms):
    """The input is the true path moved 5.8 m (5, 3) from node 100 on, before the return to
    room A: beyond the windows (1 + 0.03 m per metre of graph), within the appearance's bound
    (0.06 m per metre, plus 3). Searched by appearance too, the closure keeps at least six more
    loops than without, none off by more than 0.5 m, and ends nearer the truth (13 loops against
    5, 1.25 m against 1.51). The bound defends against the twin room as the window does: at 1 m per metre the drifted
    input's queries in room B are searched against room A too, and loops into it are kept."""
    scenario, selection, truth, drifted = twin_rooms
    jumped = chain_np(truth[0], between_np(truth[:-1], truth[1:]))
    jumped[100:, :2] += np.array([5.0, 3.0])
    one_pass = dataclasses.replace(ClosureConfig(), max_passes=1)
    runs = {places: close_trajectory_loops(scenario.log, selection.indices, jumped, selection.motions,
                                           default_params(), SlamConfig(), np.zeros(2),
                                           dataclasses.replace(one_pass, places_per_query=places))
            for places in (0, 3)}
    kept = {places: run.loops.refused == "" for places, run in runs.items()}
    assert kept[3].sum() >= kept[0].sum() + 6
    assert np.all(_loop_errors(runs[3], truth)[kept[3]] < 0.5)
    # The loops found by appearance are marked (graph.npz's ``loop_appearance``); none without the search.
    assert not runs[0].loops.appearance.any() and np.any(runs[3].loops.appearance & kept[3])
    error = {places: np.mean(np.hypot(*(run.poses - truth)[:, :2].T)) for places, run in runs.items()}
    assert error[3] < error[0]
    unbounded = close_trajectory_loops(scenario.log, selection.indices, drifted, selection.motions, default_params(),
                                       SlamConfig(), np.zeros(2), dataclasses.replace(one_pass, place_drift_per_metre=1.0))
    aliased = np.abs(_loop_errors(unbounded, truth) - np.hypot(*TWIN_OFFSET[:2])) < 3.0
    assert np.any(aliased & (unbounded.loops.refused == ""))


def test_twin_rooms_loops_after_a_jump_of_the_chain_are_kept_where_one_turn_explains_them(twin_rooms,
                                                                                          monkeypatch):
    """The input is the true path with one heading jump of 0.08 rad at node 150, in the middle of
    the revisit of room A. Through the jumped chain the loops after it disagree with the loops
    before it, which outvote them; one turn about one node between the two sides explains every
    disagreement, so they are kept, none off the truth, and the path comes nearer the truth than
    the vote alone leaves it (measured: 28 loops against 18, 13 after node 150 against 6; the
    path 0.017 m off against 0.104)."""
    from jaxslam.graph import acceptance

    scenario, selection, truth, _ = twin_rooms
    steps = between_np(truth[:-1], truth[1:])
    steps[150, 2] += 0.08
    jumped = chain_np(truth[0], steps)
    one_pass = dataclasses.replace(ClosureConfig(), max_passes=1)

    def close():
        return close_trajectory_loops(scenario.log, selection.indices, jumped, selection.motions, default_params(),
                                      SlamConfig(), np.zeros(2), one_pass)

    explained = close()
    monkeypatch.setattr(acceptance, "one_jump_explains_refused_group", lambda new, *args, **kwargs: new)
    voted = close()
    path_error = lambda poses: np.mean(np.hypot(*(poses - truth)[:, :2].T))
    assert np.sum(voted.loops.refused == "consistency") >= 8
    kept = explained.loops.refused == ""
    assert kept.sum() >= voted.num_loops + 6 and np.sum(kept & (explained.loops.query > 150)) >= 10
    assert np.all(_loop_errors(explained, truth)[kept] < 0.3)
    assert path_error(explained.poses) < 0.5 * path_error(voted.poses)


def test_office_a_jump_no_loop_spans_is_given_to_the_filter_and_a_slip_the_filter_corrected_is_not(tmp_path):
    """The office's true path turned 0.5 rad at node 101, against an odometry that did not turn:
    the places seen again after it lie beyond every window, and the closure alone keeps loops on
    either side but none across (measured: 2.93 m off, 14 loops). The jump is tried, the closure
    of the chain with it given to the filter keeps loops across it that agree with that chain,
    and it is taken (35 loops, 0.027 m). The same turn in the odometry (a slip the filter
    corrected) with the true path: tried where no node is spanned enough, not given, and the
    closure is the one without the try."""
    scenario = office_scenario(jax.random.key(0))
    selection = select_updates(scenario.log, 0.5, 0.25)
    truth = scenario.true_poses[selection.indices]
    steps = between_np(truth[:-1], truth[1:])
    steps[100, 2] += 0.5
    jumped = chain_np(truth[0], steps)

    def close(poses, motions, **changes):
        return close_trajectory_loops(scenario.log, selection.indices, poses, motions, default_params(), SlamConfig(),
                                      np.zeros(2), dataclasses.replace(ClosureConfig(), **changes))

    path_error = lambda poses: np.mean(np.hypot(*(poses - truth)[:, :2].T))
    alone, tried = close(jumped, selection.motions, jump_tries=0), close(jumped, selection.motions)
    assert alone.jumps == () and path_error(alone.poses) > 1.0
    (node, jump, sds, given), = tried.jumps
    assert node == 101 and abs(jump - 0.5) < 0.05 and sds > 4.0 and given
    assert path_error(tried.poses) < 0.1 and tried.num_loops > alone.num_loops + 10
    assert np.all(_loop_errors(tried, truth)[tried.loops.refused == ""] < 0.3)
    np.testing.assert_allclose(tried.filter_poses, jumped)  # the filter's, not the undone chain
    assert tried.summary()["jumps_tried"] == [{"node": 101, "deg": pytest.approx(np.degrees(jump)), "robust_stds": sds,
                                               "given_to_filter": True}]
    save_graph(tmp_path / "graph.npz", tried)
    np.testing.assert_allclose(load_graph(tmp_path / "graph.npz")["jumps"], [[101, jump, sds, 1.0]])
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    plot_graph(ax, load_graph(tmp_path / "graph.npz"))  # graph.png marks the jump
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert f"jump of {np.degrees(jump):.0f} deg at node 101, given to the filter" in labels
    plt.close(fig)
    slipped = selection.motions.copy()
    slipped[101, 2] += 0.5
    assert close(truth, slipped).jumps == ()  # every node spanned by the true path's loops
    forced = {tries: close(truth, slipped, min_drift_loops=1000, jump_tries=tries) for tries in (0, 1)}
    assert forced[1].jumps[0][0] == 101 and not forced[1].jumps[0][3]
    np.testing.assert_array_equal(forced[1].poses, forced[0].poses)


def test_one_jump_explains_a_jump_and_not_a_steady_drift():
    """Loops measured on the true path (out 30 m, a U-turn, back), kept ones at queries 130-148
    and a refused group at 151-159, all into the first submap. Through a chain whose heading
    jumps 0.06 rad at node 149 the group disagrees with the kept loops, and one turn there
    explains every pair: all five kept. Through a chain whose heading drifts 0.004 rad a step
    from node 120 on, the disagreement grows with the nodes between two queries, and no single
    turn explains every pair that straddles it: none kept. A jump of 0.5 rad is explained as well
    (the default reaches the widest angular window, 45 degrees), not under a 0.15 rad cap. With
    ``consistency_jump`` 0 the rule is off."""
    import types

    from jaxslam.graph.acceptance import Loops, one_jump_explains_refused_group

    steps = np.tile([0.5, 0.0, 0.0], (159, 1))
    steps[60:100, 2] = np.pi / 40
    truth = chain_np([0.0, 0.0, 0.0], steps)
    submaps = types.SimpleNamespace(first_node=np.arange(0, 160, 20))

    def loops(query, refused):
        n = query.size
        return Loops(query, np.zeros(n, int), between_np(truth[np.zeros(n, int)], truth[query]),
                     np.tile(np.eye(3) * 1e4, (n, 1, 1)), np.full(n, 0.6), np.full(n, 0.5), np.ones(n, bool),
                     np.array([refused] * n, object), np.full(n, np.nan), np.zeros(n, bool))

    found, group = loops(np.arange(130, 150, 3), ""), loops(np.arange(151, 160, 2), "consistency")
    jumped, drifted = steps.copy(), steps.copy()
    jumped[149, 2] += 0.06
    drifted[120:, 2] += 0.004
    config = ClosureConfig()
    kept = lambda estimate, config: one_jump_explains_refused_group(group, found, submaps, chain_np(truth[0], estimate),
                                                                    config).refused == ""
    assert np.all(kept(jumped, config))
    assert not np.any(kept(drifted, config))
    # A filter whose map parted by 29 degrees at one step is one turn too, up to the widest angular window.
    parted = steps.copy()
    parted[149, 2] += 0.5
    assert np.all(kept(parted, config))
    assert not np.any(kept(parted, dataclasses.replace(config, consistency_jump=0.15)))
    assert not np.any(kept(jumped, dataclasses.replace(config, consistency_jump=0.0)))
    assert not np.any(kept(jumped, dataclasses.replace(config, consistency_jump=0.05)))
    with pytest.raises(ValueError, match="consistency_jump"):
        dataclasses.replace(config, consistency_jump=-0.1)


def test_close_loops_refuses_mismatched_input(twin_rooms):
    scenario, selection, _, drifted = twin_rooms
    with pytest.raises(ValueError, match="must agree"):
        close_trajectory_loops(scenario.log, selection.indices[:-1], drifted, selection.motions, default_params(),
                               SlamConfig(), np.zeros(2))


# ---------------------------------------------------------------------------------------------
# jaxslam map: closed by default, the filter alone on request.


def test_map_closes_loops_by_default_and_not_on_request(tmp_path, twin_rooms, capsys):
    from jaxslam.cli import main
    from logs import write_flaser_log

    scenario = twin_rooms[0]
    log_path = tmp_path / "twin.clf"
    write_flaser_log(log_path, scenario.log)  # room A, room B, room A again: the loop
    common = ["map", str(log_path), "--particles", "3", "--proposal", "smp", "--no-progress",
              "--set", "max_insert_range=8"]
    assert main([*common, "--out", str(tmp_path / "closed")]) == 0
    assert main([*common, "--no-close-loops", "--out", str(tmp_path / "filter")]) == 0
    closed, alone = tmp_path / "closed", tmp_path / "filter"
    summary = json.loads((closed / "summary.json").read_text())
    graph = load_graph(closed / "graph.npz")
    assert summary["closure"]["loops_kept"] == int((graph["loop_refused"] == "").sum()) > 0
    assert summary["closure"]["loops_kept_by_appearance"] == int(((graph["loop_refused"] == "")
                                                                   & graph["loop_appearance"]).sum())
    # The filter's trajectory is the same with and without the closure; the closed one differs.
    np.testing.assert_array_equal(np.loadtxt(closed / "trajectory_filter.txt"), np.loadtxt(alone / "trajectory.txt"))
    assert not np.array_equal(np.loadtxt(closed / "trajectory.txt"), np.loadtxt(alone / "trajectory.txt"))
    assert not (alone / "graph.npz").exists() and not (alone / "trajectory_filter.txt").exists()
    assert "closure" not in json.loads((alone / "summary.json").read_text())
    assert main(["diagnose", str(closed)]) == 0 and (closed / "graph.png").is_file()
    _diagnose_names_the_returns_missed(closed, scenario, tmp_path, capsys)


def _diagnose_names_the_returns_missed(run, scenario, tmp_path, capsys):
    """``jaxslam diagnose RUN RELATIONS`` of a closed twin-rooms run lists the returns its closure
    missed (jaxslam.graph.missed), as the library function finds them."""
    from jaxslam.cli import main
    from jaxslam.graph.missed import missed_returns
    from jaxslam.io import read_relations, read_trajectory

    # The true motions between the first visit to room A and the return to it (node times), one
    # of them made 1 m wrong: a return the closed poses cannot agree with.
    times = np.loadtxt(run / "trajectory.txt")[:, 0]
    node_scans = load_graph(run / "graph.npz")["node_scans"]
    truth = scenario.true_poses
    first, last = node_scans[: node_scans.size // 5], node_scans[-node_scans.size // 5:]
    near = np.hypot(*(truth[first, None, :2] - truth[None, last, :2]).T).T < 1.0
    i, j = np.nonzero(near)
    pairs = np.stack([first[i], last[j]], 1)[::5]
    motion = between_np(truth[pairs[:, 0]], truth[pairs[:, 1]])
    motion[0, 0] += 1.0
    lines = [f"{times[a]:.6f} {times[b]:.6f} {m[0]:.6f} {m[1]:.6f} 0 0 0 {m[2]:.6f}" for (a, b), m in zip(pairs, motion)]
    (tmp_path / "twin.relations").write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    assert main(["diagnose", str(run), str(tmp_path / "twin.relations")]) == 0
    printed = capsys.readouterr().out
    missed = json.loads((run / "diagnosis.json").read_text())["closure"]["missed_returns"]
    wrong = int(np.searchsorted(node_scans, pairs[0, 1]))
    assert any(m["later_nodes"][0] <= wrong <= m["later_nodes"][1] for m in missed)
    assert "returns the closure missed" in printed and missed[0]["cause"] in printed
    _, closed = read_trajectory(run / "trajectory.txt")
    _, filtered = read_trajectory(run / "trajectory_filter.txt")
    assert missed == missed_returns(load_graph(run / "graph.npz"), times, closed, filtered,
                                    read_relations(tmp_path / "twin.relations"))


def test_closure_config_refuses_bad_values():
    for bad, words in (({"keep": 0}, "keep must be a positive integer"), ({"query_stride": 2.5}, "query_stride"),
                       ({"sigma": 0.0}, "sigma must be > 0"), ({"window_min_xy": 21.0}, "minimum exceeds"),
                       ({"min_score": 1.5}, "min_score and max_second_ratio"),
                       ({"window_xy_per_metre": float("nan")}, "finite number"),
                       ({"top_squares": -1}, "top_squares must be an integer >= 0"),
                       ({"jump_half_width": 0}, "jump_half_width must be a positive integer"),
                       ({"jump_min_sds": -1.0}, "jump_min_sds must be a finite number >= 0"),
                       ({"jump_tries": -1}, "jump_tries must be an integer >= 0")):
        with pytest.raises(ValueError, match=words):
            ClosureConfig(**bad)


def test_scan_points_match_a_loop_over_the_scans():
    """The vectorised thinning against a slow reference: each scan's valid returns, evenly spread."""
    from jaxslam.laser import scan_points
    from jaxslam.laser import beam_endpoints

    log = twin_rooms_scenario(jax.random.key(0)).log
    ranges = np.array(log.ranges[:60])
    ranges[5, :100] = 100.0  # fewer valid returns than points
    ranges[6, :] = 100.0  # none
    for num in (90, 300):
        points, valid = scan_points(ranges, log.sensor, 15.0, num)
        for s in range(ranges.shape[0]):
            ok = (ranges[s] >= log.sensor.range_min) & (ranges[s] < min(float(log.sensor.range_max), 15.0))
            beams = np.nonzero(ok)[0]
            pick = beams[np.round(np.linspace(0, beams.size - 1, min(num, beams.size))).astype(int)] if beams.size else beams
            ends = np.asarray(beam_endpoints(jnp.zeros((1, 3)), jnp.asarray(ranges[s]), log.sensor)[0][0])
            assert valid[s].sum() == pick.size
            np.testing.assert_array_equal(points[s, :pick.size], ends[pick].astype(np.float32))


def test_graph_distances_chain_loops_against_a_slow_reference():
    """Shortest paths over the chain and any number of kept loops, against Floyd-Warshall on a
    dense matrix; a query reaching a submap through two loops is nearer than through one."""
    from jaxslam.graph.windows import graph_distances

    rng = np.random.default_rng(3)
    num = 60
    travelled = np.concatenate([[0.0], np.cumsum(rng.uniform(0.0, 1.0, num - 1))])
    travelled[10] = travelled[9]  # a step of no length (a turn on the spot) is still an edge
    # Loop A: node 30 reaches node 15; loop B: node 50 reaches node 35. Node 55 reaches node 5
    # only through both (55 -> 50 -> 35 -> 30 -> 15 -> 5).
    loop_query, loop_node = np.array([30, 50]), np.array([15, 35])
    dense = np.full((num, num), np.inf)
    np.fill_diagonal(dense, 0.0)
    for i in range(num - 1):
        dense[i, i + 1] = dense[i + 1, i] = travelled[i + 1] - travelled[i]
    for q, n in zip(loop_query, loop_node):
        dense[q, n] = dense[n, q] = 0.0
    for k in range(num):  # Floyd-Warshall
        dense = np.minimum(dense, dense[:, k:k + 1] + dense[k:k + 1, :])
    queries, submap_last = np.array([12, 40, 55, 59]), np.array([5, 9, 19, 39])
    got = graph_distances(travelled, queries, submap_last, loop_query, loop_node)
    np.testing.assert_allclose(got, dense[np.ix_(queries, submap_last)], atol=1e-9)
    through_both = (travelled[55] - travelled[50]) + (travelled[35] - travelled[30]) + (travelled[15] - travelled[5])
    assert got[2, 0] == pytest.approx(through_both)
    assert got[2, 0] < travelled[55] - travelled[5] - 10.0
    no_loops = graph_distances(travelled, queries, submap_last, np.array([], int), np.array([], int))
    np.testing.assert_allclose(no_loops, np.abs(travelled[queries][:, None] - travelled[submap_last][None]), atol=1e-9)


def test_acceptance_scores_only_the_beams_the_search_used(twin_rooms):
    """A beam as long as the search's range or longer ends where the submaps hold nothing; the
    acceptance's mean fit must not count it (FR-clinic's return: 29-52 % such beams took true
    matches from 0.6 to 0.4). Moving every long beam elsewhere leaves the score unchanged, and
    a shorter search range scores fewer beams."""
    import dataclasses as dc

    from jaxslam.graph.acceptance import Loops, Searched, accept
    from jaxslam.graph.loop_search import SearchResult
    from jaxslam.graph.submaps import build_submaps, submap_pose

    scenario, selection, truth, _ = twin_rooms
    log, params, config = scenario.log, default_params(), ClosureConfig(search_range=4.0)
    first = config.nodes_per_submap  # one submap is enough
    submaps = build_submaps(truth[:first], np.asarray(log.ranges[selection.indices[:first]]), log.sensor,
                            params.insertion, 0.05, SlamConfig().max_insert_range, config.nodes_per_submap,
                            config.sigma, config.levels)
    query = np.array([5, 12])  # two nodes of submap 0, matched at their true poses
    guess = np.stack([submap_pose(submaps, 0, truth[q], truth[0]) for q in query])
    one = np.ones(query.size, np.float32)
    searched = Searched(query, np.zeros(query.size, int), guess, one * 2.0, one * 0.5,
                        SearchResult(guess.astype(np.float32), one, 0 * one, 0 * one))
    likelihood = params.likelihood._replace(sigma=jnp.float32(config.sigma))
    ranges = np.array(log.ranges[selection.indices], np.float32)
    long = (ranges >= config.search_range) & (ranges < float(log.sensor.range_max))
    assert long[query].mean() > 0.1  # the test needs long beams
    moved = np.where(long, ranges + 2.5, ranges)  # elsewhere, still a return

    def score(r, cfg):
        return accept(submaps, searched, r, log.sensor, likelihood, truth, Loops.empty(), cfg).score

    np.testing.assert_allclose(score(moved, config), score(ranges, config), atol=1e-6)
    assert np.all(score(ranges, config) > 0.8)  # the true pose fits its own submap's short beams
    wide = dc.replace(config, search_range=15.0)
    assert not np.allclose(score(moved, wide), score(ranges, wide), atol=1e-3)  # counted, they move it
