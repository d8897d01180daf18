"""experiments/closure_weights.py: the weights' increments recovered from a run's record, the
closing particles' share and gaps, and the counterfactual re-weighting (the identity at the run's
own gain), on hand-made records with known answers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import closure_weights  # noqa: E402  (experiments/closure_weights.py)

from jaxslam.diagnose import weight_increments  # noqa: E402  (the increments the script reads)


def _record(increments: np.ndarray, resampled: np.ndarray, ancestors: np.ndarray) -> dict:
    """A record whose step-t log-weights are its particles' priors plus ``increments[t]`` (the
    filter's rule: uniform after a resampling, else the previous step's normalised weights)."""
    num_steps, num_particles = increments.shape
    log_weights = np.empty_like(increments)
    prior = np.full(num_particles, -np.log(num_particles))
    for t in range(num_steps):
        log_weights[t] = prior + increments[t]
        normalised = log_weights[t] - np.logaddexp.reduce(log_weights[t])
        prior = np.full(num_particles, -np.log(num_particles)) if resampled[t] else normalised
    return {"log_weights": log_weights, "resampled": resampled, "ancestors": ancestors,
            "proposed": np.zeros((num_steps, num_particles, 3))}


def test_the_increments_are_recovered_up_to_a_constant_per_step():
    rng = np.random.default_rng(0)
    steps, particles = 12, 6
    true_increments = rng.normal(size=(steps, particles))
    resampled = np.arange(steps) % 3 == 1  # resampled after steps 1, 4, 7 and 10
    record = _record(true_increments, resampled, np.tile(np.arange(particles), (steps, 1)))
    recovered = weight_increments(record["log_weights"], record["ancestors"], record["resampled"])
    offset = recovered - true_increments
    np.testing.assert_allclose(offset, offset[:, :1] * np.ones((1, particles)), atol=1e-12)
    with pytest.raises(AssertionError):  # a wrong prior (never uniform) breaks it where a resampling happened
        wrong = weight_increments(record["log_weights"], record["ancestors"], np.zeros(steps, bool))
        np.testing.assert_allclose(wrong - true_increments, (wrong - true_increments)[:, :1] * np.ones((1, particles)),
                                   atol=1e-12)


def test_lineages_sum_their_ancestors_increments():
    # Three particles, three steps; after step 1 every particle descends from proposed particle 2.
    increments = np.array([[0.0, 1.0, 2.0], [0.5, 0.0, 3.0], [1.0, 2.0, 4.0]])
    ancestors = np.array([[0, 1, 2], [2, 2, 2], [0, 1, 2]])
    record = _record(increments, np.array([False, True, False]), ancestors)
    # The last two steps: step 2's own increment, plus step 1's of proposed particle 2 (3.0).
    summed = closure_weights.lineage_increments(record, back=2)
    recovered = weight_increments(record["log_weights"], record["ancestors"], record["resampled"])
    np.testing.assert_allclose(summed, recovered[2] + recovered[1][2])  # every lineage passes proposed particle 2
    np.testing.assert_allclose(summed[2] - summed[0], 4.0 - 1.0)  # the shared step cancels
    assert closure_weights.lineage_increments(record, back=1)[2] == pytest.approx(recovered[2][2])


def test_reweighting_at_the_runs_own_gain_is_the_runs_ra_and_sharper_weights_move_it():
    rng = np.random.default_rng(1)
    steps, particles = 8, 5
    record = _record(rng.normal(size=(steps, particles)), np.zeros(steps, bool),
                     np.tile(np.arange(particles), (steps, 1)))
    final = record["log_weights"][-1] - np.logaddexp.reduce(record["log_weights"][-1])
    errors = rng.random(particles)
    ras = closure_weights.ra_at_gains(record, final, errors, 0.1, [0.1, 1.0], back=steps)
    weights = np.exp(final)
    assert ras["0.1"] == pytest.approx(float(np.sum(weights * errors)))
    assert ras["1"] != pytest.approx(ras["0.1"])


def test_the_test_family_is_refused_before_any_work(capsys):
    assert closure_weights.main(["--worlds", "3"]) == 2
    assert "test family" in capsys.readouterr().err
