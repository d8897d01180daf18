"""experiments/learn_doors.py, learn_intel.py, learn_office.py and score_bias.py: their helpers, bad input, and a
tiny end-to-end fit (the figures come from full runs, docs/results.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import learn_doors  # noqa: E402
import learn_intel  # noqa: E402
import learn_office  # noqa: E402


def test_complete_data_estimate_counts_transitions():
    states = np.array([[0, 1], [1, 1], [1, 0], [0, 0], [0, 0]], bool)  # door 0: c o o c c; door 1: o o c c c
    got = learn_doors.complete_data_estimate(states)
    # closed -> open once out of 4 closed predecessors; open -> closed twice out of 4 open predecessors.
    assert got == {"p_open_closed": 0.25, "p_closed_open": 0.5, "transitions": 3}


def test_learn_doors_refuses_a_probability_outside_the_unit_interval(capsys):
    with pytest.raises(SystemExit):
        learn_doors.main(["--start", "0.0", "0.01"])
    assert "(0, 1)" in capsys.readouterr().err


def test_learn_intel_refuses_a_missing_log(tmp_path, capsys):
    with pytest.raises(SystemExit):
        learn_intel.main(["--data", str(tmp_path)])
    assert "log not found" in capsys.readouterr().err


def test_learn_doors_runs_end_to_end(tmp_path):
    out = tmp_path / "doors.json"
    assert learn_doors.main(["--round-trips", "1", "--particles", "8", "--steps", "2", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert len(record["history"]["objective"]) == 2 and np.all(np.isfinite(record["history"]["objective"]))
    assert 0.0 < record["learned_tail_mean"]["p_open_closed"] < 1.0


def test_learn_office_refuses_no_office(capsys):
    with pytest.raises(SystemExit):
        learn_office.main(["--score", "0"])
    assert "--score" in capsys.readouterr().err


def test_learn_office_score_puts_the_filter_beside_the_known_path(tmp_path):
    """A tiny ``--score`` run: per office, the filter's score of every term over the keys, the
    known path's score of the motion terms, and the motion residuals' mean squares along the
    filter's paths and the true path."""
    out = tmp_path / "score.json"
    assert learn_office.main(["--proposal", "op", "--particles", "4", "--scans", "40", "--score", "1",
                              "--seeds", "2", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    office = record["offices"][0]
    assert office["names"] == list(learn_office.TERMS) + ["likelihood.sigma"]
    assert np.asarray(office["filter_score"]).shape == (2, 5)
    assert np.all(np.isfinite(office["filter_score"]))
    assert len(office["known_path_score"]) == 5 and np.all(np.isfinite(office["known_path_score"][:4]))
    squares = office["residual_mean_squares"]
    assert set(squares) == {"filter_straight", "filter_turning", "true_path_straight", "true_path_turning"}
    assert all(len(v) == 3 and np.all(np.asarray(v) > 0) for v in squares.values())


def test_score_bias_runs_end_to_end_on_the_linear_gaussian_model(tmp_path, capsys):
    import score_bias

    assert score_bias.main(["--out", str(tmp_path), "--skip-office", "--seeds", "1", "--lg-keys", "4",
                            "--lg-steps", "10", "--lg-particles", "8", "--lags", "0", "3"]) == 0
    record = json.loads((tmp_path / "score_bias.json").read_text())
    assert record["args"]["out"] == "OUT/"  # no path of the machine it ran on
    assert {r["estimator"] for r in record["rows"]} == {"path-space", "lag 0", "lag 3", "adapted proposal"}
    assert all(np.isfinite(r["bias"]) and r["sd"] >= 0 for r in record["rows"])
    table = (tmp_path / "score_bias.md").read_text()
    assert "| a | lag 3 |" in table and "| r | adapted proposal |" in table
    with pytest.raises(SystemExit):
        score_bias.main(["--out", str(tmp_path), "--lags", "-1"])
    assert "lags >= 0" in capsys.readouterr().err


def test_learn_office_world_hall_fits_against_the_halls_own_terms(tmp_path):
    """``--world hall`` sets up the second world: its simulated terms (not the office's) are the
    truth a profile is taken at, and its known-path references are computed on it."""
    out = tmp_path / "hall.json"
    assert learn_office.main(["--world", "hall", "--proposal", "op", "--particles", "4", "--scans", "40",
                              "--profile", "1", "--seeds", "2", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["args"]["world"] == "hall"
    assert record["truth"]["motion.srr"] == pytest.approx(0.08) and record["truth"]["motion.srt"] == pytest.approx(0.01)
    assert set(record["known_path_motion_optimum"]) == set(learn_office.TERMS)
    assert np.all(np.isfinite(record["profile"][0]["values"]))
