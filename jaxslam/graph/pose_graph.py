"""A pose graph over SE(2) and its optimisation: :class:`PoseGraph`, :func:`optimize`.

Nodes are robot poses (x, y, theta); an edge (first, second, measurement, information) says
that node ``second`` seen from node ``first`` is at ``measurement`` (the relative pose
``between(x_first, x_second)``), with a Gaussian of that information (inverse covariance). The
optimiser is sparse Levenberg-Marquardt: each iteration builds the Gauss-Newton system from the
edges' Jacobians (NumPy, vectorised over edges) and solves it with ``scipy.sparse``'s sparse LU
(SuperLU; the choice against GTSAM and CHOLMOD: docs/design.md, "Loop closure"). Loop edges go through Dynamic Covariance Scaling (Agarwal et al. 2013), a robust
kernel that scales a loop's information down by ``s^2``, ``s = min(1, 2 phi / (phi + chi2))``,
so that one false loop cannot fold the map. The first node is held fixed (the gauge).

Everything here is host code: the graph is built once per run from the filter's output, and
its solve is a sparse factorisation, which XLA does not offer on the CPU.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from jaxslam.geometry import between_jacobians_np, between_np, rotation_np, wrap_angle_np

SEQUENTIAL, LOOP, ODOMETRY = 0, 1, 2
"""Edge kinds: between consecutive nodes (the filter's relative poses), loop closures, and the
odometry's translation between consecutive nodes (:mod:`jaxslam.graph.lengths`)."""


class Edges(NamedTuple):
    """E edges of a pose graph (NumPy arrays)."""

    first: np.ndarray
    """(E,) int: the node each measurement is taken from."""
    second: np.ndarray
    """(E,) int: the node measured."""
    measurement: np.ndarray
    """(E, 3) float64: ``second``'s pose in ``first``'s frame (m, m, rad)."""
    information: np.ndarray
    """(E, 3, 3) float64: the measurement's inverse covariance (1/m^2, 1/(m rad), 1/rad^2)."""
    kind: np.ndarray
    """(E,) int: :data:`SEQUENTIAL`, :data:`LOOP` or :data:`ODOMETRY`."""

    @property
    def count(self) -> int:
        return int(self.first.shape[0])


def concat_edges(*edges: Edges) -> Edges:
    """Edges of several sets, in order."""
    return Edges(*(np.concatenate(parts) for parts in zip(*edges)))


class PoseGraph(NamedTuple):
    """Nodes and edges (NumPy)."""

    poses: np.ndarray
    """(S, 3) float64 node poses (m, m, rad): the initial guess, or the optimised poses."""
    edges: Edges
    """The constraints between them."""


class OptimizeResult(NamedTuple):
    """What :func:`optimize` returns."""

    poses: np.ndarray
    """(S, 3) float64 optimised node poses; node 0 as given."""
    chi2: np.ndarray
    """(E,) each edge's squared Mahalanobis error at ``poses`` (unscaled information)."""
    loop_scales: np.ndarray
    """(E,) the robust kernel's scale s of each edge's information (s^2 applied; 1 for
    sequential edges and where the kernel is off)."""
    iterations: int
    """Levenberg-Marquardt iterations taken."""
    cost: float
    """Final robust cost: sum of s^2 chi2 (Dynamic Covariance Scaling's objective up to constants)."""


def edge_errors(poses: np.ndarray, edges: Edges) -> np.ndarray:
    """(E, 3) error of each edge: the measured pose's offset from the predicted one, in the
    measurement's frame, ``between(measurement, between(x_first, x_second))``."""
    predicted = between_np(poses[edges.first], poses[edges.second])
    return between_np(edges.measurement, predicted)


def chi2(poses: np.ndarray, edges: Edges) -> np.ndarray:
    """(E,) squared Mahalanobis error of each edge at ``poses``."""
    e = edge_errors(poses, edges)
    return np.einsum("ei,eij,ej->e", e, edges.information, e)


def _jacobians(poses: np.ndarray, edges: Edges) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The errors (E, 3) and their Jacobians (E, 3, 3) with respect to the first and second
    node's (x, y, theta)."""
    a, b, z = poses[edges.first], poses[edges.second], edges.measurement
    # between(a, b) = (R_a^T (t_b - t_a), theta_b - theta_a) and its Jacobians; the error turns its
    # translation's residual into the measurement's frame by R_z^T.
    local = between_np(a, b)[:, :2]
    jac_a, jac_b = between_jacobians_np(a, b)
    rzt = rotation_np(z[:, 2]).swapaxes(-1, -2)  # R_z^T (E, 2, 2)
    error = np.concatenate([np.einsum("eij,ej->ei", rzt, local - z[:, :2]),
                            wrap_angle_np(b[:, 2] - a[:, 2] - z[:, 2])[:, None]], axis=-1)
    jac_a[:, :2] = np.einsum("eij,ejk->eik", rzt, jac_a[:, :2])
    jac_b[:, :2] = np.einsum("eij,ejk->eik", rzt, jac_b[:, :2])
    return error, jac_a, jac_b


def dcs_scales(chi2_values: np.ndarray, kind: np.ndarray, phi: float | None) -> np.ndarray:
    """Dynamic Covariance Scaling's s = min(1, 2 phi / (phi + chi2)) for loop edges (1 for the
    others, and for every edge where ``phi`` is None)."""
    if phi is None:
        return np.ones_like(chi2_values)
    s = np.minimum(1.0, 2.0 * phi / (phi + chi2_values))
    return np.where(kind == LOOP, s, 1.0)


class _Sparsity(NamedTuple):
    """The Gauss-Newton matrix's CSC structure over nodes 1..S-1, fixed while the edges are:
    built once per :func:`optimize` so that each iteration only sums the blocks' values into
    it (``np.bincount``) instead of sorting a COO matrix again."""

    entry: np.ndarray
    """(K,) int: the block entries (of 4 E 9, the blocks' order) off node 0's rows and columns."""
    slot: np.ndarray
    """(K,) int: each such entry's index into the CSC data."""
    indices: np.ndarray
    """CSC row indices."""
    indptr: np.ndarray
    """CSC column pointers."""
    size: int
    """Unknowns: 3 (S - 1)."""


def _sparsity(edges: Edges, num_nodes: int) -> _Sparsity:
    """The structure of the blocks (first, first), (first, second), (second, first), (second,
    second) of every edge, in that order, each 3 x 3 row-major."""
    size = 3 * (num_nodes - 1)
    rows, cols = [], []
    for i_nodes, k_nodes in ((edges.first, edges.first), (edges.first, edges.second),
                             (edges.second, edges.first), (edges.second, edges.second)):
        rows.append(np.broadcast_to((3 * i_nodes - 3)[:, None, None] + np.arange(3)[None, :, None], (i_nodes.size, 3, 3)).ravel())
        cols.append(np.broadcast_to((3 * k_nodes - 3)[:, None, None] + np.arange(3)[None, None, :], (k_nodes.size, 3, 3)).ravel())
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    entry = np.nonzero((rows >= 0) & (cols >= 0))[0]  # node 0 is the gauge: its rows and columns are dropped
    # np.unique sorts, so the distinct entries come column-major: the CSC order.
    entries, slot = np.unique(cols[entry] * size + rows[entry], return_inverse=True)
    indptr = np.searchsorted(entries // size, np.arange(size + 1)).astype(np.int32)
    return _Sparsity(entry, slot.ravel(), (entries % size).astype(np.int32), indptr, size)


def _normal_equations(poses, edges, weights, sparsity: _Sparsity):
    """The Gauss-Newton system H dx = -g over nodes 1..S-1 (node 0 fixed) with each edge's
    information times ``weights`` (E,)."""
    num = poses.shape[0]
    error, ja, jb = _jacobians(poses, edges)
    omega = edges.information * weights[:, None, None]
    # Batched 3 x 3 products (matmul, not a three-operand einsum: that one is not contracted
    # pairwise and was half the closure's solve time on Intel).
    ja_omega = np.swapaxes(ja, 1, 2) @ omega  # J_a^T Omega (E, 3, 3)
    jb_omega = np.swapaxes(jb, 1, 2) @ omega
    blocks = np.concatenate([(ja_omega @ ja).ravel(), (ja_omega @ jb).ravel(),
                             (jb_omega @ ja).ravel(), (jb_omega @ jb).ravel()])
    data = np.bincount(sparsity.slot, blocks[sparsity.entry], minlength=sparsity.indices.size)
    h = scipy.sparse.csc_matrix((data, sparsity.indices, sparsity.indptr), shape=(sparsity.size, sparsity.size))
    ga = (ja_omega @ error[..., None])[..., 0]
    gb = (jb_omega @ error[..., None])[..., 0]
    g = np.stack([np.bincount(edges.first, ga[:, k], num) + np.bincount(edges.second, gb[:, k], num)
                  for k in range(3)], axis=-1)
    return h, g.ravel()[3:], error


def optimize(graph: PoseGraph, loop_phi: float | None = 1.0, max_iterations: int = 30, tolerance: float = 1e-6,
             initial_damping: float = 1e-4) -> OptimizeResult:
    """Levenberg-Marquardt on the pose graph, node 0 held fixed.

    Args:
        graph: the initial poses (S, 3) and the edges.
        loop_phi: Dynamic Covariance Scaling's phi for loop edges (in chi2 units; None: plain
            least squares). Small phi trusts loops less.
        max_iterations: iterations at most.
        tolerance: stop when the cost falls by less than this fraction.
        initial_damping: the first damping lambda: each step solves (H + lambda diag(H)) dx = -g
            (Marquardt's scaling; lambda falls by 3 after a step that lowers the cost, rises by 10
            until one does).

    Returns:
        :class:`OptimizeResult`.
    """
    poses = np.array(graph.poses, dtype=np.float64)
    edges = graph.edges
    if poses.ndim != 2 or poses.shape[1] != 3 or poses.shape[0] < 2:
        raise ValueError(f"optimize: poses must be (S, 3) with S >= 2, got {poses.shape}")
    for name, idx in (("first", edges.first), ("second", edges.second)):
        if idx.size and (idx.min() < 0 or idx.max() >= poses.shape[0]):
            raise ValueError(f"optimize: edge {name} indices must lie in [0, {poses.shape[0]})")

    def robust_cost(p):
        c = chi2(p, edges)
        s = dcs_scales(c, edges.kind, loop_phi)
        return float(np.sum(s**2 * c)), s

    cost, scales = robust_cost(poses)
    sparsity = _sparsity(edges, poses.shape[0])
    damping = initial_damping
    it = 0
    for it in range(1, max_iterations + 1):
        h, g, _ = _normal_equations(poses, edges, scales**2, sparsity)
        diag = h.diagonal()
        improved = False
        for _ in range(10):
            lhs = h + scipy.sparse.diags(damping * np.maximum(diag, 1e-9))
            step = scipy.sparse.linalg.spsolve(lhs.tocsc(), -g)
            trial = poses.copy()
            trial[1:] += step.reshape(-1, 3)
            trial[:, 2] = wrap_angle_np(trial[:, 2])
            trial_cost, trial_scales = robust_cost(trial)
            if np.isfinite(trial_cost) and trial_cost <= cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break
        damping = max(damping / 3.0, 1e-12)
        done = cost - trial_cost <= tolerance * max(cost, 1e-12)
        poses, cost, scales = trial, trial_cost, trial_scales
        if done:
            break
    return OptimizeResult(poses, chi2(poses, edges), scales, it, cost)
