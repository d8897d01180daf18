"""experiments/box_world.py (the table in box_world.json), its merge script and the shared resume
helper experiments/_runs.py (also behind experiments/datasets.py). Fast: no full runs."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import box_world as bw  # noqa: E402
import box_world_merge as bwm  # noqa: E402
from _runs import ResultStore, SettingsMismatch  # noqa: E402

from jaxslam.config import ConfigError, build_setup  # noqa: E402

# experiments/datasets.py under a name of its own (not the ``datasets`` package of the same name)
_spec = importlib.util.spec_from_file_location("experiments_datasets", EXPERIMENTS / "datasets.py")
datasets = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(datasets)


@pytest.fixture(scope="module")
def exp():
    return bw.load_experiment()


def test_every_method_and_table_builds(exp):
    for name, flat in exp["methods"].items():
        config, settings, params = build_setup({**exp["common"], **flat})
        assert config.proposal == flat["proposal"]
        assert (settings.linear_update, settings.angular_update) == (0.5, 0.25)
        assert config.match_lookup == "nearest" and config.beam_stride == 2
        assert float(params.likelihood.gain) == pytest.approx(0.1)
    lp0, lp = build_setup(exp["methods"]["LP a=0"])[2], build_setup(exp["methods"]["LP"])[2]
    assert float(lp0.lookahead.alpha) == 0.0 and float(lp.lookahead.alpha) == 0.5
    for table in exp["tables"].values():
        assert bw.table_cells(exp, table, table["methods"], table.get("set", {}))
    noise = exp["tables"]["noise"]
    assert noise["methods"] == ["OP", "SMP", "LP a=0", "LP"] and noise["particles"] == [50]
    assert noise["odometry_scales"] == [0.25, 0.5, 1.0, 1.5]


def test_bad_names_are_refused(exp, tmp_path, capsys):
    with pytest.raises(ConfigError):
        bw.method_settings(exp, "OP", {"no_such_name": 1})
    assert bw.main(["--out", str(tmp_path), "--set", "motion.nope=1"]) == 2
    assert bw.main(["--out", str(tmp_path), "--table", "nope"]) == 2
    assert bw.main(["--out", str(tmp_path), "--methods", "nope"]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_cell_keys_are_stable_and_distinct(exp):
    a = bw.cell_record(bw.method_settings(exp, "LP", {"beam_stride": "2"}), 50, 1)
    b = bw.cell_record(bw.method_settings(exp, "LP"), 50, 1.0)
    assert bw.cell_key(a) == bw.cell_key(b)  # typed by the builder; the scale as a float
    shuffled = {**b, "settings": dict(reversed(list(b["settings"].items())))}
    assert bw.cell_key(shuffled) == bw.cell_key(b)
    keys = {bw.cell_key(bw.cell_record(bw.method_settings(exp, m), n, s))
            for m in exp["methods"] for n in (20, 50) for s in (0.5, 1.0)}
    assert len(keys) == len(exp["methods"]) * 4
    assert "LP" not in json.loads(bw.cell_key(b))  # keyed by the record, not the name
    assert bw.cell_key(bw.cell_record(bw.method_settings(exp, "LP", {"lookahead.alpha": "0"}), 50, 1)) == \
        bw.cell_key(bw.cell_record(bw.method_settings(exp, "LP a=0"), 50, 1))


def test_binomial_standard_error():
    assert bw.binomial_se(19, 30) == pytest.approx(math.sqrt((19 / 30) * (11 / 30) / 30))
    assert bw.binomial_se(0, 30) == 0.0 and bw.binomial_se(30, 30) == 0.0
    assert math.isnan(bw.binomial_se(0, 0))
    s = bw.summarize([{"ra": 0.1}, {"ra": 0.3}, {"ra": 0.19}, {"ra": 0.2}], 0.2)
    assert (s["successes"], s["success_rate"]) == (2, 0.5)
    assert s["standard_error"] == pytest.approx(0.25)


def test_store_refuses_other_settings_and_keeps_runs(tmp_path):
    path = tmp_path / "results.json"
    store = ResultStore(path, {"a": (1, 2)}, key=lambda r: r["seed"])
    store.add({"seed": 0, "x": 1}, summary={"n": 1})
    store.add({"seed": 1, "x": 2})
    again = ResultStore(path, {"a": [1, 2]}, key=lambda r: r["seed"])  # tuples compare as JSON lists
    assert again.done(0) and again.done(1) and not again.done(2)
    assert again.sections["summary"] == {"n": 1}
    again.add({"seed": 0, "x": 3})
    assert [r["x"] for r in json.loads(path.read_text())["runs"]] == [3, 2]
    with pytest.raises(SettingsMismatch, match="other settings"):
        ResultStore(path, {"a": [1, 3]}, key=lambda r: r["seed"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]  # no temporary files left


def _fake_runs(monkeypatch, calls):
    def run_once(record, seed, world, progress=False):
        calls.append((record["N"], seed))
        ra = 0.1 if seed % 2 == 0 else 0.5
        return {f: 0 for f in bw.RUN_FIELDS} | {"seed": seed, "ra": ra}, None, None

    monkeypatch.setattr(bw, "run_once", run_once)
    monkeypatch.setattr(bw, "save_example", lambda *a: None)


def test_box_world_resumes_and_refuses(exp, tmp_path, monkeypatch, capsys):
    calls = []
    _fake_runs(monkeypatch, calls)
    out = tmp_path / "bw"
    assert bw.main(["--table", "noise", "--methods", "OP", "--runs", "2", "--out", str(out)]) == 0
    assert len(calls) == 8  # 4 scales x 2 seeds
    assert bw.main(["--table", "noise", "--methods", "OP", "--runs", "3", "--out", str(out)]) == 0
    assert len(calls) == 12  # only seed 2 of each scale is new
    data = json.loads((out / "results.json").read_text())
    assert len(data["runs"]) == 12 and len(data["cells"]) == 4
    rows = {r["odometry_scale"]: r for r in data["noise_scale"]}
    assert rows[1.0]["successes"] == 2 and rows[1.0]["runs"] == 3
    assert (out / "noise_scale.png").is_file() and "2/3" in (out / "noise_scale.md").read_text()
    # The noise table's scale-1 cell is the main table's N = 50 cell.
    assert bw.main(["--table", "table", "--methods", "OP", "--runs", "3", "--out", str(out)]) == 0
    assert len(calls) == 15  # N = 20 only
    capsys.readouterr()
    assert bw.main(["--table", "quick", "--methods", "OP", "--runs", "1", "--out", str(out)]) == 2  # another world
    err = capsys.readouterr().err
    assert "other settings" in err and "Traceback" not in err


def _results(exp, scale: float, seeds: int = 2) -> dict:
    """A results.json of box_world.py's format: the noise table's methods at N = 50 and one odometry
    scale, seed s with RA 0.1 (s + 1)."""
    settings = bw.world_settings(exp, exp["tables"]["noise"])
    cells, runs = {}, []
    for name in exp["tables"]["noise"]["methods"]:
        record = {"method": name, **bw.cell_record(bw.method_settings(exp, name), 50, scale)}
        key = bw.cell_key(record)
        cells[key] = record
        runs += [{"cell": key, **{f: 0 for f in bw.RUN_FIELDS}, "seed": s, "ra": 0.1 * (s + 1)} for s in range(seeds)]
    return json.loads(json.dumps({"settings": settings, "runs": runs, "cells": cells}))


def test_merge_refuses_other_files(exp, tmp_path, capsys):
    no_runs = tmp_path / "cells_only.json"
    no_runs.write_text(json.dumps({"settings": {}, "cells": {"OP | N=50": {"N": 50, "runs": []}}}))
    with pytest.raises(bwm.MergeError, match="no 'runs'"):
        bwm.merge_results([no_runs], exp)
    other = _results(exp, 0.5)
    other["settings"]["success_ra"] = 0.3
    (tmp_path / "other.json").write_text(json.dumps(other))
    with pytest.raises(bwm.MergeError, match="other settings"):
        bwm.merge_results([tmp_path / "other.json"], exp)
    assert bwm.main([str(tmp_path / "out"), str(no_runs)]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_merge_then_the_table_only_draws(exp, tmp_path, monkeypatch):
    (tmp_path / "half.json").write_text(json.dumps(_results(exp, 0.5)))
    (tmp_path / "one.json").write_text(json.dumps(_results(exp, 1.0)))
    out = tmp_path / "merged"
    assert bwm.main([str(out), str(tmp_path / "half.json"), str(tmp_path / "one.json")]) == 0
    assert "1/2: 0.50 ± 0.35" in (out / "noise_scale.md").read_text()
    assert (out / "noise_scale.png").is_file()
    merged = bwm.merge_results([out], exp)  # the merged folder reads back
    assert len(merged["runs"]) == 2 * 2 * len(exp["tables"]["noise"]["methods"])
    config = json.loads(bw.DEFAULT_CONFIG.read_text())
    config["tables"]["noise"]["odometry_scales"] = [0.5, 1.0]
    (tmp_path / "bw.json").write_text(json.dumps(config))
    monkeypatch.setattr(bw, "run_once", lambda *a, **k: pytest.fail("a merged cell was run again"))
    assert bw.main(["--config", str(tmp_path / "bw.json"), "--table", "noise", "--runs", "2", "--out", str(out)]) == 0


def test_datasets_uses_the_store(tmp_path, monkeypatch, capsys):
    calls = []

    def run_one(dataset, proposal, seed, out, data, settings):
        calls.append((dataset, proposal, seed))
        if seed == 1 and len(calls) < 3:
            return {"dataset": dataset, "proposal": proposal, "seed": seed, "failed": "boom"}
        return {"dataset": dataset, "proposal": proposal, "seed": seed, "trans_mean": 0.1, "trans_std": 0.0,
                "rot_mean_deg": 1.0, "rot_std_deg": 0.0, "wall_s": 1.0, "real_time_factor": 1.0, "peak_memory_mb": 1}

    monkeypatch.setattr(datasets, "run_one", run_one)
    out = tmp_path / "ds"
    base = ["--data", str(tmp_path), "--out", str(out), "--datasets", "intel", "--proposals", "op"]
    assert datasets.main(base + ["--seeds", "2"]) == 0
    assert datasets.main(base + ["--seeds", "2"]) == 0  # only the failed seed 1 again
    assert calls == [("intel", "op", 0), ("intel", "op", 1), ("intel", "op", 1)]
    assert datasets.main(base[:-1] + ["smp", "--seeds", "1"]) == 0  # an earlier call's runs stay
    data = json.loads((out / "results.json").read_text())
    assert {(r["proposal"], r["seed"]) for r in data["runs"]} == {("op", 0), ("op", 1), ("smp", 0)}
    assert set(data) == {"settings", "runs", "summary", "failed_runs", "gmapping_this_machine", "published"}
    capsys.readouterr()
    assert datasets.main(base + ["--seeds", "1", "--set", "beam_stride=1"]) == 2
    assert "other settings" in capsys.readouterr().err


def _record(dataset, proposal, seed, error):
    return {"dataset": dataset, "proposal": proposal, "seed": seed, "trans_mean": error, "trans_std": 0.0,
            "rot_mean_deg": 1.0, "rot_std_deg": 0.0, "wall_s": 10.0, "real_time_factor": 2.0, "peak_memory_mb": 100}


def test_datasets_failed_runs_and_seed_order(tmp_path, monkeypatch):
    """A run fails above twice its log's best run (any method) or where a look at its map found a
    doubled structure; the jobs go seed by seed over the logs."""
    errors = {("intel", "smp", 0): 0.05, ("intel", "lp", 0): 0.099, ("intel", "smp", 1): 0.101,
              ("intel", "lp", 1): 0.06, ("aces", "smp", 0): 1.0, ("aces", "lp", 0): 1.5,
              ("aces", "smp", 1): 2.5, ("aces", "lp", 1): 1.9}
    calls = []

    def run_one(dataset, proposal, seed, out, data, settings):
        calls.append((dataset, proposal, seed))
        return _record(dataset, proposal, seed, errors[(dataset, proposal, seed)])

    monkeypatch.setattr(datasets, "run_one", run_one)
    out = tmp_path / "ds"
    out.mkdir()
    (out / datasets.JUDGED_FILE).write_text(json.dumps({"intel/lp-seed1": "a corridor doubled"}))
    assert datasets.main(["--data", str(tmp_path), "--out", str(out), "--datasets", "intel", "aces",
                          "--proposals", "smp", "lp", "--seeds", "2"]) == 0
    assert [c[2] for c in calls] == [0, 0, 0, 0, 1, 1, 1, 1]
    failed = json.loads((out / "results.json").read_text())["failed_runs"]
    assert [f["seed"] for f in failed["intel/smp"]] == [1]  # 0.101 > 2 x 0.05; 0.099 is not
    assert [f["reason"] for f in failed["intel/lp"]] == ["a corridor doubled"]
    assert [f["seed"] for f in failed["aces/smp"]] == [1] and failed["aces/lp"] == []
    table = (out / "robustness.md").read_text()
    assert "| intel | SMP | 2 | 0.076 ± 0.026 | 1 (seeds 1) | 10 | 2.0 | 100 |" in table
    assert "| aces | LP | 2 | 1.700 ± 0.200 | 0 |" in table


def test_datasets_jobs_at_a_time_give_the_same_tables(tmp_path, monkeypatch, capsys):
    """--jobs 3 runs up to three runs at once, the same runs as one at a time, and writes the same
    tables; --jobs 0 is refused before any run."""
    import threading

    lock = threading.Lock()
    running = [0, 0]  # now, most at once

    def run_one(dataset, proposal, seed, out, data, settings):
        with lock:
            running[0] += 1
            running[1] = max(running)
        time.sleep(0.02 + 0.01 * ((seed * 7 + len(proposal)) % 3))  # overlap, and finish out of order
        with lock:
            running[0] -= 1
        return _record(dataset, proposal, seed, 0.05 + 0.01 * seed + 0.001 * len(proposal))

    monkeypatch.setattr(datasets, "run_one", run_one)
    tables, most_at_once = [], []
    for jobs in ("1", "3"):
        out = tmp_path / f"jobs{jobs}"
        running[:] = [0, 0]
        assert datasets.main(["--data", str(tmp_path), "--out", str(out), "--datasets", "intel", "aces",
                              "--proposals", "smp", "lp", "lp-odometry", "--seeds", "3", "--jobs", jobs]) == 0
        most_at_once.append(running[1])
        runs = json.loads((out / "results.json").read_text())["runs"]
        tables.append((sorted(json.dumps(r, sort_keys=True) for r in runs), (out / "robustness.md").read_text()))
    assert most_at_once == [1, 3]
    assert tables[0] == tables[1] and len(tables[0][0]) == 2 * 3 * 3
    capsys.readouterr()
    assert datasets.main(["--data", str(tmp_path), "--out", str(tmp_path / "none"), "--jobs", "0"]) == 2
    assert "--jobs must be at least 1" in capsys.readouterr().err and not (tmp_path / "none").exists()


def test_datasets_failed_maps_figure(tmp_path):
    """One panel per failed run of the chosen methods whose map exists; none failed: no file."""
    from PIL import Image

    records = [_record("intel", "smp", 0, 0.05), _record("intel", "smp", 1, 0.3), _record("intel", "op", 0, 0.9),
               _record("intel", "lp", 0, 0.05)]
    for r in records:
        folder = tmp_path / r["dataset"] / f"{r['proposal']}-seed{r['seed']}"
        folder.mkdir(parents=True)
        Image.new("L", (900, 300), 128).save(folder / "map.png")
    path = datasets.failed_maps_figure(records, tmp_path)
    assert path == tmp_path / datasets.FAILED_MAPS_FILE and path.is_file()
    width, height = Image.open(path).size
    assert width < height  # one panel (intel SMP seed 1); with the OP's too it would be two abreast
    assert datasets.failed_maps_figure(records[:1] + records[3:], tmp_path / "none") is None


def test_datasets_proposals_name_the_localizers_start(tmp_path, monkeypatch):
    """"lp" runs the library's LP as it is; "lp-odometry" pins the paper's localizers, whatever the
    default; a table-wide --set comes after (it wins)."""
    commands = []

    def fake_run(cmd, **kw):
        commands.append(cmd)
        return subprocess.CompletedProcess(cmd, 1, "", "stopped here")

    monkeypatch.setattr(datasets.subprocess, "run", fake_run)
    settings = {**datasets.SETTINGS, "set": ["lookahead.alpha=0.1"]}
    for proposal in ("lp", "lp-odometry"):
        record = datasets.run_one("intel", proposal, 0, tmp_path, tmp_path, settings)
        assert "failed" in record
    lp, paper = (" ".join(c) for c in commands)
    assert "lookahead_initial" not in lp and "--proposal lp" in lp
    assert paper.index("lookahead_initial=odometry") < paper.index("lookahead.alpha=0.1")


@pytest.mark.slow  # Monte Carlo or whole-scenario check (python3 -m pytest -m slow)
def test_quick_table_end_to_end(tmp_path):
    """One real run: OP, N = 4, the 3-lap quick world."""
    config = json.loads(bw.DEFAULT_CONFIG.read_text())
    config["tables"]["quick"].update(methods=["OP"], particles=[4])
    (tmp_path / "bw.json").write_text(json.dumps(config))
    out = tmp_path / "quick"
    t0 = time.perf_counter()
    assert bw.main(["--config", str(tmp_path / "bw.json"), "--table", "quick", "--runs", "1", "--out", str(out)]) == 0
    assert time.perf_counter() - t0 < 120
    data = json.loads((out / "results.json").read_text())
    (run,) = data["runs"]
    assert set(run) == {"cell", *bw.RUN_FIELDS} and run["ra"] >= 0 and run["num_steps"] > 0
    # The weight on the closing histories: none where no particle closes the loop.
    assert 0.0 <= run["closing_weight"] <= 1.0 + 1e-6
    assert run["closest_particle_error"] < config["success_ra"] or run["closing_weight"] == 0.0
    assert data["settings"]["scenario"] == {"laps": 3, "laps_per_visit": 3}
    assert (out / "ra_distribution.png").is_file() and (out / "examples.png").is_file()


def _simulated_dataset(folder: Path, name: str = "sim") -> tuple[str, str]:
    """A simulated log as a CARMEN file and relations from its true path (every fifth scan)."""
    import jax
    import numpy as np
    from logs import write_flaser_log

    from jaxslam.sim import office_scenario

    scenario = office_scenario(jax.random.key(0), num_scans=150, num_beams=181)
    log = scenario.log.subset(np.arange(40))
    write_flaser_log(folder / f"{name}.clf", log)
    lines = []
    for i in range(0, 35, 5):
        (x1, y1, t1), (x2, y2, t2) = scenario.true_poses[i], scenario.true_poses[i + 5]
        c, s = np.cos(t1), np.sin(t1)
        dx, dy = c * (x2 - x1) + s * (y2 - y1), -s * (x2 - x1) + c * (y2 - y1)
        lines.append(f"{1000.0 + log.timestamps[i]:.6f} {1000.0 + log.timestamps[i + 5]:.6f} {dx:.6f} {dy:.6f} 0 0 0 "
                     f"{np.arctan2(np.sin(t2 - t1), np.cos(t2 - t1)):.6f}")
    (folder / f"{name}.relations").write_text("\n".join(lines) + "\n")
    return f"{name}.clf", f"{name}.relations"


def test_datasets_batched_seeds_are_the_cli_runs(tmp_path, monkeypatch, capsys):
    """--batch-seeds: a log's seeds as one batch in the process (one device here) give each
    seed's ``jaxslam map`` run (the same trajectory, its loops closed after the filter as the
    command closes them), scored and stored as the subprocess runs are; a second call finds them
    done; --jobs does not go with it."""
    import numpy as np

    from jaxslam.cli import main as cli_main

    data, out = tmp_path / "data", tmp_path / "ds"
    data.mkdir()
    monkeypatch.setattr(datasets, "DATASETS", {"sim": _simulated_dataset(data)})
    small = ["--set", "num_particles=4", "--set", "linear_update=0.3", "--set", "max_insert_range=8"]
    base = ["--data", str(data), "--out", str(out), "--datasets", "sim", "--proposals", "op", "--seeds", "2", *small]
    assert datasets.main(base + ["--batch-seeds", "--jobs", "2"]) == 2
    assert datasets.main(base + ["--devices", "99"]) == 2 and "XLA_FLAGS" in capsys.readouterr().err
    assert datasets.main(base + ["--batch-seeds"]) == 0
    runs = json.loads((out / "results.json").read_text())["runs"]
    assert [(r["seed"], r["batch"]["runs"], r["batch"]["devices"]) for r in runs] == [(0, 2, 1), (1, 2, 1)]
    assert all(r["trans_mean"] < 0.5 and r["relations"] == 7 for r in runs)
    settings = {**datasets.SETTINGS, "set": small[1::2]}
    alone = tmp_path / "alone"
    assert cli_main(datasets.map_arguments("sim", "op", 1, alone, data, settings)) == 0
    for name in ("trajectory_filter.txt", "trajectory.txt"):  # the filter's, then closed as `jaxslam map` closes it
        batched, single = (np.loadtxt(folder / name) for folder in (out / "sim" / "op-seed1", alone))
        np.testing.assert_allclose(batched, single, rtol=0, atol=1e-6)  # the same particles; the text rounds
    capsys.readouterr()
    assert datasets.main(base + ["--batch-seeds"]) == 0  # nothing left to run
    assert json.loads((out / "results.json").read_text())["runs"] == runs


def test_box_world_batches_a_cells_seeds(exp, tmp_path, monkeypatch, capsys):
    """--batch-seeds: the seeds a cell still needs go to ``run_batch`` at once and are stored as the
    loop stores them; a second call with more seeds batches only the new ones; --devices beyond
    the machine's is refused before any work."""
    batches = []

    def run_batch(record, seeds, world, devices=None, progress=False):
        batches.append((record["N"], list(seeds), devices))
        return [({f: 0 for f in bw.RUN_FIELDS} | {"seed": s, "ra": 0.1}, None, None) for s in seeds]

    monkeypatch.setattr(bw, "run_batch", run_batch)
    monkeypatch.setattr(bw, "run_once", lambda *a, **k: pytest.fail("a batched cell was run seed by seed"))
    monkeypatch.setattr(bw, "save_example", lambda *a: None)
    out = tmp_path / "bw"
    args = ["--table", "quick", "--methods", "OP", "--out", str(out), "--batch-seeds"]
    assert bw.main(args + ["--runs", "2"]) == 0
    assert bw.main(args + ["--runs", "3", "--devices", "1"]) == 0
    assert batches == [(4, [0, 1], None), (8, [0, 1], None), (4, [2], 1), (8, [2], 1)]
    assert len(json.loads((out / "results.json").read_text())["runs"]) == 6
    capsys.readouterr()
    assert bw.main(args + ["--devices", "99"]) == 2
    assert "XLA_FLAGS" in capsys.readouterr().err


@pytest.mark.slow  # whole-scenario runs (python3 -m pytest -m slow)
def test_box_world_batch_is_the_runs_alone(exp):
    """Two seeds of the 3-lap quick world (OP, N = 4) as one batch: each seed's record is its run
    alone's (the same RA, steps and resamplings; particles bit for bit: tests/test_run_batch.py)."""
    table = exp["tables"]["quick"]
    (cell,) = bw.table_cells(exp, {**table, "particles": [4]}, ["OP"], table.get("set", {}))
    world = bw.world_settings(exp, table)
    batched = bw.run_batch(cell, [0, 1], world)
    for seed, (run, result, _) in zip([0, 1], batched):
        alone, result_alone, _ = bw.run_once(cell, seed, world)
        assert {k: run[k] for k in bw.RUN_FIELDS if k != "seconds"} == pytest.approx(
            {k: alone[k] for k in bw.RUN_FIELDS if k != "seconds"}, rel=1e-5)
        assert (result.best_path == result_alone.best_path).all()


_DATASETS_MAIN = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("experiments_datasets", sys.argv[1])
datasets = importlib.util.module_from_spec(spec)
spec.loader.exec_module(datasets)
datasets.DATASETS = {"sim": ("sim.clf", "sim.relations")}
sys.exit(datasets.main(sys.argv[2:]))
"""


@pytest.mark.slow  # two processes compile a batch each (python3 -m pytest -m slow)
def test_datasets_over_two_processes(tmp_path):
    """--coordinator: two processes on 127.0.0.1 (one host device each) split the three seeds;
    process 0 writes every run's record, and the run process 1 held is ``jaxslam map``'s run."""
    import os
    import socket

    import numpy as np

    from jaxslam.cli import main as cli_main

    data, out = tmp_path / "data", tmp_path / "ds"
    data.mkdir()
    _simulated_dataset(data)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    small = ["--set", "num_particles=4", "--set", "linear_update=0.3", "--set", "max_insert_range=8"]
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=1", "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": os.pathsep.join([str(EXPERIMENTS.parent), str(EXPERIMENTS),  # datasets.py imports _runs
                                          os.environ.get("PYTHONPATH", "")])}
    procs = [subprocess.Popen([sys.executable, "-c", _DATASETS_MAIN, str(EXPERIMENTS / "datasets.py"), "--data",
                               str(data), "--out", str(out), "--datasets", "sim", "--proposals", "op", "--seeds", "3",
                               *small, "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id",
                               str(i)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    try:
        texts = [p.communicate(timeout=600)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert all(p.returncode == 0 for p in procs), "\n".join(texts)
    runs = json.loads((out / "results.json").read_text())["runs"]
    assert [(r["seed"], r["batch"]["processes"], r["batch"]["devices"]) for r in runs] == [(0, 2, 2), (1, 2, 2),
                                                                                        (2, 2, 2)]
    settings = {**datasets.SETTINGS, "set": small[1::2]}
    monkey = pytest.MonkeyPatch()
    monkey.setattr(datasets, "DATASETS", {"sim": ("sim.clf", "sim.relations")})
    try:
        assert cli_main(datasets.map_arguments("sim", "op", 2, tmp_path / "alone", data, settings)) == 0
    finally:
        monkey.undo()
    np.testing.assert_array_equal(np.loadtxt(out / "sim" / "op-seed2" / "trajectory.txt"),
                                  np.loadtxt(tmp_path / "alone" / "trajectory.txt"))


def test_closing_steps_histories_and_refusals(tmp_path, capsys):
    """experiments/closing_steps.py: a particle proposed at a step has its parent's history (the
    filter's particles after the step before, ``particle_paths`` of the record cut there) and its
    own pose last; a folder holding another cell's runs is refused before any run."""
    import numpy as np

    import closing_steps as cs

    from jaxslam.rbpf import particle_paths

    rng = np.random.default_rng(0)
    steps, n = 7, 5
    proposed = rng.normal(size=(steps, n, 3))
    ancestors = rng.integers(0, n, (steps, n))
    start = np.array([1.0, 2.0, 0.3])
    for step in range(steps):
        got = cs.proposed_histories(proposed, ancestors, step, start)
        np.testing.assert_array_equal(got[:, :-1], particle_paths(proposed[:step], ancestors[:step], start))
        np.testing.assert_array_equal(got[:, -1], proposed[step])
    (tmp_path / "closing_steps.json").write_text(json.dumps({"cell": {"settings": {}, "N": 7, "odometry_scale": 1.0},
                                                             "runs": []}))
    assert cs.main(["--out", str(tmp_path), "--runs", "1"]) == 2
    assert "another cell" in capsys.readouterr().err
    assert cs.main(["--out", str(tmp_path), "--method", "nope"]) == 2


def test_closing_steps_one_step_drift_against_paths_built_from_known_motions():
    """``one_step_drift``: particles that move by the odometry's motion from their parents keep its
    error (slope 1 on every axis), particles that move by the true motion remove it (slope 0),
    and a particle's spread is that of the noise added to its motion (within Monte Carlo error).
    Built through resamplings (random ancestors), so a parent taken from the wrong row fails."""
    import numpy as np

    import closing_steps as cs

    from jaxslam.geometry import between_np, compose_np

    rng = np.random.default_rng(1)
    steps, n = 60, 400
    true_motion = np.column_stack([np.full(steps, 0.5), rng.normal(0, 0.05, steps), rng.normal(0, 0.2, steps)])
    odometry_motion = true_motion + rng.normal(0, [0.02, 0.01, 0.03], (steps, 3))
    truth, odometry = np.zeros((steps + 1, 3)), np.zeros((steps + 1, 3))
    for t in range(steps):
        truth[t + 1] = compose_np(truth[t], true_motion[t])
        odometry[t + 1] = compose_np(odometry[t], odometry_motion[t])
    ancestors = rng.integers(0, n, (steps, n))
    for motions, slope in ((odometry_motion, 1.0), (true_motion, 0.0)):
        proposed = np.zeros((steps, n, 3))
        noise = rng.normal(0, 0.004, (steps, n, 3))
        for t in range(steps):
            parents = truth[0][None] if t == 0 else proposed[t - 1, ancestors[t - 1]]
            proposed[t] = compose_np(parents, motions[t] + noise[t])
        drift = cs.one_step_drift(proposed, ancestors, truth[0], truth, odometry)
        np.testing.assert_allclose(drift["slope"], slope, atol=0.05)
        np.testing.assert_allclose(drift["spread"], 0.004, rtol=0.05)
        np.testing.assert_allclose(drift["odometry_error_rms"], np.sqrt(((between_np(odometry[:-1], odometry[1:])
                                                                          - true_motion) ** 2).mean(0)), rtol=1e-6)


def test_proposal_calibration_exact_posterior_and_distances():
    """experiments/proposal_calibration.py's exact posterior: distances to segments against a
    brute-force sampling of them; with no return (every range at range_max) the posterior is the
    motion prior, its mean error the prediction's and its std the prior's (the 13-point lattice
    over +-3 stds: within 3 %); a beam that hits a wall moves the across-track mean toward the truth."""
    import numpy as np

    import proposal_calibration as pc

    from jaxslam.config import default_params
    from jaxslam.laser import make_sensor, uniform_beams
    from jaxslam import motion

    segments = np.array([[0.0, 0.0, 2.0, 0.0], [2.0, 0.0, 2.0, 1.0]])
    points = np.random.default_rng(0).uniform(-1, 3, (50, 2))
    along = np.linspace(0, 1, 4001)[:, None]
    samples = np.concatenate([s[:2] + along * (s[2:] - s[:2]) for s in segments])
    brute = np.linalg.norm(points[:, None] - samples[None], axis=-1).min(1)
    np.testing.assert_allclose(pc.segment_distances(points, segments), brute, atol=3e-4)

    params = default_params()
    sensor = make_sensor(uniform_beams(9, np.pi), range_min=0.05, range_max=4.0)
    previous, u = np.array([0.5, 1.0, 0.0]), np.array([0.5, 0.0, 0.0])
    true_motion = np.array([0.49, 0.01, 0.0])
    mean, sd = pc.exact_posterior(previous, u, np.full(9, 4.0), sensor, segments, params, 1, true_motion)
    std = np.asarray(motion.noise_std(u.astype(np.float32), params.motion), np.float64)
    np.testing.assert_allclose(mean, u - true_motion, atol=1e-6)
    np.testing.assert_allclose(sd, std, rtol=0.03)
    # The four beams from -90 to -22.5 degrees hit the wall y = 0 from the true pose (0.99, 1.01, 0).
    ranges = np.full(9, 4.0)
    angles = np.asarray(sensor.beam_angles, np.float64)
    ranges[:4] = 1.01 / np.sin(-angles[:4])
    mean_hit, sd_hit = pc.exact_posterior(previous, u, ranges, sensor, segments, params, 1, true_motion)
    assert abs(mean_hit[1]) < 0.5 * abs(mean[1]) and sd_hit[1] < sd[1]
