"""The per-step diagnosis of a run: lineages against a slow backtracking reference, corrections
against a known injected jump, relation errors over time, and the command end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.diagnose import (coalescence_lag, diagnose, lineages_at_lag, neutral_coalescence_lags, pair_coalescence,
                              read_step_record, surviving_lineages, weight_increments, weight_persistence)
from jaxslam.geometry import between_np
from weight_records import record_of


def lineages_by_backtracking(ancestors: np.ndarray) -> np.ndarray:
    """Slow reference: follow every final particle's index back step by step, count the distinct."""
    steps, n = ancestors.shape
    chains = np.empty((steps, n), np.int64)
    for final in range(n):
        index = final
        for t in range(steps - 1, -1, -1):
            index = ancestors[t, index]
            chains[t, final] = index
    return np.array([np.unique(chains[t]).size for t in range(steps)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_surviving_lineages_match_backtracking(seed):
    rng = np.random.default_rng(seed)
    n, steps = 7, 40
    # Resample (draw ancestors) on a third of the steps, keep the particles elsewhere.
    ancestors = np.where(rng.random((steps, 1)) < 0.33, rng.integers(0, n, (steps, n)), np.arange(n))
    got = surviving_lineages(ancestors)
    np.testing.assert_array_equal(got, lineages_by_backtracking(ancestors))
    assert got[-1] == np.unique(ancestors[-1]).size and np.all(np.diff(got) >= 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lineages_at_lag_match_backtracking_from_every_step(seed):
    rng = np.random.default_rng(seed)
    n, steps = 7, 45
    ancestors = np.where(rng.random((steps, 1)) < 0.33, rng.integers(0, n, (steps, n)), np.arange(n))
    for lag in [1, 2, 3, 5, 8, 13, 31, steps]:  # single bits, several bits, the whole record
        # Slow reference: the record cut at each step t, its lineages counted lag steps back.
        expected = [lineages_by_backtracking(ancestors[:t + 1])[t - lag + 1] for t in range(lag - 1, steps)]
        np.testing.assert_array_equal(lineages_at_lag(ancestors, lag), expected)
    # At the last step it is the record's own surviving lineages; a lag longer than the record has none.
    assert lineages_at_lag(ancestors, 10)[-1] == surviving_lineages(ancestors)[-10]
    assert lineages_at_lag(ancestors, steps + 1).shape == (0,)


def test_lineages_at_lag_refuses_a_lag_that_is_no_number_of_steps():
    ancestors = np.tile(np.arange(4), (6, 1))
    for lag in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="lag must be a positive number of steps"):
            lineages_at_lag(ancestors, lag)


def synthetic_record(steps=30, n=5, jump_at=17, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(steps + 1, dtype=float)
    odometry = np.stack([0.5 * t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    best = odometry.copy()
    best[jump_at + 1:, 1] += 0.3  # the filter moved the path 0.3 m sideways between scans jump_at and jump_at + 1
    ancestors = np.tile(np.arange(n), (steps, 1))
    ancestors[10] = 0  # one resampling keeps only particle 0
    return {
        "scan_index": np.arange(steps + 1), "timestamp": 100.0 + t, "odometry": odometry, "best_path": best,
        "ess": np.full(steps, n / 2.0, np.float32), "resampled": np.arange(steps) == 10,
        "ancestors": ancestors.astype(np.int32),
        "proposed_poses": (best[1:, None, :] + rng.normal(0, 0.1, (steps, n, 3))).astype(np.float32),
        "log_evidence": np.zeros(steps, np.float32), "num_fallbacks": np.zeros(steps, np.int32),
        "best_particle": np.zeros(steps, np.int32), "num_particles": np.int64(n),
    }


def test_the_injected_jump_is_the_largest_correction_and_lineages_coalesce():
    record = synthetic_record()
    out = diagnose(record)
    largest = out["events"]["largest_corrections"][0]
    assert largest["step"] == 18 and largest["trans"] == pytest.approx(0.3, abs=1e-9)
    assert largest["elapsed_s"] == pytest.approx(18.0) and largest["y"] == pytest.approx(0.3)
    series = out["series"]
    assert max(series["correction_trans"][:17] + series["correction_trans"][18:]) < 1e-9
    assert series["distinct_ancestors"][10] == 1 and series["distinct_ancestors"][11] == 5
    assert out["summary"]["coalescence_step"] == 11  # the step whose resampling kept one particle
    # That resampling made every pair of particles share a parent; no other step merged any.
    assert out["summary"]["pair_coalescence_per_step"] == pytest.approx(1 / 30)
    # Step 11's resampling kept one particle: a span of steps holds one history where it includes
    # step 11 (5-step spans ending at steps 11-15; every 25-step span of the 30 steps), five elsewhere.
    np.testing.assert_array_equal(lineages_at_lag(record["ancestors"], 5), np.where((np.arange(5, 31) >= 11)
                                                                                     & (np.arange(5, 31) <= 15), 1, 5))
    lineages_back = out["summary"]["lineages_back"]
    assert lineages_back == {"25": 1.0, "50": None, "100": None, "200": None}
    assert series["ess_fraction"][0] == pytest.approx(0.5)


def test_relation_errors_over_time_are_the_trajectorys():
    from jaxslam.io.relations import Relations

    record = synthetic_record()
    times = record["timestamp"]
    poses = record["best_path"]
    pairs = np.array([[0, 5], [3, 20], [16, 19], [25, 30]])
    truth = between_np(poses[pairs[:, 0]], poses[pairs[:, 1]])
    truth[1, 0] += 0.25  # one relation 0.25 m off
    relations = Relations(times[pairs[:, 0]], times[pairs[:, 1]], truth)
    out = diagnose(record, (times, poses), relations)
    np.testing.assert_allclose(out["relations"]["trans"], [0.0, 0.25, 0.0, 0.0], atol=1e-9)
    assert out["relations"]["step"] == [5, 20, 19, 30]
    worst = out["events"]["worst_relations"][0]
    assert worst["trans"] == pytest.approx(0.25) and worst["step"] == 20
    outside = Relations(np.array([500.0]), np.array([501.0]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="none of the 1 relations lies within"):
        diagnose(record, (times, poses), outside)


def test_diagnose_command_reads_a_map_run(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--scans", "60", "--particles", "4", "--no-progress", "--out", str(out)]) == 0
    record = read_step_record(out)
    steps = record["ancestors"].shape[0]
    assert record["proposed_poses"].shape == (steps, 4, 3) and record["best_path"].shape == (steps + 1, 3)
    # Relations from the filter's own trajectory (the diagnosis is the filter's: beside a loop
    # closure, trajectory_filter.txt), one of them 0.1 m off: the diagnosis finds it.
    traj = np.loadtxt(out / "trajectory_filter.txt")
    i, j = np.array([2, 10, 30]), np.array([8, 40, 59])
    motion = between_np(traj[i, 1:], traj[j, 1:])
    motion[2, 1] += 0.1
    rel = tmp_path / "rel.txt"
    rel.write_text("".join(f"{traj[a, 0]:.6f} {traj[b, 0]:.6f} {m[0]:.9f} {m[1]:.9f} 0 0 0 {m[2]:.9f}\n"
                           for a, b, m in zip(i, j, motion)))
    assert main(["diagnose", str(out), str(rel), "--out", str(tmp_path / "d")]) == 0
    diagnosis = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    assert (tmp_path / "d" / "diagnosis.png").is_file()
    np.testing.assert_allclose(diagnosis["relations"]["trans"], [0, 0, 0.1], atol=2e-6)
    assert diagnosis["summary"]["steps"] == steps
    # The best final particle's own history is the run's trajectory: its own error is the run's.
    final = diagnosis["summary"]["final_particles"]
    assert len(diagnosis["final_particles"]["trans_mean"]) == 4
    assert final["best_trans_mean"] == pytest.approx(diagnosis["summary"]["relation_error"]["trans_mean"], abs=2e-6)
    assert final["closest_trans_mean"] <= final["best_trans_mean"]
    # The run's path at a relation's later step is one of the particles proposed there.
    then, run = np.asarray(diagnosis["relations"]["closest_then"]), np.asarray(diagnosis["relations"]["trans"])
    assert then.shape == (3,) and np.all(then <= run + 2e-6)
    weighted = np.asarray(diagnosis["relations"]["weighted_then"])  # the run records each step's weights
    assert weighted.shape == (3,) and np.all(weighted >= then - 2e-6)
    assert "largest corrections" in capsys.readouterr().out
    # A folder without the record: one clear line, exit 2, before any work.
    assert main(["diagnose", str(tmp_path / "d")]) == 2
    assert "steps.npz does not exist" in capsys.readouterr().err


def test_the_steps_that_drew_from_the_slip_component_are_listed():
    record = synthetic_record()
    assert diagnose(record)["summary"]["slip_steps"] == 0  # a record written before the slip search
    slipped = np.zeros(record["ancestors"].shape[0], np.int32)
    slipped[7] = 3
    out = diagnose(dict(record, num_slipped=slipped))
    assert out["summary"]["slip_steps"] == 1
    assert [(e["step"], e["particles"]) for e in out["events"]["slips"]] == [(8, 3)]
    assert out["series"]["slipped"][7] == 3


def per_scan_by_loops(path, processed, odometry):
    """Slow reference: a pose for every scan, the processed scan before it (or the first) composed
    with the odometry's motion since (what trajectory.txt holds for the best particle)."""
    from jaxslam.geometry import compose_np

    out = np.empty_like(odometry)
    for scan in range(odometry.shape[0]):
        k = max(int(np.sum(processed <= scan)) - 1, 0)
        out[scan] = compose_np(path[k], between_np(odometry[processed[k]], odometry[scan]))
    return out


def random_run(rng, n, num_scans, first, count, resample_share):
    """A synthetic run: odometry at every scan, ``count`` processed scans after ``first``, the
    proposed poses about the odometry and ancestors that resample ``resample_share`` of the steps."""
    processed = np.concatenate([[first], np.sort(rng.choice(np.arange(first + 1, num_scans), count, replace=False))])
    steps = processed.size - 1
    odometry = np.cumsum(np.stack([rng.uniform(0.1, 0.3, num_scans), rng.normal(0, 0.05, num_scans),
                                   rng.normal(0, 0.1, num_scans)], 1), axis=0)
    proposed = odometry[processed[1:], None, :] + rng.normal(0, 0.2, (steps, n, 3))
    resampled = rng.random((steps, 1)) < resample_share
    ancestors = np.where(resampled, rng.integers(0, n, (steps, n)), np.arange(n)).astype(np.int32)
    return processed, odometry, proposed, ancestors


@pytest.mark.parametrize("seed", [0, 1])
def test_each_final_particles_own_relation_error_against_loops(seed):
    from jaxslam.diagnose import final_particle_errors
    from jaxslam.io.relations import Relations
    from jaxslam.rbpf import particle_paths

    rng = np.random.default_rng(seed)
    n, num_scans = 5, 40
    processed, odometry, proposed, ancestors = random_run(rng, n, num_scans, 2, 14, 0.3)
    steps = processed.size - 1
    best_final = 3
    paths = particle_paths(proposed, ancestors, odometry[processed[0]])
    truth_path = per_scan_by_loops(paths[0], processed, odometry)  # particle 0's history is the truth
    times = 50.0 + 0.37 * np.arange(num_scans)
    pairs = rng.integers(0, num_scans, (25, 2))
    relations = Relations(times[pairs[:, 0]], times[pairs[:, 1]], between_np(truth_path[pairs[:, 0]],
                                                                              truth_path[pairs[:, 1]]))
    record = {"scan_index": processed, "best_path": paths[best_final], "proposed_poses": proposed.astype(np.float32),
              "ancestors": ancestors, "best_particle": np.full(steps, best_final, np.int32)}
    trajectory = (times, per_scan_by_loops(paths[best_final], processed, odometry))
    own = final_particle_errors(record, trajectory, relations)
    from jaxslam.metrics import relation_error

    expected = [relation_error(times, per_scan_by_loops(p, processed, odometry), relations) for p in paths]
    np.testing.assert_allclose(own["trans_mean"], [e.trans_mean for e in expected], atol=1e-5)
    np.testing.assert_allclose(own["rot_mean"], [e.rot_mean for e in expected], atol=1e-5)
    # Particle 0 is the truth (up to the record's float32 poses), and the others are not.
    assert own["trans_mean"][0] < 1e-5 and np.all(own["trans_mean"][ancestors[-1] != ancestors[-1][0]] > 0.01)


def test_the_closest_particle_then_against_truncated_records():
    """Each relation's best particle at its later scan, and the particles' mean by that step's
    weights, against a slow reference: the record cut after the step before (whose final
    particles are that step's parents), each proposed particle's history as a final particle's
    path (:func:`jaxslam.rbpf.particle_paths`)."""
    from jaxslam.diagnose import closest_then, weighted_then
    from jaxslam.io.relations import Relations
    from jaxslam.metrics import relation_error
    from jaxslam.rbpf import particle_paths

    rng = np.random.default_rng(5)
    n, num_scans = 4, 36
    processed, odometry, proposed, ancestors = random_run(rng, n, num_scans, 1, 15, 1.0)  # resampling every step
    start = odometry[processed[0]]
    paths = particle_paths(proposed, ancestors, start)
    times = 10.0 + 0.5 * np.arange(num_scans)
    pairs = rng.integers(0, num_scans, (30, 2))
    truth = per_scan_by_loops(paths[0], processed, odometry)
    relations = Relations(times[pairs[:, 0]], times[pairs[:, 1]], between_np(truth[pairs[:, 0]], truth[pairs[:, 1]])
                          + rng.normal(0, 0.05, (30, 3)))
    record = {"scan_index": processed, "best_path": paths[0], "proposed_poses": proposed.astype(np.float32),
              "ancestors": ancestors}
    trajectory = (times, per_scan_by_loops(paths[0], processed, odometry))
    got = closest_then(record, trajectory, relations)
    assert weighted_then(record, trajectory, relations) is None  # a record written before it held the weights
    log_w = rng.normal(0.0, 2.0, ancestors.shape)
    record["log_weights"] = (log_w - np.log(np.exp(log_w).sum(axis=1, keepdims=True))).astype(np.float32)
    got_weighted = weighted_then(record, trajectory, relations)

    expected, expected_weighted = np.empty(30), np.empty(30)
    for r, (a, b) in enumerate(pairs):
        step = max(int(np.sum(processed <= max(a, b))) - 1, 0)
        if step == 0:
            histories = start[None, None, :]
        else:  # step's proposed particle j: its parent's path (the record cut before the step), then its own pose
            parents = particle_paths(proposed[:step - 1], ancestors[:step - 1], start)
            histories = np.concatenate([parents, proposed[step - 1][:, None, :]], axis=1)
        one = Relations(times[[a]], times[[b]], np.asarray(relations.motion)[[r]])
        errors = np.array([relation_error(times, per_scan_by_loops(h, processed[:step + 1], odometry), one).trans_mean
                           for h in histories])
        expected[r] = errors.min()
        weights = np.exp(np.float64(record["log_weights"][step - 1])) if step else np.full(n, 1.0 / n)
        expected_weighted[r] = np.sum(weights / weights.sum() * np.broadcast_to(errors, (n,)))
    np.testing.assert_allclose(got, expected, atol=1e-5)
    np.testing.assert_allclose(got_weighted, expected_weighted, atol=1e-5)
    assert np.all(got_weighted >= got - 1e-9) and np.any(got_weighted > got + 1e-3)


def test_pair_coalescence_against_drawing_pairs():
    rng = np.random.default_rng(3)
    ancestors = rng.integers(0, 4, (50, 6))
    # Slow reference: every unordered pair of distinct particles, counted.
    pairs = [(i, j) for i in range(6) for j in range(i + 1, 6)]
    expected = [np.mean([row[i] == row[j] for i, j in pairs]) for row in ancestors]
    np.testing.assert_allclose(pair_coalescence(ancestors), expected, atol=1e-12)
    assert np.all(pair_coalescence(np.tile(np.arange(6), (3, 1))) == 0)


def test_a_lineage_that_always_wins_coalesces_before_neutral_drift():
    # Every step particle 0 doubles and the last dies: the final four share the ancestor proposed
    # 2 steps before the last, the fewest possible (a step merges one pair). Relabelled, the luck
    # moves around: going back, the last step leaves 3 lineages; the one before merges two of them
    # where both copies are among the 3 (probability 1/2); the one before that the last two where
    # they are the copies (1/C(4, 2) = 1/6).
    ancestors = np.tile([0, 0, 1, 2], (40, 1))
    assert coalescence_lag(ancestors) == 2
    neutral = neutral_coalescence_lags(ancestors, draws=400)
    assert neutral.min() >= 2 and np.median(neutral) >= 4
    assert np.mean(neutral == 2) == pytest.approx(1 / 12, abs=3 * np.sqrt((1 / 12) * (11 / 12) / 400))


def test_a_neutral_record_sits_inside_its_neutral_lags():
    rng = np.random.default_rng(4)
    quantiles = []
    for _ in range(40):
        # Resample at a random third of the steps with random parents: the record is itself neutral drift.
        ancestors = np.where(rng.random((60, 1)) < 0.33, rng.integers(0, 6, (60, 6)), np.arange(6))
        neutral = neutral_coalescence_lags(ancestors, draws=100, seed=int(rng.integers(1 << 30)))
        lag = coalescence_lag(ancestors)
        quantiles.append(0.5 * (np.mean(neutral < lag) + np.mean(neutral <= lag)))  # mid-rank: ties split
    # Uniform on [0, 1] under the null: the mean of 40 has a standard deviation of 0.29 / sqrt(40) = 0.046.
    assert np.mean(quantiles) == pytest.approx(0.5, abs=0.14)


def test_weight_increments_are_recovered_from_the_record():
    rng = np.random.default_rng(0)
    increments = rng.normal(0.0, 0.3, (40, 6))
    record = record_of(increments, rng, every=7)
    log_weights, ancestors, resampled = record["log_weights"], record["ancestors"], record["resampled"]
    got = weight_increments(log_weights, ancestors, resampled)
    np.testing.assert_allclose(got, increments - increments.mean(axis=1, keepdims=True), atol=1e-9)
    # A particle of weight zero drops out of its step's centring instead of spreading NaN over it.
    log_weights[5, 2] = -np.inf
    got = weight_increments(log_weights, ancestors, resampled)
    assert np.isnan(got[5, 2]) and np.all(np.isfinite(np.delete(got[5], 2)))
    np.testing.assert_allclose(np.nanmean(got[5]), 0.0, atol=1e-12)


@pytest.mark.parametrize("persistent, expected", [(True, 1.0), (False, 0.0)])
def test_weight_persistence_tells_lasting_weights_from_noise(persistent, expected):
    rng = np.random.default_rng(1)
    steps, n, every = 400, 30, 16
    noise = rng.normal(0.0, 0.2, (steps, n))
    if persistent:  # each stretch's particles differ by a lasting 0.2 nats a step, plus a little noise
        quality = rng.normal(0.0, 0.2, (steps // every + 1, n))
        noise = quality[np.arange(steps) // every] + 0.02 * noise
    record = record_of(noise, rng, every=every)
    log_weights, ancestors, resampled = record["log_weights"], record["ancestors"], record["resampled"]
    out = weight_persistence(log_weights, ancestors, resampled)
    assert len(out["stretches"]) == steps // every
    assert all(s["steps"] == every for s in out["stretches"])
    # Noise: each stretch's correlation of n = 30 pairs has a standard deviation of about
    # 1 / sqrt(29) = 0.19, their median over 25 stretches about 1.25 * 0.19 / 5 = 0.05: 0.15 is three of it.
    assert out["median_correlation"] == pytest.approx(expected, abs=0.15 if not persistent else 0.01)
    assert out["median_increment_spread"] == pytest.approx(0.2, rel=0.1)
    assert diagnose({**synthetic_record(), "log_weights": np.zeros((30, 5))})["summary"]["weight_persistence"][
        "stretches"] == 0
