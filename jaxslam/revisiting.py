"""Revisiting accuracy (RA) of Grzonka et al.: how well a filter closes the loop at a checkpoint.

The robot passes over a checkpoint X at the start and again at the end of a run. Every
SLAM particle's path contains an estimate of both passages; a filter that kept the right
hypothesis puts the two estimates in the same relation as the true poses (the same place,
when the robot truly is back at X). For each particle i with normalised weight w_i,

    e_i = || t_i || + lambda * | theta_i |,   (t_i, theta_i) = between(true_rel, est_rel_i)

where ``est_rel_i = between(x_i[first], x_i[last])`` is the particle's relative pose
between the first and last passage and ``true_rel`` the same from ground truth; then

    RA = sum_i w_i e_i      (m, with lambda in m/rad).

The paper counts a run as a success when RA < 0.2. Self-contained (NumPy); planned to
move into :mod:`jaxslam.metrics`.
"""

from __future__ import annotations

import numpy as np

from jaxslam.geometry import between


def _wrap(theta):
    return np.pi - np.mod(np.pi - theta, 2.0 * np.pi)


def checkpoint_passages(true_poses: np.ndarray, checkpoint, radius: float) -> np.ndarray:
    """Indices of the closest approaches of a path to ``checkpoint``.

    A passage is a maximal run of consecutive poses within ``radius`` metres of the
    checkpoint; each contributes the index of its closest pose (the first on a tie).

    Args:
      true_poses: (T, 3) or (T, 2) ground-truth path (m).
      checkpoint: (2,) position of X (m).
      radius: the disc (m) that counts as passing over X.

    Returns:
      (P,) int64 increasing indices (empty when the path never comes within ``radius``).
    """
    xy = np.asarray(true_poses, np.float64)[:, :2]
    dist = np.hypot(*(xy - np.asarray(checkpoint, np.float64)[None, :]).T)
    inside = np.concatenate([[0], (dist <= radius).astype(np.int8), [0]])
    edges = np.diff(inside)
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    return np.array([a + int(np.argmin(dist[a:b])) for a, b in zip(starts, stops)], dtype=np.int64)


def passage_errors(
    paths: np.ndarray,
    first: int,
    last: int,
    true_first,
    true_last,
    rotation_weight: float = 1.0,
) -> np.ndarray:
    """Per-particle error e_i (m) of the relative pose between two passages.

    Args:
      paths: (N, S, 3) every particle's path, indexed like ``first`` and ``last``.
      first, last: indices into the paths of the first and last passage.
      true_first, true_last: (3,) the true poses there.
      rotation_weight: lambda (m/rad) weighting the rotational error.

    Returns:
      (N,) ||translation error|| + lambda * |rotation error|.
    """
    paths = np.asarray(paths, np.float64)
    est = np.asarray(between(paths[:, first], paths[:, last]), np.float64)
    true = np.asarray(between(np.asarray(true_first, np.float64), np.asarray(true_last, np.float64)), np.float64)
    diff = np.asarray(between(np.broadcast_to(true, est.shape), est), np.float64)
    return np.hypot(diff[:, 0], diff[:, 1]) + rotation_weight * np.abs(_wrap(diff[:, 2]))


def revisiting_accuracy(
    paths: np.ndarray,
    log_weights: np.ndarray,
    first: int,
    last: int,
    true_first,
    true_last,
    rotation_weight: float = 1.0,
) -> float:
    """RA = sum_i w_i e_i: the weighted mean over particles of :func:`passage_errors`.

    Args:
      paths: (N, S, 3) each final particle's path (its ancestry).
      log_weights: (N,) log-weights (any normalisation; -inf allowed, not all).
      first, last: path indices of the first and last passage over X.
      true_first, true_last: (3,) ground-truth poses at those passages.
      rotation_weight: lambda (m/rad).

    Returns:
      RA in metres (lower is better; the paper's success threshold is 0.2).
    """
    log_w = np.asarray(log_weights, np.float64)
    if not np.any(np.isfinite(log_w)):
        raise ValueError("revisiting_accuracy: every particle has weight zero")
    w = np.exp(log_w - np.max(log_w))
    w /= w.sum()
    errors = passage_errors(paths, first, last, true_first, true_last, rotation_weight)
    return float(np.sum(w * errors))


def particle_paths(proposed_poses: np.ndarray, ancestors: np.ndarray, initial_pose) -> np.ndarray:
    """Every final particle's path (N, S, 3) from a filter's per-step proposed poses and
    ancestors (``SlamInfo.proposed_poses`` (S-1, N, 3), ``SlamInfo.ancestors`` (S-1, N)),
    with the shared initial pose prepended."""
    proposed = np.asarray(proposed_poses)
    anc = np.asarray(ancestors)
    steps, n = anc.shape
    paths = np.empty((n, steps + 1, 3), proposed.dtype)
    paths[:, 0] = np.asarray(initial_pose)
    idx = np.arange(n)
    for t in range(steps - 1, -1, -1):
        idx = anc[t, idx]
        paths[:, t + 1] = proposed[t, idx]
    return paths
