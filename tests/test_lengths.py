"""The chain's step lengths (jaxslam.graph.lengths): each scan's structure, and the graph that weighs
a step's translation between what the scan pins and the odometry's."""

import numpy as np
import pytest

from jaxslam.config import default_params
from jaxslam.geometry import between_np, chain_np
from jaxslam.graph import pose_graph
from jaxslam.graph.drift import sequential_edges
from jaxslam.graph.lengths import scan_structure, weighed_steps
from jaxslam.graph.pose_graph import ODOMETRY, SEQUENTIAL, PoseGraph
from jaxslam.laser import make_sensor, uniform_beams

BEAMS = np.asarray(uniform_beams(361))


def _ranges_to_walls(walls: list[tuple[float, float, float]]) -> np.ndarray:
    """(1, 361) ranges from the origin to the nearest of the lines ``a x + b y = c`` (inf: none)."""
    direction = np.stack([np.cos(BEAMS), np.sin(BEAMS)], -1)
    ranges = np.full(BEAMS.size, np.inf)
    for a, b, c in walls:
        along = direction @ np.array([a, b])
        hit = np.where(np.abs(along) > 1e-9, c / np.where(np.abs(along) > 1e-9, along, 1.0), np.inf)
        ranges = np.minimum(ranges, np.where(hit > 0, hit, np.inf))
    return np.minimum(ranges, 80.0)[None]


def test_a_corridor_pins_only_across_it_and_a_room_every_way():
    sensor = make_sensor(BEAMS, range_max=80.0)
    corridor = scan_structure(_ranges_to_walls([(0, 1, 1.0), (0, 1, -1.0)]), sensor, 15.0)[0]
    room = scan_structure(_ranges_to_walls([(1, 0, 2.0), (0, 1, 2.0), (0, 1, -2.0)]), sensor, 15.0)[0]
    nothing = scan_structure(np.full((1, BEAMS.size), 80.0), sensor, 15.0)[0]
    np.testing.assert_allclose(corridor, [[0, 0], [0, 1]], atol=1e-6)  # walls along x: their normals along y
    assert np.trace(room) == pytest.approx(1.0)
    assert 0.3 < np.linalg.eigvalsh(room)[0]  # the front wall's normals and the sides' about halve it
    np.testing.assert_array_equal(nothing, np.zeros((2, 2)))


def _steps(seed: int, num: int = 30, turning: bool = True):
    """A chain (wandering, or straight): the filter's steps 2 % long and 2 cm off sideways, the
    odometry's exact in length and 3 cm off sideways."""
    rng = np.random.default_rng(seed)
    true_steps = np.zeros((num, 3))
    true_steps[1:, 0] = rng.uniform(0.3, 0.7, num - 1)
    true_steps[1:, 2] = rng.normal(0, 0.1, num - 1) * turning
    filter_steps = true_steps.copy()
    filter_steps[1:, 0] *= 1.02
    filter_steps[1:, 1] += rng.normal(0, 0.02, num - 1)
    odometry = true_steps.copy()
    odometry[1:, 1] += rng.normal(0, 0.03, num - 1)
    return filter_steps, odometry


def _fused_reference(filter_steps, odometry, structure, motion, resolution):
    """Each step's translation in a chain without loops (slow NumPy): the information-weighted mean
    of the chain's and the odometry's, the heading the chain's."""
    from jaxslam.motion import noise_std

    fused = filter_steps.copy()
    for i in range(1, filter_steps.shape[0]):
        turn = np.array([[np.cos(filter_steps[i, 2]), -np.sin(filter_steps[i, 2])],
                         [np.sin(filter_steps[i, 2]), np.cos(filter_steps[i, 2])]])
        chain_information = turn @ structure[i] @ turn.T * 4 / resolution**2 + 1e-6 * np.eye(2)
        odometry_information = np.diag(1 / np.asarray(noise_std(odometry[i], motion), np.float64)[:2] ** 2)
        fused[i, :2] = np.linalg.solve(chain_information + odometry_information,
                                       chain_information @ filter_steps[i, :2] + odometry_information @ odometry[i, :2])
    return fused


def _solved_steps(filter_steps, odometry, structure):
    """The chain's steps after the graph of :func:`weighed_steps` (no loops), and the reference's."""
    motion, resolution = default_params().motion, 0.05
    chain = chain_np(np.zeros(3), filter_steps[1:])
    edges = weighed_steps(sequential_edges(chain, odometry, motion), structure, odometry, motion, resolution)
    steps = chain.shape[0] - 1
    assert np.all(edges.kind[:steps] == SEQUENTIAL) and np.all(edges.kind[steps:] == ODOMETRY)
    assert np.all(edges.information[edges.kind == ODOMETRY, 2, :] == 0)  # the heading is the chain's alone
    poses = pose_graph.optimize(PoseGraph(chain, edges), loop_phi=None, max_iterations=50, tolerance=1e-12).poses
    return between_np(poses[:-1], poses[1:]), _fused_reference(filter_steps, odometry, structure, motion, resolution)[1:]


@pytest.mark.parametrize("seed", [0, 1])
def test_the_graph_weighs_each_steps_translation_by_its_scan_against_the_odometry(seed):
    """A turning chain whose scans see walls of every share and angle: the solved steps are the
    information-weighted means the slow reference computes, frame by frame."""
    filter_steps, odometry = _steps(seed)
    rng = np.random.default_rng(seed + 10)
    structure = np.zeros((filter_steps.shape[0], 2, 2))
    for i, (share, angle) in enumerate(zip(rng.uniform(0, 0.5, len(structure)), rng.uniform(0, np.pi, len(structure)))):
        axis = np.array([np.cos(angle), np.sin(angle)])
        structure[i] = share * np.eye(2) + (1 - 2 * share) * np.outer(axis, axis)
    solved, reference = _solved_steps(filter_steps, odometry, structure)
    np.testing.assert_allclose(solved, reference, atol=1e-6)
    assert np.abs(solved - filter_steps[1:]).max() > 1e-3  # the odometry moved them


def test_along_a_corridor_the_odometrys_length_holds_and_in_a_room_the_chains():
    """FR-clinic's case: the filter's steps 2 % long where its scans slide along the walls."""
    filter_steps, odometry = _steps(2, turning=False)
    corridor = np.broadcast_to(np.diag([0.0, 1.0]), (filter_steps.shape[0], 2, 2))  # walls along x
    room = np.broadcast_to(np.eye(2) / 2, (filter_steps.shape[0], 2, 2))
    along_corridor, _ = _solved_steps(filter_steps, odometry, corridor)
    in_room, _ = _solved_steps(filter_steps, odometry, room)
    assert np.abs(along_corridor[:, 0] / odometry[1:, 0] - 1).max() < 1e-3
    # In a room the scan pins the length to 2.5 cm a step against the odometry's 4-8 cm: the chain's
    # 2 % stretch keeps most of itself.
    kept = (in_room[:, 0] / odometry[1:, 0] - 1) / 0.02
    assert np.all((kept > 0.5) & (kept < 0.95))


def test_weighed_steps_refuses_a_cell_size_of_zero():
    filter_steps, odometry = _steps(0, 5)
    chain = chain_np(np.zeros(3), filter_steps[1:])
    motion = default_params().motion
    with pytest.raises(ValueError, match="resolution"):
        weighed_steps(sequential_edges(chain, odometry, motion), np.zeros((5, 2, 2)), odometry, motion, 0.0)
    with pytest.raises(ValueError, match="structure"):
        weighed_steps(sequential_edges(chain, odometry, motion), np.zeros((4, 2, 2)), odometry, motion, 0.05)
