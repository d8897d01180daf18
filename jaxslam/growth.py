"""The maps' pools grown as a run needs them: the growth policy, and the chunk function that
drives :func:`jaxslam.slam.run`, :func:`jaxslam.slam.run_batch` and :func:`jaxslam.island_runs.run`.

A run's pools (:class:`~jaxslam.maps.PagedMaps`) start at a guess. A step that needs more room
than they have is not taken, nor is any step after it (the state stays the one before it:
``SlamInfo.pool_overflow``). ``run`` (one run), ``run_batch`` (R runs over a device mesh) and
:func:`jaxslam.island_runs.run` (the island filter as one run) step their runs with
:func:`growing_chunks` in :func:`jaxslam.driver.run_in_chunks`: after a chunk in which a run's
step s did not fit, it keeps each run's steps before its stall, grows every run's pools
(:func:`grow_pools`, the one policy; :func:`larger_pool_for` sizes them) and takes each run's
chunk again from its own stalled step (a run that did not stall takes no-op steps). The steps' keys are fixed and the pools' size never changes a result, so a run
that grew is bit for bit the run that started in pools large enough.
"""

from __future__ import annotations

import itertools
import sys
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import maps as paged
from jaxslam import rbpf
from jaxslam.config import SlamConfig, SlamParams
from jaxslam.driver import ChunkFn
from jaxslam.maps import PagedGridSpec, PagedMaps, PoolSize


class PoolUse(NamedTuple):
    """What sizes the grown pools: tiles and blocks in use, and the largest requests seen (of
    one map set, or the largest over a batch's runs)."""

    tiles_in_use: int
    peak_request: int
    blocks_in_use: int
    peak_block_request: int


def pool_use(maps: PagedMaps) -> PoolUse:
    """``maps``' :class:`PoolUse` (device scalars)."""
    return PoolUse(paged.tiles_in_use(maps), maps.peak_request, paged.blocks_in_use(maps), maps.peak_block_request)


def larger_pool(maps: PagedMaps, spec: PagedGridSpec) -> PoolSize:
    """The pools' sizes after ``maps``' pools overflowed (:func:`larger_pool_for`)."""
    return larger_pool_for(maps.pool_size, pool_use(maps), spec)


def larger_pool_for(old: PoolSize, use: PoolUse, spec: PagedGridSpec) -> PoolSize:
    """The pools' sizes after pools of ``old`` sizes overflowed: each at least twice the old, and
    room for what is in use plus two of the largest requests seen; the tile pool no larger than
    int32 slot indices allow (:func:`jaxslam.maps.max_pool_tiles`). ``RuntimeError`` when the
    tile pool overflowed at that size."""
    tiles, peak, blocks, peak_blocks = (int(v) for v in use)
    most = paged.max_pool_tiles(spec)
    max_new = min(max(2 * old.max_new_tiles, 2 * peak), most)
    capacity = min(max(2 * old.capacity, tiles + 2 * max_new), most)
    if capacity == old.capacity and tiles + peak > capacity:  # a larger allowance per step would not fit either
        raise RuntimeError(
            f"the maps need more than {capacity} tiles of {spec.tile_size} x {spec.tile_size} cells ({tiles} in use, "
            f"a step asking for {peak} more), the most a pool can index with int32; use fewer particles, "
            "a smaller max_insert_range or a coarser resolution")
    max_new_blocks = max(2 * old.max_new_blocks, 2 * peak_blocks)
    return PoolSize(capacity, max_new, max(2 * old.block_capacity, blocks + 2 * max_new_blocks), max_new_blocks)


def report_growth(pool: PoolSize, where: str) -> None:
    """The stderr line of a growth of the map pools."""
    print(f"jaxslam: the map pools grew to {pool.capacity} tiles ({pool.max_new_tiles} new per step) "
          f"and {pool.block_capacity} blocks ({pool.max_new_blocks} new per step) {where} (one recompile)",
          file=sys.stderr)


def pool_report(maps: PagedMaps, growths: list) -> dict:
    """:attr:`jaxslam.slam.SlamResult.map_pool`."""
    return {
        **maps.pool_size._asdict(),
        "tiles_in_use": int(paged.tiles_in_use(maps)), "peak_request": int(maps.peak_request),
        "blocks_in_use": int(paged.blocks_in_use(maps)), "peak_block_request": int(maps.peak_block_request),
        "bytes": int(sum(np.asarray(a).nbytes for a in maps)), "growths": growths,
    }


def initial_state(key, prepared: rbpf.PreparedLog, params: SlamParams, config: SlamConfig,
                  initial_pool) -> rbpf.SlamState:
    """A run's first state: :func:`jaxslam.rbpf.init` in pools of ``initial_pool``, grown until
    the first scan alone fits; by default in pools of :func:`jaxslam.rbpf.pool_size` sized from
    the first scan's footprint (before anything compiles the step, so a wide scan costs no
    recompile)."""
    pool = rbpf.pool_size(config) if initial_pool is None else PoolSize(*(int(v) for v in initial_pool))
    while True:
        state = rbpf.init(key, jnp.asarray(prepared.first_ranges), prepared.sensor, params, config,
                          jnp.asarray(prepared.initial_pose), pool=pool)
        if not bool(state.maps.overflow):
            break
        pool = larger_pool(state.maps, config.grid)
    if initial_pool is None:
        sized = PoolSize(*np.maximum(pool, rbpf.pool_size(config, int(state.maps.peak_request))).tolist())
        if sized != pool:
            state = state._replace(maps=paged.grow(config.grid, state.maps, sized))
    return state


class Runs(NamedTuple):
    """How :func:`growing_chunks` steps its R runs: one run on one device, or a batch over a mesh."""

    chunk: Callable[..., tuple[Any, Any, bool, Callable[[], PoolUse]]]
    """``chunk(state, key_data (C, R, ...), inputs (C, R, ...), valid (C, R)) -> (state, info,
    overflow, use)``: the runs' chunk (a step where ``valid`` is False is a no-op); ``info`` the
    per-step diagnostics (C, L, ...) on the host of the runs :attr:`local` names; ``overflow``
    whether a valid step of some run (any process's) did not fit the pools; ``use()`` the
    :class:`PoolUse` that sizes grown pools (the largest over the runs; the same in every process)."""
    grow: Callable[[Any, PoolSize], Any]
    """``grow(state, pool) -> state``: every run's maps in pools of ``pool``'s sizes."""
    local: np.ndarray
    """(L,) the runs (of R) whose ``info`` this process gets, in the order of its axis 1."""


def grow_pools(runs: Runs, state, pool: PoolSize, use: PoolUse, spec: PagedGridSpec, growths: list, step: int,
               progress: bool) -> tuple[Any, PoolSize]:
    """The one growth policy: after pools of ``pool``'s sizes overflowed, every run's pools grown
    to :func:`larger_pool_for`'s sizes; the growth appended to ``growths`` (``step`` and the new
    sizes) and, with ``progress``, reported on stderr. Returns the state and the new sizes."""
    pool = larger_pool_for(pool, use, spec)
    growths.append({"step": step, **pool._asdict()})
    if progress:
        report_growth(pool, f"at step {step}; that step and the chunk's rest are taken again")
    return runs.grow(state, pool), pool


def growing_chunks(runs: Runs, pool: PoolSize, spec: PagedGridSpec, growths: list, *, first_step: int = 0,
                   progress: bool = False) -> ChunkFn:
    """The chunk function of :func:`jaxslam.driver.run_in_chunks` that steps the runs (the carry
    their state, in pools of ``pool``'s sizes at the start) and grows their pools as they need
    (each growth appended to ``growths``, and reported on stderr with ``progress``): the driver
    of :func:`jaxslam.slam.run` and :func:`jaxslam.slam.run_batch`.

    Its items are ``(key_data (S, R, ...), inputs (S, R, ...), valid (S, R))`` on the host
    (``valid`` False on a run's steps past its end), its outputs the infos (S, L, ...) of the
    runs :attr:`Runs.local` names; ``first_step`` is the step of the first item (a resumed run's
    steps done; it numbers the growths)."""
    chunks = itertools.count()

    def chunk_fn(state, xs_chunk, valid):
        nonlocal pool
        key_data, inputs, run_valid = xs_chunk
        start = first_step + next(chunks) * valid.shape[0]
        state, info, pool = _chunk_growing(runs, state, (key_data, inputs), run_valid & valid[:, None], pool, spec,
                                           growths, start, progress)
        return state, info

    return chunk_fn


def _chunk_growing(runs: Runs, state, xs, valid: np.ndarray, pool: PoolSize, spec: PagedGridSpec, growths: list,
                   start: int, progress: bool):
    """One chunk of the runs from step ``start``: where a run's step s did not fit the pools (its
    state is the one before s), its steps before s are kept, the pools grown, and its chunk taken
    again from s (a run that did not stall takes no-op steps), until no run stalls. Returns the
    state, the chunk's infos (C, L, ...) and the pools' sizes."""
    size = valid.shape[0]
    taken = np.zeros(len(runs.local), int)  # steps of the chunk each local run has kept
    kept = None
    while True:
        state, info, overflow, use = runs.chunk(state, *xs, valid)
        stalled = _first_stalls(np.asarray(info.pool_overflow) & valid[:, runs.local])
        kept = _keep_steps(kept, info, taken, stalled)
        if not overflow:
            return state, kept, pool
        at = (taken + stalled)[stalled < size]  # where this process's runs stalled (none: the chunk's start)
        state, pool = grow_pools(runs, state, pool, use(), spec, growths, start + (int(at.min()) if at.size else 0),
                                 progress)
        shift = np.full(valid.shape[1], size)
        shift[runs.local] = stalled
        xs, valid = jax.tree.map(lambda a: _shift_steps(a, shift), xs), _shift_valid(valid, shift)
        taken = np.minimum(taken + stalled, size)


def _first_stalls(stalled: np.ndarray) -> np.ndarray:
    """(L,) each run's first step of ``stalled`` (C, L), C where none."""
    return np.where(stalled.any(axis=0), np.argmax(stalled, axis=0), stalled.shape[0])


def _keep_steps(kept, info, taken: np.ndarray, stalled: np.ndarray):
    """``kept`` (the chunk's infos (C, L, ...) so far; None before the first pass) with each run's
    steps of ``info`` before its stall written from its ``taken``-th step on."""
    if kept is None:  # the first pass: nothing taken yet
        return jax.tree.map(np.array, info)
    size = kept.pool_overflow.shape[0]
    count = np.clip(np.minimum(stalled, size - taken), 0, None)
    rows, cols = np.nonzero(np.arange(size)[:, None] < count[None, :])

    def put(old, new):
        old[rows + taken[cols], cols] = np.asarray(new)[rows, cols]
        return old

    return jax.tree.map(put, kept, info)


def _shift_steps(a: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``a`` (C, R, ...) with run r's items from ``shift[r]`` on, padded by its last item."""
    size = a.shape[0]
    rows = np.minimum(np.arange(size)[:, None] + shift[None, :], size - 1)
    return a[rows, np.arange(a.shape[1])[None, :]]


def _shift_valid(valid: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``valid`` (C, R) with run r's from ``shift[r]`` on, False past the chunk's end."""
    return _shift_steps(valid, shift) & (np.arange(valid.shape[0])[:, None] + shift[None, :] < valid.shape[0])
