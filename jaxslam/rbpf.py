"""Grid-based Rao-Blackwellized particle filter SLAM: the filter itself, pure and jittable.

Each of N particles carries a pose and its own occupancy grid map. A step draws every
particle's next pose from the configured proposal (:data:`jaxslam.proposals.PROPOSALS`; all
see the map m_{t-1}), updates its weight, inserts the scan into its map at the new pose, and
resamples when the ESS falls below ``resample_threshold * N``. The maps are paged
(:mod:`jaxslam.maps`): tiles in one pool and blocks of page table in another, shared by
all particles, so resampling copies small directories, and an insertion copies only the shared
blocks and tiles it writes.

``init``, ``step`` and ``filter`` are pure (``config`` static); ``prepare`` is the host side
that turns a :class:`~jaxslam.laserlog.LaserLog` into the arrays ``filter`` takes, in the
filter's local frame. Driving a long log from the host (chunks, a progress bar, growing the
map pools, checkpoints) is :func:`jaxslam.slam.run`. This module imports nothing from
:mod:`jaxslam.io` or :mod:`jaxslam.outputs` (tests/test_layout.py checks).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import maps as paged
from jaxslam import motion, occupancy, particle_filter
from jaxslam.config import ConfigError, RunSettings, SlamConfig, SlamParams
from jaxslam.grid import in_bounds, world_to_cell
from jaxslam.laser import SensorSpec, subsample_beams
from jaxslam.laserlog import LaserLog, UpdateSelection, local_frame_offset, local_log, select_updates
from jaxslam.likelihood_field import see_through_log_likelihood
from jaxslam.maps import PagedMaps, PoolSize
from jaxslam.proposals import PROPOSALS
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.sensor_model import sensor_model
from jaxslam.slip_search import searches_window, with_slip_search, without_slip_search


class SlamState(NamedTuple):
    """The particle set."""

    poses: Float[Array, "N 3"]
    """Pose of each particle at the last processed scan."""
    log_weights: Float[Array, "N"]
    """Normalised log-weights (logsumexp = 0)."""
    maps: PagedMaps
    """Every particle's map: directories (N, DY, DX) of shared blocks of page table into one pool of tiles."""
    step: Int[Array, ""]
    """Number of steps taken since ``init``."""


class SlamInfo(NamedTuple):
    """Diagnostics of one step (stacked over steps by ``run``)."""

    ess: Float[Array, ""]
    """Effective sample size after the weight update, before resampling."""
    resampled: Bool[Array, ""]
    """Whether the particles were resampled."""
    best_particle: Int[Array, ""]
    """Index (in ``proposed_poses``) of the particle with the largest weight."""
    mean_pose: Float[Array, "3"]
    """Weighted mean of the proposed poses (circular mean in theta)."""
    pose_covariance: Float[Array, "3 3"]
    """Weighted covariance of the proposed poses."""
    log_evidence: Float[Array, ""]
    """log p(z_t | z_{1:t-1}, u_{1:t}) as estimated by the filter (the step's increment of the
    log-likelihood, with the sensor model normalised as a density: its ``log_normalizer_fn``;
    -inf when ``degenerate``; 0 for a step not taken)."""
    degenerate: Bool[Array, ""]
    """Every particle got weight zero (-inf); the weights were reset to uniform."""
    proposed_poses: Float[Array, "N 3"]
    """Every particle's new pose, before resampling."""
    log_weights: Float[Array, "N"]
    """The proposed particles' log-weights after this step's update, before resampling,
    normalised (logsumexp 0): which histories the filter favoured at this step."""
    ancestors: Int[Array, "N"]
    """After the step, particle i descends from proposed particle ``ancestors[i]``."""
    num_fallbacks: Int[Array, ""]
    """Particles whose proposal fell back (SMP: failed match; LP: no weight)."""
    num_slipped: Int[Array, ""]
    """Particles whose new pose came from the odometry's slip component (:func:`jaxslam.slip_search.slip_mixture`;
    0 at a step where the slip search did not run)."""
    outside_samples: Int[Array, ""]
    """Beam samples (all particles) that fell outside the virtual grid and were dropped."""
    poses_outside: Int[Array, ""]
    """Particles whose pose lies outside the virtual grid."""
    tiles_in_use: Int[Array, ""]
    """Pool tiles some particle's map references after the step."""
    pool_overflow: Bool[Array, ""]
    """The maps' pools could not hold this step's new tiles or blocks, or those of an earlier
    step (the flag is sticky: ``state.maps.overflow``): the step was not taken (see :func:`step`).
    :func:`jaxslam.slam.run` grows the pools and takes it again; :func:`filter` reports
    ``marginal_loglik = -inf``."""


TILES_PER_PARTICLE = 24
"""The least per-particle allowance of :func:`pool_size`: an insertion's request on Intel (64-cell
tiles, 15 m beams), and all of it where a log's first scan is not known."""


def pool_size(config: SlamConfig, first_scan_tiles: int | None = None) -> PoolSize:
    """The maps' pools a run starts with (see :class:`~jaxslam.maps.PagedMaps`). An insertion
    copies or creates up to about 20 tiles per particle on Intel (64-cell tiles, 15 m beams; more
    after a resampling, fewer when the particles own their tiles) and up to 4 blocks. The first
    step asks for the most: every tile the first scan touched is shared, so every particle copies
    all of them. ``first_scan_tiles`` (the tiles the first scan touched, ``maps.peak_request``
    after :func:`init`; None: unknown) raises the allowance per particle to that footprint
    (rounded up to a multiple of 8 tiles) where it is larger: a 360-degree scan in open space
    touches about twice Intel's (first scans: FR-clinic 43 tiles, ACES 26, MIT CSAIL 16, Intel 11;
    the first 400 scans' largest request per particle at N = 8: 42.6, 18.3, 16.3 and 13.6), and
    sizing from Intel's alone made FR-clinic's first step outgrow the pool and recompile. The
    tile pool starts with room for three such requests: what the particles hold (on Intel's first
    3,000 scans 1.9 to 2.1 requests' worth at the end, at N = 30 to 1,000) and the next request
    (there at most 0.74 of one), at most :func:`~jaxslam.maps.max_pool_tiles` (a pool beyond
    2**31 cells, from about N = 7,300 on 64-cell tiles, is indexed by (slot, cell) pairs). It is
    the largest allocation per particle (0.9 MB at 64-cell tiles), so it starts no larger:
    :func:`jaxslam.slam.run` grows the pools when a step needs more (one recompile each time,
    reported; while it grows both the old and the new pools are held, so starting smaller and
    growing costs more peak memory than starting large enough:
    docs/design.md, "Per-particle stages run in blocks")."""
    spec = config.grid
    k = spec.window_tiles(config.max_insert_range, config.field_radius)
    kb = spec.window_blocks(k)
    n = config.num_particles
    most = paged.max_pool_tiles(spec)  # int32 slots: memory runs out long before
    # Rounded up to a multiple of 8: logs of one laser share a compiled step unless their first
    # footprints differ by more (a pool's size is a static shape).
    per_particle = (TILES_PER_PARTICLE if first_scan_tiles is None
                    else max(TILES_PER_PARTICLE, -(-int(first_scan_tiles) // 8) * 8))
    max_new_tiles = min(n * min(k * k, per_particle) + k * k, most)
    max_new_blocks = n * kb * kb + kb * kb
    return PoolSize(min(3 * max_new_tiles + 256, most), max_new_tiles, 4 * max_new_blocks + 64, max_new_blocks)


@jax.jit(static_argnames=("config", "pool"))
def init(
    key: PRNGKeyArray,
    first_ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: SlamParams,
    config: SlamConfig,
    initial_pose: Float[Array, "3"] | None = None,
    *,
    pool: PoolSize | None = None,
) -> SlamState:
    """All particles at ``initial_pose`` (default the origin) sharing one map, the first scan's.

    ``key`` is unused (the start is deterministic) but kept first for a uniform API.
    ``initial_pose`` must be given inside ``jax.jit`` callers that trace it; None means the origin.
    ``pool`` (static) sizes the maps' pools; None: :func:`pool_size`.
    """
    spec = config.grid
    n = config.num_particles
    pool = pool_size(config) if pool is None else PoolSize(*pool)
    pose = jnp.zeros(3, jnp.float32) if initial_pose is None else jnp.asarray(initial_pose, jnp.float32)
    # The insertion is not differentiable (cells are chosen by rounding the pose): no gradient
    # enters it, so none leaves it either (its tangents would only be NaN-prone noise).
    one, _ = paged.insert_scans(spec, paged.empty(spec, 1, *pool), jax.lax.stop_gradient(pose[None]),
                                    jnp.asarray(first_ranges, jnp.float32), sensor,
                                    jax.lax.stop_gradient(params.insertion), config.max_insert_range,
                                    config.field_radius)
    return SlamState(
        poses=jnp.broadcast_to(pose, (n, 3)),
        log_weights=jnp.full((n,), -math.log(n), jnp.float32),
        maps=paged.resample(one, jnp.zeros((n,), jnp.int32)),
        step=jnp.int32(0),
    )


def first_scan_tiles(prepared: PreparedLog, params: SlamParams, config: SlamConfig) -> int:
    """The tiles a log's first scan touches (``first_scan_tiles`` of :func:`pool_size`: every
    particle copies them at the first step), measured before a run: :func:`init`'s insertion of
    the first scan into one particle's map, whose ``peak_request`` it is. It compiles that
    insertion for one particle (a few seconds), so callers ask for it only where the pools'
    size decides something (:func:`jaxslam.resources.estimate_run_bytes` near the machine's
    memory)."""
    one = dataclasses.replace(config, num_particles=1)
    state = init(jax.random.key(0), jnp.asarray(prepared.first_ranges), prepared.sensor, params, one,
                 jnp.asarray(prepared.initial_pose))
    return int(state.maps.peak_request)


def step(
    key: PRNGKeyArray,
    state: SlamState,
    inputs: StepInputs,
    sensor: SensorSpec,
    params: SlamParams,
    config: SlamConfig,
    valid: Bool[Array, ""] | bool = True,
) -> tuple[SlamState, SlamInfo]:
    """One RBPF update (see :func:`step_with_score_terms`)."""
    new_state, info, _ = step_with_score_terms(key, state, inputs, sensor, params, config, valid)
    return new_state, info


def step_with_score_terms(
    key: PRNGKeyArray,
    state: SlamState,
    inputs: StepInputs,
    sensor: SensorSpec,
    params: SlamParams,
    config: SlamConfig,
    valid: Bool[Array, ""] | bool = True,
) -> tuple[SlamState, SlamInfo, particle_filter.ScoreTerms]:
    """:func:`step`, with the step's share of the score (:func:`particle_filter.fixed_lag_score`;
    a step not taken has none).

    One RBPF update with scan ``inputs.ranges`` (all beams) after motion ``inputs.motion``: every
    particle proposes its pose (:func:`propose`; with the slip search, :func:`jaxslam.slip_search.with_slip_search`,
    where :func:`jaxslam.slip_search.searches_window`), the weights are updated and the particles resampled
    (:func:`weigh_and_resample`), and the survivors insert the scan into their maps
    (:func:`update_maps`).

    The step is taken only when ``valid`` (False: a padding step past the end of a log) and the
    maps' pools hold its new tiles. A step not taken changes nothing (poses, weights, maps, step
    count) and adds no evidence (``info.log_evidence`` 0); ``state.maps.overflow`` and
    ``info.pool_overflow`` say when the pools were too small, and stay set, so that every later
    step is not taken either: grow the pools (:func:`jaxslam.maps.grow`) and take the
    steps again from the first one not taken (:func:`jaxslam.slam.run` does). The gate is
    :func:`_gate_inputs` before the step and :func:`_gate_outputs` after it."""
    active, inputs, params = _gate_inputs(valid, state, inputs, params)
    key_prop, key_res = jax.random.split(key)
    lik_inputs, lik_sensor = likelihood_inputs(inputs, sensor, config)
    propose_fn = with_slip_search(propose) if searches_window(config) else without_slip_search(propose)
    out, num_slipped = propose_fn(key_prop, state, lik_inputs, lik_sensor, params, config)
    update = weigh_and_resample(key_res, state, out, params, config)
    mapped = update_maps(state.maps, out.pose, update.ancestors, inputs.ranges, sensor, params, config, active)
    info = _info(out, num_slipped, update, mapped, lik_inputs, lik_sensor, params, config)
    new_state = SlamState(out.pose[mapped.ancestors], update.new_log_weights, mapped.maps, state.step + 1)
    terms = update.score_terms._replace(ancestors=mapped.ancestors)
    return _gate_outputs(mapped.taken, state, new_state, info, terms)


# ---------------------------------------------------------------------------------------------
# The step's parts, in the order it takes them.


def _gate_inputs(valid: Bool[Array, ""] | bool, state: SlamState, inputs: StepInputs, params: SlamParams
                 ) -> tuple[Bool[Array, ""], StepInputs, SlamParams]:
    """The gate before a step: ``(active, inputs, params)``. The step is active when ``valid`` and
    the pools have not overflowed (``state.maps.overflow``). An inactive step sees a scan with no
    usable beam (:func:`_noop_inputs`: nothing enters the maps, every weight increment is 0) and
    may not resample (``resample_threshold`` 0); its pose draws are discarded
    (:func:`_gate_outputs`)."""
    active = jnp.asarray(valid, bool) & ~state.maps.overflow
    inputs = jax.tree.map(lambda a, b: jnp.where(active, a, b), inputs, _noop_inputs(inputs))
    params = params._replace(resample_threshold=jnp.where(active, params.resample_threshold, 0.0))
    return active, inputs, params


def likelihood_inputs(inputs: StepInputs, sensor: SensorSpec, config: SlamConfig) -> tuple[StepInputs, SensorSpec]:
    """The scans (this step's and the future ones) and the laser as the likelihoods see them: every
    ``config.beam_stride``-th beam (:func:`jaxslam.laser.subsample_beams`; the insertion takes
    all beams)."""
    lik_sensor, lik_ranges = subsample_beams(sensor, inputs.ranges, config.beam_stride)
    _, lik_future = subsample_beams(sensor, inputs.future_ranges, config.beam_stride)
    return inputs._replace(ranges=lik_ranges, future_ranges=lik_future), lik_sensor


def propose(key: PRNGKeyArray, state: SlamState, inputs: StepInputs, sensor: SensorSpec, params: SlamParams,
            config: SlamConfig, step_motion: motion.MotionParams | None = None) -> ProposalOutput:
    """Every particle's new pose and log-weight increment, (N,)-batched: the configured proposal
    (``PROPOSALS[config.proposal].propose_fn``) in each particle's map, with the particle's key
    of ``split(key, N)``, and with ``config.free_space_samples`` the free-space evidence at the
    drawn pose added to the increment. ``inputs`` and ``sensor`` as the likelihoods see them
    (:func:`likelihood_inputs`); ``step_motion``: the motion model for this step (None:
    ``params.motion``; the slip search's :func:`jaxslam.slip_search.slip_motion`)."""
    propose_fn = PROPOSALS[config.proposal].propose_fn
    field = paged.fields(state.maps)
    if config.free_space_samples:  # how far each beam clears: the same at every particle's pose
        free_lengths = occupancy.free_lengths(inputs.ranges, sensor, params.insertion, config.max_insert_range)

    def propose_one(particle):
        key, pose, directory = particle
        own = field._replace(directory=directory)
        out = propose_fn(key, pose, own, inputs, sensor, params, config, step_motion)
        if config.free_space_samples:
            # The free-space evidence weighs the drawn pose, not the draw: every proposal's target
            # gains the factor, and the increment (an importance weight) is multiplied by it.
            out = out._replace(log_weight_increment=out.log_weight_increment + see_through_log_likelihood(
                config.grid, own, out.pose, free_lengths, sensor, params.likelihood, config.free_space_samples))
        return out

    # No gradient reaches the previous poses: the maps they built do not move with them (the
    # insertion is not differentiable), and a pose moved against a fixed map is a biased and
    # very noisy motion gradient (motion.sample_with_score).
    # In blocks of config.particle_block particles: the window posterior's candidates times beams
    # would otherwise be the step's largest intermediate, N times over.
    return particle_filter.map_in_blocks(
        propose_one,
        (jax.random.split(key, config.num_particles), jax.lax.stop_gradient(state.poses), field.directory),
        config.particle_block)


def weigh_and_resample(key: PRNGKeyArray, state: SlamState, out: ProposalOutput, params: SlamParams,
                       config: SlamConfig) -> particle_filter.WeightUpdate:
    """The weights times the proposals' increments, normalised, and the particles resampled when
    the ESS falls below ``params.resample_threshold`` * N
    (:func:`jaxslam.particle_filter.reweight_and_resample`)."""
    return particle_filter.reweight_and_resample(key, out.pose, state.log_weights, out.log_weight_increment,
                                                 params.resample_threshold, config.resampler)


class MapUpdate(NamedTuple):
    """What :func:`update_maps` returns."""

    maps: PagedMaps
    """The maps after the step: the survivors' with the scan, resampled by ``ancestors``."""
    ancestors: Int[Array, "N"]
    """The resampling's ancestors where the step is taken, else the identity."""
    taken: Bool[Array, ""]
    """Whether the step is taken: active, and its insertion fitted in the pools."""
    outside: Int[Array, "N"]
    """Beam samples per particle that fell outside the virtual grid."""


def update_maps(maps: PagedMaps, poses: Float[Array, "N 3"], ancestors: Int[Array, "N"], ranges: Float[Array, "B"],
                sensor: SensorSpec, params: SlamParams, config: SlamConfig, active: Bool[Array, ""]) -> MapUpdate:
    """The scan (all beams) inserted into the maps of the particles the resampling keeps, at their
    new ``poses`` (the others' maps are dropped next), then the maps resampled. An insertion that
    did not fit in the pools writes nothing and the step is not taken: the maps keep their
    particles, and ``overflow`` stays set (it is sticky)."""
    n = config.num_particles
    survivors = jnp.zeros((n,), bool).at[ancestors].set(True)
    inserted, outside = paged.insert_scans(config.grid, maps, jax.lax.stop_gradient(poses), ranges, sensor,
                                           jax.lax.stop_gradient(params.insertion), config.max_insert_range,
                                           config.field_radius, survivors,
                                           config.particle_block)  # not differentiable: see init
    taken = active & ~inserted.overflow
    ancestors = jnp.where(taken, ancestors, jnp.arange(n, dtype=ancestors.dtype))
    resampled = paged.resample(inserted, ancestors)
    return MapUpdate(resampled._replace(overflow=maps.overflow | resampled.overflow), ancestors, taken, outside)


def _info(out: ProposalOutput, num_slipped: Int[Array, ""], update: particle_filter.WeightUpdate, mapped: MapUpdate,
          lik_inputs: StepInputs, lik_sensor: SensorSpec, params: SlamParams, config: SlamConfig) -> SlamInfo:
    """The step's :class:`SlamInfo`, as if it were taken (:func:`_gate_outputs` corrects a step
    not taken)."""
    grid = config.grid.grid
    return SlamInfo(
        ess=update.ess,
        resampled=update.resampled,
        best_particle=jnp.argmax(update.log_weights).astype(jnp.int32),
        mean_pose=update.mean_pose,
        pose_covariance=update.pose_covariance,
        # The sensor model's normalising constant, the same for every particle, so it is left
        # out of the weights: with it the log-evidence is that of a density in likelihood.sigma.
        log_evidence=update.log_evidence + sensor_model(config).log_normalizer_fn(
            lik_inputs.ranges, lik_sensor, params.likelihood, config.resolution),
        degenerate=update.degenerate,
        proposed_poses=out.pose,
        log_weights=update.log_weights,
        ancestors=mapped.ancestors,
        num_fallbacks=jnp.sum(out.fallback).astype(jnp.int32),
        num_slipped=num_slipped,
        outside_samples=jnp.sum(mapped.outside).astype(jnp.int32),
        poses_outside=jnp.sum(~in_bounds(grid, world_to_cell(grid, out.pose[:, :2]))).astype(jnp.int32),
        tiles_in_use=paged.tiles_in_use(mapped.maps).astype(jnp.int32),
        pool_overflow=mapped.maps.overflow,
    )


def _gate_outputs(taken: Bool[Array, ""], state: SlamState, new_state: SlamState, info: SlamInfo,
                  terms: particle_filter.ScoreTerms
                  ) -> tuple[SlamState, SlamInfo, particle_filter.ScoreTerms]:
    """The gate after a step: a step not ``taken`` keeps ``state``'s poses, weights and step count,
    reports no evidence (0) and no share of the score. Its maps and ancestors are already the
    previous ones (:func:`update_maps`)."""
    def keep(a, b):
        return jnp.where(taken, a, b)

    info = info._replace(log_evidence=keep(info.log_evidence, 0.0),
                         log_weights=keep(info.log_weights, state.log_weights))
    new_state = SlamState(keep(new_state.poses, state.poses), keep(new_state.log_weights, state.log_weights),
                          new_state.maps, keep(new_state.step, state.step))
    terms = terms._replace(log_weights=keep(terms.log_weights, state.log_weights),
                           increments=keep(terms.increments, 0.0))
    return new_state, info, terms


def _noop_inputs(inputs: StepInputs) -> StepInputs:
    """Inputs of a step not taken: no motion and only invalid (below range_min) beams."""
    invalid = jnp.full_like(inputs.ranges, -1.0)
    return StepInputs(
        motion=jnp.zeros_like(inputs.motion),
        ranges=invalid,
        future_motions=jnp.zeros_like(inputs.future_motions),
        future_ranges=jnp.full_like(inputs.future_ranges, -1.0),
        future_valid=jnp.zeros_like(inputs.future_valid),
    )


def build_inputs(log: LaserLog, selection: UpdateSelection, lookahead_steps: int) -> StepInputs:
    """Stacked ``StepInputs`` (NumPy) for the S - 1 steps after the first processed scan.

    Step s (processed scan s = 1 .. S-1) carries scans s+1 .. s+K as its future; past the
    end of the log those entries are marked invalid (the horizon shrinks).
    """
    idx = selection.indices
    s = np.arange(1, idx.size)
    k = np.arange(1, lookahead_steps + 1)
    future = s[:, None] + k[None, :]  # (S-1, K)
    valid = future < idx.size
    future_c = np.minimum(future, idx.size - 1)
    return StepInputs(
        motion=selection.motions[s].astype(np.float32),
        ranges=log.ranges[idx[s]].astype(np.float32),
        future_motions=np.where(valid[..., None], selection.motions[future_c], 0.0).astype(np.float32),
        future_ranges=log.ranges[idx[future_c]].astype(np.float32).reshape(s.size, lookahead_steps, log.num_beams),
        future_valid=valid,
    )


class PreparedLog(NamedTuple):
    """A log as :func:`filter` consumes it: arrays only, in the filter's local frame (built by
    :func:`prepare`). Logs with the same number of processed scans and beams can be stacked
    (``jax.tree.map(jnp.stack, ...)``) and vmapped over."""

    first_ranges: Float[Array, "B"]
    """The first processed scan (m): the map every particle starts with."""
    initial_pose: Float[Array, "3"]
    """The robot's pose at the first processed scan (local frame; m, m, rad)."""
    inputs: StepInputs
    """The stacked (S - 1, ...) inputs of the steps after it (:func:`build_inputs`)."""
    sensor: SensorSpec
    """The laser."""


def check_extent(log: LaserLog, config: SlamConfig) -> None:
    """Refuse (``ConfigError``) a log whose odometry leaves the virtual grid, before any work:
    the message names the setting to change (``map_extent``). Beams that reach past the grid's
    edge, or a path that drifts off it later, are counted (``SlamInfo.outside_samples``,
    ``poses_outside``) and reported with the same advice."""
    reach = float(np.abs(np.asarray(log.odometry[:, :2], np.float64) - local_frame_offset(log)).max(initial=0.0))
    half = config.grid.num_tiles[0] * config.grid.tile_size * config.resolution / 2.0
    if reach >= half:
        need = 2.0 * (reach + config.max_insert_range)
        raise ConfigError(f"the log's odometry reaches {reach:.1f} m from its start, beyond the map: the virtual grid "
                          f"spans +-{half:.1f} m (map_extent={config.map_extent:g} m); set --set "
                          f"map_extent={math.ceil(need / 64) * 64} or more (memory grows with the area mapped, the "
                          f"directories with the extent)")


def check_config_for_log(log: LaserLog, config: SlamConfig) -> None:
    """Refuse (``ConfigError``) settings that are in their own range but wrong for this log, before
    any work: a ``beam_stride`` longer than the scan (the likelihoods would use its first beam
    alone), a ``max_insert_range`` at or below the laser's ``range_min`` (no beam ever reaches
    the map), or odometry that leaves the virtual grid (:func:`check_extent`)."""
    beams = int(log.num_beams)
    if config.beam_stride > beams:
        raise ConfigError(f"beam_stride={config.beam_stride} is more than the log's {beams} beams per scan (the "
                          f"likelihoods would use one beam); set --set beam_stride=... to at most {beams}")
    range_min = float(np.asarray(log.sensor.range_min))
    if config.max_insert_range <= range_min:
        raise ConfigError(f"max_insert_range={config.max_insert_range:g} m is not above the laser's range_min="
                          f"{range_min:g} m: no beam would reach the map; set --set max_insert_range=... above it")
    check_extent(log, config)


# ---------------------------------------------------------------------------------------------
# A whole log as one pure function.


FilterOutput = particle_filter.FilterOutput
"""What :func:`filter` returns: the final :class:`SlamState`, the (S - 1, ...) stacked
:class:`SlamInfo` and ``marginal_loglik``, the estimate of log p(z_2:S | z_1, u, params)."""


def prepare(log: LaserLog, config: SlamConfig, settings: RunSettings = RunSettings()
            ) -> tuple[PreparedLog, UpdateSelection, np.ndarray]:
    """Host side of a run: check the settings against the log (:func:`check_config_for_log`),
    move it to the local frame
    (:func:`local_frame_offset`), select the scans to process and stack their inputs.

    Returns ``(prepared, selection, frame_offset)``: the arrays :func:`filter` takes, which scans
    of ``log`` it processes, and the (2,) translation (m) to add to local x, y for the world's.
    """
    check_config_for_log(log, config)
    frame_offset = local_frame_offset(log)
    local = local_log(log, frame_offset)
    selection = select_updates(local, settings.linear_update, settings.angular_update)
    prepared = PreparedLog(  # NumPy on the host: slam.run slices it into chunks; jit takes it as it is
        first_ranges=np.asarray(local.ranges[selection.indices[0]], np.float32),
        initial_pose=np.asarray(local.odometry[selection.indices[0]], np.float32),
        inputs=build_inputs(local, selection, config.lookahead_steps),
        sensor=local.sensor,
    )
    return prepared, selection, frame_offset


def filter(key: PRNGKeyArray, prepared: PreparedLog, params: SlamParams, config: SlamConfig,
           pool: PoolSize | None = None) -> FilterOutput:  # noqa: A001 (the module's filter, as dynamax's)
    """The whole filter as one pure function: :func:`init`, then a ``lax.scan`` of :func:`step`.

    Jittable (``config`` and ``pool`` static), vmappable over keys, params and stacked
    ``prepared`` logs, differentiable in ``params``. The per-step keys are derived from ``key``
    as in :func:`jaxslam.slam.run`, so both give the same particles. Unlike ``run`` it cannot
    grow the map pools: from the first step whose tiles do not fit, no step is taken
    (:func:`step`), ``state.maps.overflow`` is set and ``marginal_loglik`` is -inf; pass a
    larger ``pool`` (:func:`pool_size` is the default). Reverse-mode
    autodiff keeps every step's residuals, the maps included, so its memory grows with the
    steps (benchmarks/bench_gradients.py; the LP's horizon keeps nothing: it runs without
    gradient, :mod:`jaxslam.proposals.lookahead`). The OP's and the LP's motion-noise gradients
    are score estimates (:func:`jaxslam.motion.sample_with_score`), with either lookup; the SMP's
    is the drawn pose's score with ``config.smp_weight="importance"`` (what learning sets) and
    goes through the draw with the default "quadrature", which is not a score estimate
    (:mod:`jaxslam.proposals.scan_match`).

    Args:
      key: the run's key.
      prepared: :func:`prepare`'s arrays.
      params: traced parameters.
      config: static settings; ``config.score_lag`` picks the score estimate the gradient is: None
        the path-space score, an int the fixed-lag smoothed score
        (:func:`jaxslam.particle_filter.fixed_lag_score`); the value is the same.
      pool: static sizes of the map pools (default :func:`pool_size`).
    """
    key_init, key_steps = jax.random.split(key)
    state = init(key_init, prepared.first_ranges, prepared.sensor, params, config, prepared.initial_pose, pool=pool)
    # Not rematerialised: the maps are in the scan's carry, so a checkpoint would save nothing.
    out = particle_filter.scan_filter(
        lambda k, s, inp: step_with_score_terms(k, s, inp, prepared.sensor, params, config),
        key_steps, state, prepared.inputs, lambda info: info.log_evidence, checkpoint=False,
        score_lag=config.score_lag)
    return out._replace(marginal_loglik=jnp.where(out.state.maps.overflow, -jnp.inf, out.marginal_loglik))


def known_path_loglik_fn(path_log: LaserLog, config: SlamConfig, settings: RunSettings = RunSettings(),
                         pool: PoolSize | None = None) -> Callable[[SlamParams], Float[Array, ""]]:
    """``params -> log p(scans | path, params)``: how well the sensor model explains a log whose
    poses are known, for fitting it against ground truth.

    ``path_log.odometry`` is taken as the true path (pass a log whose odometry is its ground
    truth, or a corrected path). The function is :func:`filter` with one particle and every
    motion noise zero: the map is built along the path and each processed scan is scored in the
    map of the scans before it, so its value is exact, not an estimate, and differentiable in the
    sensor's parameters (``params.motion`` is ignored). Jitted; compiled once. -inf where the
    map's pool could not hold the path's tiles: pass a larger ``pool`` (default :func:`pool_size`
    of one particle).
    """
    one = dataclasses.replace(config, num_particles=1)
    prepared, _, _ = prepare(path_log, one, settings)

    @jax.jit
    def loglik_fn(params: SlamParams) -> Float[Array, ""]:
        noise_free = params._replace(motion=jax.tree.map(jnp.zeros_like, params.motion))
        return filter(jax.random.key(0), prepared, noise_free, one, pool=pool).marginal_loglik

    return loglik_fn


def particle_paths(proposed_poses: np.ndarray, ancestors: np.ndarray, initial_pose) -> np.ndarray:
    """Every final particle's path (N, S, 3) from a filter's per-step proposed poses and
    ancestors (``SlamInfo.proposed_poses`` (S-1, N, 3), ``SlamInfo.ancestors`` (S-1, N)),
    with the shared initial pose prepended."""
    proposed = np.asarray(proposed_poses)
    anc = np.asarray(ancestors)
    steps, n = anc.shape
    paths = np.empty((n, steps + 1, 3), proposed.dtype)
    paths[:, 0] = np.asarray(initial_pose)
    idx = np.arange(n)
    for t in range(steps - 1, -1, -1):
        idx = anc[t, idx]
        paths[:, t + 1] = proposed[t, idx]
    return paths


def final_best_particle(ancestors, best_particles) -> int:
    """The final particle a run reports (its map, its path): the heaviest after the last step.

    Where the last step resampled, every final weight is equal and their argmax would be
    whichever survivor came first. The heaviest particle before that resampling is then reported
    through the final particle that descends from it (the first, where it left several).

    Args:
      ancestors: (S-1, N) ``SlamInfo.ancestors`` (or the step record's).
      best_particles: (S-1,) ``SlamInfo.best_particle``: each step's heaviest proposed particle.

    Returns:
      The final particle's index; 0 for a run of no step, or where the last resampling dropped
      the heaviest (the systematic and residual resamplers never do: its weight is at least
      1 / N; a stratified or multinomial draw can), whose final weights are all equal.
    """
    ancestors, best_particles = np.asarray(ancestors), np.asarray(best_particles)
    kept = np.flatnonzero(ancestors[-1] == best_particles[-1]) if ancestors.shape[0] else np.zeros(0, np.int64)
    return int(kept[0]) if kept.size else 0


def backtrack_path(info: SlamInfo, final_index: int) -> np.ndarray:
    """Poses (S-1, 3) along the ancestry of particle ``final_index`` of the final set."""
    zero = np.zeros(3, np.asarray(info.proposed_poses).dtype)
    return particle_paths(info.proposed_poses, info.ancestors, zero)[final_index, 1:]

