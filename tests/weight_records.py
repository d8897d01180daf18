"""A filter's ``steps.npz`` record for given log-weight increments, for the tests of the
diagnosis of lost histories (tests/test_diagnose.py, tests/test_lineage_loss_experiment.py)."""

from __future__ import annotations

import numpy as np


def record_of(increments: np.ndarray, rng: np.random.Generator, every: int | None = None) -> dict[str, np.ndarray]:
    """The record of a filter whose particles get ``increments`` (S, N) at each step and resample
    systematically (a slow NumPy reference of the filter's rule): every ``every`` steps, or where
    the ESS falls below N/2 when ``every`` is None. With the fields :func:`jaxslam.diagnose.diagnose`
    reads; the poses and path are zeros."""
    steps, n = increments.shape
    log_weights, ancestors = np.empty((steps, n)), np.empty((steps, n), np.int32)
    resampled, ess = np.zeros(steps, bool), np.empty(steps)
    current = np.full(n, -np.log(n))
    for t in range(steps):
        updated = current + increments[t]
        updated -= np.logaddexp.reduce(updated)
        log_weights[t], ess[t] = updated, 1.0 / np.sum(np.exp(2 * updated))
        resampled[t] = (t % every == every - 1) if every else ess[t] < n / 2
        if resampled[t]:
            cumulative = np.cumsum(np.exp(updated))
            ancestors[t] = np.minimum(np.searchsorted(cumulative, (rng.random() + np.arange(n)) / n), n - 1)
            current = np.full(n, -np.log(n))
        else:
            ancestors[t], current = np.arange(n), updated
    return {"scan_index": np.arange(steps + 1), "timestamp": np.arange(steps + 1, dtype=float),
            "odometry": np.zeros((steps + 1, 3)), "best_path": np.zeros((steps + 1, 3)),
            "ess": ess.astype(np.float32), "resampled": resampled, "ancestors": ancestors,
            "proposed_poses": np.zeros((steps, n, 3), np.float32), "log_weights": log_weights,
            "log_evidence": np.zeros(steps, np.float32), "num_fallbacks": np.zeros(steps, np.int32),
            "best_particle": np.zeros(steps, np.int32), "num_particles": np.int64(n)}
