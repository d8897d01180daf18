"""The particle axis over devices, as islands: the island particle filter (Vergé, Dubarry, Del
Moral & Moulines 2015, "On parallel implementation of sequential Monte Carlo methods: the island
particle model", Statistics and Computing 25) of :mod:`jaxslam.rbpf` filters.

N particles are split into I islands of N / I. An island is one RBPF (:mod:`jaxslam.rbpf`) with
its own map pools (:class:`~jaxslam.maps.PagedMaps`: tiles and blocks shared by that
island's particles only, sized by :func:`jaxslam.rbpf.pool_size` of the island's config), its
own within-island weights and its own selective resampling. Above the islands sits a second
particle filter whose particles are the islands: island g's weight is multiplied every step by
its own estimate of the step's evidence (``SlamInfo.log_evidence``, the mean of its particles'
weighted increments), the island weights are normalised globally, and when their ESS falls
below ``island_threshold * I`` the islands are resampled as wholes (the island bootstrap),
with the configured resampler (:data:`jaxslam.resampling.RESAMPLERS`): a zero-weight island is
never drawn. The draw is arranged so that every drawn island keeps its place
(:func:`jaxslam.resampling.keep_in_place`): only the islands not drawn receive a copy of another
island's state, maps and pools included. The product of the islands' weights and their
particles' weights is a weighting of all N particles; the step's evidence is
logsumexp(island log-weights + island increments), and their sum over the steps
(``marginal_loglik``) is an unbiased estimate of the likelihood in exp, as the one-island
filter's.

Devices: the island axis lies on a 1-D mesh (``jax.sharding.Mesh`` over ``num_devices``
devices, axis :data:`AXIS`), and the whole filter (init and ``lax.scan``) runs inside one
``jax.shard_map``: each device holds I / D islands and steps them one after the other
(``lax.map``; ``batch_islands``: as one vmap, faster, but equal across device counts only to
rounding). A step's cross-device traffic is one all-gather of a few floats per island
(evidence, ESS, best particle) and, on an exchange, the states of the islands copied across devices: one
``ppermute`` of one island per (device shift, local slot) pair that some copy needs, under a
``lax.cond`` on the (replicated) island draw, so that a step without exchange moves no map.
One device is the same code, with one island per step key when I = 1
(:func:`filter` with ``num_islands=1`` is :func:`jaxslam.rbpf.filter` bit for bit).
:func:`filter` runs in pools of a fixed size; :func:`jaxslam.island_runs.run` runs the same
filter chunk by chunk on the package's driver, growing the pools as they fill.

Keys: the step's key (split from ``filter``'s key as :func:`jaxslam.rbpf.filter` does) gives
island g the key ``fold_in(key_t, g)`` (the step key itself when I = 1) and the island draw
``fold_in(key_t, I)``: derived from the island index, not the device, so that a run depends on
the island count but not on the device count.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import particle_filter, rbpf, resampling
from jaxslam.config import ConfigError, SlamConfig, SlamParams
from jaxslam.laser import SensorSpec
from jaxslam.maps import PoolSize
from jaxslam.proposals.base import StepInputs

AXIS = "islands"
"""Name of the mesh axis the islands lie on."""


class IslandState(NamedTuple):
    """I islands of N / I particles each."""

    islands: rbpf.SlamState
    """Every island's particle set, stacked on a leading island axis (I, ...): poses (I, N/I, 3),
    within-island log-weights (I, N/I), maps (each island's own pools), step counts (I,). Inside
    :func:`filter`'s ``shard_map`` a device holds its I / D islands."""
    log_weights: Float[Array, "I"]
    """The islands' normalised log-weights (logsumexp = 0), the same on every device."""


class IslandInfo(NamedTuple):
    """Diagnostics of one island step (stacked over the steps by :func:`filter`)."""

    islands: rbpf.SlamInfo
    """Every island's own step diagnostics (I, ...), before the islands' exchange (its
    ``ancestors`` index the island's own particles)."""
    log_evidence: Float[Array, ""]
    """The step's log-evidence: logsumexp(island log-weights + island increments); -inf when
    every island got weight zero; 0 for a step not taken."""
    island_log_weights: Float[Array, "I"]
    """The islands' normalised log-weights after the update, before their resampling."""
    island_ess: Float[Array, ""]
    """ESS of the island weights (1 .. I), after the update, before their resampling."""
    ess: Float[Array, ""]
    """ESS of all N particles' weights (island weight x within-island weight), after the update,
    before any resampling: 1 / sum_g W_g^2 / ESS_g."""
    exchanged: Bool[Array, ""]
    """Whether the islands were resampled (some island may still keep its own state)."""
    island_ancestors: Int[Array, "I"]
    """After the step, island g holds a copy of island ``island_ancestors[g]`` (g itself where it
    was drawn or nothing was resampled)."""
    best_island: Int[Array, ""]
    """The island of the particle with the largest overall weight."""
    best_particle: Int[Array, ""]
    """That particle's index among all N (island x N / I + index in ``proposed_poses``)."""
    best_pose: Float[Array, "3"]
    """That particle's proposed pose."""
    degenerate: Bool[Array, ""]
    """Every island got weight zero; the island weights were reset to uniform."""
    pool_overflow: Bool[Array, ""]
    """Some island's pools could not hold its tiles: no island took the step (the flag is
    sticky; :func:`filter` then reports ``marginal_loglik = -inf``, and
    :func:`jaxslam.island_runs.run` grows the pools and takes the step again)."""


def island_config(config: SlamConfig, num_islands: int) -> SlamConfig:
    """The config of one island: ``config`` with ``num_particles / num_islands`` particles
    (ConfigError unless ``num_islands`` divides it)."""
    if num_islands < 1 or config.num_particles % num_islands:
        raise ConfigError(f"num_islands={num_islands} must be a positive divisor of num_particles="
                          f"{config.num_particles} (each island holds num_particles / num_islands particles)")
    return dataclasses.replace(config, num_particles=config.num_particles // num_islands)


def check_devices(num_islands: int, num_devices: int) -> None:
    """Refuse (ConfigError) a device count that does not divide the islands or exceeds the
    devices JAX sees, before any work."""
    if num_devices < 1 or num_islands % num_devices:
        raise ConfigError(f"num_islands={num_islands} is not a multiple of num_devices={num_devices}: every device "
                          f"holds num_islands / num_devices islands")
    available = jax.device_count()
    if num_devices > available:
        raise ConfigError(f"num_devices={num_devices} is more than the {available} devices JAX sees (on CPU, set "
                          f"XLA_FLAGS=--xla_force_host_platform_device_count=... before importing jax)")


def init(key: PRNGKeyArray, first_ranges: Float[Array, "B"], sensor: SensorSpec, params: SlamParams,
         config: SlamConfig, num_islands: int, initial_pose: Float[Array, "3"] | None = None, *,
         pool: PoolSize | None = None) -> IslandState:
    """``num_islands`` islands (static) of ``config.num_particles / num_islands`` particles, each
    :func:`jaxslam.rbpf.init` (all at ``initial_pose`` sharing the first scan's map, in the
    island's own pools: ``pool``, default :func:`jaxslam.rbpf.pool_size` of the island's
    config), with equal island weights. Inside :func:`filter` every device builds its own
    islands (``num_islands`` is then the device's count)."""
    one = rbpf.init(key, first_ranges, sensor, params, island_config(config, num_islands), initial_pose, pool=pool)
    return replicate(one, num_islands)


def replicate(one: rbpf.SlamState, num_islands: int) -> IslandState:
    """``num_islands`` copies of one island's state ``one``, with equal island weights."""
    islands = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_islands,) + x.shape), one)
    return IslandState(islands, jnp.full((num_islands,), -math.log(num_islands), jnp.float32))


def device_mesh(num_devices: int) -> Mesh:
    """The 1-D mesh (axis :data:`AXIS`) of the first ``num_devices`` of ``jax.devices()``."""
    return Mesh(np.array(jax.devices()[:num_devices]), (AXIS,))


def mesh_specs() -> tuple[IslandState, IslandInfo]:
    """The ``shard_map`` specs of an :class:`IslandState` and of stacked :class:`IslandInfo`:
    the islands split over the mesh (the infos' second axis), everything else replicated."""
    replicated = PartitionSpec()
    return (IslandState(PartitionSpec(AXIS), replicated),
            IslandInfo(PartitionSpec(None, AXIS), *([replicated] * (len(IslandInfo._fields) - 1))))


def island_keys(key: PRNGKeyArray, island_index: Int[Array, "L"], num_islands: int
                ) -> tuple[PRNGKeyArray, PRNGKeyArray]:
    """``(keys of the islands island_index (L,), key of the island draw)`` of a step of key
    ``key``: ``fold_in(key, g)`` for island g and ``fold_in(key, num_islands)`` for the draw, the
    step key itself for a lone island (so that one island is :func:`jaxslam.rbpf.filter`)."""
    if num_islands == 1:
        return jnp.broadcast_to(key, island_index.shape), jax.random.fold_in(key, 1)
    return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, island_index), jax.random.fold_in(key, num_islands)


def step(key: PRNGKeyArray, state: IslandState, inputs: StepInputs, sensor: SensorSpec, params: SlamParams,
         config: SlamConfig, island_threshold: Float[Array, ""] | float = 0.5, axis_name: str | None = None,
         batch_islands: bool = False, valid: Bool[Array, ""] | bool = True) -> tuple[IslandState, IslandInfo]:
    """One island step: every island takes :func:`jaxslam.rbpf.step_with_score_terms` with its
    own key, the island weights take the islands' evidence and are normalised over all islands,
    and when their ESS < ``island_threshold`` x I the islands are resampled as wholes (see the
    module docstring).

    ``config`` is the whole filter's (``num_particles`` = N, all islands). Without
    ``axis_name``, ``state.islands`` holds all I islands (one device). Inside ``shard_map`` over
    the mesh axis ``axis_name``, it holds this device's I / D islands (``state.log_weights``
    stays all I): the step gathers the islands' few floats from every device and copies the
    islands an exchange needs across devices.

    ``batch_islands`` (static): step the device's islands as one ``vmap`` rather than one after
    the other (``lax.map``); faster where the islands are small, but the device count then
    changes the last bits of the evidence (benchmarks/bench_islands.py).

    The step is taken by all islands or by none, as :func:`jaxslam.rbpf.step` is by all
    particles or none: not when ``valid`` is False (a padding step), nor when some island's
    pools could not hold its tiles. A step not taken changes no island and no island weight,
    adds no evidence, and sets every island's (sticky) ``maps.overflow`` where some island's
    pools overflowed, so that no later step is taken either: grow the pools and take the steps
    again from it (:func:`jaxslam.island_runs.run` does).
    """
    num_islands = state.log_weights.shape[0]
    num_local = state.islands.log_weights.shape[0]
    num_devices = num_islands // num_local
    one = island_config(config, num_islands)
    device = jnp.int32(0) if axis_name is None else jax.lax.axis_index(axis_name).astype(jnp.int32)
    local_index = device * num_local + jnp.arange(num_local, dtype=jnp.int32)
    keys, key_draw = island_keys(key, local_index, num_islands)

    def island_step(k, s):
        return rbpf.step_with_score_terms(k, s, inputs, sensor, params, one, valid)

    # By default one island at a time (a loop): every island is then the same unbatched program
    # whatever the device's island count, so that the device count changes no bit, and one
    # island is rbpf.filter's program. A vmap fuses a batch of 1 and of 4 differently: the
    # evidence and proposed poses differed in the last bits between 1 and 4 devices.
    if num_local == 1:
        islands, infos, terms = jax.tree.map(lambda x: x[None], island_step(keys[0], jax.tree.map(
            lambda x: x[0], state.islands)))
    elif batch_islands:
        islands, infos, terms = jax.vmap(island_step)(keys, state.islands)
    else:
        islands, infos, terms = jax.lax.map(lambda args: island_step(*args), (keys, state.islands))

    summary = _summary(islands, infos, terms, axis_name)
    increments, ess_islands, best_log_weight = summary[:, 0], summary[:, 1], summary[:, 2]
    overflow = jnp.any(summary[:, 7] > 0)
    taken = jnp.asarray(valid, bool) & ~overflow
    # A step not taken moves no island weight (increments 0) and draws no island (threshold 0).
    increments = jnp.where(taken, increments, 0.0)
    island_threshold = jnp.where(taken, jnp.asarray(island_threshold, jnp.float32), 0.0)
    # Islands whose pools held the step took it; where another's did not, they go back (all or none).
    islands = jax.lax.cond(overflow, lambda: _stalled(state.islands, islands), lambda: islands)

    ancestors, new_log_weights, update = resample_islands(key_draw, state.log_weights, increments, island_threshold,
                                                          config.resampler)
    islands = _exchange(islands, ancestors, device, num_devices, axis_name)

    overall = update.log_weights + best_log_weight
    best_island = jnp.argmax(overall).astype(jnp.int32)
    info = IslandInfo(
        islands=infos,
        log_evidence=update.log_evidence,
        island_log_weights=update.log_weights,
        island_ess=update.ess,
        ess=jnp.exp(-jax.scipy.special.logsumexp(2.0 * update.log_weights - jnp.log(ess_islands))),
        exchanged=update.resampled,
        island_ancestors=ancestors,
        best_island=best_island,
        best_particle=best_island * one.num_particles + summary[best_island, 6].astype(jnp.int32),
        best_pose=summary[best_island, 3:6],
        degenerate=update.degenerate,
        pool_overflow=overflow,
    )
    return IslandState(islands, new_log_weights), info


def _summary(islands: rbpf.SlamState, infos: rbpf.SlamInfo, terms: particle_filter.ScoreTerms,
             axis_name: str | None) -> Float[Array, "I 8"]:
    """The islands' few floats after their steps, from every device: evidence, ESS, largest
    log-weight, that particle's pose and index, pools' overflow (columns 0, 1, 2, 3-5, 6, 7)."""
    best_local = jnp.argmax(terms.log_weights, axis=1)
    best_pose = jnp.take_along_axis(infos.proposed_poses, best_local[:, None, None], axis=1)[:, 0]
    summary = jnp.concatenate([infos.log_evidence[:, None], infos.ess[:, None],
                               jnp.max(terms.log_weights, axis=1)[:, None], best_pose,
                               best_local[:, None].astype(jnp.float32),
                               islands.maps.overflow[:, None].astype(jnp.float32)], axis=1)  # (L, 8)
    if axis_name is not None:
        summary = jax.lax.all_gather(summary, axis_name, tiled=True)  # (I, 8)
    return summary


def _stalled(before: rbpf.SlamState, stepped: rbpf.SlamState) -> rbpf.SlamState:
    """The islands ``before`` a step some island's pools could not hold, each with its pools'
    (sticky) overflow flag set and the largest requests seen by the step (``stepped``'s: they
    size the grown pools, :func:`jaxslam.growth.larger_pool_for`)."""
    maps = before.maps._replace(overflow=jnp.ones_like(before.maps.overflow), peak_request=stepped.maps.peak_request,
                                peak_block_request=stepped.maps.peak_block_request)
    return before._replace(maps=maps)


def resample_islands(key: PRNGKeyArray, log_weights: Float[Array, "I"], increments: Float[Array, "I"],
                     island_threshold: Float[Array, ""] | float, resampler: str
                     ) -> tuple[Int[Array, "I"], Float[Array, "I"], particle_filter.WeightUpdate]:
    """The islands' weight update and selective resampling (the island bootstrap):
    :func:`jaxslam.particle_filter.reweight_and_resample` of the islands' normalised
    ``log_weights`` by their log-evidence ``increments``, with the draw arranged so that every
    island drawn keeps its place (:func:`jaxslam.resampling.keep_in_place`).

    Returns ``(ancestors, new_log_weights, update)``: island g takes island ``ancestors[g]``'s
    state, the islands' log-weights after the step (uniform when resampled), and the update
    (evidence, ESS, normalised weights before the resampling; its own ``ancestors`` unarranged).
    """
    update = particle_filter.reweight_and_resample(key, jnp.zeros(log_weights.shape + (3,), jnp.float32),
                                                   log_weights, increments,
                                                   jnp.asarray(island_threshold, jnp.float32), resampler)
    ancestors, order = resampling.keep_in_place(update.ancestors)
    return ancestors, update.new_log_weights[order], update


def _exchange(islands: rbpf.SlamState, ancestors: Int[Array, "I"], device: Int[Array, ""], num_devices: int,
              axis_name: str | None) -> rbpf.SlamState:
    """This device's islands after the island draw ``ancestors`` (arranged in place: a source
    is never itself replaced, so the copies may be made in any order). A copy within the device
    is a gather; one from another device is a ``ppermute`` of one island per (shift, slot) pair
    that some copy needs, each under a ``lax.cond`` on the replicated draw (no traffic, and no
    copy, when nothing is exchanged)."""
    num_islands = ancestors.shape[0]
    num_local = num_islands // num_devices
    per_device = ancestors.reshape(num_devices, num_local)
    source_device = per_device // num_local  # (D, L)
    replaced = per_device != jnp.arange(num_islands, dtype=ancestors.dtype).reshape(num_devices, num_local)
    mine = per_device[device]
    from_here = replaced[device] & (source_device[device] == device)

    def copy_local(states):
        gathered = jax.tree.map(lambda x: x[mine % num_local], states)
        return jax.tree.map(lambda new, old: jnp.where(_expand(from_here, new), new, old), gathered, states)

    islands = jax.lax.cond(jnp.any(from_here), copy_local, lambda s: s, islands)
    for shift in range(1, num_devices):  # static: the mesh's size
        perm = [(d, (d + shift) % num_devices) for d in range(num_devices)]
        # Slot k of device r copies from device r - shift: that device sends it.
        wanted = replaced & (source_device == (jnp.arange(num_devices)[:, None] - shift) % num_devices)  # (D, L)
        receiver = (device + shift) % num_devices
        for slot in range(num_local):
            def transfer(states, slot=slot, perm=perm):
                payload = jax.tree.map(lambda x: x[per_device[receiver, slot] % num_local], states)
                received = jax.lax.ppermute(payload, axis_name, perm)
                take = wanted[device, slot]
                return jax.tree.map(lambda x, y: x.at[slot].set(jnp.where(take, y, x[slot])), states, received)

            islands = jax.lax.cond(jnp.any(wanted[:, slot]), transfer, lambda s: s, islands)
    return islands


def _expand(mask: Bool[Array, "L"], like: Array) -> Bool[Array, "..."]:
    return mask.reshape(mask.shape + (1,) * (like.ndim - 1))


FilterOutput = particle_filter.FilterOutput
"""What :func:`filter` returns: the final :class:`IslandState`, the (S - 1, ...) stacked
:class:`IslandInfo` and ``marginal_loglik``, the estimate of log p(z_2:S | z_1, u, params)."""


def filter(key: PRNGKeyArray, prepared: rbpf.PreparedLog, params: SlamParams, config: SlamConfig,
           num_islands: int, num_devices: int = 1, island_threshold: Float[Array, ""] | float = 0.5,
           pool: PoolSize | None = None, batch_islands: bool = False
           ) -> FilterOutput:  # noqa: A001 (the module's filter, as rbpf's)
    """The island filter over a whole log as one pure function: :func:`init`, then a
    ``lax.scan`` of :func:`step`, inside one ``shard_map`` over ``num_devices`` devices.

    Jittable (``config``, ``num_islands``, ``num_devices``, ``pool`` and ``batch_islands``
    static; ``key``, ``params`` and ``island_threshold`` traced). The settings are checked before any work
    (ConfigError: islands that do not divide the particles, devices that do not divide the
    islands or that JAX does not have). The per-step keys are split from ``key`` as
    :func:`jaxslam.rbpf.filter` does; with ``num_islands=1`` the result is its result bit for bit
    (the state's ``islands`` with a leading axis of 1). The result depends on the island count,
    not on the device count. The gradient (through ``params``) is the path-space score of both
    levels (:func:`jaxslam.resampling.resample_if_needed`); ``config.score_lag`` is not supported.

    Args:
      key: the run's key.
      prepared: :func:`jaxslam.rbpf.prepare`'s arrays (the same on every device).
      params: traced parameters; ``params.resample_threshold`` is each island's own.
      config: static settings; ``num_particles`` is all islands' N.
      num_islands: I, dividing N.
      num_devices: D, dividing I; the first D of ``jax.devices()``.
      island_threshold: resample the islands when their ESS < ``island_threshold`` x I.
      pool: static sizes of each island's pools (default :func:`jaxslam.rbpf.pool_size` of the
        island's config).
      batch_islands: vmap a device's islands instead of looping over them (:func:`step`): the
        result then depends on the device count in the last bits.
    """
    island_config(config, num_islands)
    check_devices(num_islands, num_devices)
    if config.score_lag is not None:
        raise ConfigError("islands.filter does not support score_lag (the fixed-lag score of the island filter is "
                          "not implemented); set score_lag=None")
    mesh = device_mesh(num_devices)
    num_local = num_islands // num_devices

    def on_device(key, prepared, params, island_threshold):
        key_init, key_steps = jax.random.split(key)
        state = init(key_init, prepared.first_ranges, prepared.sensor, params,
                     dataclasses.replace(config, num_particles=config.num_particles // num_devices), num_local,
                     prepared.initial_pose, pool=pool)
        state = state._replace(log_weights=jnp.full((num_islands,), -math.log(num_islands), jnp.float32))
        out = particle_filter.scan_filter(
            lambda k, s, inp: step(k, s, inp, prepared.sensor, params, config, island_threshold, AXIS,
                                   batch_islands),
            key_steps, state, prepared.inputs, lambda info: info.log_evidence, checkpoint=False)
        overflow = jax.lax.all_gather(out.state.islands.maps.overflow, AXIS, tiled=True)
        return out._replace(marginal_loglik=jnp.where(jnp.any(overflow), -jnp.inf, out.marginal_loglik))

    replicated = PartitionSpec()
    state_specs, info_specs = mesh_specs()
    out_specs = FilterOutput(state_specs, info_specs, replicated)
    # check_vma=False: the library's loops start from replicated constants while the islands vary
    # over the mesh; the replicated outputs are computed alike on every device from gathered floats.
    on_mesh = jax.shard_map(on_device, mesh=mesh, in_specs=(replicated,) * 4, out_specs=out_specs, check_vma=False)
    return on_mesh(key, prepared, params, jnp.asarray(island_threshold, jnp.float32))
