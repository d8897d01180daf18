"""experiments/lineage_loss.py: chance against selection in a run's lost histories, on records
whose weights are built to be one or the other. Fast: no mapping runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import lineage_loss  # noqa: E402

from jaxslam.diagnose import write_step_record  # noqa: E402
from weight_records import record_of  # noqa: E402


def test_chance_and_lasting_weights_are_told_apart(tmp_path):
    rng = np.random.default_rng(0)
    steps, n, spread = 2000, 30, 0.2
    runs = {"chance": rng.normal(0.0, spread, (steps, n)),  # every step's differences drawn afresh
            # each particle index keeps its advantage for the whole run (plus a little noise)
            "lasting": rng.normal(0.0, spread, (1, n)) + rng.normal(0.0, 0.02, (steps, n))}
    for name, increments in runs.items():
        (tmp_path / name).mkdir()
        write_step_record(tmp_path / name / "steps.npz", record_of(increments, np.random.default_rng(0)))
    out = tmp_path / "figures" / "lineage_loss.json"
    figure = tmp_path / "figures" / "lineages.png"
    assert lineage_loss.main([str(tmp_path / "chance"), str(tmp_path / "lasting"), "--out", str(out),
                              "--thresholds", "0.5", "--spreads", "0.2", "--figure", str(figure)]) == 0
    assert figure.stat().st_size > 10_000
    figures = {Path(r["run"]).name: r for r in json.loads(out.read_text())["runs"]}
    chance, lasting = figures["chance"], figures["lasting"]
    # Chance: the replay merges as fast with the increments dealt at random. Over 2,000 steps
    # (about 110 resamplings) the ratio's standard deviation is 0.044 (8 seeds of this record):
    # 0.15 is over three of it. The persistence is near 0, and the recorded merging is the
    # replay's own (the same rule on the same increments).
    assert chance["drift_share"] == pytest.approx(1.0, abs=0.15)
    assert abs(chance["persistence"]) < 0.2 and chance["increment_spread"] == pytest.approx(spread, rel=0.1)
    assert chance["pair_coalescence"] == pytest.approx(chance["replayed"], rel=0.15)
    # Lasting: weights diverge as (steps x spread)^2 instead of steps x spread^2, so the filter
    # resamples about four times as often and chance alone explains a small part of the merging.
    assert lasting["persistence"] > 0.9 and lasting["drift_share"] < 0.5
    assert lasting["resamplings"] > 2 * chance["resamplings"]
    # The same lineages winning leave fewer histories at every lag than luck does.
    # Relabelled, luck's resamplings keep about the histories they kept; the lasting run's keep
    # more than it did over the shorter lags, where its one winning lineage shows.
    for lag in ("25", "50", "100", "200"):
        assert 1 <= lasting["lineages_back"][lag] < chance["lineages_back"][lag] <= n
        assert chance["lineages_back"][lag] == pytest.approx(chance["neutral_lineages_back"][lag], rel=0.25, abs=1)
    for lag in ("25", "50"):
        assert lasting["lineages_back"][lag] < lasting["neutral_lineages_back"][lag]
    # The curve holds the same figures at those lags, and never grows with the lag.
    for run in (chance, lasting):
        curve = dict(zip(map(str, run["lineages_curve"]["lags"]), run["lineages_curve"]["held"]))
        assert all(curve[lag] == run["lineages_back"][lag] for lag in run["lineages_back"])
        assert np.all(np.diff(run["lineages_curve"]["held"]) <= 0) and run["lineages_curve"]["held"][0] <= n


def test_a_folder_without_a_record_or_a_folder_for_the_figure_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "lineage_loss.json"
    assert lineage_loss.main([str(tmp_path), "--out", str(out)]) == 2
    assert "no steps.npz" in capsys.readouterr().err and not out.exists()
    (tmp_path / "run").mkdir()
    write_step_record(tmp_path / "run" / "steps.npz", record_of(np.zeros((20, 4)), np.random.default_rng(0)))
    assert lineage_loss.main([str(tmp_path / "run"), "--out", str(out), "--figure", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err and not out.exists()
