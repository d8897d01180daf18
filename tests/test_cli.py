"""The command line: map, demo, eval, and clear errors for bad input."""

from __future__ import annotations

import json
import os

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
    assert summary["params"]["motion.srr"] == 0.05  # as given, not float32 noise (0.05000000074505806)
    assert summary["timings"]["real_time_factor"] > 0
    traj = np.loadtxt(out / "trajectory.txt")
    assert traj.shape == (50, 4)  # one pose per scan of the log, skipped scans included
    assert "processed" in capsys.readouterr().out


def test_map_refine_writes_a_refined_trajectory(tmp_path, small_log):
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=20)
    out = tmp_path / "out"
    assert main(["map", str(log_path), "--particles", "3", "--proposal", "smp", "--no-progress", "--refine",
                 "--set", "linear_update=0.3", "--set", "max_insert_range=8", "--out", str(out)]) == 0
    plain, refined = np.loadtxt(out / "trajectory.txt"), np.loadtxt(out / "trajectory_refined.txt")
    assert refined.shape == plain.shape == (20, 4)
    np.testing.assert_array_equal(refined[:, 0], plain[:, 0])  # the same scans, the same stamps
    summary = json.loads((out / "summary.json").read_text())
    assert 0.5 < summary["refinement"]["matched_fraction"] <= 1.0
    assert summary["refinement"]["odometry_noise_scale"] == [1.0, 1.0, 1.0]  # 20 scans: no loop to trust it by
    assert summary["timings"]["refinement"] > 0.0


def test_config_file_and_flags(tmp_path, small_log):
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=20)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"config": {"beam_stride": 2, "linear_update": 0.3}, "params": {"likelihood.sigma": 0.08}}))
    out = tmp_path / "out"
    assert main(["map", str(log_path), "--config", str(cfg), "--particles", "3", "--proposal", "smp", "--no-progress",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["beam_stride"] == 2
    assert summary["params"]["likelihood.sigma"] == 0.08


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


def _setup_of_a_run(monkeypatch, argv):
    """The (config, settings, params) ``main(argv)`` hands the filter (which is not run)."""
    import jaxslam.cli.map

    seen = []

    def trap(key, log, config, params, settings, **kwargs):
        seen.append((config, settings, params))
        raise KeyboardInterrupt  # main's own way out, exit code 130

    monkeypatch.setattr(jaxslam.pipeline, "run", trap)  # the filter jaxslam map calls (jaxslam.pipeline.map_log)
    assert main(argv) == 130
    return seen[0]


def test_the_map_default_is_the_smp_and_help_shows_the_defaults(tmp_path, small_log, monkeypatch, capsys):
    """One set of defaults (issue 84): jaxslam map runs the library's, the SMP with 30 particles
    (the proposal of the README's figures), and --help says what they are; the LP's own settings
    are the ones --proposal lp runs with."""
    from jaxslam.cli import DEMO_DEFAULTS, MAP_DEFAULTS, build_setup_from_args, make_parser
    from jaxslam.config import SlamConfig, build_setup

    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=12)
    argv = ["map", str(log_path), "--no-progress", "--out", str(tmp_path / "o")]
    config, settings, params = _setup_of_a_run(monkeypatch, argv)
    assert (config.proposal, config.num_particles, config.num_localizers, config.horizon) == ("smp", 30, 100, 5)
    assert (settings.linear_update, settings.angular_update, float(params.lookahead.alpha)) == (0.5, 0.25, 0.5)
    assert SlamConfig().proposal == "smp" and MAP_DEFAULTS.get("proposal", "smp") == "smp"
    # The command's setup is the library's: no second set of defaults to drift from the first.
    assert build_setup_from_args(make_parser().parse_args(argv), MAP_DEFAULTS)[0] == build_setup({})[0]
    lp, _, _ = _setup_of_a_run(monkeypatch, argv + ["--proposal", "lp"])
    assert (lp.proposal, lp.num_particles, lp.num_localizers, lp.horizon) == ("lp", 30, 100, 5)
    sub = make_parser()._subparsers._group_actions[0].choices
    text = " ".join(sub["map"].format_help().split())
    assert "(default lp" not in text
    for words in ("(default smp)", "Defaults: --proposal smp, 30 particles", "SLAM particles N (default 30)",
                  "per SLAM particle (default 100)", "processed scans (default 5)", "(default 0.5)",
                  "after 0.5 m or 0.25 rad of odometry",
                  "LP: num_localizers = 100, horizon = 5, lookahead_initial = scan_match", "JAXSLAM_CACHE_DIR"):
        assert words in text, words
    demo = " ".join(sub["demo"].format_help().split())
    assert f"(default {DEMO_DEFAULTS['proposal']}, as map's" in demo and "(default 20)" in demo
    assert "after 0.25 m or 0.25 rad" in demo


def test_progress_says_reading_and_compiling(tmp_path, small_log, capsys):
    """With the bar on: a word while the log is read, and "compiling..." before the first chunk."""
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=8)
    assert main(["map", str(log_path), "--particles", "2", "--proposal", "op", "--set", "linear_update=0.3",
                 "--set", "max_insert_range=8", "--out", str(tmp_path / "o"), "--odometry-lead", "0.05"]) == 0
    err = capsys.readouterr().err
    assert f"reading {log_path} ..." in err
    assert "compiling..." in err and err.index("reading") < err.index("compiling...")
    # --odometry-lead: the odometry read 0.05 s earlier, and the summary says so.
    notes = json.loads((tmp_path / "o" / "summary.json").read_text())["log_notes"]
    assert any("odometry read 0.050 s earlier" in note for note in notes), notes


@pytest.mark.parametrize(
    "args, message",
    [
        (["--set", "motion.nope=1"], "unknown name"),
        (["--set", "linear_update"], "NAME=VALUE"),
        (["--set", "num_particles=lots"], "num_particles"),
        (["--set", "lookahead.alpha=1.5"], "alpha"),
        (["--set", "lookahead.localizer_gain=0"], "localizer_gain"),
        (["--odometry-lead", "soon"], "--odometry-lead 'soon': give auto or a number of seconds"),
        (["--odometry-lead", "nan"], "--odometry-lead 'nan'"),
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

    from jaxslam.cli.demo import _ground_truth_error_line
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
    # Relations that claim 1.1 m per second where the trajectory moved 1.0 m: error 0.1 m each;
    # and one that claims the robot slid 0.5 m sideways as it went 1 m ahead: error 0.5 m.
    rel.write_text("".join(f"{a:.6f} {a + 1:.6f} 1.1 0 0 0 0 0\n" for a in t[:-1]) + "0 1 1.0 0.5 0 0 0 0\n")
    out = tmp_path / "errors.json"
    assert main(["eval", str(traj), str(rel), "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert table["count"] == 5
    assert table["trans_mean"] == pytest.approx(0.9 / 5, abs=1e-5)
    assert table["sideways_count"] == 1
    assert table["trans_mean_no_sideways"] == pytest.approx(0.1, abs=1e-5)
    printed = capsys.readouterr().out
    assert "trans_mean" in printed and "sideways_count" in printed


def test_doors_command_writes_a_summary(tmp_path, capsys):
    out = tmp_path / "doors"
    assert main(["doors", "--particles", "200", "--filter", "static", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["filter"] == "static" and summary["particles"] == 200
    assert (out / "static.png").is_file()
    assert "final position error" in capsys.readouterr().out
    assert main(["doors", "--particles", "0", "--out", str(out)]) == 2
    assert "--particles must be >= 1" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# The persistent compilation cache (jaxslam.compile_cache): on for the command line only.


def test_the_cache_folder_follows_the_environment(tmp_path):
    from pathlib import Path

    from jaxslam.compile_cache import cache_dir

    assert cache_dir({"JAXSLAM_CACHE_DIR": str(tmp_path / "c")}) == tmp_path / "c"
    for off in ("off", "OFF", "0", "none"):
        assert cache_dir({"JAXSLAM_CACHE_DIR": off}) is None
    assert cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "jaxslam" / "jax"
    assert cache_dir({"JAXSLAM_CACHE_DIR": " ", "HOME": str(tmp_path)}).parts[-3:] == (".cache", "jaxslam", "jax")
    assert cache_dir({}) == Path.home() / ".cache" / "jaxslam" / "jax"


_COUNT_CACHE_EVENTS = """
import sys
import jax.monitoring
events = {"hits": 0, "writes": 0}
def listen(event, **kwargs):
    if event == "/jax/compilation_cache/cache_hits":
        events["hits"] += 1
    elif event == "/jax/compilation_cache/cache_misses":  # recorded as an entry is written
        events["writes"] += 1
jax.monitoring.register_event_listener(listen)
import jaxslam
assert not jax.config.jax_compilation_cache_dir, "import jaxslam turned the cache on"
from jaxslam.cli import main
code = main(sys.argv[1:])
print("CACHE", events["hits"], events["writes"])
sys.exit(code)
"""


def _run_cli_process(args, env_updates):
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # the test session's cache (conftest): this test's is its own
    env.update(env_updates)
    repo = str(Path(__file__).resolve().parents[1])  # this checkout's jaxslam, not an installed one
    env["PYTHONPATH"] = os.pathsep.join([repo, env["PYTHONPATH"]]) if env.get("PYTHONPATH") else repo
    proc = subprocess.run([sys.executable, "-c", _COUNT_CACHE_EVENTS, *args], capture_output=True, text=True,
                          env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    hits, writes = (int(v) for v in proc.stdout.split("CACHE ")[1].split()[:2])
    return hits, writes, proc


def test_a_second_run_reads_its_compilations_from_the_cache(tmp_path, small_log):
    """The same command twice, each in a fresh process: the first compiles and writes the cache
    folder, the second finds every entry there (JAX's cache-hit events) and writes none."""
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=12)
    cache = tmp_path / "cache"
    args = ["map", str(log_path), "--particles", "2", "--proposal", "op", "--no-progress", "--set",
            "linear_update=0.3", "--set", "max_insert_range=8", "--out", str(tmp_path / "out")]
    hits, writes, _ = _run_cli_process(args, {"JAXSLAM_CACHE_DIR": str(cache)})
    entries = sorted(p.name for p in cache.glob("*-cache"))
    assert hits == 0 and writes == len(entries) > 0
    hits, writes, _ = _run_cli_process(args, {"JAXSLAM_CACHE_DIR": str(cache)})
    assert sorted(p.name for p in cache.glob("*-cache")) == entries  # nothing new
    assert writes == 0 and hits >= len(entries)
    hits, writes, _ = _run_cli_process([*args, "--no-cache"], {"JAXSLAM_CACHE_DIR": str(cache)})
    assert hits == writes == 0


def test_an_unusable_cache_folder_is_warned_of_once_and_the_run_goes_on(tmp_path, small_log, capsys, monkeypatch):
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=8)
    (tmp_path / "a_file").write_text("not a folder\n")
    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "a_file" / "cache"))  # cannot be created, even by root
    import jax

    before = jax.config.jax_compilation_cache_dir
    assert main(["map", str(log_path), "--particles", "2", "--proposal", "op", "--no-progress", "--set",
                 "linear_update=0.3", "--set", "max_insert_range=8", "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    warned = [line for line in err if "compilation cache" in line]
    assert len(warned) == 1 and warned[0].startswith("jaxslam map: warning: the compilation cache folder"), err
    assert "running without it" in warned[0] and str(tmp_path / "a_file" / "cache") in warned[0]
    assert (tmp_path / "out" / "map.pgm").is_file()
    assert jax.config.jax_compilation_cache_dir == before  # left as it was


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores file permissions")
def test_a_read_only_cache_folder_is_not_used(tmp_path):
    from jaxslam.compile_cache import enable

    (tmp_path / "ro").mkdir(mode=0o500)
    try:
        folder, warning = enable(environ={"JAXSLAM_CACHE_DIR": str(tmp_path / "ro")})
    finally:
        os.chmod(tmp_path / "ro", 0o700)
    assert folder is None and "cannot be used" in warning and "running without it" in warning
    assert list((tmp_path / "ro").iterdir()) == []
