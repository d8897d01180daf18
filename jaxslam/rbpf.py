"""Grid-based Rao-Blackwellized particle filter SLAM: the filter itself, pure and jittable.

Each of N particles carries a pose and its own occupancy grid map. A step draws every
particle's next pose from the configured proposal (:data:`jaxslam.proposals.PROPOSALS`; all
see the map m_{t-1}), updates its weight, inserts the scan into its map at the new pose, and
resamples when the ESS falls below ``resample_threshold * N``. The maps are paged
(:mod:`jaxslam.paged_map`): tiles in one pool and blocks of page table in another, shared by
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

from jaxslam import motion, paged_map, particle_filter, resampling, window_posterior
from jaxslam.config import ConfigError, RunSettings, SlamConfig, SlamParams
from jaxslam.grid import in_bounds, world_to_cell
from jaxslam.laser import SensorSpec, subsample_beams
from jaxslam.laserlog import LaserLog, UpdateSelection, select_updates
from jaxslam.paged_map import PagedMaps, PoolSize
from jaxslam.proposals import PROPOSALS
from jaxslam.proposals.base import ProposalOutput, StepInputs
from jaxslam.sensor_model import sensor_model


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
    """Particles whose new pose came from the odometry's slip component (:func:`slip_mixture`;
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
    """The maps' pools a run starts with (see :class:`~jaxslam.paged_map.PagedMaps`). An insertion
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
    (there at most 0.74 of one), at most :func:`~jaxslam.paged_map.max_pool_tiles` (a pool beyond
    2**31 cells, from about N = 7,300 on 64-cell tiles, is indexed by (slot, cell) pairs). It is
    the largest allocation per particle (0.9 MB at 64-cell tiles), so it starts no larger:
    :func:`jaxslam.slam.run` grows the pools when a step needs more (one recompile each time,
    reported; while it grows both the old and the new pools are held, so starting smaller and
    growing costs more peak memory than starting large enough:
    docs/notes/2026-11-26-memory-per-particle.md)."""
    spec = config.grid
    k = spec.window_tiles(config.max_insert_range, config.field_radius)
    kb = spec.window_blocks(k)
    n = config.num_particles
    most = paged_map.max_pool_tiles(spec)  # int32 slots: memory runs out long before
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
    one, _ = paged_map.insert_scans(spec, paged_map.empty(spec, 1, *pool), jax.lax.stop_gradient(pose[None]),
                                    jnp.asarray(first_ranges, jnp.float32), sensor,
                                    jax.lax.stop_gradient(params.insertion), config.max_insert_range,
                                    config.field_radius)
    return SlamState(
        poses=jnp.broadcast_to(pose, (n, 3)),
        log_weights=jnp.full((n,), -math.log(n), jnp.float32),
        maps=paged_map.resample(one, jnp.zeros((n,), jnp.int32)),
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

    One RBPF update with scan ``inputs.ranges`` (all beams) after motion ``inputs.motion``.

    The step is taken only when ``valid`` (False: a padding step past the end of a log) and the
    maps' pools hold its new tiles. A step not taken changes nothing (poses, weights, maps, step
    count) and adds no evidence (``info.log_evidence`` 0); ``state.maps.overflow`` and
    ``info.pool_overflow`` say when the pools were too small, and stay set, so that every later
    step is not taken either: grow the pools (:func:`jaxslam.paged_map.grow`) and take the
    steps again from the first one not taken (:func:`jaxslam.slam.run` does)."""
    spec = config.grid
    n = config.num_particles
    # A step not taken sees a scan with no usable beam (nothing enters the maps, every weight
    # increment is 0) and may not resample; its pose draws are discarded.
    active = jnp.asarray(valid, bool) & ~state.maps.overflow
    inputs = jax.tree.map(lambda a, b: jnp.where(active, a, b), inputs, _noop_inputs(inputs))
    params = params._replace(resample_threshold=jnp.where(active, params.resample_threshold, 0.0))
    key_prop, key_res = jax.random.split(key)

    lik_sensor, lik_ranges = subsample_beams(sensor, inputs.ranges, config.beam_stride)
    _, lik_future = subsample_beams(sensor, inputs.future_ranges, config.beam_stride)
    lik_inputs = inputs._replace(ranges=lik_ranges, future_ranges=lik_future)
    propose_fn = PROPOSALS[config.proposal].propose_fn
    # No gradient reaches the previous poses: the maps they built do not move with them (the
    # insertion is not differentiable), and a pose moved against a fixed map is a biased and
    # very noisy motion gradient (motion.sample_with_score).
    # In blocks of config.particle_block particles: the window posterior's candidates times beams
    # would otherwise be the step's largest intermediate, N times over.
    field = paged_map.fields(state.maps)

    def propose_all(key, step_motion):
        def propose_one(particle):
            key, pose, directory = particle
            return propose_fn(key, pose, field._replace(directory=directory), lik_inputs, lik_sensor, params,
                              config, step_motion)

        return particle_filter.map_in_blocks(
            propose_one, (jax.random.split(key, n), jax.lax.stop_gradient(state.poses), field.directory),
            config.particle_block)

    out: ProposalOutput = propose_all(key_prop, None)
    num_slipped = jnp.int32(0)
    if searches_window(config):
        # The slip search. The odometry is common to every particle, so one particle can tell
        # whether this step's odometry slipped: the heaviest, whose map is the filter's best.
        # When its posterior puts more than scan_match.slip_trigger on the slip component, the
        # proposals run again under it and every particle draws from the mixture
        # (slip_mixture); at other steps the slip component's share is taken as 0.
        heaviest = jnp.argmax(state.log_weights)
        slip_odds = jax.lax.stop_gradient(slip_log_odds(
            state.poses[heaviest], field._replace(directory=field.directory[heaviest]), lik_inputs, lik_sensor,
            params, config))

        def with_slip(out):
            slipped = propose_all(jax.random.fold_in(key_prop, _TAG_SLIP), slip_motion(params))
            return slip_mixture(jax.random.fold_in(key_prop, _TAG_SLIP_CHOICE), out, slipped,
                                params.scan_match.slip_probability)

        triggered = jax.nn.sigmoid(slip_odds) > params.scan_match.slip_trigger
        out, chose_slip = jax.lax.cond(triggered, with_slip, lambda out: (out, jnp.zeros((n,), bool)), out)
        num_slipped = jnp.sum(chose_slip).astype(jnp.int32)

    update = particle_filter.reweight_and_resample(key_res, out.pose, state.log_weights, out.log_weight_increment,
                                                   params.resample_threshold, config.resampler)
    # Only the particles the resampling keeps insert the scan: the others' maps are dropped next.
    survivors = jnp.zeros((n,), bool).at[update.ancestors].set(True)
    maps, outside = paged_map.insert_scans(spec, state.maps, jax.lax.stop_gradient(out.pose), inputs.ranges, sensor,
                                           jax.lax.stop_gradient(params.insertion), config.max_insert_range,
                                           config.field_radius, survivors,
                                           config.particle_block)  # not differentiable: see init
    # An insertion that did not fit wrote nothing: the step is not taken.
    taken = active & ~maps.overflow
    ancestors = jnp.where(taken, update.ancestors, jnp.arange(n, dtype=update.ancestors.dtype))
    maps = paged_map.resample(maps, ancestors)
    maps = maps._replace(overflow=state.maps.overflow | maps.overflow)
    info = SlamInfo(
        ess=update.ess,
        resampled=update.resampled,
        best_particle=jnp.argmax(update.log_weights).astype(jnp.int32),
        mean_pose=update.mean_pose,
        pose_covariance=update.pose_covariance,
        # The sensor model's normalising constant, the same for every particle, so it is left
        # out of the weights: with it the log-evidence is that of a density in likelihood.sigma.
        log_evidence=jnp.where(taken, update.log_evidence + sensor_model(config).log_normalizer_fn(
            lik_ranges, lik_sensor, params.likelihood, config.resolution), 0.0),
        degenerate=update.degenerate,
        proposed_poses=out.pose,
        log_weights=jnp.where(taken, update.log_weights, state.log_weights),
        ancestors=ancestors,
        num_fallbacks=jnp.sum(out.fallback).astype(jnp.int32),
        num_slipped=num_slipped,
        outside_samples=jnp.sum(outside).astype(jnp.int32),
        poses_outside=jnp.sum(~in_bounds(spec.grid, world_to_cell(spec.grid, out.pose[:, :2]))).astype(jnp.int32),
        tiles_in_use=paged_map.tiles_in_use(maps).astype(jnp.int32),
        pool_overflow=maps.overflow,
    )
    new_state = SlamState(jnp.where(taken, out.pose[ancestors], state.poses),
                          jnp.where(taken, update.new_log_weights, state.log_weights), maps,
                          state.step + jnp.where(taken, 1, 0).astype(state.step.dtype))
    terms = particle_filter.ScoreTerms(jnp.where(taken, update.log_weights, state.log_weights),
                                       jnp.where(taken, update.score_terms.increments, 0.0), ancestors)
    return new_state, info, terms


_TAG_SLIP, _TAG_SLIP_CHOICE = 0x511, 0x512  # fold-in tags of the slip search's keys


def searches_window(config: SlamConfig) -> bool:
    """Whether ``config``'s proposal searches the window posterior (the SMP, the LP from the
    match), and so gets the slip search (static)."""
    return config.proposal == "smp" or (config.proposal == "lp" and config.lookahead_initial == "scan_match")


def slip_motion(params: SlamParams) -> motion.MotionParams:
    """The motion model's slip component: zero-mean noise of ``scan_match.slip_std_xy`` (x, y) and
    ``slip_std_theta`` (heading) round the odometry's prediction, whatever the motion (the window
    posterior is then sized from these stds)."""
    sm = params.scan_match
    zero = jnp.zeros_like(sm.slip_std_xy)
    return motion.motion_params(zero, zero, zero, zero, sm.slip_std_xy, sm.slip_std_theta)


def slip_log_odds(pose: Float[Array, "3"], field, inputs: StepInputs, sensor: SensorSpec, params: SlamParams,
                  config: SlamConfig) -> Float[Array, ""]:
    """log [epsilon eta_slip / ((1 - epsilon) eta_usual)] for one particle: the posterior log-odds
    that this step's odometry slipped, eta_c the window posterior's evidence (its ``log_eta``)
    under the usual motion model and under its slip component (:func:`slip_motion`), epsilon
    ``scan_match.slip_probability``. ``inputs`` and ``sensor`` beam-subsampled as the proposals'."""
    def log_evidence(step_params):
        return window_posterior.window_posterior(pose, field, inputs.motion, inputs.ranges, sensor, step_params,
                                                 config, fit_gain=1.0).log_eta

    eps = params.scan_match.slip_probability
    slipped = log_evidence(params._replace(motion=slip_motion(params)))
    odds = resampling.safe_log(eps) + slipped - jnp.log1p(-eps) - log_evidence(params)
    return jnp.where(jnp.isnan(odds), -jnp.inf, odds)


def slip_mixture(key: PRNGKeyArray, usual: ProposalOutput, slipped: ProposalOutput,
                 slip_probability: Float[Array, ""]) -> tuple[ProposalOutput, Bool[Array, "N"]]:
    """Each particle's draw under the motion model (1 - epsilon) p_usual + epsilon p_slip, from
    one draw under each component.

    Each proposal's increment estimates its component's evidence eta_c = p(z_t | x_{t-1}, m, u_t)
    under that component. The particle keeps the slip draw with probability
    epsilon eta_slip / ((1 - epsilon) eta_usual + epsilon eta_slip) and its increment is the
    log of that denominator, whichever draw it keeps: the evidence under the mixture (where
    each draw is from its component's posterior, the proposal is then the mixture's posterior
    and this is its exact weight). Increments of -inf under both give -inf and the usual draw.

    Args:
      key: for the choices.
      usual, slipped: (N,)-batched outputs of the proposals under the usual motion model and
        under :func:`slip_motion`.
      slip_probability: epsilon in [0, 1).

    Returns:
      ``(mixed, chose_slip)``: the outputs kept (the increment replaced) and (N,) bool.
    """
    eps = jnp.asarray(slip_probability, usual.log_weight_increment.dtype)
    log_usual = jnp.log1p(-eps) + usual.log_weight_increment
    log_slip = resampling.safe_log(eps) + slipped.log_weight_increment
    # Double where: logaddexp(-inf, -inf) has a NaN gradient, which a sum over particles spreads.
    none = jnp.isneginf(log_usual) & jnp.isneginf(log_slip)
    total = jnp.where(none, -jnp.inf, jnp.logaddexp(jnp.where(none, 0.0, log_usual), jnp.where(none, 0.0, log_slip)))
    finite = jnp.isfinite(total)
    slip_share = jnp.exp(jnp.where(finite, log_slip - jnp.where(finite, total, 0.0), -jnp.inf))
    chose_slip = jax.random.uniform(key, total.shape) < jax.lax.stop_gradient(slip_share)

    def pick(a, b):
        return jnp.where(chose_slip.reshape(chose_slip.shape + (1,) * (a.ndim - 1)), b, a)

    mixed = jax.tree.map(pick, usual, slipped)
    return mixed._replace(log_weight_increment=total), chose_slip


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


# ---------------------------------------------------------------------------------------------
# The filter's local frame (the one place that moves poses between it and the log's frame).


def local_frame_offset(log: LaserLog) -> np.ndarray:
    """(2,) float64: the origin of the filter's local frame in the log's frame, where the virtual
    grid is centred: the translation of the log's first odometry pose, rounded to a multiple of
    64 m. Subtracted on the host in float64 before anything is cast to float32 (float32 resolves
    0.5 m at 5,000 km from the origin, e.g. in UTM coordinates)."""
    # Rounded to a multiple of 64 m: a log that starts within 32 m of the origin runs exactly as
    # given, and shifting a log by a multiple of 64 m changes no bit of the filter's arithmetic
    # (the local logs are equal); |local coordinates| <= 32 m + the log's extent.
    return np.round(np.asarray(log.odometry[0, :2], dtype=np.float64) / 64.0) * 64.0 + 0.0


def to_world(poses, frame_offset) -> np.ndarray:
    """Local-frame poses (..., 3) or points (..., 2) in the log's (world) frame: float64, the
    (2,) ``frame_offset`` added."""
    out = np.array(poses, dtype=np.float64)
    out[..., :2] += frame_offset
    return out


def to_local(poses, frame_offset) -> np.ndarray:
    """World-frame poses (..., 3) or points (..., 2) in the filter's local frame: float64, the
    (2,) ``frame_offset`` subtracted."""
    out = np.array(poses, dtype=np.float64)
    out[..., :2] -= frame_offset
    return out


def grid_to_world(grid, frame_offset):
    """A grid (``GridSpec`` or ``PagedGridSpec``) of the local frame placed in the log's frame:
    its origin moved by the (2,) ``frame_offset``."""
    x0, y0 = (float(v) for v in frame_offset)
    return dataclasses.replace(grid, origin=(grid.origin[0] + x0, grid.origin[1] + y0))


def local_log(log: LaserLog, frame_offset) -> LaserLog:
    """``log`` with its odometry and ground truth in the local frame of ``frame_offset``
    (:func:`local_frame_offset`); the same object when the offset is zero."""
    if not np.any(frame_offset):
        return log
    ground_truth = None if log.ground_truth is None else to_local(log.ground_truth, frame_offset)
    return dataclasses.replace(log, odometry=to_local(log.odometry, frame_offset), ground_truth=ground_truth)


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

