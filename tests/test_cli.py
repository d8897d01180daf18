"""The command line: map, demo, eval, and clear errors for bad input."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.sim import office_scenario
from logs import write_flaser_log


@pytest.fixture(scope="module")
def small_log():
    return office_scenario(jax.random.key(0), num_scans=150, num_beams=181).log.subset(np.arange(50))


def test_map_writes_every_output(tmp_path, small_log, capsys):
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log)
    out = tmp_path / "out"
    code = main(["map", str(log_path), "--particles", "4", "--proposal", "op", "--no-progress",
                 "--set", "linear_update=0.3", "--set", "max_insert_range=8", "--set", "motion.srr=0.05",
                 "--out", str(out)])
    assert code == 0
    for name in ("map.pgm", "map.yaml", "map.png", "trajectory.txt", "summary.json", "slam.png"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans_in_log"] == 50
    assert summary["config"]["num_particles"] == 4
    assert summary["config"]["linear_update"] == 0.3
    assert summary["params"]["motion.srr"] == pytest.approx(0.05)
    assert summary["timings"]["real_time_factor"] > 0
    traj = np.loadtxt(out / "trajectory.txt")
    assert traj.shape == (50, 4)  # one pose per scan of the log, skipped scans included
    assert "processed" in capsys.readouterr().out


def test_map_refine_writes_a_refined_trajectory(tmp_path, small_log):
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=20)
    out = tmp_path / "out"
    assert main(["map", str(log_path), "--particles", "3", "--no-progress", "--refine", "--set", "linear_update=0.3",
                 "--set", "max_insert_range=8", "--out", str(out)]) == 0
    plain, refined = np.loadtxt(out / "trajectory.txt"), np.loadtxt(out / "trajectory_refined.txt")
    assert refined.shape == plain.shape == (20, 4)
    np.testing.assert_array_equal(refined[:, 0], plain[:, 0])  # the same scans, the same stamps
    summary = json.loads((out / "summary.json").read_text())
    assert 0.5 < summary["refinement"]["matched_fraction"] <= 1.0
    assert summary["refinement"]["seconds"] > 0.0


def test_config_file_and_flags(tmp_path, small_log):
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=20)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"config": {"beam_stride": 2, "linear_update": 0.3}, "params": {"likelihood.sigma": 0.08}}))
    out = tmp_path / "out"
    assert main(["map", str(log_path), "--config", str(cfg), "--particles", "3", "--no-progress", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["beam_stride"] == 2
    assert summary["params"]["likelihood.sigma"] == pytest.approx(0.08)


def test_config_file_sets_what_no_flag_overrides(tmp_path, small_log):
    """The command's defaults (--particles 30, --proposal smp) yield to the file; a flag that is
    given wins over it."""
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=12)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"config": {"num_particles": 2, "proposal": "op", "linear_update": 0.3}}))
    out = tmp_path / "out"
    assert main(["map", str(log_path), "--config", str(cfg), "--no-progress", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["config"]["num_particles"], summary["config"]["proposal"]) == (2, "op")
    assert main(["map", str(log_path), "--config", str(cfg), "--particles", "3", "--no-progress",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["config"]["num_particles"], summary["config"]["proposal"]) == (3, "op")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--set", "motion.nope=1"], "unknown parameter"),
        (["--set", "linear_update"], "NAME=VALUE"),
        (["--set", "num_particles=lots"], "num_particles"),
        (["--set", "lookahead.alpha=1.5"], "alpha"),
        (["--set", "lookahead.localizer_gain=0"], "localizer_gain"),
    ],
)
def test_bad_settings_name_the_problem(tmp_path, small_log, capsys, args, message):
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=5)
    assert main(["map", str(log_path), "--no-progress", "--out", str(tmp_path / "o"), *args]) == 2
    assert message in capsys.readouterr().err


def test_bad_log_names_file_and_line(tmp_path, small_log, capsys):
    log_path = tmp_path / "broken.clf"
    write_flaser_log(log_path, small_log, stop=5)
    lines = log_path.read_text().splitlines()
    lines[3] = lines[3][: len(lines[3]) // 2]  # truncate the third FLASER line
    log_path.write_text("\n".join(lines) + "\n")
    assert main(["map", str(log_path), "--no-progress", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "broken.clf" in err and ":4" in err


def test_missing_file_is_a_clear_error(tmp_path, capsys):
    assert main(["map", str(tmp_path / "nope.bag"), "--no-progress"]) == 2
    assert "nope.bag" in capsys.readouterr().err


@pytest.mark.slow  # Monte Carlo or whole-scenario check (python3 -m pytest -m slow)
def test_demo_runs(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--scans", "60", "--particles", "4", "--no-progress", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans_processed"] > 10
    assert (out / "map.png").is_file()
    # The simulated office's truth is known: the demo stores and prints its error against it.
    error = summary["ground_truth_error"]
    assert error["scans"] == summary["scans_processed"]
    for what in ("best_path", "odometry"):
        assert 0.0 <= error[f"{what}_mean_m"] <= error[f"{what}_max_m"] < float("inf")
    printed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("ground truth error")]
    assert len(printed) == 1
    assert f"{error['best_path_mean_m']:.3f} m" in printed[0] and f"{error['odometry_max_m']:.3f} m" in printed[0]


def test_ground_truth_error_is_of_the_processed_scans_and_printed_in_one_line():
    """What the demo stores (summary.json's ground_truth_error) and prints, on made-up paths:
    the best path 0.1 m beside the truth, the odometry 0 to 0.4 m; a real log has no entry."""
    from types import SimpleNamespace

    from jaxslam.cli import _ground_truth_error_line
    from jaxslam.outputs import ground_truth_error

    truth = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], axis=1)
    odometry = truth + np.stack([np.zeros(10), np.linspace(0.0, 0.9, 10), np.zeros(10)], axis=1)
    idx = np.array([0, 2, 4])
    log = SimpleNamespace(ground_truth=truth, odometry=odometry)
    result = SimpleNamespace(selection=SimpleNamespace(indices=idx), best_path=truth[idx] + [0.0, 0.1, 0.0])
    error = ground_truth_error(log, result)
    assert error == pytest.approx({"scans": 3, "best_path_mean_m": 0.1, "best_path_max_m": 0.1,
                                   "odometry_mean_m": 0.2, "odometry_max_m": 0.4})
    line = _ground_truth_error_line(error)
    assert line.startswith("ground truth error at the 3 processed scans") and "ground_truth_error" in line
    assert "mean 0.100 m, max 0.100 m" in line and "odometry mean 0.200 m, max 0.400 m" in line
    assert ground_truth_error(SimpleNamespace(ground_truth=None, odometry=odometry), result) is None


def test_eval_prints_and_writes_the_error_table(tmp_path, capsys):
    t = np.arange(5, dtype=float)
    poses = np.stack([t, np.zeros(5), np.zeros(5)], axis=1)
    traj = tmp_path / "traj.txt"
    traj.write_text("".join(f"{a:.6f} {p[0]} {p[1]} {p[2]}\n" for a, p in zip(t, poses)))
    rel = tmp_path / "rel.txt"
    # Relations that claim 1.1 m per second where the trajectory moved 1.0 m: error 0.1 m each.
    rel.write_text("".join(f"{a:.6f} {a + 1:.6f} 1.1 0 0 0 0 0\n" for a in t[:-1]))
    out = tmp_path / "errors.json"
    assert main(["eval", str(traj), str(rel), "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert table["count"] == 4
    assert table["trans_mean"] == pytest.approx(0.1, abs=1e-5)
    assert "trans_mean" in capsys.readouterr().out


def test_doors_command_writes_a_summary(tmp_path, capsys):
    out = tmp_path / "doors"
    assert main(["doors", "--particles", "200", "--filter", "static", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["filter"] == "static" and summary["particles"] == 200
    assert (out / "static.png").is_file()
    assert "final position error" in capsys.readouterr().out
    assert main(["doors", "--particles", "0", "--out", str(out)]) == 2
    assert "--particles must be >= 1" in capsys.readouterr().err
