"""The island filter (:mod:`jaxslam.islands`) on the package's one driver of long runs: chunk by
chunk over a log, with the islands' map pools grown as the run needs them.

:func:`jaxslam.islands.filter` is the whole log as one pure function, in pools of a fixed size
(a full pool stops it: ``marginal_loglik = -inf``). :func:`run` steps the same filter with
:func:`jaxslam.growth.growing_chunks`, the policy :func:`jaxslam.slam.run` and
:func:`jaxslam.slam.run_batch` use: a chunk in which some island's pools could not hold a step
is taken again from that step after every island's pools grew (one recompile). Every island
has pools of the same size, so the island filter is one run of the driver, its state the
islands on their device mesh. The steps' keys are :func:`jaxslam.islands.filter`'s and the
pools' size changes no result, so a run that grew is bit for bit one that started large enough.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Float, PRNGKeyArray

from jaxslam import islands, particle_filter, rbpf
from jaxslam import maps as paged
from jaxslam.config import ConfigError, SlamConfig, SlamParams
from jaxslam.driver import run_in_chunks
from jaxslam.growth import PoolUse, Runs, growing_chunks, initial_state, pool_use
from jaxslam.islands import AXIS, IslandInfo, IslandState
from jaxslam.laser import SensorSpec
from jaxslam.maps import PoolSize


class IslandRun(NamedTuple):
    """What :func:`run` returns."""

    state: IslandState
    """The islands after the last step (on the device mesh)."""
    info: IslandInfo
    """Every step's diagnostics, stacked (S - 1, ...) (NumPy), as :func:`jaxslam.islands.filter`'s."""
    marginal_loglik: float
    """The sum of the steps' log-evidence: the estimate of log p(z_2:S | z_1, u, params)."""
    growths: list
    """Each growth of the islands' pools: the step it happened at and the new sizes."""


def run(key: PRNGKeyArray, prepared: rbpf.PreparedLog, params: SlamParams, config: SlamConfig, num_islands: int,
        num_devices: int = 1, island_threshold: Float[Array, ""] | float = 0.5, *, chunk_size: int = 32,
        initial_pool: PoolSize | None = None, batch_islands: bool = False, progress: bool = False) -> IslandRun:
    """The island filter over ``prepared``'s steps, ``chunk_size`` steps per compiled call, with
    the islands' pools grown as they fill (see the module docstring).

    The same key gives :func:`jaxslam.islands.filter`'s particles (its step keys and its
    initial state), whatever the pools' sizes. The settings are checked before any work
    (ConfigError), as ``filter`` checks them.

    Args:
      key: the run's key.
      prepared: :func:`jaxslam.rbpf.prepare`'s arrays.
      params: traced parameters; ``params.resample_threshold`` is each island's own.
      config: static settings; ``num_particles`` is all islands' N.
      num_islands: I, dividing N.
      num_devices: D, dividing I; the first D of ``jax.devices()``.
      island_threshold: resample the islands when their ESS < ``island_threshold`` x I.
      chunk_size: steps per compiled call (the last chunk padded with steps not taken).
      initial_pool: each island's pools at the start (default :func:`jaxslam.rbpf.pool_size`
        sized from the first scan's footprint, :func:`jaxslam.growth.initial_state`).
      batch_islands: vmap a device's islands (:func:`jaxslam.islands.step`).
      progress: a tqdm bar, and a line on stderr for each growth.
    """
    one = islands.island_config(config, num_islands)
    islands.check_devices(num_islands, num_devices)
    if chunk_size < 1:
        raise ConfigError(f"chunk_size must be >= 1, got {chunk_size}")
    num_steps = int(np.shape(prepared.inputs.motion)[0])
    mesh = islands.device_mesh(num_devices)
    key_init, key_steps = jax.random.split(key)
    # islands.filter builds every island from the same key: one island's start, replicated.
    start = initial_state(key_init, prepared, params, one, initial_pool)
    state = _on_mesh(islands.replicate(start, num_islands), mesh)
    step_keys = jax.random.split(key_steps, max(num_steps, 1))
    with_run_axis = lambda a: np.asarray(a)[:num_steps, None]  # noqa: E731 (the driver's (S, R = 1, ...) items)
    xs = (with_run_axis(jax.random.key_data(step_keys)), jax.tree.map(with_run_axis, prepared.inputs),
          np.ones((num_steps, 1), bool))
    runs = _island_runs(mesh, prepared.sensor, params, config, num_devices, jnp.float32(island_threshold),
                        batch_islands, jax.random.key_impl(key))
    growths: list = []
    chunk_fn = growing_chunks(runs, start.maps.pool_size, config.grid, growths, progress=progress)
    chunked = run_in_chunks(chunk_fn, xs, num_steps, chunk_size, state, progress=progress, unit="scan",
                            desc=f"islands {num_islands} x {one.num_particles}")
    info = jax.tree.map(lambda a: a[:, 0], chunked.outputs)
    return IslandRun(chunked.carry, info, float(np.sum(info.log_evidence, dtype=np.float32)), growths)


def _on_mesh(state: IslandState, mesh: Mesh) -> IslandState:
    """``state`` placed as :func:`_chunk_steps` holds it: the islands split over the mesh, their
    weights on every device."""
    specs = islands.mesh_specs()[0]
    return IslandState(jax.device_put(state.islands, NamedSharding(mesh, specs.islands)),
                       jax.device_put(state.log_weights, NamedSharding(mesh, specs.log_weights)))


def _island_runs(mesh: Mesh, sensor: SensorSpec, params: SlamParams, config: SlamConfig, num_devices: int,
                 island_threshold, batch_islands: bool, impl) -> Runs:
    """:func:`run`'s :class:`~jaxslam.growth.Runs`: the island filter as the driver's one run."""

    def chunk(state, key_data, inputs, valid):
        keys = jax.random.wrap_key_data(key_data[:, 0], impl=impl)
        state, info = _run_chunk(state, keys, jax.tree.map(lambda a: a[:, 0], inputs), valid[:, 0], sensor, params,
                                 island_threshold, config=config, num_devices=num_devices,
                                 batch_islands=batch_islands)
        info = jax.tree.map(lambda a: np.asarray(a)[:, None], info)
        return state, info, bool(np.any(info.pool_overflow & valid)), lambda: _largest_use(state)

    def grow(state, pool):
        grown = jax.vmap(lambda maps: paged.grow(config.grid, maps, pool))(state.islands.maps)
        return _on_mesh(state._replace(islands=state.islands._replace(maps=grown)), mesh)

    return Runs(chunk, grow, np.zeros(1, int))


def _largest_use(state: IslandState) -> PoolUse:
    """The :class:`~jaxslam.growth.PoolUse` that sizes every island's grown pools: the largest
    over the islands."""
    return PoolUse(*(int(np.max(np.asarray(v))) for v in jax.vmap(pool_use)(state.islands.maps)))


def _chunk_steps(state: IslandState, keys, inputs, valid, sensor, params, island_threshold, config: SlamConfig,
                 num_devices: int, batch_islands: bool) -> tuple[IslandState, IslandInfo]:
    """:func:`jaxslam.islands.step` over one chunk inside the islands' ``shard_map`` (as
    :func:`jaxslam.islands.filter` runs it); ``valid`` False on the padding steps."""
    def on_device(state, keys, inputs, valid, sensor, params, island_threshold):
        return particle_filter.scan_steps(
            lambda key, s, xs: islands.step(key, s, xs[0], sensor, params, config, island_threshold, AXIS,
                                            batch_islands, valid=xs[1]), state, keys, (inputs, valid))

    state_specs, info_specs = islands.mesh_specs()
    # check_vma=False as in islands.filter: the replicated outputs are computed alike on every device.
    on_mesh = jax.shard_map(on_device, mesh=islands.device_mesh(num_devices),
                            in_specs=(state_specs,) + (PartitionSpec(),) * 6, out_specs=(state_specs, info_specs),
                            check_vma=False)
    return on_mesh(state, keys, inputs, valid, sensor, params, island_threshold)


_run_chunk = jax.jit(_chunk_steps, static_argnames=("config", "num_devices", "batch_islands"),
                     donate_argnames=("state",))
"""One chunk of the island filter, compiled (the state donated)."""
