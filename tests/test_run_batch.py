"""``slam.run_batch``: R runs as one program over devices, and over processes (jax.distributed).

Each run of a batch must be the same seed's run alone (``slam.run``): bit for bit (particles,
weights, maps, diagnostics) when each device takes its runs one after the other (the default);
to float rounding when it vmaps them (``vectorize=True``: XLA sums in another order). Several
host devices need ``--xla_force_host_platform_device_count`` before jax is imported, so the
batches run in subprocesses (tests/run_batch_worker.py, started together at the module's start)
and the runs alone in this process.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from run_batch_worker import CHUNK_SIZE, LOG_OF_RUN, SEEDS, batch_logs, result_arrays

from jaxslam import slam

WORKER = Path(__file__).with_name("run_batch_worker.py")
REPO = Path(__file__).resolve().parents[1]
COMPARED = ("poses", "log_weights", "best_path", "ancestors", "proposed_poses", "ess", "logodds")


def _worker(out: Path, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, str(WORKER), str(out), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env)


def _wait(procs: list[subprocess.Popen], timeout: float = 600) -> list[tuple[int, str]]:
    done = []
    try:
        for p in procs:
            text, _ = p.communicate(timeout=timeout)
            done.append((p.returncode, text))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    return done


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _two_processes(out: Path, *args: str) -> list[subprocess.Popen]:
    port = str(_free_port())
    return [_worker(out, "--devices", "2", "--processes", "2", "--process-id", str(p), "--port", port, *args)
            for p in range(2)]


@pytest.fixture(scope="module")
def batches(tmp_path_factory):
    """The batches, started at once in subprocesses (they compile side by side while this
    process runs the runs alone): ``{name: (folder, processes)}``."""
    devices, processes = tmp_path_factory.mktemp("two_devices"), tmp_path_factory.mktemp("two_processes")
    started = {"two_devices": (devices, [_worker(devices, "--devices", "2", "--pool", "24", "8", "4", "2",
                                                        "--also-vectorized")]),
               "two_processes": (processes, _two_processes(processes))}
    yield started
    for _, procs in started.values():
        for p in procs:
            if p.poll() is None:
                p.kill()


@pytest.fixture(scope="module")
def runs_alone(batches):
    """Each run of the batch alone (``slam.run``, one device), as ``result_arrays``."""
    logs, config, params, settings = batch_logs()
    return [result_arrays(slam.run(jax.random.key(seed), logs[i], config, params, settings, chunk_size=CHUNK_SIZE,
                                   progress=False)) for seed, i in zip(SEEDS, LOG_OF_RUN)]


def _assert_same_runs(out: Path, runs_alone: list[dict], prefix: str = "", exact: bool = True) -> None:
    for r, alone in enumerate(runs_alone):
        files = sorted(out.glob(f"{prefix}run{r}-process*.npz"))
        assert len(files) == 1, f"run {r}: held by {len(files)} processes"
        batched = np.load(files[0])
        for name in COMPARED:
            if exact or not np.issubdtype(alone[name].dtype, np.floating):
                np.testing.assert_array_equal(batched[name], alone[name], err_msg=f"run {r}: {name}")
            else:  # float32 sums in another order: 1e-7 seen in the poses, 1e-6 in the weights
                np.testing.assert_allclose(batched[name], alone[name], rtol=1e-5, atol=1e-5, err_msg=f"run {r}: {name}")


def test_a_batch_over_two_devices_is_each_run_alone(batches, runs_alone):
    """Three runs (padded to four) over two host devices, two logs of different lengths, pools
    that start too small: every run is its run alone, bit for bit, though the batch grew its
    pools for all runs at once and took chunks again; vmapped on each device, to float rounding."""
    out, procs = batches["two_devices"]
    ((rc, text),) = _wait(procs)
    assert rc == 0, text
    _assert_same_runs(out, runs_alone)
    assert all(int(np.load(f)["growths"]) >= 2 for f in out.glob("run*.npz"))  # the pools did grow
    _assert_same_runs(out, runs_alone, "vmap-", exact=False)  # vectorize=True


def test_a_batch_over_two_processes_is_each_run_alone(batches, runs_alone, tmp_path):
    """Two processes on the loopback interface (jax.distributed), two host devices each: the
    three runs are split over the four devices, each process gets back its own runs, and each
    is the same seed's run alone in one process."""
    out, procs = batches["two_processes"]
    done = _wait(procs)
    if any(rc != 0 for rc, _ in done):
        probe = _wait(_two_processes(tmp_path, "--probe"))
        if any(rc != 0 for rc, _ in probe):
            pytest.skip("this platform cannot run a collective across two CPU processes on 127.0.0.1: "
                        + next(text for rc, text in probe if rc != 0)[-500:])
    assert all(rc == 0 for rc, _ in done), "\n".join(text for _, text in done)
    _assert_same_runs(out, runs_alone)
    assert {f.name.split("-")[1] for f in out.glob("*.npz")} == {"process0.npz", "process1.npz"}


def test_bad_batches_are_refused_before_any_work():
    logs, config, params, settings = batch_logs()
    with pytest.raises(ValueError, match="1-D array of typed PRNG keys"):
        slam.run_batch(jax.random.key(0), logs[0], config, params, settings)
    with pytest.raises(ValueError, match="3 keys and 2 logs"):
        slam.run_batch(jnp.stack([jax.random.key(s) for s in SEEDS]), list(logs), config, params, settings)
    with pytest.raises(ValueError, match="chunk_size"):
        slam.run_batch(jnp.stack([jax.random.key(0)]), logs[0], config, params, settings, chunk_size=0)
