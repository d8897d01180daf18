"""Every bad input is refused before any work, on one line, with exit code 2; outputs are never mixed.

The corpus is generated here (no stored files): each case writes what it needs (a small
synthetic CARMEN log, a config file, a file or a read-only folder where the output should go)
and runs the command line in-process, with the log reader and the filter replaced by traps,
so a refusal that came after the work started fails the test.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.config import ConfigError, build_setup
from jaxslam.io.files import publish_folder
from jaxslam.outputs import SLAM_OUTPUT_NAMES, strict_json_values
from jaxslam.sim import office_scenario
from logs import write_flaser_log

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture(scope="module")
def small_log():
    return office_scenario(jax.random.key(0), num_scans=150, num_beams=181).log.subset(np.arange(12))


# ---------------------------------------------------------------------------------------------
# The corpus: (case id, command and arguments, words the message must hold, setup).
# Arguments may hold {log}, {cfg}, {out}, {file}, {ro}, {traj}, {rel}: paths made by the setup.


def _config(content):
    """Setup: write ``content`` (an object as JSON, or a string as is) as the config file."""
    def setup(paths):
        text = content if isinstance(content, str) else json.dumps(content)
        paths["cfg"].write_text(text)
    return setup


def _sets(*items):
    return [a for item in items for a in ("--set", item)]


MAP = ["map", "{log}", "--no-progress", "--out", "{out}"]
WITH_CFG = [*MAP, "--config", "{cfg}"]

CASES = [
    # Config values from a config file: exact types, finite numbers, physical ranges.
    ("cfg-int-given-float", WITH_CFG, ["beam_stride must be an integer, got 2.9"], _config({"config": {"beam_stride": 2.9}})),
    ("cfg-int-given-bool", WITH_CFG, ["beam_stride must be an integer, got True"], _config({"config": {"beam_stride": True}})),
    ("cfg-int-given-whole-float", WITH_CFG, ["num_localizers must be an integer, got 50.0"],
     _config({"config": {"num_localizers": 50.0}})),
    ("cfg-float-given-bool", WITH_CFG, ["linear_update must be a number, got False"],
     _config({"config": {"linear_update": False}})),
    ("cfg-nan", WITH_CFG, ["linear_update must be a finite number", "nan"], _config('{"config": {"linear_update": NaN}}')),
    ("cfg-infinity-param", WITH_CFG, ["motion.srr must be a finite number", "inf"],
     _config('{"params": {"motion.srr": Infinity}}')),
    ("cfg-zero-particles", WITH_CFG, ["num_particles must be >= 1, got 0"], _config({"config": {"num_particles": 0}})),
    ("cfg-negative-resolution", WITH_CFG, ["resolution must be > 0", "-0.05"], _config({"config": {"resolution": -0.05}})),
    ("cfg-proposal-number", WITH_CFG, ["proposal must be a string, got 5"], _config({"config": {"proposal": 5}})),
    ("cfg-proposal-unknown", WITH_CFG, ["proposal must be one of", "'ekf'"], _config({"config": {"proposal": "ekf"}})),
    ("cfg-field-radius", WITH_CFG, ["field_radius must be in 1..11", "got 12"], _config({"config": {"field_radius": 12}})),
    ("cfg-param-string", WITH_CFG, ["motion.srr must be a number", "'fast'"], _config({"params": {"motion.srr": "fast"}})),
    # Config-file structures.
    ("cfg-config-not-object", WITH_CFG, ["'config' must be a JSON object"], _config({"config": 5})),
    ("cfg-params-list", WITH_CFG, ["'params' must be a JSON object"], _config({"params": [1, 2]})),
    ("cfg-top-level-list", WITH_CFG, ["expected a JSON object"], _config([1, 2])),
    ("cfg-unknown-section", WITH_CFG, ["expected a JSON object with keys 'config' and/or 'params'"],
     _config({"settings": {"linear_update": 1}})),
    ("cfg-not-json", WITH_CFG, ["cannot read config file"], _config("{config: nope")),
    ("cfg-missing-file", [*MAP, "--config", "{out}.json"], ["cannot read config file"], None),
    ("cfg-unknown-field", WITH_CFG, ["unknown name", "map_padding", "config or run settings field", "dotted parameter"],
     _config({"config": {"map_padding": 5}})),
    ("cfg-tile-size", WITH_CFG, ["tile_size must be a power of two", "got 48"], _config({"config": {"tile_size": 48}})),
    ("set-extent-negative", [*MAP, *_sets("map_extent=-5")], ["map_extent must be > 0", "-5"], None),
    ("set-int-given-float", [*MAP, *_sets("beam_stride=2.9")], ["beam_stride must be a", "integer", "'2.9'"], None),
    ("set-int-given-word", [*MAP, *_sets("num_particles=lots")], ["num_particles", "integer", "'lots'"], None),
    ("set-no-equals", [*MAP, *_sets("linear_update")], ["NAME=VALUE"], None),
    ("set-unknown", [*MAP, *_sets("motion.nope=1")], ["unknown name", "motion.nope", "map_extent", "motion.srr"], None),
    ("set-inf-setting", [*MAP, *_sets("linear_update=inf")], ["linear_update must be a finite number"], None),
    ("set-negative-horizon", [*MAP, *_sets("horizon=-1")], ["horizon must be >= 0, got -1"], None),
    ("set-zero-insert-range", [*MAP, *_sets("max_insert_range=0")], ["max_insert_range must be > 0"], None),
    ("set-angular-update-negative", [*MAP, *_sets("angular_update=-0.1")], ["angular_update must be >= 0"], None),
    ("set-linear-update-negative", [*MAP, *_sets("linear_update=-1")], ["linear_update must be >= 0", "-1"], None),
    # Every numeric setting against its own range, before any arithmetic uses it (resolution = 0
    # was a ZeroDivisionError in map_extent / resolution).
    ("set-zero-resolution", [*MAP, *_sets("resolution=0")], ["resolution must be > 0", "got 0.0"], None),
    ("set-tiny-resolution", [*MAP, *_sets("resolution=1e-9")], ["map_extent / resolution must be at most 46,340"],
     None),
    ("set-zero-extent", [*MAP, *_sets("map_extent=0")], ["map_extent must be > 0", "got 0.0"], None),
    ("set-zero-particles", [*MAP, *_sets("num_particles=0")], ["num_particles must be >= 1, got 0"], None),
    ("set-zero-beam-stride", [*MAP, *_sets("beam_stride=0")], ["beam_stride must be >= 1, got 0"], None),
    ("set-zero-field-radius", [*MAP, *_sets("field_radius=0")], ["field_radius must be in 1..11", "got 0"], None),
    ("set-negative-match-iterations", [*MAP, *_sets("match_iterations=-1")], ["match_iterations must be >= 0"],
     None),
    ("set-zero-refine-rounds", [*MAP, *_sets("refine_rounds=0")], ["refine_rounds must be >= 1, got 0"], None),
    ("set-zero-localizers", [*MAP, *_sets("num_localizers=0")], ["num_localizers must be >= 1, got 0"], None),
    ("set-zero-tile-size", [*MAP, *_sets("tile_size=0")], ["tile_size must be a power of two", "got 0"], None),
    # Physically invalid parameters.
    ("param-negative-noise", [*MAP, *_sets("motion.srr=-0.1")], ["motion.srr must be >= 0", "-0.1"], None),
    ("param-negative-std-floor", [*MAP, *_sets("motion.min_rotation_std=-1e-3")], ["min_rotation_std must be >= 0"], None),
    ("param-zero-sigma", [*MAP, *_sets("likelihood.sigma=0")], ["likelihood.sigma must be > 0", "got 0.0"], None),
    ("param-negative-z-hit", [*MAP, *_sets("likelihood.z_hit=-0.5")], ["likelihood.z_hit must be >= 0"], None),
    ("param-zero-z-rand", [*MAP, *_sets("likelihood.z_rand=0")], ["likelihood.z_rand must be > 0"], None),
    ("param-nan-gain", [*MAP, *_sets("likelihood.gain=nan")], ["likelihood.gain must be a finite number", "nan"], None),
    ("param-zero-gain", [*MAP, *_sets("likelihood.gain=0")], ["likelihood.gain must be > 0"], None),
    ("param-positive-free", [*MAP, *_sets("insertion.logodds_free=0.4")], ["logodds_free must be < 0", "0.4"], None),
    ("param-negative-occupied", [*MAP, *_sets("insertion.logodds_occupied=-0.85")], ["logodds_occupied must be > 0"],
     None),
    ("param-clamp-above-zero", [*MAP, *_sets("insertion.logodds_min=1")], ["logodds_min must be < 0"], None),
    ("param-clamp-below-zero", [*MAP, *_sets("insertion.logodds_max=-1")], ["logodds_max must be > 0"], None),
    ("param-zero-step", [*MAP, *_sets("scan_match.linear_step=0")], ["scan_match.linear_step must be > 0"], None),
    ("param-negative-angular-step", [*MAP, *_sets("scan_match.angular_step=-0.05")], ["angular_step must be > 0"], None),
    ("param-negative-min-score", [*MAP, *_sets("scan_match.min_score=-0.1")], ["min_score must be >= 0"], None),
    ("param-negative-resample", [*MAP, *_sets("resample_threshold=-0.5")], ["resample_threshold must be >= 0"], None),
    ("param-alpha-one", [*MAP, *_sets("lookahead.alpha=1")], ["lookahead.alpha must be in [0, 1)", "1.0"], None),
    ("param-correction", [*MAP, *_sets("lookahead.selection_correction=0.5")], ["selection_correction must be 0 or 1"],
     None),
    ("param-alpha-flag-nan", [*MAP, "--alpha", "nan"], ["lookahead.alpha must be a finite number"], None),
    # Flags.
    ("chunk-size-zero", [*MAP, "--chunk-size", "0"], ["--chunk-size must be an integer >= 1", "got 0"], None),
    ("chunk-size-negative", [*MAP, "--chunk-size", "-4"], ["--chunk-size must be an integer >= 1", "got -4"], None),
    ("chunk-size-word", [*MAP, "--chunk-size", "big"], ["--chunk-size", "invalid int value", "'big'"], None),
    ("seed-negative", [*MAP, "--seed", "-1"], ["--seed must be an integer in [0, 2**32 - 1", "got -1"], None),
    ("seed-too-large", [*MAP, "--seed", str(2**32)], ["--seed must be an integer in [0", "got 4294967296"], None),
    ("particles-zero", [*MAP, "--particles", "0"], ["--particles must be an integer >= 1", "got 0"], None),
    ("particles-fraction", [*MAP, "--particles", "2.5"], ["--particles", "invalid int value", "'2.5'"], None),
    ("localizers-zero", [*MAP, "--localizers", "0"], ["--localizers must be an integer >= 1"], None),
    ("max-scans-zero", [*MAP, "--max-scans", "0"], ["--max-scans must be an integer >= 1"], None),
    ("proposal-unknown-flag", [*MAP, "--proposal", "ekf"], ["--proposal", "invalid choice", "'ekf'"], None),
    ("demo-chunk-size", ["demo", "--no-progress", "--out", "{out}", "--chunk-size", "0"],
     ["jaxslam demo: error:", "--chunk-size"], None),
    ("demo-scans", ["demo", "--no-progress", "--out", "{out}", "--scans", "1"], ["--scans must be an integer >= 2"], None),
    ("doors-seed", ["doors", "--out", "{out}", "--seed", "-5"], ["jaxslam doors: error:", "--seed", "got -5"], None),
    # Output folders.
    ("out-is-a-file", ["map", "{log}", "--no-progress", "--out", "{file}"], ["--out", "is an existing file"], None),
    ("out-under-a-file", ["map", "{log}", "--no-progress", "--out", "{file}/sub"], ["--out", "is a file, not a folder"],
     None),
    ("doors-out-is-a-file", ["doors", "--out", "{file}"], ["jaxslam doors: error: --out", "is an existing file"], None),
    ("eval-out-is-a-folder", ["eval", "{traj}", "{rel}", "--out", "{ro}"], ["jaxslam eval: error: --out",
                                                                            "is an existing folder"], None),
]

READ_ONLY_CASES = [
    ("out-read-only-folder", ["map", "{log}", "--no-progress", "--out", "{ro}"], ["--out", "cannot be written"]),
    ("out-in-read-only-folder", ["map", "{log}", "--no-progress", "--out", "{ro}/new"],
     ["--out", "cannot be created", "not writable"]),
    ("eval-out-in-read-only-folder", ["eval", "{traj}", "{rel}", "--out", "{ro}/errors.json"],
     ["jaxslam eval: error: --out", "not writable"]),
]


def _prepare(tmp_path, small_log):
    paths = {"log": tmp_path / "office.clf", "cfg": tmp_path / "cfg.json", "out": tmp_path / "out",
             "file": tmp_path / "a_file.txt", "ro": tmp_path / "ro", "traj": tmp_path / "traj.txt",
             "rel": tmp_path / "rel.txt"}
    write_flaser_log(paths["log"], small_log)
    paths["file"].write_text("not a folder\n")
    paths["ro"].mkdir()
    paths["traj"].write_text("0 0 0 0\n1 1 0 0\n")
    paths["rel"].write_text("0 1 1 0 0 0 0 0\n")
    return paths


@pytest.fixture
def no_work(monkeypatch):
    """Traps: reading the log, running a filter or reading a trajectory fails the test (patched
    where the commands read them: ``jaxslam.cli.map``, ``jaxslam.cli.evaluate``)."""
    import jaxslam.cli.evaluate
    import jaxslam.cli.map
    import jaxslam.localization.doors
    import jaxslam.localization.mcl

    def trap(*args, **kwargs):
        raise AssertionError("the work started before the input was refused")

    monkeypatch.setattr(jaxslam.cli.map, "read_log", trap)
    monkeypatch.setattr(jaxslam.cli.evaluate, "read_trajectory", trap)
    monkeypatch.setattr(jaxslam.pipeline, "run", trap)
    monkeypatch.setattr(jaxslam.localization.doors, "filter", trap)
    monkeypatch.setattr(jaxslam.localization.mcl, "filter", trap)


def _run_refused(argv, words, capsys):
    try:
        code = main(argv)
    except SystemExit as exit_:  # argparse's own refusals
        code = exit_.code
    captured = capsys.readouterr()
    err = captured.err
    assert code == 2, (argv, err)
    assert "Traceback" not in err and "Traceback" not in captured.out
    lines = err.strip().splitlines()
    assert len(lines) == 1, err  # one line ...
    command = argv[0]
    assert lines[0].startswith(f"jaxslam {command}: error: "), err  # ... jaxslam <command>: error: ...
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


def test_the_corpus_is_large_enough():
    assert len(CASES) + len(READ_ONLY_CASES) >= 25
    assert len({case[0] for case in CASES + READ_ONLY_CASES}) == len(CASES) + len(READ_ONLY_CASES)


@pytest.mark.parametrize("case_id, argv, words, setup", CASES, ids=[case[0] for case in CASES])
def test_bad_input_is_refused_before_any_work(case_id, argv, words, setup, tmp_path, small_log, capsys, no_work):
    paths = _prepare(tmp_path, small_log)
    if setup is not None:
        setup(paths)
    argv = [a.format(**paths) for a in argv]
    _run_refused(argv, words, capsys)
    assert not paths["out"].exists()  # no output folder appeared
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # nor a temporary one


@pytest.mark.skipif(IS_ROOT, reason="root ignores file permissions")
@pytest.mark.parametrize("case_id, argv, words", READ_ONLY_CASES, ids=[case[0] for case in READ_ONLY_CASES])
def test_read_only_output_is_refused_before_any_work(case_id, argv, words, tmp_path, small_log, capsys, no_work):
    paths = _prepare(tmp_path, small_log)
    os.chmod(paths["ro"], 0o500)
    try:
        _run_refused([a.format(**paths) for a in argv], words, capsys)
        assert list(paths["ro"].iterdir()) == []
    finally:
        os.chmod(paths["ro"], 0o700)


def test_a_real_process_refuses_on_one_line_without_a_traceback(tmp_path, small_log):
    """The same through ``python -m jaxslam.cli``: exit status 2, one line on stderr."""
    write_flaser_log(tmp_path / "office.clf", small_log)
    for args, word in ((["--set", "motion.srr=-1"], "motion.srr must be >= 0"),
                       (["--particles", "many"], "invalid int value")):
        proc = subprocess.run([sys.executable, "-m", "jaxslam.cli", "map", str(tmp_path / "office.clf"),
                               "--no-progress", "--out", str(tmp_path / "out"), *args],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr
        assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
        assert proc.stderr.startswith("jaxslam map: error: ") and word in proc.stderr
        assert not (tmp_path / "out").exists()


def test_every_numeric_setting_has_a_range_checked_before_any_arithmetic():
    """Every parameter has a range; every int and float field refuses an out-of-range value
    (-1, and 0 where it must be positive) with a ConfigError naming it, never another error."""
    import dataclasses

    from jaxslam.config import RunSettings, SlamConfig, param_defaults, param_ranges
    from jaxslam.proposals import proposal_settings

    assert set(param_ranges()) == set(param_defaults())
    numeric = [f.name for cls in (SlamConfig, RunSettings) for f in dataclasses.fields(cls)
               if type(f.default) in (int, float)]
    numeric += [name for name, setting in proposal_settings().items() if type(setting.default) in (int, float)]
    assert {"num_localizers", "horizon"} <= set(numeric)  # the proposals' own settings too
    positive = {"num_particles", "resolution", "map_extent", "tile_size", "max_insert_range", "field_radius",
                "beam_stride", "num_localizers"}
    for name in numeric:
        for bad in (-1, 0) if name in positive else (-1,):
            with pytest.raises(ConfigError, match=name):
                build_setup({name: str(bad)})


def test_settings_wrong_for_the_log_are_refused_before_the_run(small_log):
    import dataclasses

    from jaxslam.laser import make_sensor
    from jaxslam.rbpf import check_config_for_log, prepare

    config, _, _ = build_setup({"beam_stride": small_log.num_beams})
    check_config_for_log(small_log, config)  # every num_beams-th beam: one, but allowed
    with pytest.raises(ConfigError, match=f"beam_stride={small_log.num_beams + 1} is more than"):
        prepare(small_log, build_setup({"beam_stride": small_log.num_beams + 1})[0])
    sensor = small_log.sensor
    near_blind = dataclasses.replace(small_log, sensor=make_sensor(sensor.beam_angles, range_min=1.0,
                                                                   range_max=float(sensor.range_max)))
    with pytest.raises(ConfigError, match="max_insert_range=0.5 m is not above the laser's range_min=1 m"):
        prepare(near_blind, build_setup({"max_insert_range": 0.5})[0])


def test_values_that_are_legitimate_are_accepted():
    """What the bounds must not refuse: strings from --set that parse, NumPy scalars, values
    above 1 that the tests and docs use as "always" (resample thresholds) or "never" (min_score)."""
    config, settings, params = build_setup({
        "beam_stride": "3", "num_particles": np.int64(5), "max_insert_range": 8, "linear_update": "0",
        "resample_threshold": 1.01, "lookahead.resample_threshold": 2.0, "scan_match.min_score": 1.01,
        "motion.srr": 0, "motion.srt": np.float32(0.0), "likelihood.z_hit": 0, "scan_match.window_sigmas": "3",
        "map_extent": "100", "resolution": 0.1, "horizon": 0,
    })
    assert config.beam_stride == 3 and type(config.beam_stride) is int
    assert config.num_particles == 5 and type(config.num_particles) is int
    assert config.max_insert_range == 8.0 and type(config.max_insert_range) is float
    assert config.map_extent == 100.0 and config.grid.num_tiles == (16, 16) and config.grid.origin == (-51.2, -51.2)
    assert settings.linear_update == 0.0
    assert float(params.resample_threshold) == pytest.approx(1.01)
    with pytest.raises(ConfigError, match="beam_stride must be an integer, got 2.9"):
        build_setup({"beam_stride": 2.9})


# ---------------------------------------------------------------------------------------------
# Outputs: atomic, stale files removed, strict JSON.


def test_publish_folder_replaces_the_whole_folder(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "trajectory_refined.txt").write_text("stale\n")  # an earlier run's, not written now
    (target / "map.pgm").write_text("old map\n")
    (target / "notes.txt").write_text("mine\n")  # not a SLAM output: kept
    (target / "extra").mkdir()
    (target / "extra" / "x.txt").write_text("x\n")

    def write(folder):
        assert folder.parent == tmp_path and folder.name.startswith(".out.tmp-")
        (folder / "map.pgm").write_text("new map\n")
        (folder / "summary.json").write_text("{}")

    publish_folder(target, write, SLAM_OUTPUT_NAMES)
    assert sorted(p.name for p in target.iterdir()) == ["extra", "map.pgm", "notes.txt", "summary.json"]
    assert (target / "map.pgm").read_text() == "new map\n"
    assert (target / "notes.txt").read_text() == "mine\n" and (target / "extra" / "x.txt").read_text() == "x\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary or backup folder left


def test_a_failed_write_leaves_the_old_folder_untouched(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    for name in SLAM_OUTPUT_NAMES:
        (target / name).write_text(f"old {name}\n")
    before = {p.name: p.read_text() for p in target.iterdir()}

    def write(folder):
        (folder / "map.pgm").write_text("half of a new run\n")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        publish_folder(target, write, SLAM_OUTPUT_NAMES)
    assert {p.name: p.read_text() for p in target.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_publish_folder_makes_a_new_folder_and_its_parents(tmp_path):
    target = tmp_path / "a" / "b" / "out"
    publish_folder(target, lambda folder: (folder / "summary.json").write_text("{}"), SLAM_OUTPUT_NAMES)
    assert [p.name for p in target.iterdir()] == ["summary.json"]
    assert oct(target.stat().st_mode & 0o777) == oct(0o777 & ~_umask())


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_a_second_run_removes_the_first_runs_stale_files(tmp_path, small_log):
    """A run with --refine (the default), then one with --no-refine into the same folder:
    trajectory_refined.txt goes."""
    log_path = tmp_path / "office.clf"
    write_flaser_log(log_path, small_log, stop=8)
    out = tmp_path / "out"
    common = ["map", str(log_path), "--particles", "2", "--proposal", "op", "--no-progress",
              "--set", "linear_update=0.3", "--set", "max_insert_range=8", "--out", str(out)]
    assert main([*common, "--refine"]) == 0
    assert (out / "trajectory_refined.txt").is_file()
    (out / "errors.json").write_text("{}")  # e.g. jaxslam eval's table: not a map output, kept
    assert main([*common, "--no-refine"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["map.pgm", "map.yaml", "map.png", "trajectory.txt", "trajectory_filter.txt", "graph.npz",
                            "graph.png", "summary.json", "slam.png", "steps.npz", "errors.json"])
    summary = json.loads((out / "summary.json").read_text())
    assert "refinement" not in summary and summary["null_reasons"] == {}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["office.clf", "out"]


def test_strict_json_nulls_non_finite_numbers_with_reasons():
    summary = {"log_evidence": float("-inf"), "mean_ess": None, "timings": {"total": 1.0, "real_time_factor": math.inf},
               "values": [1.0, float("nan")], "params": {"a": np.float32(0.5)}, "count": np.int64(3)}
    clean, reasons = strict_json_values(summary, {"log_evidence": "every particle's weight was zero at step 12",
                                                   "mean_ess": "no step was taken"})
    text = json.dumps(clean, allow_nan=False)  # strict JSON
    assert "NaN" not in text and "Infinity" not in text
    assert clean["log_evidence"] is None and clean["timings"]["real_time_factor"] is None
    assert clean["values"] == [1.0, None] and clean["params"]["a"] == 0.5 and clean["count"] == 3
    assert reasons["log_evidence"] == "every particle's weight was zero at step 12"
    assert reasons["mean_ess"] == "no step was taken"
    assert "inf" in reasons["timings.real_time_factor"] and "nan" in reasons["values[1]"]


def test_a_degenerate_run_writes_null_log_evidence_with_its_step(tmp_path, small_log, monkeypatch):
    """A run whose every particle's weight went to zero at a step: log_evidence is null in
    summary.json, and null_reasons names the step and the scan."""
    import jaxslam.slam
    from jaxslam.config import default_params
    from jaxslam.outputs import write_slam_outputs

    config, settings, params = build_setup({"num_particles": 2, "proposal": "op", "linear_update": 0.3,
                                            "max_insert_range": 8.0})
    result = jaxslam.slam.run(jax.random.key(0), small_log, config, default_params(), settings, progress=False)
    steps = result.info.degenerate.shape[0]
    degenerate = np.zeros(steps, bool)
    degenerate[2] = True
    log_evidence = np.asarray(result.info.log_evidence).copy()
    log_evidence[2] = -np.inf
    result = result._replace(info=result.info._replace(degenerate=degenerate, log_evidence=log_evidence))
    summary = write_slam_outputs(tmp_path / "out", small_log, result, params, seed=0, source="test")
    written = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert written == summary
    assert written["log_evidence"] is None
    scan = int(result.selection.indices[3])
    assert written["null_reasons"]["log_evidence"].startswith(f"every particle's weight was zero at step 3 (scan {scan}")
    assert "NaN" not in (tmp_path / "out" / "summary.json").read_text()


# ---------------------------------------------------------------------------------------------
# The memory check: a run that cannot fit is refused before the filter runs, naming the estimate.


def _trap_filter(monkeypatch):
    import jaxslam.cli.map

    def trap(*args, **kwargs):
        raise AssertionError("the filter ran")

    monkeypatch.setattr(jaxslam.pipeline, "run", trap)  # the filter jaxslam map calls (jaxslam.pipeline.map_log)


def test_the_memory_estimate_counts_page_tables_pool_insertion_lp_terms_and_xla():
    from jaxslam.config import SlamConfig
    from jaxslam.rbpf import pool_size
    from jaxslam.resources import estimate_run_bytes

    config = SlamConfig(num_particles=10)
    need, how = estimate_run_bytes(config, 181)
    pools = pool_size(config)
    samples = 15 * 20 + 1  # max_insert_range 15 m at 5 cm, one sample a cell
    assert need == ((10 * 25 * 25 + pools.block_capacity * 16 * 16) * 4 * 2 + pools.capacity * 64 * 64 * 3 * 2
                    + 10 * 181 * samples * 40 + 2**30)
    assert how.startswith(f"(10 particles x 25 x 25 blocks + {pools.block_capacity} blocks x 16 x 16 tiles) x 4 "
                          f"bytes x 2 + {pools.capacity} tiles x 64 x 64 cells")
    lp, how_lp = estimate_run_bytes(SlamConfig(num_particles=10, proposal="lp", num_localizers=50), 181)
    assert lp == need + 10 * 50 * 91 * 4 * 2 and "50 localizers x 91 beams" in how_lp


def test_available_memory_is_read_from_meminfo():
    from jaxslam.resources import available_memory_bytes

    available = available_memory_bytes()
    if not Path("/proc/meminfo").is_file():
        assert available is None
    else:
        assert available is not None and available > 2**20


def test_a_run_too_large_for_the_machine_is_refused_before_the_filter(tmp_path, small_log, capsys, monkeypatch):
    write_flaser_log(tmp_path / "office.clf", small_log)
    _trap_filter(monkeypatch)
    argv = ["map", str(tmp_path / "office.clf"), "--particles", "100000", "--set", "map_extent=2000",
            "--no-progress", "--out", str(tmp_path / "out")]
    line = _run_refused(argv, ["the run needs about", "100000 particles x", "GB are available", "--particles",
                               "map_extent"], capsys)
    assert int(line.split("needs about ")[1].split()[0]) > 300  # GB: 100000 x 625 x 625 tiles x 4 bytes x 2
    assert not (tmp_path / "out").exists()


def test_a_log_leaving_the_map_is_refused_before_the_filter(tmp_path, small_log, capsys, monkeypatch):
    write_flaser_log(tmp_path / "office.clf", small_log)
    _trap_filter(monkeypatch)
    argv = ["map", str(tmp_path / "office.clf"), "--set", "map_extent=2", "--no-progress", "--out",
            str(tmp_path / "out")]
    _run_refused(argv, ["beyond the map", "map_extent=2 m", "--set map_extent="], capsys)
    assert not (tmp_path / "out").exists()


def test_the_memory_refusal_names_the_numbers(tmp_path, small_log, capsys, monkeypatch):
    import jaxslam.cli.map
    import jaxslam.resources

    write_flaser_log(tmp_path / "office.clf", small_log)
    _trap_filter(monkeypatch)
    monkeypatch.setattr(jaxslam.cli.map, "available_memory_bytes", lambda: 8 * 10**9)
    argv = ["map", str(tmp_path / "office.clf"), "--particles", "30000", "--set", "linear_update=0.3",
            "--no-progress", "--out", str(tmp_path / "out")]
    from jaxslam.cli import MAP_DEFAULTS

    config, _, _ = build_setup({**MAP_DEFAULTS, "num_particles": 30000})  # the command's defaults: the SMP
    need, how = jaxslam.resources.estimate_run_bytes(config, small_log.num_beams)
    assert how.startswith("(30000 particles x 25 x 25 blocks + ")
    expected = f"{need / 1e9:.0f}" if need >= 10e9 else f"{need / 1e9:.1f}"
    _run_refused(argv, [f"needs about {expected} GB ({how}",
                        "but 8.0 GB are available"], capsys)


def test_a_wide_first_scan_is_counted_by_the_memory_check(tmp_path, small_log, capsys, monkeypatch):
    """On 8-cell tiles the office's first scan touches more tiles than Intel's allowance (the pools'
    size without a footprint). With the machine's memory between the estimate at that allowance
    and the estimate at the scan's footprint, the run is refused, and the message's figures are
    the footprint's: a check at Intel's allowance would have let it run out of memory."""
    import jaxslam.cli.map
    import jaxslam.resources
    from jaxslam.cli import MAP_DEFAULTS
    from jaxslam.io import read_log
    from jaxslam.rbpf import TILES_PER_PARTICLE, first_scan_tiles, prepare

    write_flaser_log(tmp_path / "office.clf", small_log)
    _trap_filter(monkeypatch)
    config, settings, params = build_setup({**MAP_DEFAULTS, "num_particles": 2000, "tile_size": 8})
    log = read_log(tmp_path / "office.clf")
    tiles = first_scan_tiles(prepare(log, config, settings)[0], params, config)
    assert tiles > TILES_PER_PARTICLE
    allowance, _ = jaxslam.resources.estimate_run_bytes(config, log.num_beams)
    need, how = jaxslam.resources.estimate_run_bytes(config, log.num_beams, tiles)
    assert need > allowance
    monkeypatch.setattr(jaxslam.cli.map, "available_memory_bytes", lambda: (need + allowance) // 2)
    argv = ["map", str(tmp_path / "office.clf"), "--particles", "2000", "--set", "tile_size=8",
            "--no-progress", "--out", str(tmp_path / "out")]
    expected = f"{need / 1e9:.0f}" if need >= 10e9 else f"{need / 1e9:.1f}"
    _run_refused(argv, [f"needs about {expected} GB ({how}"], capsys)
    assert not (tmp_path / "out").exists()


def test_a_log_the_memory_check_prepares_is_prepared_once(tmp_path, small_log, monkeypatch):
    """Where the widest footprint does not fit but the first scan's does, the check prepares the
    log to measure it, and the run takes that preparation: the log is prepared once."""
    import jaxslam.cli.map
    import jaxslam.rbpf
    import jaxslam.resources
    from jaxslam.cli import MAP_DEFAULTS
    from jaxslam.io import read_log
    from jaxslam.rbpf import first_scan_tiles, prepare

    write_flaser_log(tmp_path / "office.clf", small_log)
    config, settings, params = build_setup({**MAP_DEFAULTS, "num_particles": 2000, "tile_size": 8})
    log = read_log(tmp_path / "office.clf")
    need, _ = jaxslam.resources.estimate_run_bytes(config, log.num_beams,
                                                   first_scan_tiles(prepare(log, config, settings)[0], params, config))
    widest = config.grid.window_tiles(config.max_insert_range, config.field_radius) ** 2
    assert jaxslam.resources.estimate_run_bytes(config, log.num_beams, widest)[0] > need
    monkeypatch.setattr(jaxslam.cli.map, "available_memory_bytes", lambda: need)
    calls, runs = [], []
    monkeypatch.setattr(jaxslam.cli.map, "prepare", lambda *a: calls.append(a) or prepare(*a))

    def trap(*args, **kwargs):
        runs.append(kwargs["prepared"])
        raise AssertionError("the filter ran")

    monkeypatch.setattr(jaxslam.pipeline, "run", trap)
    with pytest.raises(AssertionError, match="the filter ran"):
        main(["map", str(tmp_path / "office.clf"), "--particles", "2000", "--set", "tile_size=8",
              "--no-progress", "--out", str(tmp_path / "out")])
    assert len(calls) == 1 and runs[0] is not None and runs[0][0].inputs.ranges.shape[0] > 0


def test_a_small_run_passes_the_memory_check_and_an_unreadable_meminfo_skips_it(tmp_path, small_log, monkeypatch):
    import jaxslam.cli.map
    import jaxslam.resources

    write_flaser_log(tmp_path / "office.clf", small_log)
    _trap_filter(monkeypatch)
    for available in (jaxslam.resources.available_memory_bytes, lambda: None):
        monkeypatch.setattr(jaxslam.cli.map, "available_memory_bytes", available)
        with pytest.raises(AssertionError, match="the filter ran"):  # the check let it through to the filter
            main(["map", str(tmp_path / "office.clf"), "--particles", "100000" if available() is None else "4",
                  "--no-progress", "--out", str(tmp_path / "out")])


def test_a_huge_insertion_reach_is_refused_by_the_memory_check(tmp_path, small_log, capsys, monkeypatch):
    """Refused before any work: the estimate at the smallest footprint already exceeds the machine,
    so the log is not even prepared (measuring its first scan would trace 20 million samples a beam)."""
    import jaxslam.cli.map

    write_flaser_log(tmp_path / "office.clf", small_log)
    _trap_filter(monkeypatch)
    monkeypatch.setattr(jaxslam.cli.map, "prepare", lambda *a, **k: pytest.fail("the log was prepared"))
    argv = ["map", str(tmp_path / "office.clf"), "--particles", "3", "--set", "max_insert_range=1e6",
            "--no-progress", "--out", str(tmp_path / "out")]
    _run_refused(argv, ["the run needs about", "samples x 40 bytes", "GB are available"], capsys)


def test_a_full_disk_is_refused_before_the_run(tmp_path, small_log, capsys, monkeypatch):
    import collections

    import jaxslam.io.files

    write_flaser_log(tmp_path / "office.clf", small_log)
    _trap_filter(monkeypatch)
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(jaxslam.io.files.shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 10**6, 10**6))
    argv = ["map", str(tmp_path / "office.clf"), "--particles", "3", "--no-progress", "--out", str(tmp_path / "out")]
    _run_refused(argv, ["a disk with 1 MB free", "need about", "free some space"], capsys)


# ---------------------------------------------------------------------------------------------
# The corpus, part 2: logs, bags, trajectories and relations, read for real (only the filter is
# trapped for the refusals). Each case: (case id, argv, exit code, words of the message, setup);
# exit code 0 cases must run and print a "warning: " line holding the words (or none: words []).


def _edit_log(edit):
    """Setup: rewrite the FLASER log's lines (a list, the comment first) with ``edit(lines)``."""
    def setup(paths):
        lines = paths["log"].read_text().splitlines()
        edit(lines)
        paths["log"].write_text("\n".join(lines) + "\n")
    return setup


def _log_bytes(make):
    """Setup: replace the log by ``make(text)`` bytes (``text``: the valid log's text)."""
    def setup(paths):
        paths["log"].write_bytes(make(paths["log"].read_text()))
    return setup


def _field(line_index, field_index, value):
    def edit(lines):
        fields = lines[line_index].split()
        fields[field_index] = value
        lines[line_index] = " ".join(fields)
    return edit


def _ranges(value, scans):
    """Every range of the given scans (0-based, line = scan + 1) set to ``value``."""
    def edit(lines):
        for scan in scans:
            fields = lines[scan + 1].split()
            n = int(fields[1])
            fields[2:2 + n] = [value] * n
            lines[scan + 1] = " ".join(fields)
    return edit


def _swap(i, j):
    def edit(lines):
        lines[i], lines[j] = lines[j], lines[i]
    return edit


def _duplicate(i):
    def edit(lines):
        lines.insert(i + 1, lines[i])
    return edit


def _shift_times(from_line, seconds):
    def edit(lines):
        for k in range(from_line, len(lines)):
            fields = lines[k].split()
            for f in (-1, -3):
                fields[f] = f"{float(fields[f]) + seconds:.6f}"
            lines[k] = " ".join(fields)
    return edit


def _standing_odom(lines):
    """ODOM lines of a robot that stands still, interleaved with the (moving) FLASER lines."""
    out = [lines[0]]
    for line in lines[1:]:
        stamp = float(line.split()[-3])
        out += [f"ODOM 0 0 0 0 0 0 {stamp - 0.001:.6f} host {stamp - 0.001:.6f}", line]
    out.append(f"ODOM 0 0 0 0 0 0 {stamp + 0.001:.6f} host {stamp + 0.001:.6f}")
    lines[:] = out


def _truncate(lines):
    lines[3] = " ".join(lines[3].split()[:-3])


def _bag(kind, topics=("/scan", "/odom"), corrupt=None):
    """Setup: a small ROS 1 ('ros1') or ROS 2 ('ros2') bag at {bag}; ``corrupt(path)`` damages it."""
    def setup(paths):
        from test_io_rosbag import _store, standard_messages, write_bag

        ts = _store(kind)
        messages = [m for m in standard_messages(ts) if m[0] in topics]
        path = paths["bag1"] if kind == "ros1" else paths["bag2"]
        write_bag(path, messages, ros2=(kind == "ros2"))
        if corrupt:
            corrupt(path)
    return setup


def _cut_in_half(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _break_metadata(path):
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")


def _text(key, content):
    def setup(paths):
        paths[key].write_text(content)
    return setup


def _both(*setups):
    def setup(paths):
        for s in setups:
            s(paths)
    return setup


LOG = ["map", "{log}", "--no-progress", "--out", "{out}"]
BAG1 = ["map", "{bag1}", "--no-progress", "--out", "{out}"]
BAG2 = ["map", "{bag2}", "--no-progress", "--out", "{out}"]
EVAL = ["eval", "{traj}", "{rel}"]
SMALL_RUN = ["--particles", "2", "--proposal", "op", "--set", "linear_update=0.3", "--set", "max_insert_range=8"]
UTF8_BOM = b"\xef\xbb\xbf"

IO_CASES = [
    # CARMEN logs.
    ("log-truncated-line", LOG, 2, ["office.clf:4: truncated FLASER (n=181) line"], _edit_log(_truncate)),
    ("log-nan-range", LOG, 2, ["office.clf:3: beam 5 has range nan (NaN or negative)"], _edit_log(_field(2, 7, "nan"))),
    ("log-negative-range", LOG, 2, ["office.clf:3: beam 0 has range -1.0 (NaN or negative)"],
     _edit_log(_field(2, 2, "-1.0"))),
    ("log-non-numeric-range", LOG, 2, ["office.clf:2: field 4 (range) is not a number: 'abc'"],
     _edit_log(_field(1, 3, "abc"))),
    ("log-non-numeric-timestamp", LOG, 2, ["office.clf:2:", "is not a number: 'noon'"], _edit_log(_field(1, -3, "noon"))),
    ("log-zero-readings", LOG, 2, ["office.clf:2: FLASER line with 0 readings"],
     _edit_log(lambda lines: lines.insert(1, "FLASER 0 0 0 0 0 0 0 1000.0 host 1000.0"))),
    ("log-timestamps-backwards", LOG, 2, ["office.clf:4: timestamp goes backwards"], _edit_log(_swap(2, 3))),
    ("log-empty", LOG, 2, ["office.clf: is empty"], _text("log", "")),
    ("log-blank-lines-only", LOG, 2, ["office.clf: is empty"], _text("log", "\n  \n\n")),
    ("log-comments-only", LOG, 2, ["office.clf: holds only comments: no FLASER, ROBOTLASER1 or ODOM line"],
     _text("log", "# a CARMEN log\n# written by nobody\n")),
    ("log-utf16-bom", LOG, 2, ["office.clf: looks like UTF-16 text; save it as UTF-8 (or ASCII)"],
     _log_bytes(lambda text: text.encode("utf-16"))),
    ("log-utf16-be-no-bom", LOG, 2, ["office.clf: looks like UTF-16 text"], _log_bytes(lambda t: t.encode("utf-16-be"))),
    ("log-unrecognised", LOG, 2, ["office.clf: unrecognised log format", "CARMEN text log"],
     _text("log", "hello world\n")),
    ("log-missing", ["map", "{out}.clf", "--no-progress", "--out", "{out}"], 2, ["no such file or folder"], None),
    ("log-no-laser-lines", LOG, 2, ["no laser lines (expected FLASER or ROBOTLASER1)"],
     _text("log", "ODOM 0 0 0 0 0 0 1000.0 host 1000.0\n")),
    ("log-all-zero-ranges", LOG, 2, ["the laser looks dead: 12 of 12 scans have no valid return", "first: scan 0"],
     _edit_log(_ranges("0.0", range(12)))),
    ("log-all-max-ranges", LOG, 2, ["the laser looks dead: 12 of 12 scans", "range_max=81.91"],
     _edit_log(_ranges("81.910", range(12)))),
    ("log-mostly-dead", LOG, 2, ["the laser looks dead: 11 of 12 scans"], _edit_log(_ranges("0.0", range(1, 12)))),
    ("log-odometry-odom-without-odom", [*LOG, "--odometry", "odom"], 2, ["odometry_source='odom'", "no ODOM lines"],
     None),
    ("log-odometry-flag-word", [*LOG, "--odometry", "wheels"], 2, ["--odometry", "invalid choice", "'wheels'"], None),
    ("log-scan-topic-on-carmen", [*LOG, "--scan-topic", "/laser"], 2, ["--scan-topic does not apply to a CARMEN log"],
     None),
    # Settings in their own range but wrong for the log: refused once it is read, before the filter.
    ("log-beam-stride-beyond-beams", [*LOG, *_sets("beam_stride=100000")], 2,
     ["beam_stride=100000 is more than the log's 181 beams per scan", "at most 181"], None),
    # Bags.
    ("bag-truncated", BAG1, 2, ["test.bag", "cannot open the bag"], _bag("ros1", corrupt=_cut_in_half)),
    ("bag-garbage", BAG1, 2, ["test.bag: cannot open the bag"],
     lambda paths: paths["bag1"].write_bytes(b"#ROSBAG V2.0\nthis is not a bag")),
    ("bag-no-scan-topic", BAG1, 2, ["no topic '/scan' in the bag", "/odom"], _bag("ros1", topics=("/odom",))),
    ("bag-no-odom-topic", BAG1, 2, ["no topic '/odom' in the bag"], _bag("ros1", topics=("/scan",))),
    ("bag-other-scan-topic", [*BAG1, "--scan-topic", "/laser"], 2, ["no topic '/laser' in the bag"], _bag("ros1")),
    ("bag-odometry-flag", [*BAG1, "--odometry", "odom"], 2, ["--odometry does not apply to a bag"], _bag("ros1")),
    ("bag2-folder-without-metadata", BAG2, 2, ["a folder without metadata.yaml"],
     lambda paths: paths["bag2"].mkdir()),
    ("bag2-no-scan-topic", BAG2, 2, ["no topic '/scan' in the bag"], _bag("ros2", topics=("/odom",))),
    ("bag2-broken-metadata", BAG2, 2, ["cannot open the bag"], _bag("ros2", corrupt=_break_metadata)),
    # Trajectories and relations for eval.
    ("eval-traj-three-fields", EVAL, 2, ["traj.txt:2: expected 4 fields 'timestamp x y theta', got 3"],
     _text("traj", "0 0 0 0\n1 1 0\n")),
    ("eval-traj-non-numeric", EVAL, 2, ["traj.txt:1: non-numeric field", "'0 zero 0 0'"], _text("traj", "0 zero 0 0\n")),
    ("eval-traj-nan", EVAL, 2, ["traj.txt:2: non-finite value"], _text("traj", "0 0 0 0\n1 nan 0 0\n")),
    ("eval-traj-backwards", EVAL, 2, ["traj.txt:2: timestamp goes backwards"], _text("traj", "1 0 0 0\n0 1 0 0\n")),
    ("eval-traj-empty", EVAL, 2, ["traj.txt: the trajectory file holds no poses"], _text("traj", "# nothing\n")),
    ("eval-traj-missing", ["eval", "{out}.txt", "{rel}"], 2, ["no such trajectory file"], None),
    ("eval-rel-too-few-columns", EVAL, 2, ["rel.txt:1: expected 8 fields 't1 t2 x y z roll pitch yaw', got 5"],
     _text("rel", "0 1 1 0 0\n")),
    ("eval-rel-non-numeric", EVAL, 2, ["rel.txt:1: field 3 is not a number: 'one'"], _text("rel", "0 1 one 0 0 0 0 0\n")),
    ("eval-rel-nan", EVAL, 2, ["rel.txt:1: non-finite value"], _text("rel", "0 1 nan 0 0 0 0 0\n")),
    ("eval-rel-not-planar", EVAL, 2, ["rel.txt:1: z, roll, pitch must be 0"], _text("rel", "0 1 1 0 0.5 0 0 0\n")),
    ("eval-rel-empty", EVAL, 2, ["rel.txt: the relations file holds no relations"], _text("rel", "")),
    ("eval-rel-missing", ["eval", "{traj}", "{out}.txt"], 2, ["no such relations file"], None),
    ("eval-rel-time-not-in-trajectory", EVAL, 2, ["timestamp 5.000000", "is not in the trajectory"],
     _text("rel", "0 5 1 0 0 0 0 0\n")),
    # Odd but usable: exit 0 with a warning (or, for the byte-order mark, none).
    ("log-utf8-bom", [*LOG, *SMALL_RUN], 0, [], _log_bytes(lambda text: UTF8_BOM + text.encode())),
    ("log-duplicate-timestamps", [*LOG, *SMALL_RUN], 0,
     ["1 laser lines repeat the timestamp of the next laser line (first: lines 4 and 5", "only the last line is kept"],
     _edit_log(_duplicate(3))),
    ("log-some-zero-scans", [*LOG, *SMALL_RUN], 0, ["2 of 12 scans have no valid return", "first: scan 3"],
     _edit_log(_ranges("0.0", (3, 7)))),
    ("log-some-max-scans", [*LOG, *SMALL_RUN], 0, ["1 of 12 scans have no valid return", "range_max=81.91"],
     _edit_log(_ranges("90.0", (5,)))),
    ("log-time-gap", [*LOG, *SMALL_RUN], 0, ["1 gaps in time longer than 10 x the median scan interval",
                                              "after scan 5"], _edit_log(_shift_times(7, 100.0))),
    ("log-odom-contradicts-flaser", [*LOG, *SMALL_RUN], 0,
     ["the ODOM lines contradict the FLASER lines' odometry", "the odometry of the FLASER lines is used",
      "--odometry odom"], _edit_log(_standing_odom)),
    ("eval-traj-duplicate-timestamp", EVAL, 0,
     ["traj.txt: 1 poses repeat the timestamp of the next pose (first: lines 2 and 3", "only the last pose is kept"],
     _both(_text("traj", "0 0 0 0\n1 5 5 0\n1 1 0 0\n"), _text("rel", "0 1 1 0 0 0 0 0\n"))),
]


def _io_paths(tmp_path, small_log):
    paths = _prepare(tmp_path, small_log)
    paths["bag1"] = tmp_path / "test.bag"
    paths["bag2"] = tmp_path / "test_ros2"
    return paths


def _run_case(argv, setup, paths):
    """Set up and run one case in-process: (exit code, stdout, stderr)."""
    import contextlib
    import io

    if setup is not None:
        setup(paths)
    argv = [a.format(**paths) for a in argv]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exit_:
            code = exit_.code
    return code, out.getvalue(), err.getvalue()


def test_the_io_corpus_is_large_enough():
    ids = [case[0] for case in CASES + READ_ONLY_CASES + IO_CASES]
    assert len(ids) >= 60 and len(set(ids)) == len(ids)


@pytest.fixture
def trap_filter(monkeypatch):
    _trap_filter(monkeypatch)


@pytest.mark.parametrize("case_id, argv, code, words, setup", [c for c in IO_CASES if c[2] == 2],
                         ids=[c[0] for c in IO_CASES if c[2] == 2])
def test_bad_file_is_refused(case_id, argv, code, words, setup, tmp_path, small_log, capsys, trap_filter):
    paths = _io_paths(tmp_path, small_log)
    if setup is not None:
        setup(paths)
    _run_refused([a.format(**paths) for a in argv], words, capsys)
    assert not paths["out"].exists()


@pytest.mark.parametrize("case_id, argv, code, words, setup", [c for c in IO_CASES if c[2] == 0],
                         ids=[c[0] for c in IO_CASES if c[2] == 0])
def test_odd_file_runs_with_a_warning(case_id, argv, code, words, setup, tmp_path, small_log, capsys):
    paths = _io_paths(tmp_path, small_log)
    if setup is not None:
        setup(paths)
    assert main([a.format(**paths) for a in argv]) == 0
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out
    warned = [line for line in captured.err.splitlines() if line.startswith("warning: ")]
    for word in words:
        assert any(word in line for line in warned), (word, captured.err)
    if not words:  # nothing about the log (the run itself may warn, e.g. of beams beyond the map)
        assert not any("office.clf" in line for line in warned), captured.err
    if argv[0] == "map":
        summary = json.loads((paths["out"] / "summary.json").read_text())
        for word in words:
            assert any(word in w for w in summary["warnings"]), (word, summary["warnings"])
        times = np.loadtxt(paths["out"] / "trajectory.txt")[:, 0]
        assert np.all(np.diff(times) > 0)  # no timestamp written twice


def test_duplicate_timestamps_keep_the_last_in_map_and_eval(tmp_path, small_log, capsys):
    """The one rule: of a repeated timestamp the last scan (map) or pose (eval) is used."""
    paths = _io_paths(tmp_path, small_log)
    paths["traj"].write_text("0 0 0 0\n1 20 20 0\n1 1 0 0\n")
    paths["rel"].write_text("0 1 1 0 0 0 0 0\n")
    out = tmp_path / "errors.json"
    assert main(["eval", str(paths["traj"]), str(paths["rel"]), "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert table["count"] == 1 and table["warnings"] and "only the last pose is kept" in table["warnings"][0]
    assert max(abs(v) for k, v in table.items() if isinstance(v, float)) < 1e-9  # the last pose: zero error
    from jaxslam.io import read_log
    from jaxslam.laserlog import check_log

    _edit_log(_duplicate(3))(paths)
    lines = paths["log"].read_text().splitlines()
    lines[4] = lines[4].replace(lines[4].split()[5], "9.999", 1)  # the second of the pair differs
    paths["log"].write_text("\n".join(lines) + "\n")
    log = check_log(read_log(paths["log"]))
    assert log.num_scans == 12 and np.all(np.diff(log.timestamps) > 0)
    assert log.ranges[2, 3] == np.float32(9.999)  # the later line of the pair was kept
    assert any("only the last line is kept" in w for w in log.warnings)


def corpus_table(path="/tmp/corpus_table.md") -> str:
    """Run every case of the corpus (both parts) in a temporary folder and write a markdown table
    ``case | exit code | first line of the message`` with the count at the top:
    ``python -c "import sys; sys.path.insert(0, 'tests'); import test_bad_inputs as t; t.corpus_table()"``."""
    import tempfile

    log = office_scenario(jax.random.key(0), num_scans=150, num_beams=181).log.subset(np.arange(12))
    cases = [(c[0], c[1], c[3]) for c in CASES] + [(c[0], c[1], c[4]) for c in IO_CASES]
    cases += [(c[0], c[1], "read-only") for c in READ_ONLY_CASES]
    rows = []
    for case_id, argv, setup in cases:
        with tempfile.TemporaryDirectory() as tmp:
            paths = _io_paths(Path(tmp), log)
            if setup == "read-only":
                if IS_ROOT:
                    rows.append((case_id, "-", "(skipped: root ignores file permissions)"))
                    continue
                os.chmod(paths["ro"], 0o500)
                setup = None
            try:
                code, out, err = _run_case(argv, setup, paths)
            finally:
                os.chmod(paths["ro"], 0o700)
        lines = [line for line in err.splitlines() if line.strip()]
        if code == 0:
            warned = [line for line in lines if line.startswith("warning: ")]
            first = warned[0] if warned else (out.splitlines() or [""])[0]
        else:
            first = lines[0] if lines else ""
        rows.append((case_id, code, first.replace("|", "\\|").replace(tmp, "TMP")))
    text = [f"{len(rows)} cases", "", "| case | exit code | first line of the message |", "|---|---|---|"]
    text += [f"| {case_id} | {code} | {first} |" for case_id, code, first in rows]
    Path(path).write_text("\n".join(text) + "\n")
    return path
