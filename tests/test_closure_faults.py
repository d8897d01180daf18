"""experiments/closure_faults.py (the loop closure's stress set): the drift, scale and slip faults, the
cell names, the table's ratio and targets, and the refusal of bad input. Fast: no real log, no
``jaxslam map`` run (the runs are replaced by fake records)."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import closure_faults as cf  # noqa: E402
import faults  # noqa: E402

from jaxslam.geometry import between_np, wrap_angle_np  # noqa: E402
from jaxslam.laser import make_sensor, uniform_beams  # noqa: E402
from jaxslam.laserlog import LaserLog  # noqa: E402


def wavy_log(num_scans: int = 600) -> LaserLog:
    """Steps of 0.02-0.2 m (some backwards, some sideways) with a heading that turns back and forth,
    90-degree turns at scans 100, 250 and 420; timestamps at 10 Hz far from zero, 5 beams."""
    rng = np.random.default_rng(3)
    turn = 0.05 * np.sin(np.arange(num_scans - 1) / 15.0)
    for start in (100, 250, 420):
        turn[start:start + 10] += math.radians(9.0)
    forward = rng.uniform(0.02, 0.2, num_scans - 1) * np.where(rng.random(num_scans - 1) < 0.1, -1.0, 1.0)
    sideways = rng.normal(0.0, 0.01, num_scans - 1)
    pose = np.array([5.0, -3.0, 2.5])
    odometry = [pose.copy()]
    for dx, dy, dtheta in zip(forward, sideways, turn):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + np.array([c * dx - s * dy, s * dx + c * dy, dtheta])
        odometry.append(pose.copy())
    odometry = np.array(odometry)
    odometry[:, 2] = wrap_angle_np(odometry[:, 2])
    sensor = make_sensor(uniform_beams(5, np.pi), range_min=0.0, range_max=10.0)
    ranges = rng.uniform(0.5, 9.0, (num_scans, 5)).astype(np.float32)
    timestamps = 1.2e9 + np.arange(num_scans) / 10.0
    return LaserLog(timestamps, odometry, ranges, sensor, odometry + 0.01, "wavy")


def reference_drift_and_scale(odometry, drift_deg_per_m, scale_pct):
    """A slow loop: each step in the frame of its start pose, its translation scaled, its heading
    change plus drift times its recorded length, chained pose by pose."""
    out = [np.array(odometry[0], np.float64)]
    heading = odometry[0, 2]
    for a, b in zip(odometry[:-1], odometry[1:]):
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        local = (c * dx + s * dy, -s * dx + c * dy)
        dtheta = math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2]))
        length = math.hypot(*local)
        k = 1.0 + scale_pct / 100.0
        c, s = math.cos(heading), math.sin(heading)
        last = out[-1]
        heading = heading + dtheta + math.radians(drift_deg_per_m) * length
        out.append(np.array([last[0] + k * (c * local[0] - s * local[1]),
                             last[1] + k * (s * local[0] + c * local[1]), heading]))
    out = np.array(out)
    out[:, 2] = wrap_angle_np(out[:, 2])
    return out


def _steps(odometry):
    return between_np(odometry[:-1], odometry[1:])


# ----------------------------------------------------------------------------- the faults

@pytest.mark.parametrize("drift, scale", [(0.1, 0.0), (0.5, 0.0), (1.0, 0.0), (1.0, 3.0), (0.25, 5.0)])
def test_the_drift_matches_a_loop_reference(drift, scale):
    log = wavy_log()
    faulted = cf.drift_and_scale(log.odometry, drift, scale)
    reference = reference_drift_and_scale(log.odometry, drift, scale)
    np.testing.assert_allclose(faulted[:, :2], reference[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle_np(faulted[:, 2] - reference[:, 2]), 0.0, atol=1e-9)
    # Each step's heading change gained drift x its recorded length; the end turned by drift x the path's length.
    before, after = _steps(log.odometry), _steps(faulted)
    length = np.hypot(before[:, 0], before[:, 1])
    np.testing.assert_allclose(wrap_angle_np(after[:, 2] - before[:, 2]), math.radians(drift) * length, atol=1e-9)
    np.testing.assert_array_equal(faulted[0], log.odometry[0])


@pytest.mark.parametrize("scale", [1.0, 3.0, 5.0])
def test_the_scale_fault_scales_every_step_and_leaves_the_headings(scale):
    log = wavy_log()
    faulted = cf.drift_and_scale(log.odometry, 0.0, scale)
    before, after = _steps(log.odometry), _steps(faulted)
    np.testing.assert_allclose(after[:, :2], (1.0 + scale / 100.0) * before[:, :2], atol=1e-12)
    np.testing.assert_allclose(np.hypot(after[:, 0], after[:, 1]) / np.hypot(before[:, 0], before[:, 1]),
                               1.0 + scale / 100.0, rtol=1e-9)
    np.testing.assert_allclose(wrap_angle_np(after[:, 2] - before[:, 2]), 0.0, atol=1e-12)
    np.testing.assert_allclose(wrap_angle_np(faulted[:, 2] - log.odometry[:, 2]), 0.0, atol=1e-9)


def test_a_zero_fault_is_the_identity():
    log = wavy_log()
    np.testing.assert_allclose(cf.drift_and_scale(log.odometry, 0.0, 0.0), log.odometry, atol=1e-9)
    same, slips = cf.apply_cell(log, cf.FaultCell(), seed=4)
    assert same is log and slips.size == 0
    clean, _ = cf.apply_cell(log, cf.CELLS["clean"], seed=0)
    np.testing.assert_array_equal(clean.odometry, log.odometry)
    with pytest.raises(ValueError, match="finite and >= 0"):
        cf.apply_cell(log, cf.FaultCell(drift_deg_per_m=-0.5), seed=0)


@pytest.mark.parametrize("name", ["drift0.5+slips3x25", "drift1+scale3+slips5x40", "drift0.25+scale1+slips3x10"])
def test_combinations_are_drift_and_scale_then_slips_at_the_clean_logs_turns(name):
    log = wavy_log()
    cell = cf.parse_cell(name)
    for seed in (0, 1):
        faulted, slips = cf.apply_cell(log, cell, seed)
        turns = faults.find_turns(log.odometry, log.timestamps, cell.slips, seed, cf.TURN_WINDOW_S)
        np.testing.assert_array_equal(slips, turns)
        drifted = dataclasses.replace(log, odometry=cf.drift_and_scale(log.odometry, cell.drift_deg_per_m,
                                                                      cell.scale_pct))
        expected, _ = faults.inject_faults(drifted, "heading", math.radians(cell.slip_deg), steps=turns)
        np.testing.assert_allclose(faulted.odometry, expected.odometry, atol=1e-12)
        # The slips fall where the slips-only cell's do, and the same seed gives the same log.
        slips_only, only_at = cf.apply_cell(log, cf.FaultCell(slips=cell.slips, slip_deg=cell.slip_deg), seed)
        np.testing.assert_array_equal(only_at, slips)
        np.testing.assert_array_equal(cf.apply_cell(log, cell, seed)[0].odometry, faulted.odometry)
        np.testing.assert_array_equal(faulted.timestamps, log.timestamps)
        np.testing.assert_array_equal(faulted.ranges, log.ranges)
        # At a slip the step's heading change gained the slip on top of the drift.
        k = int(slips[0])
        before, after = _steps(drifted.odometry), _steps(faulted.odometry)
        assert math.degrees(wrap_angle_np(after[k - 1, 2] - before[k - 1, 2])) == pytest.approx(cell.slip_deg)


# ----------------------------------------------------------------------------- the cells

def test_the_cell_list_holds_the_issues_cells_and_the_ladders():
    for name in ("clean", "drift0.1", "drift0.25", "drift0.5", "drift1", "scale1", "scale3", "scale5",
                 "slips3x10", "slips3x25", "slips5x40", "drift0.5+slips3x25", "drift1+scale3+slips5x40"):
        assert name in cf.CELLS
    assert cf.CELLS["drift0.5+slips3x25"] == cf.FaultCell(0.5, 0.0, 3, 25.0)
    assert cf.CELLS["drift1+scale3+slips5x40"] == cf.FaultCell(1.0, 3.0, 5, 40.0)
    assert set(cf.TARGETS) <= set(cf.CELLS)
    for name, cell in cf.CELLS.items():
        assert cf.parse_cell(name) == cell and cf.cell_name(cell) == name


@pytest.mark.parametrize("name, problem", [
    ("drfit0.5", "unknown part 'drfit0.5'"), ("drift", "unknown part"), ("slips3", "unknown part"),
    ("slips3x", "unknown part"), ("drift0.5 + scale3", "unknown part"), ("drift-0.5", "negative size"),
    ("scale-3", "negative size"), ("slips3x-25", "negative size"), ("scale3+drift1", "in the order"),
    ("drift1+drift2", "in the order"), ("drift0", "size zero"), ("slips0x25", "size zero"),
    ("slips3x0", "size zero"), ("", "expected 'clean'"), ("clean+drift1", "unknown part 'clean'")])
def test_the_cell_name_parser_refuses_bad_names(name, problem):
    with pytest.raises(ValueError, match=problem):
        cf.parse_cell(name)


def test_cells_sort_in_the_lists_order_then_by_size():
    assert cf.cell_order(["drift1+scale3+slips5x40", "drift2", "clean", "scale1", "drift1.5"]) == \
        ["clean", "scale1", "drift1+scale3+slips5x40", "drift1.5", "drift2"]


# ----------------------------------------------------------------------------- the table

def fake(dataset, cell, seed, refined, filtered=0.5, closed=0.1, loops=4, failed=False):
    if failed:
        return {"dataset": dataset, "cell": cell, "seed": seed, "failed": "boom"}
    return {"dataset": dataset, "cell": cell, "seed": seed, "refined_trans_mean": refined,
            "filter_trans_mean": filtered, "closed_trans_mean": closed, "loops_kept": loops}


def fake_records():
    return [fake("intel", "clean", 0, 0.04), fake("intel", "clean", 1, 0.02),
            fake("intel", "drift0.5+slips3x25", 0, 0.05), fake("intel", "drift0.5+slips3x25", 1, 0.05),
            fake("intel", "drift1+scale3+slips5x40", 0, 0.09), fake("intel", "drift1+scale3+slips5x40", 1, 0.10),
            fake("aces", "clean", 0, 0.03), fake("aces", "drift0.5+slips3x25", 0, 0.03),
            fake("aces", "drift0.5+slips3x25", 1, None, failed=True),
            fake("aces", "drift1+scale3+slips5x40", 0, 0.05), fake("aces", "drift0.1", 0, 0.2),
            fake("mit-csail", "drift0.5+slips3x25", 0, 0.01)]


def test_the_ratio_and_the_targets_verdicts():
    table = cf.summarize_cells(fake_records())
    first, second = table[("intel", "drift0.5+slips3x25")], table[("intel", "drift1+scale3+slips5x40")]
    assert first["ratio"] == pytest.approx(0.05 / (0.03 + 0.01)) and first["verdict"] == "pass"  # 1.25: on the line
    assert second["ratio"] == pytest.approx(0.095 / 0.04) and second["verdict"] == "fail"  # 2.375 > 2
    assert table[("aces", "drift1+scale3+slips5x40")]["ratio"] == pytest.approx(1.25)
    assert table[("aces", "drift1+scale3+slips5x40")]["verdict"] == "pass"
    crashed = table[("aces", "drift0.5+slips3x25")]
    assert crashed["crashed"] == 1 and crashed["ratio"] == pytest.approx(0.75) and crashed["verdict"] == "fail"
    assert table[("mit-csail", "drift0.5+slips3x25")]["verdict"] == "no clean run"
    assert table[("aces", "drift0.1")]["verdict"] is None and table[("aces", "drift0.1")]["ratio"] == pytest.approx(5.0)
    assert first["filter"] == pytest.approx(0.5) and first["loops_kept"] == pytest.approx(4.0)
    text = cf.closure_faults_markdown(fake_records())
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): line for line in text.splitlines()[4:]}
    assert "1.25" in rows[("intel", "drift0.5+slips3x25")] and "**pass**" in rows[("intel", "drift0.5+slips3x25")]
    assert "2.38" in rows[("intel", "drift1+scale3+slips5x40")] and "**fail**" in rows[("intel", "drift1+scale3+slips5x40")]
    assert "1 (1 crashed)" in rows[("aces", "drift0.5+slips3x25")]
    assert "**" not in rows[("aces", "drift0.1")]
    assert list(rows)[:3] == [("intel", "clean"), ("intel", "drift0.5+slips3x25"), ("intel", "drift1+scale3+slips5x40")]


def test_the_figures_lines_and_the_written_tables(tmp_path):
    records = fake_records() + [fake("intel", "drift0.25", 0, 0.06, filtered=0.9)]
    panels = cf.figure_lines(records)
    xs, refined, filtered, cells = panels["drift"]["intel"]
    assert cells == ["clean", "drift0.25"] and xs == [0.0, 0.25] and refined == [pytest.approx(0.03), 0.06]
    assert filtered == [0.5, 0.9] and "intel" not in panels["scale"]
    assert panels["combination"]["intel"][3] == ["clean", "drift0.5+slips3x25", "drift1+scale3+slips5x40"]
    store = cf.ResultStore(tmp_path / "results.json", {"s": 1}, key=lambda r: (r["dataset"], r["cell"], r["seed"]))
    store.add(*records)
    cf.write_tables(store)
    data = json.loads((tmp_path / "results.json").read_text())
    ratios = {(r["dataset"], r["cell"], r["seed"]): r["refined_ratio"] for r in data["runs"]}
    assert ratios[("intel", "drift0.5+slips3x25", 0)] == pytest.approx(0.05 / 0.05)
    assert ratios[("mit-csail", "drift0.5+slips3x25", 0)] is None
    assert data["cells"]["intel/drift0.5+slips3x25"]["verdict"] == "pass"
    assert (tmp_path / "closure_faults.md").is_file() and (tmp_path / "closure_faults.png").stat().st_size > 0


# ----------------------------------------------------------------------------- main

@pytest.fixture
def data_folder(tmp_path):
    """A folder with empty files named as the datasets' logs and relations (only their presence is checked)."""
    folder = tmp_path / "data"
    folder.mkdir()
    for names in cf.DATASETS.values():
        for name in names:
            (folder / name).write_text("")
    return folder


@pytest.mark.parametrize("argv, problem", [
    (["--faults", "drfit0.5"], "--faults: fault cell 'drfit0.5': unknown part"),
    (["--faults", "clean", "drift-1"], "negative size"),
    (["--datasets", "atlantis"], "unknown dataset(s) atlantis"),
    (["--particles", "0"], "--particles must be at least 1"),
    (["--seeds", "-1"], "--seeds must be >= 0"),
    (["--set", "nonsense"], "--set: "),
    (["--data", "MISSING"], "data folder not found"),
    (["--datasets", "intel", "--data", "EMPTY"], "not found: "),
])
def test_bad_input_is_refused_before_any_run(argv, problem, data_folder, tmp_path, capsys, monkeypatch):
    def no_run(*args, **kwargs):
        raise AssertionError("a run started")

    monkeypatch.setattr(cf, "run_one", no_run)
    (tmp_path / "EMPTY").mkdir()
    argv = [str(tmp_path / a) if a in ("MISSING", "EMPTY") else a for a in argv]
    base = ["--out", str(tmp_path / "out")] + ([] if "--data" in argv else ["--data", str(data_folder)])
    assert cf.main(base + argv) == 2
    err = capsys.readouterr().err
    assert problem in err
    if "EMPTY" in " ".join(argv):
        assert "intel.sort.bag" in err
    assert not (tmp_path / "out").exists()


def test_a_log_that_cannot_be_written_as_carmen_is_refused_before_any_run(data_folder, tmp_path, capsys,
                                                                          monkeypatch):
    """FR-clinic's interleaved beam layouts are not evenly spaced: its faulted copy cannot be mapped."""
    from jaxslam.laser import make_sensor
    from jaxslam.laserlog import LaserLog

    def log_of(angles):
        return LaserLog(np.arange(3.0), np.zeros((3, 3)), np.full((3, angles.size), 2.0, np.float32),
                        make_sensor(angles), source=f"{angles.size} beams")

    even, interleaved = np.linspace(-1.5, 1.5, 9), np.sort(np.concatenate([np.linspace(-1.5, 1.5, 5), [0.1, 0.2]]))
    monkeypatch.setattr(cf.faults, "read_dataset",
                        lambda dataset, data, max_scans: (log_of(interleaved if dataset == "aces" else even), None))
    monkeypatch.setattr(cf, "run_one", lambda *args, **kwargs: pytest.fail("a run started"))
    base = ["--out", str(tmp_path / "out"), "--data", str(data_folder)]
    assert cf.main(base + ["--datasets", "intel", "aces"]) == 2
    assert "aces: its faulted log could not be mapped" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    assert cf.unwritable_log(["intel", "mit-csail"], data_folder, None) is None


def test_main_runs_clean_first_and_skips_finished_runs(data_folder, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(cf, "unwritable_log", lambda *args: None)  # the logs here are empty files

    def fake_run(dataset, cell, seed, out, data, settings, keep_log):
        calls.append((dataset, cell, seed))
        return fake(dataset, cell, seed, 0.02 if cell == "clean" else 0.03)

    monkeypatch.setattr(cf, "run_one", fake_run)
    argv = ["--out", str(tmp_path / "out"), "--data", str(data_folder), "--datasets", "mit-csail",
            "--faults", "drift0.5+slips3x25", "--seeds", "0", "1", "--proposal", "smp"]
    assert cf.main(argv) == 0
    assert calls == [("mit-csail", "clean", 0), ("mit-csail", "drift0.5+slips3x25", 0),
                     ("mit-csail", "clean", 1), ("mit-csail", "drift0.5+slips3x25", 1)]
    assert cf.main(argv) == 0 and len(calls) == 4  # resumed: nothing left to run
    assert "**pass**" in (tmp_path / "out" / "closure_faults.md").read_text()
    assert cf.main(argv[:-1] + ["lp"]) == 2  # the folder holds runs of other settings
