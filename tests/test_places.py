"""Loop candidates by appearance (jaxslam.graph.places): the scans' polar signatures against slow
references, the heading a shift says, and the look-alike refusal. The closure with them, on the
twin rooms, is in test_graph.py."""

from __future__ import annotations

import numpy as np

from jaxslam.graph import ClosureConfig
from jaxslam.graph.acceptance import Loops
from jaxslam.graph.places import SECTORS, context_similarity, refuse_look_alikes, scan_contexts


def _room_points(rng, turn=0.0, count=180):
    """Points of a scan in an irregular room seen from the origin turned by ``turn`` (rad): the
    room's walls at random ranges per bearing, in the turned robot's frame."""
    bearing = np.linspace(-np.pi, np.pi, count, endpoint=False)
    ranges = 2.0 + 8.0 * rng.random(count)
    world = np.stack([ranges * np.cos(bearing), ranges * np.sin(bearing)], -1)
    c, s = np.cos(-turn), np.sin(-turn)
    return (world @ np.array([[c, s], [-s, c]])).astype(np.float32)


def test_scan_contexts_match_a_loop_over_the_points():
    rng = np.random.default_rng(0)
    points = rng.uniform(-16, 16, (3, 50, 2)).astype(np.float32)
    valid = rng.random((3, 50)) < 0.8
    contexts = scan_contexts(points, valid, 15.0, rings=5, sectors=12)
    expected = np.zeros((3, 5, 12), np.float32)
    for scan in range(3):
        for (x, y), ok in zip(points[scan], valid[scan]):
            radius = np.hypot(x, y)
            if ok and radius < 15.0:
                sector = int((np.arctan2(y, x) + np.pi) / (2 * np.pi) * 12) % 12
                expected[scan, min(int(radius / 3.0), 4), sector] = 1.0
    np.testing.assert_array_equal(contexts, expected)


def test_context_similarity_is_the_best_shift_and_says_the_heading_within_the_turn_allowed():
    """Against np.roll over every shift; a room seen turned by 0.5 rad is found turned by 0.5
    (within half a sector) and alike; limited to 0.3 rad of no turn, that shift is not taken."""
    rng = np.random.default_rng(1)
    query = (rng.random((4, SECTORS)) < 0.3).astype(np.float32)
    others = (rng.random((5, 4, SECTORS)) < 0.3).astype(np.float32)
    similarity, heading = context_similarity(query, others, np.zeros(5), np.full(5, np.pi))
    for k in range(5):
        overlaps = [np.sum(query * np.roll(others[k], -s, axis=1)) for s in range(SECTORS)]
        norm = np.sqrt(query.sum() * others[k].sum())
        assert np.isclose(similarity[k], max(overlaps) / norm, atol=1e-5)

    points = _room_points(np.random.default_rng(2))
    turned = _room_points(np.random.default_rng(2), turn=0.5)
    valid = np.ones(points.shape[0], bool)
    node, query = scan_contexts(np.stack([points, turned]), np.stack([valid, valid]), 15.0)
    similarity, heading = context_similarity(query, node[None], np.zeros(1), np.full(1, np.pi))
    assert similarity[0] > 0.8 and abs(heading[0] - 0.5) <= np.pi / SECTORS + 1e-6
    limited, _ = context_similarity(query, node[None], np.zeros(1), np.full(1, 0.3))
    assert limited[0] < 0.6 * similarity[0]


def _loops(query, submap, measurement, score, refused, appearance=(True, False)):
    count = len(query)
    return Loops(np.array(query), np.array(submap), np.array(measurement, float), np.tile(np.eye(3), (count, 1, 1)),
                 np.array(score, float), np.zeros(count), np.ones(count, bool), np.array(refused, object),
                 np.full(count, np.nan), np.array(appearance, bool))


def test_a_query_that_matches_two_places_as_well_is_refused_by_appearance():
    """Row 0 is found by appearance; row 1, the same query's match of another submap, puts the
    query 5 m away at 0.95 of its score: refused. Where row 1 puts it at the same place, scores
    under 0.9 of it, or fell under the score test, row 0 stays."""
    config = ClosureConfig()
    origins = np.array([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    elsewhere = _loops([7, 7], [0, 2], [[1.0, 0.0, 0.0], [-34.0, 0.0, 0.0]], [0.8, 0.76], ["", "consistency"])
    assert list(refuse_look_alikes(elsewhere, origins, config).refused) == ["ambiguous", "consistency"]
    same_place = elsewhere._replace(measurement=np.array([[1.0, 0.0, 0.0], [-39.0, 0.0, 0.0]]))
    assert refuse_look_alikes(same_place, origins, config).refused[0] == ""
    weaker = elsewhere._replace(score=np.array([0.8, 0.7]))
    assert refuse_look_alikes(weaker, origins, config).refused[0] == ""
    unmatched = elsewhere._replace(refused=np.array(["", "score"], object))
    assert refuse_look_alikes(unmatched, origins, config).refused[0] == ""
    # A windowed loop is never judged here, however alike another place.
    assert refuse_look_alikes(elsewhere._replace(appearance=np.array([False, True])), origins, config).refused[0] == ""
