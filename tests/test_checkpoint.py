"""Checkpoint and resume of ``jaxslam map``: Ctrl-C / SIGTERM stop at a chunk boundary with a
checkpoint (exit 130 / 143, no traceback), ``--resume`` finishes the run with the outputs of an
uninterrupted one, and a checkpoint of a different run is refused."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

import jaxslam.cli.map
import jaxslam.slam
from jaxslam.cli import checkpoint_path, main
from jaxslam.driver import run_in_chunks
from jaxslam.sim import office_scenario
from logs import write_flaser_log

ARGS = ["--particles", "4", "--proposal", "op", "--chunk-size", "4", "--no-progress", "--seed", "3",
        "--set", "linear_update=0.2", "--set", "max_insert_range=8"]
VARYING = {"timings", "peak_memory_mb", "scans_per_second"}


@pytest.fixture(scope="module")
def log_path(tmp_path_factory):
    log = office_scenario(jax.random.key(0), num_scans=150, num_beams=181).log.subset(np.arange(60))
    path = tmp_path_factory.mktemp("log") / "office.clf"
    write_flaser_log(path, log)
    return path


@pytest.fixture(scope="module")
def uninterrupted(log_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("full") / "out"
    assert main(["map", str(log_path), *ARGS, "--out", str(out)]) == 0
    assert not checkpoint_path(out).exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans_processed"] > 20  # several chunks of 4 steps
    return out


def _after_chunk(monkeypatch, chunk_index, action):
    """Call ``action()`` after chunk ``chunk_index`` (0-based), before the CLI's own callback."""

    def wrapped(*args, on_chunk=None, **kwargs):
        def hook(index, carry, outputs_so_far):
            if index == chunk_index:
                action()
            return on_chunk(index, carry, outputs_so_far)

        return run_in_chunks(*args, on_chunk=hook, **kwargs)

    monkeypatch.setattr(jaxslam.slam, "run_in_chunks", wrapped)


def _interrupt(log_path, out, monkeypatch, capsys, sig=signal.SIGINT, extra=()):
    _after_chunk(monkeypatch, 1, lambda: os.kill(os.getpid(), sig))
    code = main(["map", str(log_path), *ARGS, *extra, "--out", str(out)])
    monkeypatch.undo()
    err = capsys.readouterr().err
    return code, err


def _same_outputs(a, b):
    for name in ("trajectory.txt", "map.pgm", "map.yaml"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    sa, sb = (json.loads((p / "summary.json").read_text()) for p in (a, b))
    assert {k: v for k, v in sa.items() if k not in VARYING} == {k: v for k, v in sb.items() if k not in VARYING}


def test_ctrl_c_checkpoints_and_resume_reproduces_the_uninterrupted_run(log_path, uninterrupted, tmp_path,
                                                                      monkeypatch, capsys):
    out = tmp_path / "out"
    code, err = _interrupt(log_path, out, monkeypatch, capsys)
    assert code == 130, err
    assert "Traceback" not in err
    assert "interrupted at step 8 of" in err and "resume with --resume" in err
    assert len(err.strip().splitlines()) == 1
    ckpt = checkpoint_path(out)
    assert ckpt.is_file() and not out.exists()  # the checkpoint lies beside the (unwritten) output folder
    with np.load(ckpt) as z:
        assert int(z["steps_done"]) == 8 and z["info.ancestors"].shape[0] == 8
    assert main(["map", str(log_path), *ARGS, "--resume", "--out", str(out)]) == 0
    assert not ckpt.exists()  # a finished run deletes its checkpoint
    _same_outputs(out, uninterrupted)


def test_sigterm_exits_143_and_periodic_checkpoints_resume_too(log_path, uninterrupted, tmp_path, monkeypatch,
                                                              capsys):
    out = tmp_path / "out"
    code, err = _interrupt(log_path, out, monkeypatch, capsys, sig=signal.SIGTERM, extra=["--checkpoint-every", "3"])
    assert code == 143, err
    assert "Traceback" not in err and "interrupted at step 8 of" in err
    # a resumed run that is interrupted again, after its own chunk 2 (steps 9-16): resumes again
    code, err = _interrupt(log_path, out, monkeypatch, capsys, extra=["--resume", "--checkpoint-every", "3"])
    assert code == 130 and "interrupted at step 16 of" in err, err
    assert main(["map", str(log_path), *ARGS, "--resume", "--out", str(out)]) == 0
    _same_outputs(out, uninterrupted)


def test_checkpoint_every_writes_during_the_run(log_path, tmp_path, monkeypatch):
    out = tmp_path / "out"
    seen = {}

    def look():
        ckpt = checkpoint_path(out)
        seen["exists"] = ckpt.is_file()
        if ckpt.is_file():
            with np.load(ckpt) as z:
                seen["steps"] = int(z["steps_done"])

    _after_chunk(monkeypatch, 2, look)  # before the CLI's callback of chunk 3: the one after chunk 2 is there
    assert main(["map", str(log_path), *ARGS, "--checkpoint-every", "2", "--out", str(out)]) == 0
    assert seen == {"exists": True, "steps": 8}
    assert not checkpoint_path(out).exists()


@pytest.mark.parametrize("change, word", [(["--seed", "4"], "seed: 3 there, 4 here"),
                                          (["--chunk-size", "8"], "chunk_size: 4 there, 8 here"),
                                          (["--set", "motion.srr=0.3"], "params.motion.srr")])
def test_a_checkpoint_of_another_run_is_refused(log_path, tmp_path, monkeypatch, capsys, change, word):
    out = tmp_path / "out"
    code, _ = _interrupt(log_path, out, monkeypatch, capsys)
    assert code == 130

    def trap(*args, **kwargs):
        raise AssertionError("the filter ran")

    monkeypatch.setattr(jaxslam.pipeline, "run", trap)  # the filter jaxslam map calls (jaxslam.pipeline.map_log)
    code = main(["map", str(log_path), *ARGS, *change, "--resume", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("jaxslam map: error: --resume:") and len(err.strip().splitlines()) == 1
    assert "different run" in err and word in err, err
    assert checkpoint_path(out).is_file()  # kept


def test_resume_without_a_checkpoint_is_refused(log_path, tmp_path, capsys):
    code = main(["map", str(log_path), *ARGS, "--resume", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "no checkpoint at" in err and len(err.strip().splitlines()) == 1


def test_sigterm_to_a_real_process_during_its_first_compile(tmp_path):
    """SIGTERM as soon as the progress bar shows (the first chunk is compiling): the process stops
    at the first chunk boundary, exit 143, a checkpoint, no traceback (no signal raised inside JAX)."""
    log = office_scenario(jax.random.key(0), num_scans=150, num_beams=181).log
    write_flaser_log(tmp_path / "office.clf", log)
    out = tmp_path / "out"
    err_path = tmp_path / "stderr.txt"
    argv = [sys.executable, "-m", "jaxslam.cli", "map", str(tmp_path / "office.clf"), "--particles", "4",
            "--proposal", "smp", "--chunk-size", "2", "--set", "linear_update=0.1", "--out", str(out)]
    with open(err_path, "w") as err_file:
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=err_file, text=True)
        try:
            deadline = time.monotonic() + 120
            while "RBPF" not in err_path.read_text() and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)
            assert proc.poll() is None, err_path.read_text()
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=300)
        finally:
            if proc.poll() is None:
                proc.kill()
    err = err_path.read_text()
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "interrupted at step 2 of" in err, err
    assert checkpoint_path(out).is_file() and not out.exists()
