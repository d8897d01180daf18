"""SLAM on a whole log, driven from the host: :func:`run` and its :class:`SlamResult`.

:func:`run` is :func:`jaxslam.rbpf.filter` for logs of any length: it selects the scans
(:func:`jaxslam.rbpf.prepare`), then runs the step in fixed-size chunks of one compiled
``lax.scan`` (:mod:`jaxslam.driver`), so that a tqdm bar shows progress, a run can stop at a
chunk boundary and resume bit for bit, and the maps' pools grow when a step needs more room
than they have (the chunk is repeated from that step). Per-step keys are derived from the
run's key as ``filter`` derives them, so both give the same particles.
"""

from __future__ import annotations

import time
from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import PRNGKeyArray

from jaxslam import maps as paged
from jaxslam import particle_filter, rbpf
from jaxslam.config import RunSettings, SlamConfig, SlamParams
from jaxslam.driver import ChunkedRun, pad_items, run_in_chunks
from jaxslam.grid import GridSpec
from jaxslam.growth import PoolUse, Runs, growing_chunks, initial_state, pool_report, pool_use
from jaxslam.laserlog import LaserLog, UpdateSelection, grid_to_world, local_log, to_local, to_world, trajectory_per_scan
from jaxslam.maps import PagedGridSpec, PoolSize
from jaxslam.rbpf import SlamInfo, SlamState


class SlamResult(NamedTuple):
    """What ``run`` returns (host arrays)."""

    state: SlamState
    """The final particle set, poses in the local frame (see ``frame_offset``)."""
    info: SlamInfo
    """Per-step diagnostics, stacked over the S - 1 steps after the first scan (NumPy); poses
    (``proposed_poses``, ``mean_pose``) in the local frame (see ``frame_offset``)."""
    selection: UpdateSelection
    """The processed scans and the motion between them."""
    config: SlamConfig
    """The config used (its ``grid`` is in the local frame; ``world_grid`` places it in the log's)."""
    settings: RunSettings
    """The host-side settings used (the update rule)."""
    best_path: np.ndarray
    """(S, 3) float64 poses at the processed scans along the ancestry of the final best particle
    (world frame)."""
    trajectory: np.ndarray
    """(T, 3) a pose for every scan of the log (see ``laserlog.trajectory_per_scan``)."""
    timings: dict
    """Seconds: ``compile`` (first chunk, compile included), ``total`` wall time, and
    ``real_time_factor`` = log duration / total."""
    frame_offset: np.ndarray
    """(2,) float64 (x0, y0) in metres: the translation of the log's first odometry pose rounded to a
    multiple of 64 m, which ``run`` subtracted from the log before the filter ran (the filter's
    *local frame*; zero for a log that starts within 32 m of the origin). ``state``
    and ``info`` are in that frame; ``best_path`` and ``trajectory`` are in the log's (world)
    frame. ``to_world`` converts."""
    map_pool: dict
    """The maps' pools: their sizes at the end (the fields of :class:`~jaxslam.maps.PoolSize`),
    ``tiles_in_use`` and ``blocks_in_use``, ``peak_request`` and ``peak_block_request`` (the most
    new tiles and blocks one step asked for), ``bytes`` (pools and directories) and ``growths``:
    one entry per growth (``step`` and the new sizes), each a repeated chunk and a recompile."""
    closure: "LoopClosure | None" = None
    """The loop closure behind the filter (:func:`jaxslam.graph.close_loops`: the pose graph, its
    loops and the optimised ``trajectory``), when ``run`` was asked for it (``close_loops``);
    None for the filter alone. ``best_path`` and ``trajectory`` stay the filter's."""

    @property
    def best_particle(self) -> int:
        """Index of the final particle whose map and path are the result's: the heaviest, or where
        the last step resampled, the descendant of the heaviest before it
        (:func:`jaxslam.rbpf.final_best_particle`)."""
        return rbpf.final_best_particle(self.info.ancestors, self.info.best_particle)

    @property
    def world_grid(self) -> PagedGridSpec:
        """The virtual grid placed in the log's (world) frame."""
        return grid_to_world(self.config.grid, self.frame_offset)

    def dense_map(self, particle: int | None = None, local: bool = False) -> tuple[np.ndarray, np.ndarray, GridSpec]:
        """One particle's map (default the best) as dense host arrays over the tiles it wrote:
        ``(logodds (H, W) float16, hit_dist2 (H, W) uint8, grid)``, the grid in the world frame
        (``local``: in the filter's local frame, as ``state``'s poses are)."""
        particle = self.best_particle if particle is None else int(particle)
        logodds, field, box = paged.to_dense(self.config.grid, self.state.maps, particle)
        if local:
            return logodds, field, box
        return logodds, field, grid_to_world(box, self.frame_offset)

    def closed_map(self, log, params) -> tuple[np.ndarray, np.ndarray, GridSpec]:
        """The map drawn again at the loop closure's optimised poses, as :meth:`dense_map` returns
        a map (:func:`jaxslam.graph.draw_map`); the filter's best map where no loop was kept (the
        poses are then the filter's)."""
        if self.closure is None or self.closure.num_loops == 0:
            return self.dense_map()
        from jaxslam import graph  # on first use: see run's import of it

        return graph.draw_map(self.closure, log, params, self.config, self.frame_offset)

    def to_world(self, poses) -> np.ndarray:
        """Poses (..., 3) or points (..., 2) of the local frame (``state.poses``,
        ``info.proposed_poses``, ``info.mean_pose``) in the world frame: float64, ``frame_offset`` added."""
        return to_world(poses, self.frame_offset)

    def to_local(self, poses) -> np.ndarray:
        """World-frame poses (..., 3) or points (..., 2) (``trajectory``, the log's odometry) in the
        filter's local frame, as ``state`` and its maps are: float64, ``frame_offset`` subtracted."""
        return to_local(poses, self.frame_offset)


class RunInterrupted(Exception):
    """``run``'s ``on_chunk`` asked to stop: ``steps_done`` of ``num_steps`` steps were taken."""

    def __init__(self, steps_done: int, num_steps: int):
        super().__init__(f"interrupted at step {steps_done} of {num_steps}")
        self.steps_done = steps_done
        self.num_steps = num_steps


class RunProgress(NamedTuple):
    """Where a run stands after a chunk (what ``on_chunk`` gets, and what ``resume`` takes back)."""

    steps_done: int
    """Steps taken so far (a multiple of the chunk size, or all of them)."""
    num_steps: int
    """Steps of the whole run (processed scans - 1)."""
    state: SlamState
    """The particle set after ``steps_done`` steps (local frame). In ``on_chunk`` it is the
    device state the next chunk will donate: copy it (``np.array``) before returning."""
    info: SlamInfo
    """The per-step diagnostics of those steps, stacked (NumPy). In ``on_chunk`` a zero-argument
    callable returning them (they are concatenated only when asked)."""


def run(
    key: PRNGKeyArray,
    log: LaserLog,
    config: SlamConfig,
    params: SlamParams,
    settings: RunSettings = RunSettings(),
    *,
    chunk_size: int = 32,
    progress: bool = True,
    on_chunk=None,
    resume: RunProgress | None = None,
    initial_pool: tuple[int, int] | None = None,
    close_loops: "ClosureConfig | None" = None,
    prepared: tuple | None = None,
) -> SlamResult:
    """Map a whole log: select the scans, then ``lax.scan`` the step over them in chunks; with
    ``close_loops``, then close the loops of the best particle's path (``result.closure``).

    The filter runs in a local frame: the translation (x0, y0) of the log's first odometry pose,
    rounded to a multiple of 64 m, is subtracted from the odometry (and ground truth) on the host
    in float64 before anything is cast to float32 (float32 resolves 0.5 m at 5,000 km from the
    origin, e.g. in UTM coordinates), and added back to ``best_path`` and ``trajectory`` in
    float64. The rounding keeps a log that starts within 32 m of the origin bit for bit as it
    was, and makes a shift of the whole log by a multiple of 64 m change nothing but the offset.
    ``result.frame_offset`` holds it; ``result.state`` and ``result.info`` stay in the local
    frame (``result.to_world`` converts). The maps' virtual grid (``config.grid``) is centred on
    the local origin, so every log compiles the same step.

    The maps' pool starts at :func:`jaxslam.rbpf.pool_size`, sized from the first scan's footprint
    (before the step compiles); a chunk in which a step needed more tiles than the pool had is
    taken again from that step with a grown pool (:mod:`jaxslam.growth`; one recompile; reported
    on stderr and in ``result.map_pool``). A log whose odometry leaves the virtual grid is refused
    first (:func:`jaxslam.rbpf.check_config_for_log`).

    Args:
      key: the run's randomness (the same key reproduces the run bit for bit).
      log: the laser log.
      config: static settings of the step.
      params: traced numbers.
      settings: host-side settings: the update rule.
      chunk_size: steps per compiled call (every chunk has this many steps, the last padded
        with no-op steps, so the step compiles once).
      progress: show a tqdm bar.
      on_chunk: ``on_chunk(RunProgress) -> stop`` called on the host after every chunk (its
        ``info`` a callable); a true return value stops the run at that chunk boundary and
        ``run`` raises :class:`RunInterrupted` (e.g. to checkpoint and stop on a signal).
      resume: a :class:`RunProgress` saved by an ``on_chunk`` of a run with the same key, log,
        config, params, settings and ``chunk_size``: the run goes on from it, and its result is
        bit for bit the uninterrupted run's (the per-step keys are derived from ``key`` as before
        and the steps done are skipped; the chunks fall on the same steps).
      initial_pool: ``(capacity, max_new_tiles)`` of the maps' pool at the start (default
        :func:`jaxslam.rbpf.pool_size` of the first scan's footprint); the pool grows as needed, and
        its size never changes the result.
      close_loops: a :class:`jaxslam.graph.ClosureConfig`: after the filter, build the pose graph,
        search it for loops and optimise it (:func:`jaxslam.graph.close_loops`; ``result.closure``,
        ``result.closed_map``); None (the default): the filter alone.
      prepared: :func:`jaxslam.rbpf.prepare`'s output for this ``log``, ``config`` and
        ``settings`` where the caller has it (the command line's memory check), so that the log
        is prepared once; None (the default): prepared here.
    """
    _check_chunk_size(chunk_size)
    t_start = time.perf_counter()
    prepared, selection, frame_offset = rbpf.prepare(log, config, settings) if prepared is None else prepared
    local = local_log(log, frame_offset)  # from here on, the local frame
    state, info, growths, first_chunk_seconds = _filter_one(
        key, prepared, selection.indices.size - 1, local.sensor, params, config, chunk_size, progress, on_chunk,
        resume, initial_pool)
    result = _finish(state, info, prepared, local, selection, frame_offset, config, settings, growths,
                     first_chunk_seconds, time.perf_counter() - t_start)
    if close_loops is not None:
        # Imported here: jaxslam.graph (with scipy.sparse) is 0.74 s of `import jaxslam`'s start-up
        # (docs/design.md, "Imports"), and most runs of the library do not close loops.
        from jaxslam import graph

        result = result._replace(closure=graph.close_loops(log, result, params, close_loops, progress=progress))
    return result


def _filter_one(key, prepared: rbpf.PreparedLog, num_steps: int, sensor, params: SlamParams, config: SlamConfig,
                chunk_size: int, progress: bool, on_chunk, resume: RunProgress | None, initial_pool):
    """:func:`run`'s filter: the runs' driver (:func:`jaxslam.growth.growing_chunks`) with one run, from
    the start or from ``resume``. Returns the final state, the infos of all ``num_steps`` steps
    (NumPy), the pools' growths and the first chunk's seconds; :class:`RunInterrupted` where
    ``on_chunk`` stopped the run."""
    key_init, key_steps = jax.random.split(key)
    step_keys = jax.random.split(key_steps, max(num_steps, 1))
    done, prior_info = 0, None
    if resume is None:
        state = initial_state(key_init, prepared, params, config, initial_pool)
    else:
        _check_resume(resume, num_steps, chunk_size, config)
        done, prior_info = int(resume.steps_done), resume.info
        state = jax.tree.map(jnp.asarray, resume.state)
    growths = [] if initial_pool is None or state.maps.pool_size == tuple(initial_pool) else [
        {"step": 0, **state.maps.pool_size._asdict()}]
    if resume is not None and done == num_steps and num_steps > 0:  # saved after the last chunk
        return state, jax.tree.map(np.asarray, prior_info), growths, 0.0

    def with_prior(outputs):  # the driver's (S, 1, ...) infos of this run, after those of the resumed steps
        info = jax.tree.map(lambda a: a[:, 0], outputs)
        if prior_info is None:
            return info
        return jax.tree.map(lambda a, b: np.concatenate([np.asarray(a), b]), prior_info, info)

    def callback(index, carry, outputs_so_far):
        steps = min(done + (index + 1) * chunk_size, num_steps)
        return on_chunk(RunProgress(steps, num_steps, carry, lambda: with_prior(outputs_so_far())))

    one_run = lambda a: np.asarray(a)[done:, None]  # noqa: E731 (the steps to take, with a run axis)
    xs = (one_run(jax.random.key_data(step_keys)), jax.tree.map(one_run, prepared.inputs),
          np.ones((max(num_steps - done, 0), 1), bool))
    chunk_fn = growing_chunks(_one_run(sensor, params, config, jax.random.key_impl(key)), state.maps.pool_size,
                              config.grid, growths, first_step=done, progress=progress)
    chunked = run_in_chunks(chunk_fn, xs, num_steps - done, chunk_size, state, progress=progress, unit="scan",
                            desc=f"RBPF {config.proposal.upper()} N={config.num_particles}",
                            on_chunk=None if on_chunk is None else callback)
    if done + chunked.num_done < num_steps:
        raise RunInterrupted(done + chunked.num_done, num_steps)
    return chunked.carry, with_prior(chunked.outputs), growths, chunked.first_chunk_seconds


def _one_run(sensor, params: SlamParams, config: SlamConfig, impl) -> Runs:
    """:func:`run`'s :class:`~jaxslam.growth.Runs`: :func:`_run_chunk` on the one run (the run
    axis of the driver's arrays dropped; ``impl`` the run's PRNG implementation)."""

    def chunk(state, key_data, inputs, valid):
        keys = jax.random.wrap_key_data(key_data[:, 0], impl=impl)
        state, info = _run_chunk(state, keys, jax.tree.map(lambda a: a[:, 0], inputs), valid[:, 0], sensor, params,
                                 config)
        info = jax.tree.map(lambda a: np.asarray(a)[:, None], info)
        return state, info, bool(np.any(info.pool_overflow & valid)), lambda: pool_use(state.maps)

    def grow(state, pool):
        return state._replace(maps=paged.grow(config.grid, state.maps, pool))

    return Runs(chunk, grow, np.zeros(1, int))


# ---------------------------------------------------------------------------------------------
# Several runs as one program, over devices and hosts.


RUNS_AXIS = "runs"
"""The name of :func:`run_batch`'s mesh axis: the runs are split over it."""


def run_batch(
    keys: PRNGKeyArray,
    logs: LaserLog | Sequence[LaserLog],
    config: SlamConfig,
    params: SlamParams,
    settings: RunSettings = RunSettings(),
    *,
    devices: int | Sequence[jax.Device] | None = None,
    chunk_size: int = 32,
    progress: bool = True,
    initial_pool: tuple[int, int, int, int] | None = None,
    vectorize: bool = False,
) -> list[SlamResult | None]:
    """R runs of :func:`run` as one program, the runs spread over ``devices``.

    Every array of the state carries a leading run axis split over a 1-D device mesh
    (:data:`RUNS_AXIS`, ``jax.shard_map``), so each device holds R / D of the runs and steps them
    without talking to the others; the devices agree only, once per chunk, on whether some
    run's map pools overflowed. R is padded up to a multiple of D with copies of the last run,
    whose results are dropped. The per-step keys are derived from each run's key as ``run``
    derives them, and a step not taken is a no-op, so each run is :func:`run`'s with its key,
    log, config, params and settings, up to how XLA compiles the batch: with each device taking
    its runs one after the other (``lax.map``, the default) the tests' runs are their runs alone
    bit for bit (particles, weights, diagnostics; tests/test_run_batch.py), but that is not
    guaranteed: at the defaults (SMP, 30 particles, 136 steps of the simulated office) three
    runs of four were, and one drew a pose 1.9 cm away at step 129 (a near tie that rounded the
    other way) and went on as another run of the same filter (benchmarks/bench_run_batch.py).

    Several hosts: call it in every process after ``jax.distributed.initialize``, with the same
    arguments; ``devices`` defaults to ``jax.devices()``, every process's. Each process gets back
    the results of the runs its own devices held (the others' are None in the list).

    Pool growth: the runs share their pools' sizes (one program). When a step of some run needs
    more room than its pools have, every run's pools grow and each run takes its chunk again from
    its own stalled step, as :func:`run` does (:mod:`jaxslam.growth`; both go through its driver).
    Checkpoints and ``resume`` are :func:`run`'s alone.

    Args:
      keys: (R,) the runs' keys.
      logs: one log for every run, or R logs (e.g. a simulated world per seed): the same beams
        and sensor; they may process different numbers of scans (a shorter run's last chunks
        are no-op steps for it).
      config, params, settings: as :func:`run`'s, the same for every run.
      devices: the devices of the mesh, or how many of ``jax.devices()`` (:func:`batch_devices`;
        default all of them).
      chunk_size: steps per compiled call, as :func:`run`'s.
      progress: a tqdm bar over the longest run's steps (and growth lines on stderr).
      initial_pool: the maps' pool sizes at the start (a :class:`~jaxslam.maps.PoolSize`;
        default :func:`jaxslam.rbpf.pool_size` of the largest first-scan footprint).
      vectorize: vmap the runs a device holds rather than take them one after the other
        (``lax.map``). Faster where a device has room to spare for several runs at once (a GPU
        holding R / D > 1 runs); but XLA sums the vmapped weights and window posteriors in
        another order, so each run equals its run alone to float rounding only (about 1e-7 m in
        the poses from the first steps), and a long run can drift from it: a resampling decision
        flips and it becomes another run of the same filter (at the defaults above, one run of
        four flipped one at step 84).

    Returns:
      A list of R :class:`SlamResult` (None for a run held by another process). ``timings`` are
      the batch's: ``total`` is the whole batch's wall time, ``compile`` its first chunk's.
    """
    keys, logs = _check_batch(keys, logs, chunk_size)
    devices = batch_devices(devices)
    t_start = time.perf_counter()
    runs, sensor, params = _prepare_runs(logs, config, settings, params)
    split = [jax.random.split(k) for k in keys]  # (init, steps) keys of each run, as run splits them
    mesh = Mesh(np.array(devices), (RUNS_AXIS,))
    source = np.minimum(np.arange(-(-len(runs) // len(devices)) * len(devices)), len(runs) - 1)  # the run a slot copies
    state, pool, growths = _batch_start(split, runs, source, mesh, params, config, initial_pool)
    xs, num_steps = _batch_steps(split, runs, source)
    batch = _batch_runs(mesh, sensor, params, config, vectorize, state)
    chunked = run_in_chunks(growing_chunks(batch, pool, config.grid, growths, progress=progress), xs,
                            max(int(num_steps.max()), 1), chunk_size, state, progress=progress, unit="scan",
                            desc=f"RBPF {config.proposal.upper()} N={config.num_particles}, {len(runs)} runs on "
                                 f"{len(devices)} devices")
    return _batch_results(chunked, batch.local, runs, num_steps, config, settings, growths,
                          time.perf_counter() - t_start)


def _check_batch(keys, logs, chunk_size) -> tuple[PRNGKeyArray, list[LaserLog]]:
    """:func:`run_batch`'s keys as a key array, and one log for each (``ValueError`` where not)."""
    _check_chunk_size(chunk_size)
    keys = jnp.asarray(keys) if not isinstance(keys, jax.Array) else keys
    if keys.ndim != 1 or not jnp.issubdtype(keys.dtype, jax.dtypes.prng_key):
        raise ValueError(f"run_batch: keys must be a 1-D array of typed PRNG keys (jax.random.key), got shape "
                         f"{keys.shape} of {keys.dtype}")
    num_runs = keys.shape[0]
    logs = [logs] * num_runs if isinstance(logs, LaserLog) else list(logs)
    if num_runs < 1 or len(logs) != num_runs:
        raise ValueError(f"run_batch: {num_runs} keys and {len(logs)} logs; give one log, or one per key, and a key "
                         "at least")
    return keys, logs


def _prepare_runs(logs: list[LaserLog], config: SlamConfig, settings: RunSettings, params: SlamParams):
    """The host side of each distinct log, once (the runs of one log share it): per run
    ``(prepared, selection, frame_offset, local log)``; the laser and ``params`` as host arrays
    (replicated on every process's devices). ``ValueError`` where the logs' lasers differ."""
    prepared_by_log = {}
    for log in logs:
        if id(log) not in prepared_by_log:
            prepared, selection, frame_offset = rbpf.prepare(log, config, settings)
            prepared_by_log[id(log)] = (prepared, selection, frame_offset, local_log(log, frame_offset))
    runs = [prepared_by_log[id(log)] for log in logs]
    sensor = jax.tree.map(np.asarray, runs[0][0].sensor)
    for prepared, *_ in runs[1:]:
        if not all(np.array_equal(a, b) for a, b in zip(prepared.sensor, sensor)):
            raise ValueError("run_batch: the logs' lasers differ (beam angles, range limits or mounting); a batch "
                             "maps logs of one laser")
    return runs, sensor, jax.tree.map(np.asarray, params)


def _global_runs(mesh, leaf_of_slot, shape: tuple, slots: int) -> jax.Array:
    """A global array (slots, *shape) split over the runs, each process building its own slots
    (``leaf_of_slot(slot)``)."""
    return jax.make_array_from_callback((slots,) + tuple(shape), NamedSharding(mesh, P(RUNS_AXIS)),
                                        lambda index: np.stack([leaf_of_slot(r) for r in range(slots)[index[0]]]))


def _batch_start(split, runs, source: np.ndarray, mesh, params, config: SlamConfig, initial_pool):
    """The batch's first state: one initial state per distinct log, in pools of one size, as a
    global state over the slots (``source``: the run each copies). Returns it, the pools' sizes
    and the growths list (a growth at step 0 where ``initial_pool`` had to grow)."""
    starts = {}
    for (prepared, *_), (k_init, _) in zip(runs, split):
        if id(prepared) not in starts:
            starts[id(prepared)] = initial_state(k_init, prepared, params, config, initial_pool)
    pool = PoolSize(*np.max([s.maps.pool_size for s in starts.values()], axis=0).tolist())
    starts = {k: s._replace(maps=paged.grow(config.grid, s.maps, pool)) if s.maps.pool_size != pool else s
              for k, s in starts.items()}
    growths = [] if initial_pool is None or pool == PoolSize(*initial_pool) else [{"step": 0, **pool._asdict()}]
    start_leaves = {k: jax.tree.leaves(s) for k, s in starts.items()}
    first = next(iter(starts.values()))
    state = jax.tree.unflatten(jax.tree.structure(first), [
        _global_runs(mesh, lambda r, i=i: np.asarray(start_leaves[id(runs[source[r]][0])][i]), np.shape(leaf),
                     source.size)
        for i, leaf in enumerate(jax.tree.leaves(first))])
    return state, pool, growths


def _batch_steps(split, runs, source: np.ndarray):
    """The driver's steps of the batch: ``(key_data, inputs, valid)`` (S, slots, ...) on the host,
    each slot its run's per-step keys (as :func:`run` derives them) and inputs, padded to the
    longest run (``valid`` False past a run's end); and each run's number of steps."""
    num_steps = np.array([selection.indices.size - 1 for _, selection, _, _ in runs])
    total_steps = max(int(num_steps.max()), 1)
    step_keys = np.stack([jax.random.key_data(pad_items(jax.random.split(k_steps, max(int(n), 1)), total_steps))
                          for (_, k_steps), n in zip(split, num_steps)], axis=1)  # (S, R, ...) key data
    inputs = jax.tree.map(lambda *a: np.stack(a, axis=1)[:, source],
                          *(pad_items(prepared.inputs, total_steps) for prepared, *_ in runs))
    run_valid = np.arange(total_steps)[:, None] < num_steps[None, :]  # (S, R)
    return (step_keys[:, source], inputs, run_valid[:, source]), num_steps


def _batch_runs(mesh, sensor, params, config: SlamConfig, vectorize: bool, state) -> Runs:
    """:func:`run_batch`'s :class:`~jaxslam.growth.Runs`: :func:`_run_chunk_batch` over the
    slots of ``state`` on ``mesh``, the host's chunks turned into global arrays and back."""
    slots = state.step.shape[0]

    def to_runs(chunk):
        """A chunk (C, slots, ...) on the host as a global array (slots, C, ...) split over the runs."""
        return _global_runs(mesh, lambda r: chunk[:, r], (chunk.shape[0],) + chunk.shape[2:], slots)

    def chunk(state, key_data, inputs, valid):
        state, info, overflow, use = _run_chunk_batch(state, to_runs(key_data), jax.tree.map(to_runs, inputs),
                                                      to_runs(valid), sensor, params, config, mesh, vectorize)
        local = jax.tree.map(_local_runs, info)  # {slot: (C, ...)} of this process's slots
        info = jax.tree.map(lambda d: np.stack([d[r] for r in sorted(d)], axis=1), local, is_leaf=_is_runs)
        return state, info, bool(overflow.addressable_data(0)), lambda: PoolUse(
            *(int(u.addressable_data(0)) for u in use))

    def grow(state, pool):
        return _grow_batch(state, config, pool, mesh)

    return Runs(chunk, grow, np.array(sorted(_local_runs(state.step))))


def _batch_results(chunked: ChunkedRun, local: np.ndarray, runs, num_steps: np.ndarray, config: SlamConfig,
                   settings: RunSettings, growths: list, total: float) -> list[SlamResult | None]:
    """Each run's :class:`SlamResult` from the driver's result (None for a run another process holds)."""
    final = jax.tree.map(_local_runs, chunked.carry)
    results: list[SlamResult | None] = [None] * len(runs)
    for j, r in enumerate(local.tolist()):
        if r >= len(runs):  # a padding copy
            continue
        prepared, selection, frame_offset, run_log = runs[r]
        results[r] = _finish(jax.tree.map(lambda d: d[r], final, is_leaf=_is_runs),
                             jax.tree.map(lambda a: a[:num_steps[r], j], chunked.outputs), prepared, run_log,
                             selection, frame_offset, config, settings, list(growths), chunked.first_chunk_seconds,
                             total)
    return results


def _is_runs(x) -> bool:
    """A leaf's ``{slot: its slice}`` (from :func:`_local_runs`)."""
    return isinstance(x, dict)


def batch_devices(devices: int | Sequence[jax.Device] | None = None) -> list[jax.Device]:
    """The devices :func:`run_batch` spreads its runs over: ``devices`` itself, the first
    ``devices`` of ``jax.devices()`` (every process's) when an int, or all of them when None.
    ``ValueError`` when there are not that many (the message says how to make host devices)."""
    if devices is None:
        return jax.devices()
    if isinstance(devices, (int, np.integer)) and not isinstance(devices, bool):
        if not 1 <= devices <= jax.device_count():
            raise ValueError(f"{devices} devices asked for, jax sees {jax.device_count()} "
                             f"({jax.devices()[0].platform}); on a CPU, set XLA_FLAGS="
                             f"--xla_force_host_platform_device_count={max(int(devices), 1)} before jax is imported "
                             "(several host devices on shared cores run no faster)")
        return jax.devices()[:int(devices)]
    devices = list(devices)
    if not devices:
        raise ValueError("run_batch: no devices")
    return devices


def _local_runs(array: jax.Array) -> dict[int, np.ndarray]:
    """The runs of a global array split over :data:`RUNS_AXIS` that this process's devices hold:
    ``{run index: its slice (host)}``."""
    out = {}
    for shard in array.addressable_shards:
        first = shard.index[0].start or 0
        data = np.asarray(shard.data)
        out.update({first + i: data[i] for i in range(data.shape[0])})
    return out


@partial(jax.jit, static_argnames=("config", "mesh", "vectorize"), donate_argnames=("state",))
def _run_chunk_batch(state, step_key_data, inputs, valid, sensor, params, config, mesh, vectorize):
    """:func:`_chunk_steps` over the runs (``vectorize``: vmapped; else ``lax.map``: one after the
    other on each device), the runs split over ``mesh`` (the state donated). Also returns,
    the same on every device, whether a valid step of some run overflowed its pools, and the
    largest pool use of any run (a :class:`~jaxslam.growth.PoolUse` that sizes the grown pools)."""
    def local(state, step_key_data, inputs, valid, sensor, params):
        keys = jax.random.wrap_key_data(step_key_data)
        if vectorize:
            state, info = jax.vmap(_chunk_steps, in_axes=(0, 0, 0, 0, None, None, None))(
                state, keys, inputs, valid, sensor, params, config)
        else:  # one run after the other: each the very program of a run alone (bit for bit)
            state, info = jax.lax.map(lambda run: _chunk_steps(*run, sensor, params, config),
                                      (state, keys, inputs, valid))
        overflow = jax.lax.pmax(jnp.any(info.pool_overflow & valid).astype(jnp.int32), RUNS_AXIS)
        use = PoolUse(*(jax.lax.pmax(jnp.max(u).astype(jnp.int32), RUNS_AXIS)
                         for u in jax.vmap(pool_use)(state.maps)))
        return state, info, overflow > 0, use

    runs = P(RUNS_AXIS)
    return jax.shard_map(local, mesh=mesh, in_specs=(runs, runs, runs, runs, P(), P()),
                         out_specs=(runs, runs, P(), P()), check_vma=False)(
        state, step_key_data, inputs, valid, sensor, params)


@partial(jax.jit, static_argnames=("config", "pool", "mesh"))
def _grow_batch(state, config, pool, mesh):
    """Every run's maps in pools of ``pool``'s sizes (:func:`jaxslam.maps.grow`)."""
    def local(state):
        return jax.vmap(lambda s: s._replace(maps=paged.grow(config.grid, s.maps, pool)))(state)

    return jax.shard_map(local, mesh=mesh, in_specs=P(RUNS_AXIS), out_specs=P(RUNS_AXIS),
                         check_vma=False)(state)


def _finish(state: SlamState, info: SlamInfo, prepared: rbpf.PreparedLog, run_log: LaserLog,
            selection: UpdateSelection, frame_offset, config: SlamConfig, settings: RunSettings, growths: list,
            first_chunk_seconds: float, total: float) -> SlamResult:
    """One run's :class:`SlamResult` from its final state and stacked infos (what :func:`run` and
    :func:`run_batch` share): the best particle's path and the per-scan trajectory, in the world frame."""

    best = rbpf.final_best_particle(info.ancestors, info.best_particle)  # SlamResult.best_particle
    best_path = np.concatenate([np.asarray(prepared.initial_pose)[None], rbpf.backtrack_path(info, best)])
    trajectory = to_world(trajectory_per_scan(run_log, selection.indices, best_path), frame_offset)
    best_path = to_world(best_path, frame_offset)
    timings = {
        "compile": first_chunk_seconds,
        "total": total,
        "real_time_factor": run_log.duration / total if total > 0 else float("inf"),
    }
    return SlamResult(state, info, selection, config, settings, best_path, trajectory, timings, frame_offset,
                      pool_report(state.maps, growths))


def _check_chunk_size(chunk_size) -> None:
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")


def _check_resume(resume: RunProgress, num_steps: int, chunk_size: int, config: SlamConfig) -> None:
    """``ValueError`` unless ``resume`` is a point of a run of ``num_steps`` steps in chunks of
    ``chunk_size`` with ``config``'s particles and grid."""
    done = int(resume.steps_done)
    if resume.num_steps != num_steps or not 0 <= done <= num_steps or (done % chunk_size and done != num_steps):
        raise ValueError(f"resume: {done} of {resume.num_steps} steps done does not fit this run "
                         f"({num_steps} steps, chunks of {chunk_size})")
    expected = (config.num_particles,) + config.grid.num_blocks
    if np.shape(resume.state.maps.directory) != expected:
        raise ValueError(f"resume: the saved map directories are {np.shape(resume.state.maps.directory)}, this "
                         f"run's are {expected} (particles, blocks)")



def _chunk_steps(state, keys, inputs, valid, sensor, params, config):
    """:func:`jaxslam.rbpf.step` over one chunk; ``valid`` False on the padding steps past the
    end of the log (not taken, as every step after one the pools could not hold)."""
    return particle_filter.scan_steps(
        lambda key, s, xs: rbpf.step(key, s, xs[0], sensor, params, config, valid=xs[1]), state, keys, (inputs, valid))


_run_chunk = jax.jit(_chunk_steps, static_argnames=("config",), donate_argnames=("state",))
"""One run's chunk, compiled (the state donated)."""
