"""A process of tests/test_run_batch.py: ``slam.run_batch`` on several host devices, maybe as one
of several processes (``jax.distributed`` on the loopback interface); writes each run it holds
to ``OUT/run{r}-process{p}.npz``.

    python tests/run_batch_worker.py OUT --devices 2 [--pool C M B MB] [--also-vectorized]
    python tests/run_batch_worker.py OUT --devices 2 --processes 2 --process-id 0 --port 12345
    python tests/run_batch_worker.py OUT --devices 2 --processes 2 --process-id 0 --port 12345 --probe

The device count must be set before jax is imported, so this is its own process. ``--probe``
only checks that the processes can run a collective across them (the test skips where not).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

# The batch the tests run: one world, three runs (seeds 7, 8, 9) over two logs of it (the second
# starts later and is shorter, so its runs process fewer scans and start from another map).
SEEDS = (7, 8, 9)
LOG_OF_RUN = (0, 1, 0)


def batch_logs():
    """The two logs of the runs, the config, params and settings (small: a test's budget)."""
    import jax

    from jaxslam.config import RunSettings, SlamConfig, default_params
    from jaxslam.sim import office_scenario

    log = office_scenario(jax.random.key(3)).log
    logs = (log.subset(np.arange(44)), log.subset(np.arange(6, 36)))
    config = SlamConfig(num_particles=4, proposal="op", max_insert_range=10.0, beam_stride=1, map_extent=128.0)
    return logs, config, default_params(), RunSettings(linear_update=0.3, angular_update=0.25)


CHUNK_SIZE = 8


def result_arrays(result) -> dict[str, np.ndarray]:
    """What the tests compare of a :class:`jaxslam.slam.SlamResult`."""
    logodds = np.stack([result.dense_map(p, local=True)[0] for p in range(result.state.poses.shape[0])])
    return {"poses": np.asarray(result.state.poses), "log_weights": np.asarray(result.state.log_weights),
            "best_path": result.best_path, "ancestors": np.asarray(result.info.ancestors),
            "proposed_poses": np.asarray(result.info.proposed_poses), "ess": np.asarray(result.info.ess),
            "logodds": logodds, "growths": np.asarray(len(result.map_pool["growths"]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--devices", type=int, default=2, help="host (CPU) devices of this process")
    ap.add_argument("--processes", type=int, default=1)
    ap.add_argument("--process-id", type=int, default=0)
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--pool", type=int, nargs=4, default=None, help="initial_pool (small: the pools grow)")
    ap.add_argument("--probe", action="store_true", help="only a collective across the processes")
    ap.add_argument("--also-vectorized", action="store_true",
                    help="then the batch again with vectorize=True (default pools): OUT/vmap-run{r}-process{p}.npz")
    args = ap.parse_args(argv)
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_force_host_platform_device_count={args.devices}").strip()
    os.environ["JAX_PLATFORMS"] = "cpu"
    import jax

    if args.processes > 1:
        jax.distributed.initialize(f"127.0.0.1:{args.port}", num_processes=args.processes, process_id=args.process_id)
    if args.probe:
        from jax.experimental import multihost_utils

        ids = multihost_utils.process_allgather(np.int32(jax.process_index()))
        print("probe", len(jax.devices()), ids.tolist())
        return 0
    from jaxslam import slam

    logs, config, params, settings = batch_logs()
    keys = jax.numpy.stack([jax.random.key(s) for s in SEEDS])
    results = slam.run_batch(keys, [logs[i] for i in LOG_OF_RUN], config, params, settings, chunk_size=CHUNK_SIZE,
                             progress=False, initial_pool=args.pool)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for r, result in enumerate(results):
        if result is not None:
            np.savez(out / f"run{r}-process{jax.process_index()}.npz", **result_arrays(result))
    if args.also_vectorized:
        results = slam.run_batch(keys, [logs[i] for i in LOG_OF_RUN], config, params, settings,
                                 chunk_size=CHUNK_SIZE, progress=False, vectorize=True)
        for r, result in enumerate(results):
            if result is not None:
                np.savez(out / f"vmap-run{r}-process{jax.process_index()}.npz", **result_arrays(result))
    print(f"process {jax.process_index()}: {len(jax.devices())} devices, held runs "
          f"{[r for r, x in enumerate(results) if x is not None]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
