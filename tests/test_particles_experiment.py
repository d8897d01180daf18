"""experiments/particles.py (the N-sweep): the coalescence lag against a brute-force ancestry walk,
the failure rules, the table and the figure. Fast: no mapping runs."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import particles  # noqa: E402


def _lag_by_walking(ancestors: np.ndarray, times: np.ndarray) -> float:
    """The coalescence lag the slow way: every final particle's whole ancestry, then the last step
    at which all of them pass through one particle."""
    steps, n = ancestors.shape
    lineage = np.empty((steps, n), np.int64)  # lineage[t, i]: final particle i's ancestor among step t's
    idx = np.arange(n)
    for t in range(steps - 1, -1, -1):
        idx = ancestors[t, idx]
        lineage[t] = idx
    common = [t for t in range(steps) if np.unique(lineage[t]).size == 1]
    return float(times[-1] - (times[common[-1]] if common else times[0]))


@pytest.mark.parametrize("seed", range(5))
def test_coalescence_lag_matches_a_walk_of_every_ancestry(seed):
    rng = np.random.default_rng(seed)
    steps, n = 40, 6
    # Mostly identity steps, with resamplings that concentrate on few particles now and then.
    ancestors = np.tile(np.arange(n), (steps, 1))
    for t in rng.choice(steps, size=8, replace=False):
        ancestors[t] = rng.integers(0, 1 + rng.integers(1, n), size=n)
    times = np.cumsum(rng.uniform(0.5, 2.0, size=steps))
    assert particles.coalescence_lag(ancestors, times) == pytest.approx(_lag_by_walking(ancestors, times))


def test_coalescence_lag_is_the_whole_run_when_histories_never_meet():
    ancestors = np.tile(np.arange(4), (10, 1))
    times = np.arange(10.0) * 3.0
    assert particles.coalescence_lag(ancestors, times) == pytest.approx(27.0)
    ancestors[-1] = 2  # everything descends from particle 2 of the last step
    assert particles.coalescence_lag(ancestors, times) == pytest.approx(0.0)


def _run(world, proposal, n, seed, error, lag=100.0, ms=50.0, peak=900.0):
    return {"world": world, "proposal": proposal, "N": n, "seed": seed, "error": error, "coalescence_lag_s": lag,
            "ms_per_update": ms, "peak_memory_mb": peak}


def test_failures_judge_logs_against_the_best_run_at_any_n_and_the_box_world_by_ra():
    runs = [_run("fr-clinic", "smp", 30, 0, 0.30), _run("fr-clinic", "smp", 30, 1, 0.09),
            _run("fr-clinic", "smp", 300, 0, 0.05), _run("fr-clinic", "lp", 300, 0, 0.10),
            _run("box", "smp", 30, 0, 0.25), _run("box", "smp", 30, 1, 0.12)]
    failed = particles.failures(runs, success_ra=0.2)
    # The best fr-clinic run (0.05 m at N = 300) judges every N: above 0.10 m fails.
    assert failed[("fr-clinic", "smp", 30)] == [0]
    assert failed[("fr-clinic", "smp", 300)] == [] and failed[("fr-clinic", "lp", 300)] == []
    assert failed[("box", "smp", 30)] == [0]
    rows = {(r["world"], r["proposal"], r["N"]): r for r in particles.summary_rows(runs, 0.2)}
    assert rows[("fr-clinic", "smp", 30)]["failed"] == 1 and rows[("fr-clinic", "smp", 30)]["runs"] == 2
    assert rows[("fr-clinic", "smp", 30)]["error_mean"] == pytest.approx(0.195)
    assert rows[("fr-clinic", "smp", 30)]["error_se"] == pytest.approx(np.std([0.30, 0.09], ddof=1) / np.sqrt(2))
    assert rows[("fr-clinic", "smp", 30)]["closest_particle_error_median"] is None  # a log scores one trajectory


def test_the_box_worlds_closest_particle_is_the_median_over_runs():
    runs = [dict(_run("box", "smp", 100, s, 5.0), closest_particle_error=e) for s, e in enumerate((0.1, 3.0, 0.3))]
    row = particles.summary_rows(runs, 0.2)[0]
    assert row["closest_particle_error_median"] == pytest.approx(0.3)
    assert "| 5.000 ± 0.000 | 0.300 |" in particles.markdown([row])


def test_table_and_figure_are_written(tmp_path):
    runs = [_run("box", p, n, s, 0.1 + 0.01 * s, lag=10.0 * n, ms=n / 10) for p in ("smp", "lp")
            for n in (30, 100) for s in range(2)]
    rows = particles.summary_rows(runs, 0.2)
    text = particles.markdown(rows)
    assert text.count("\n") == 2 + 4 and "| box | lp | 100 | 2 | 0 |" in text
    particles.figure(tmp_path / "particles.png", rows)
    assert (tmp_path / "particles.png").stat().st_size > 10_000


def test_refuses_a_sweep_with_nothing_to_run(capsys):
    with pytest.raises(SystemExit):
        particles.main(["--out", "unused"])
    assert "nothing to run" in capsys.readouterr().err
