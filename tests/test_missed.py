"""The returns a closure missed (jaxslam.graph.missed): which relations count, how they group,
and what the graph's candidates say of each."""

import numpy as np
import pytest

from jaxslam.geometry import between_np
from jaxslam.graph.missed import missed_returns
from jaxslam.io.relations import Relations


def _lap_path(num_nodes=200, spacing=0.5):
    """Nodes every ``spacing`` m round a 10 x 15 m rectangle (50 m a lap), two laps: node i and
    node i + 100 are the same place."""
    s = np.arange(num_nodes) * spacing % 50.0
    corners = np.array([[0, 0], [15, 0], [15, 10], [0, 10], [0, 0]], float)
    lengths = np.array([15, 10, 15, 10], float)
    side = np.minimum(np.searchsorted(np.cumsum(lengths), s, side="right"), 3)
    along = s - np.concatenate([[0.0], np.cumsum(lengths)])[side]
    direction = (corners[side + 1] - corners[side]) / lengths[side, None]
    xy = corners[side] + along[:, None] * direction
    return np.column_stack([xy, np.arctan2(direction[:, 1], direction[:, 0])])


def _shifted(poses, nodes, dx):
    out = poses.copy()
    out[nodes, 0] += dx
    return out


@pytest.fixture()
def case():
    """The true laps; relations between the laps (node i to i + 100) and between neighbours;
    a closed path that is 1 m off on nodes 150-170, 0.5 m off on 110-115 and 0.4 m off on
    194-199 (each more than 20 nodes from the next); the filter's 2 m off on 150-170; submaps of 20 nodes; candidate loops."""
    truth = _lap_path()
    times = 10.0 + np.arange(truth.shape[0]) * 2.0
    pairs = np.array([(i, i + 100) for i in range(100)] + [(i, i + 1) for i in range(199)])
    relations = Relations(times[pairs[:, 0]], times[pairs[:, 1]], between_np(truth[pairs[:, 0]], truth[pairs[:, 1]]))
    closed = _shifted(_shifted(_shifted(truth, np.arange(150, 171), 1.0), np.arange(110, 116), 0.5),
                      np.arange(194, 200), 0.4)
    filtered = _shifted(truth, np.arange(150, 171), 2.0)
    graph = {"node_scans": np.arange(200), "poses": truth, "submap_first_node": np.arange(0, 200, 20),
             # query 155 into submap 3 (nodes 60-79, over the earlier nodes 50-70), ambiguous; 160 into
             # submap 2, under the score; 158 kept into submap 8 (elsewhere); 197 kept into submap 4.
             "loop_query": np.array([155, 160, 158, 197]), "loop_submap": np.array([3, 2, 8, 4]),
             "loop_refused": np.array(["ambiguous", "score", "", ""]),
             "loop_score": np.array([0.6, 0.4, 0.7, 0.65]), "loop_second_ratio": np.array([0.95, 0.5, 0.2, 0.3])}
    return graph, times, closed, filtered, relations


def test_missed_returns_group_the_relations_and_name_each_cause(case):
    graph, times, closed, filtered, relations = case
    missed = missed_returns(graph, times, closed, filtered, relations)
    # Three returns, the summed error largest first; the neighbours' relations (0.5 m of path) are
    # off at the shifted stretches' ends but span no loop.
    assert [m["later_nodes"] for m in missed] == [[150, 170], [110, 115], [194, 199]]
    first, second, third = missed
    assert first["earlier_nodes"] == [50, 70] and first["relations"] == 21
    np.testing.assert_allclose([first["closed_error_m"], first["filter_error_m"], first["path_between_m"]],
                               [1.0, 2.0, 50.0], atol=1e-9)
    np.testing.assert_allclose(first["later_elapsed_s"], [300.0, 340.0])
    assert first["submaps"] == [1, 4]  # those over nodes 50-70 (2 and 3), and one either side
    assert first["candidates"] == {"ambiguous": 1, "score": 1}
    assert first["best"] == {"query": 155, "submap": 3, "score": 0.6, "second_ratio": 0.95, "refused": "ambiguous"}
    assert first["kept_elsewhere"] == 1 and first["cause"] == "refused: ambiguous"
    assert second["earlier_nodes"] == [10, 15] and second["relations"] == 6
    assert second["candidates"] == {} and second["best"] is None and second["cause"] == "no candidate"
    np.testing.assert_allclose(second["closed_error_m"], 0.5, atol=1e-9)
    assert third["candidates"] == {"kept": 1} and third["cause"] == "kept, yet off"


def test_missed_returns_keep_to_loops_and_to_the_error_threshold(case):
    graph, times, closed, filtered, relations = case
    # Under the threshold the 0.4 and 0.5 m returns are not missed; a path shorter than one lap
    # between the laps' relations' nodes (50 m) leaves none spanning a loop.
    assert [m["later_nodes"] for m in missed_returns(graph, times, closed, filtered, relations, min_error=0.6)] \
        == [[150, 170]]
    assert missed_returns(graph, times, closed, filtered, relations, min_path=60.0) == []
    # A gap of five nodes in the stretch: one return, unless gap_nodes is under it.
    gapped = _shifted(closed, np.arange(158, 163), -1.0)
    assert missed_returns(graph, times, gapped, filtered, relations)[0]["later_nodes"] == [150, 170]
    assert [m["later_nodes"] for m in missed_returns(graph, times, gapped, filtered, relations, gap_nodes=5)
            ][:2] == [[150, 157], [163, 170]]
    truth = _lap_path()
    assert missed_returns(graph, times, truth, truth, relations) == []


def test_missed_returns_refuse_a_graph_of_another_run(case):
    graph, times, closed, filtered, relations = case
    with pytest.raises(ValueError, match="is graph.npz this run's"):
        missed_returns(dict(graph, node_scans=np.arange(300)), times, closed, filtered, relations)
    with pytest.raises(ValueError, match="do not match their 200 timestamps"):
        missed_returns(graph, times, closed[:-1], filtered, relations)


def test_missed_returns_tell_a_search_that_did_not_look_from_one_that_did_not_reach(case):
    graph, times, closed, filtered, relations = case
    truth = _lap_path()
    # The windowed search's record: query 111 against submap 0 (over the earlier nodes 10-15),
    # its window 0.3 m from the true pose; 112 against submap 1, 3 m from it; 153 against
    # submap 9 (not over the earlier nodes of its return); nothing from 194-199.
    guess = between_np(truth[[0, 60, 20]], truth[[111, 153, 112]]) + np.array([[0.3, 0, 0], [0, 0, 0], [3.0, 0, 0]])
    record = {"searched_query": np.array([111, 153, 112]), "searched_submap": np.array([0, 9, 1]), "searched_guess": guess,
              "searched_score": np.array([0.2, 0.3, 0.1]), "searched_half_xy": np.array([1.5, 2.0, 2.5]),
              "searched_half_theta": np.full(3, 0.5), "searched_chain_pass": np.ones(3, int)}
    first, second, third = missed_returns(dict(graph, **record), times, closed, filtered, relations)
    assert second["cause"] == "no candidate"  # a window held the pose, and nothing scored there
    assert second["searched"] == {"pairs": 2, "best_score": 0.2, "window_m": [1.5, 2.5],
                                  "guess_off_m": pytest.approx([0.3, 1.65]), "reached": 1, "pairs_elsewhere": 0}
    assert first["searched"]["pairs"] == 0 and first["searched"]["pairs_elsewhere"] == 1
    assert first["cause"] == "refused: ambiguous"  # its candidates say more than its record
    wide_of_it = {**record, "searched_half_xy": np.array([0.25, 2.0, 2.5])}
    assert missed_returns(dict(graph, **wide_of_it), times, closed, filtered, relations)[1]["cause"] == "out of the window"
    turned = {**record, "searched_half_theta": np.array([0.0, 0.5, 0.5]),
              "searched_guess": guess + np.array([0.0, 0.0, 0.1])}
    assert missed_returns(dict(graph, **turned), times, closed, filtered, relations)[1]["searched"]["reached"] == 0
    # The first return's ambiguous candidate came from a window that missed the relations' pose
    # by 2 m: the window is the cause, and the refusal was right.
    missed_it = {**record, "searched_query": np.array([155, 153, 112]), "searched_submap": np.array([3, 9, 1]),
                 "searched_guess": np.concatenate([between_np(truth[[60]], truth[[155]]) + [2.0, 0, 0], guess[1:]])}
    assert missed_returns(dict(graph, **missed_it), times, closed, filtered, relations)[0]["cause"] == "out of the window"
    elsewhere = {**record, "searched_query": np.array([1, 2, 3]), "searched_submap": np.array([0, 0, 0])}
    assert missed_returns(dict(graph, **elsewhere), times, closed, filtered, relations)[1]["cause"] == "not searched"
    assert missed_returns(graph, times, closed, filtered, relations)[1]["searched"] is None
    # Relations the other way round (t1 the later scan) say the same; a lap and a step apart, so
    # that their motion is no identity.
    a, b = np.arange(99), np.arange(99) + 101
    onwards = Relations(times[a], times[b], between_np(truth[a], truth[b]))
    backwards = Relations(times[b], times[a], between_np(truth[b], truth[a]))
    reached = missed_returns(dict(graph, **record), times, closed, filtered, onwards)[1]
    assert reached["later_nodes"] == [110, 115] and reached["searched"]["guess_off_m"] == pytest.approx([0.3, 1.65])
    assert missed_returns(dict(graph, **record), times, closed, filtered, backwards)[1] == reached
