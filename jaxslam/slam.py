"""SLAM on a whole log, driven from the host: :func:`run` and its :class:`SlamResult`.

:func:`run` is :func:`jaxslam.rbpf.filter` for logs of any length: it selects the scans
(:func:`jaxslam.rbpf.prepare`), then runs the step in fixed-size chunks of one compiled
``lax.scan`` (:mod:`jaxslam.driver`), so that a tqdm bar shows progress, a run can stop at a
chunk boundary and resume bit for bit, and the maps' pools grow when a step needs more room
than they have (the chunk is repeated from that step). Per-step keys are derived from the
run's key as ``filter`` derives them, so both give the same particles.
"""

from __future__ import annotations

import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from jaxslam import paged_map, particle_filter, rbpf
from jaxslam.config import RunSettings, SlamConfig, SlamParams
from jaxslam.driver import pad_items, run_in_chunks
from jaxslam.grid import GridSpec
from jaxslam.laserlog import LaserLog, UpdateSelection
from jaxslam.paged_map import PagedGridSpec, PagedMaps, PoolSize
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
    """(T, 3) a pose for every scan of the log (see ``io.trajectory.trajectory_per_scan``)."""
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
    """The maps' pools: their sizes at the end (the fields of :class:`~jaxslam.paged_map.PoolSize`),
    ``tiles_in_use`` and ``blocks_in_use``, ``peak_request`` and ``peak_block_request`` (the most
    new tiles and blocks one step asked for), ``bytes`` (pools and directories) and ``growths``:
    one entry per growth (``step`` and the new sizes), each a repeated chunk and a recompile."""

    @property
    def best_particle(self) -> int:
        """Index of the final particle with the largest weight (whose map and path are the result's)."""
        return particle_filter.best_particle(self.state.log_weights)

    @property
    def world_grid(self) -> PagedGridSpec:
        """The virtual grid placed in the log's (world) frame."""
        return rbpf.grid_to_world(self.config.grid, self.frame_offset)

    def dense_map(self, particle: int | None = None, local: bool = False) -> tuple[np.ndarray, np.ndarray, GridSpec]:
        """One particle's map (default the best) as dense host arrays over the tiles it wrote:
        ``(logodds (H, W) float16, hit_dist2 (H, W) uint8, grid)``, the grid in the world frame
        (``local``: in the filter's local frame, as ``state``'s poses are)."""
        particle = self.best_particle if particle is None else int(particle)
        logodds, field, box = paged_map.to_dense(self.config.grid, self.state.maps, particle)
        if local:
            return logodds, field, box
        return logodds, field, rbpf.grid_to_world(box, self.frame_offset)

    def to_world(self, poses) -> np.ndarray:
        """Poses (..., 3) or points (..., 2) of the local frame (``state.poses``,
        ``info.proposed_poses``, ``info.mean_pose``) in the world frame: float64, ``frame_offset`` added."""
        return rbpf.to_world(poses, self.frame_offset)

    def to_local(self, poses) -> np.ndarray:
        """World-frame poses (..., 3) or points (..., 2) (``trajectory``, the log's odometry) in the
        filter's local frame, as ``state`` and its maps are: float64, ``frame_offset`` subtracted."""
        return rbpf.to_local(poses, self.frame_offset)


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
) -> SlamResult:
    """Map a whole log: select the scans, then ``lax.scan`` the step over them in chunks.

    The filter runs in a local frame: the translation (x0, y0) of the log's first odometry pose,
    rounded to a multiple of 64 m, is subtracted from the odometry (and ground truth) on the host
    in float64 before anything is cast to float32 (float32 resolves 0.5 m at 5,000 km from the
    origin, e.g. in UTM coordinates), and added back to ``best_path`` and ``trajectory`` in
    float64. The rounding keeps a log that starts within 32 m of the origin bit for bit as it
    was, and makes a shift of the whole log by a multiple of 64 m change nothing but the offset.
    ``result.frame_offset`` holds it; ``result.state`` and ``result.info`` stay in the local
    frame (``result.to_world`` converts). The maps' virtual grid (``config.grid``) is centred on
    the local origin, so every log compiles the same step.

    The maps' pool starts at :func:`jaxslam.rbpf.pool_size`; a chunk in which a step needed more tiles than
    the pool had is repeated from its start with a grown pool (one recompile; reported on
    stderr and in ``result.map_pool``). A log whose odometry leaves the virtual grid is refused
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
        :func:`jaxslam.rbpf.pool_size`); the pool grows as needed, and its size never changes the result.
    """
    from jaxslam.io.trajectory import trajectory_per_scan  # the readers load only when a log is run

    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    t_start = time.perf_counter()
    prepared, selection, frame_offset = rbpf.prepare(log, config, settings)
    log = rbpf.local_log(log, frame_offset)  # from here on, the local frame
    sensor = log.sensor
    initial_pose = jnp.asarray(prepared.initial_pose)
    key_init, key_steps = jax.random.split(key)

    inputs = prepared.inputs
    num_steps = selection.indices.size - 1
    step_keys = jax.random.split(key_steps, max(num_steps, 1))
    done = 0
    prior_info = None
    if resume is None:
        state = _initial_state(key_init, prepared, params, config, initial_pool)
    else:
        _check_resume(resume, num_steps, chunk_size, config)
        done = int(resume.steps_done)
        state = jax.tree.map(jnp.asarray, resume.state)
        prior_info = resume.info
        step_keys = step_keys[done:]
        inputs = jax.tree.map(lambda a: a[done:], inputs)

    growths = [] if initial_pool is None or state.maps.pool_size == tuple(initial_pool) else [
        {"step": 0, **state.maps.pool_size._asdict()}]
    chunk_fn = _chunk_fn_growing_pools(iter(range(done, max(num_steps, 1), chunk_size)), chunk_size, sensor, params,
                                       config, growths, progress)

    def with_prior(info):
        if prior_info is None:
            return info
        return jax.tree.map(lambda a, b: np.concatenate([np.asarray(a), b]), prior_info, info)

    def callback(index, carry, outputs_so_far):
        steps = min(done + (index + 1) * chunk_size, num_steps)
        return on_chunk(RunProgress(steps, num_steps, carry, lambda: with_prior(outputs_so_far())))

    if resume is not None and done == num_steps and num_steps > 0:  # saved after the last chunk
        state, info, first_chunk_seconds = state, jax.tree.map(np.asarray, prior_info), 0.0
    else:
        chunked = run_in_chunks(chunk_fn, (step_keys, inputs), num_steps - done, chunk_size, state,
                                progress=progress, desc=f"RBPF {config.proposal.upper()} N={config.num_particles}",
                                unit="scan", on_chunk=None if on_chunk is None else callback)
        if done + chunked.num_done < num_steps:
            raise RunInterrupted(done + chunked.num_done, num_steps)
        state, info, first_chunk_seconds = chunked.carry, with_prior(chunked.outputs), chunked.first_chunk_seconds

    best = particle_filter.best_particle(state.log_weights)  # SlamResult.best_particle
    best_path = np.concatenate([np.asarray(initial_pose)[None], rbpf.backtrack_path(info, best)])
    trajectory = rbpf.to_world(trajectory_per_scan(log, selection.indices, best_path), frame_offset)
    best_path = rbpf.to_world(best_path, frame_offset)
    total = time.perf_counter() - t_start
    timings = {
        "compile": first_chunk_seconds,
        "total": total,
        "real_time_factor": log.duration / total if total > 0 else float("inf"),
    }
    return SlamResult(state, info, selection, config, settings, best_path, trajectory, timings, frame_offset,
                      _pool_report(state.maps, growths))


def _initial_state(key, prepared: rbpf.PreparedLog, params: SlamParams, config: SlamConfig,
                   initial_pool) -> SlamState:
    """:func:`jaxslam.rbpf.init` in pools of ``initial_pool`` (default :func:`jaxslam.rbpf.pool_size`),
    grown until the first scan alone fits."""
    pool = rbpf.pool_size(config) if initial_pool is None else PoolSize(*(int(v) for v in initial_pool))
    while True:
        state = rbpf.init(key, jnp.asarray(prepared.first_ranges), prepared.sensor, params, config,
                          jnp.asarray(prepared.initial_pose), pool=pool)
        if not bool(state.maps.overflow):
            return state
        pool = _larger_pool(state.maps)


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


def _chunk_fn_growing_pools(chunk_starts, chunk_size: int, sensor, params: SlamParams, config: SlamConfig,
                            growths: list, progress: bool):
    """The chunk function of :func:`run`: :func:`_run_chunk`, and when a step did not fit the
    pools, the steps before it kept, the pools grown (each growth appended to ``growths``) and
    the chunk taken again from that step."""

    def chunk_fn(state, xs, valid):
        keys, chunk_inputs = xs
        start = next(chunk_starts)
        done_infos, offset = [], 0
        while True:
            state, info = _run_chunk(state, keys, chunk_inputs, valid, sensor, params, config)
            stalled = np.flatnonzero(np.asarray(info.pool_overflow) & valid)
            if stalled.size == 0:
                done_infos.append(info)
                break
            # Step s did not fit the pool: its state is the one before it. Keep the steps before
            # it, grow the pool from what s asked for, and take the chunk's rest again from s.
            s = int(stalled[0])
            done_infos.append(jax.tree.map(lambda a: a[:s], info))
            pool = _larger_pool(state.maps)
            state = state._replace(maps=paged_map.grow(config.grid, state.maps, pool))
            offset += s
            growths.append({"step": start + offset, **pool._asdict()})
            if progress:
                print(f"jaxslam: the map pools grew to {pool.capacity} tiles ({pool.max_new_tiles} new per step) "
                      f"and {pool.block_capacity} blocks ({pool.max_new_blocks} new per step) at step "
                      f"{start + offset}; that step and the chunk's rest are taken again (one recompile)",
                      file=sys.stderr)
            keys, chunk_inputs = (jax.tree.map(lambda a: pad_items(a[s:], chunk_size), t) for t in (keys, chunk_inputs))
            valid = np.concatenate([valid[s:], np.zeros(s, bool)])
        info = jax.tree.map(lambda *parts: np.concatenate([np.asarray(p) for p in parts])[:chunk_size], *done_infos)
        return state, info

    return chunk_fn


def _pool_report(maps: PagedMaps, growths: list) -> dict:
    """:attr:`SlamResult.map_pool`."""
    return {
        **maps.pool_size._asdict(),
        "tiles_in_use": int(paged_map.tiles_in_use(maps)), "peak_request": int(maps.peak_request),
        "blocks_in_use": int(paged_map.blocks_in_use(maps)), "peak_block_request": int(maps.peak_block_request),
        "bytes": int(sum(np.asarray(a).nbytes for a in maps)), "growths": growths,
    }



@jax.jit(static_argnames=("config",), donate_argnames=("state",))
def _run_chunk(state, keys, inputs, valid, sensor, params, config):
    """:func:`jaxslam.rbpf.step` over one chunk; ``valid`` False on the padding steps past the
    end of the log (not taken, as every step after one the pools could not hold)."""
    return particle_filter.scan_steps(
        lambda key, s, xs: rbpf.step(key, s, xs[0], sensor, params, config, valid=xs[1]), state, keys, (inputs, valid))


def _larger_pool(maps: PagedMaps) -> PoolSize:
    """The pools' sizes after ``maps``' pools overflowed: each at least twice the old, and room for
    what is in use plus two of the largest requests seen."""
    old = maps.pool_size
    max_new = max(2 * old.max_new_tiles, 2 * int(maps.peak_request))
    max_new_blocks = max(2 * old.max_new_blocks, 2 * int(maps.peak_block_request))
    return PoolSize(max(2 * old.capacity, int(paged_map.tiles_in_use(maps)) + 2 * max_new), max_new,
                    max(2 * old.block_capacity, int(paged_map.blocks_in_use(maps)) + 2 * max_new_blocks),
                    max_new_blocks)
