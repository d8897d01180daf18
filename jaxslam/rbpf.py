"""Grid-based Rao-Blackwellized particle filter SLAM.

Each of N particles carries a pose and its own occupancy grid map. A step
draws every particle's next pose from the configured proposal (odometry,
scan matching or look-ahead; all see the map m_{t-1}), updates its weight,
inserts the scan into its map at the new pose, and resamples when the ESS
falls below ``resample_threshold * N``. The maps are paged (:mod:`jaxslam.paged_map`):
tiles in one pool and blocks of page table in another, shared by all particles, so resampling
copies small directories, and an insertion copies only the shared blocks and tiles it writes.

``init`` / ``step`` are pure and jittable (``config`` static); ``run`` drives
a whole :class:`~jaxslam.laserlog.LaserLog`: update selection in NumPy (the host-side
:class:`~jaxslam.config.RunSettings`), then a ``lax.scan`` over the processed scans in
fixed-size chunks (:mod:`jaxslam.driver`) so that a tqdm bar shows progress and the step
compiles once.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import particle_filter
from jaxslam.config import RunSettings, SlamConfig, SlamParams
from jaxslam.driver import pad_items, run_in_chunks
from jaxslam import paged_map
from jaxslam.grid import GridSpec, in_bounds, world_to_cell
from jaxslam.laser import SensorSpec, subsample_beams
from jaxslam.likelihood_field import endpoint_log_normalizer
from jaxslam.laserlog import LaserLog, UpdateSelection, select_updates
from jaxslam.paged_map import PagedGridSpec, PagedMaps, PoolSize
from jaxslam.proposals import lookahead, odometry, scan_match
from jaxslam.proposals.base import ProposalOutput, StepInputs


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
    log-likelihood, with the endpoint model normalised as a density:
    :func:`jaxslam.likelihood_field.endpoint_log_normalizer`; -inf when ``degenerate``)."""
    degenerate: Bool[Array, ""]
    """Every particle got weight zero (-inf); the weights were reset to uniform."""
    proposed_poses: Float[Array, "N 3"]
    """Every particle's new pose, before resampling."""
    ancestors: Int[Array, "N"]
    """After the step, particle i descends from proposed particle ``ancestors[i]``."""
    num_fallbacks: Int[Array, ""]
    """Particles whose proposal fell back (SMP: failed match; LP: no weight)."""
    outside_samples: Int[Array, ""]
    """Beam samples (all particles) that fell outside the virtual grid and were dropped."""
    poses_outside: Int[Array, ""]
    """Particles whose pose lies outside the virtual grid."""
    tiles_in_use: Int[Array, ""]
    """Pool tiles some particle's map references after the step."""
    pool_overflow: Bool[Array, ""]
    """The maps' pools could not hold this step's new tiles or blocks: the step was not taken (the
    state is the one it was given, with ``maps.overflow`` set). Grow the pools
    (:func:`jaxslam.paged_map.grow`) and take it again; ``run`` does."""


def _proposal_fn(kind: str):
    if kind == "op":
        return odometry.propose
    if kind == "smp":
        return scan_match.propose
    return lookahead.propose


def pool_size(config: SlamConfig) -> PoolSize:
    """The maps' pools a run starts with (see :class:`~jaxslam.paged_map.PagedMaps`). An insertion
    copies or creates up to about 20 tiles per particle (64-cell tiles, 15 m beams; more after a
    resampling, fewer when the particles own their tiles) and up to 4 blocks; the pools start
    with room for that many and a few steps of growth, and ``run`` grows them when a step needs
    more (one recompile each time, reported)."""
    spec = config.grid
    k = spec.window_tiles(config.max_insert_range, config.field_radius)
    kb = spec.window_blocks(k)
    n = config.num_particles
    max_new_tiles = n * min(k * k, 24) + k * k
    max_new_blocks = n * kb * kb + kb * kb
    return PoolSize(4 * max_new_tiles + 256, max_new_tiles, 4 * max_new_blocks + 64, max_new_blocks)


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
    one, _ = paged_map.insert_scans(spec, paged_map.empty(spec, 1, *pool), pose[None],
                                    jnp.asarray(first_ranges, jnp.float32), sensor, params.insertion,
                                    config.max_insert_range, config.field_radius)
    return SlamState(
        poses=jnp.broadcast_to(pose, (n, 3)),
        log_weights=jnp.full((n,), -math.log(n), jnp.float32),
        maps=paged_map.resample(one, jnp.zeros((n,), jnp.int32)),
        step=jnp.int32(0),
    )


def step(
    key: PRNGKeyArray,
    state: SlamState,
    inputs: StepInputs,
    sensor: SensorSpec,
    params: SlamParams,
    config: SlamConfig,
) -> tuple[SlamState, SlamInfo]:
    """One RBPF update with scan ``inputs.ranges`` (all beams) after motion ``inputs.motion``.

    When the maps' pool cannot hold the step's new tiles the step is not taken: the state comes
    back as it was, ``maps.overflow`` and ``info.pool_overflow`` set; grow the pool
    (:func:`jaxslam.paged_map.grow`) and call again with the same key (``run`` does)."""
    spec = config.grid
    n = config.num_particles
    key_prop, key_res = jax.random.split(key)

    lik_sensor, lik_ranges = subsample_beams(sensor, inputs.ranges, config.beam_stride)
    _, lik_future = subsample_beams(sensor, inputs.future_ranges, config.beam_stride)
    lik_inputs = inputs._replace(ranges=lik_ranges, future_ranges=lik_future)
    propose = _proposal_fn(config.proposal)
    # No gradient reaches the previous poses: the maps they built do not move with them (the
    # insertion is not differentiable), and a pose moved against a fixed map is a biased and
    # very noisy motion gradient (motion.sample_with_score).
    out: ProposalOutput = jax.vmap(propose, in_axes=(0, 0, paged_map.FIELD_AXES, None, None, None, None))(
        jax.random.split(key_prop, n), jax.lax.stop_gradient(state.poses), paged_map.fields(state.maps), lik_inputs,
        lik_sensor, params, config)

    update = particle_filter.reweight_and_resample(key_res, out.pose, state.log_weights, out.log_weight_increment,
                                                   params.resample_threshold, config.resampler)
    # Only the particles the resampling keeps insert the scan: the others' maps are dropped next.
    survivors = jnp.zeros((n,), bool).at[update.ancestors].set(True)
    maps, outside = paged_map.insert_scans(spec, state.maps, out.pose, inputs.ranges, sensor, params.insertion,
                                           config.max_insert_range, config.field_radius, survivors)
    # An insertion that did not fit wrote nothing: the step is not taken (retried after growth).
    stalled = maps.overflow
    ancestors = jnp.where(stalled, jnp.arange(n, dtype=update.ancestors.dtype), update.ancestors)
    maps = paged_map.resample(maps, ancestors)
    info = SlamInfo(
        ess=update.ess,
        resampled=update.resampled,
        best_particle=jnp.argmax(update.log_weights).astype(jnp.int32),
        mean_pose=update.mean_pose,
        pose_covariance=update.pose_covariance,
        # The endpoint model's normalising constant, the same for every particle, so it is left
        # out of the weights: with it the log-evidence is that of a density in likelihood.sigma.
        log_evidence=update.log_evidence + endpoint_log_normalizer(lik_ranges, lik_sensor, params.likelihood,
                                                                   config.resolution),
        degenerate=update.degenerate,
        proposed_poses=out.pose,
        ancestors=ancestors,
        num_fallbacks=jnp.sum(out.fallback).astype(jnp.int32),
        outside_samples=jnp.sum(outside).astype(jnp.int32),
        poses_outside=jnp.sum(~in_bounds(spec.grid, world_to_cell(spec.grid, out.pose[:, :2]))).astype(jnp.int32),
        tiles_in_use=paged_map.tiles_in_use(maps).astype(jnp.int32),
        pool_overflow=stalled,
    )
    new_state = SlamState(jnp.where(stalled, state.poses, out.pose[ancestors]),
                          jnp.where(stalled, state.log_weights, update.new_log_weights), maps,
                          state.step + jnp.where(stalled, 0, 1).astype(state.step.dtype))
    return new_state, info


# ---------------------------------------------------------------------------------------------
# Driving a whole log.


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
        grid = self.config.grid
        x0, y0 = self.frame_offset
        return dataclasses.replace(grid, origin=(grid.origin[0] + float(x0), grid.origin[1] + float(y0)))

    def dense_map(self, particle: int | None = None, local: bool = False) -> tuple[np.ndarray, np.ndarray, GridSpec]:
        """One particle's map (default the best) as dense host arrays over the tiles it wrote:
        ``(logodds (H, W) float16, hit_dist2 (H, W) uint8, grid)``, the grid in the world frame
        (``local``: in the filter's local frame, as ``state``'s poses are)."""
        particle = self.best_particle if particle is None else int(particle)
        logodds, field, box = paged_map.to_dense(self.config.grid, self.state.maps, particle)
        if local:
            return logodds, field, box
        x0, y0 = self.frame_offset
        return logodds, field, dataclasses.replace(box, origin=(box.origin[0] + float(x0), box.origin[1] + float(y0)))

    def to_world(self, poses) -> np.ndarray:
        """Poses (..., 3) or points (..., 2) of the local frame (``state.poses``,
        ``info.proposed_poses``, ``info.mean_pose``) in the world frame: float64, ``frame_offset`` added."""
        out = np.array(poses, dtype=np.float64)
        out[..., :2] += self.frame_offset
        return out

    def to_local(self, poses) -> np.ndarray:
        """World-frame poses (..., 3) or points (..., 2) (``trajectory``, the log's odometry) in the
        filter's local frame, as ``state`` and its maps are: float64, ``frame_offset`` subtracted."""
        out = np.array(poses, dtype=np.float64)
        out[..., :2] -= self.frame_offset
        return out


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


FilterOutput = particle_filter.FilterOutput
"""What :func:`filter` returns: the final :class:`SlamState`, the (S - 1, ...) stacked
:class:`SlamInfo` and ``marginal_loglik``, the estimate of log p(z_2:S | z_1, u, params)."""


def prepare(log: LaserLog, config: SlamConfig, settings: RunSettings = RunSettings()
            ) -> tuple[PreparedLog, UpdateSelection, np.ndarray]:
    """Host side of a run: check the log against the grid, move it to the local frame
    (:func:`local_frame_offset`), select the scans to process and stack their inputs.

    Returns ``(prepared, selection, frame_offset)``: the arrays :func:`filter` takes, which scans
    of ``log`` it processes, and the (2,) translation (m) to add to local x, y for the world's.
    """
    prepared, selection, frame_offset, _ = _prepare(log, config, settings)
    return prepared, selection, frame_offset


def _prepare(log: LaserLog, config: SlamConfig, settings: RunSettings):
    """:func:`prepare`, and the log moved to the local frame (``run`` goes on with it)."""
    check_extent(log, config)
    frame_offset = local_frame_offset(log)
    local = _local_log(log, frame_offset)
    selection = select_updates(local, settings.linear_update, settings.angular_update)
    prepared = PreparedLog(  # NumPy on the host: run() slices it into chunks; jit takes it as it is
        first_ranges=np.asarray(local.ranges[selection.indices[0]], np.float32),
        initial_pose=np.asarray(local.odometry[selection.indices[0]], np.float32),
        inputs=build_inputs(local, selection, config.lookahead_steps),
        sensor=local.sensor,
    )
    return prepared, selection, frame_offset, local


def filter(key: PRNGKeyArray, prepared: PreparedLog, params: SlamParams, config: SlamConfig,
           pool: PoolSize | None = None) -> FilterOutput:  # noqa: A001 (the module's filter, as dynamax's)
    """The whole filter as one pure function: :func:`init`, then a ``lax.scan`` of :func:`step`.

    Jittable (``config`` and ``pool`` static), vmappable over keys, params and stacked
    ``prepared`` logs, differentiable in ``params``. The per-step keys are derived from ``key``
    as in :func:`run`, so both give the same particles. Unlike ``run`` it cannot grow the map
    pools: a step whose tiles do not fit inserts nothing and sets ``state.maps.overflow``
    (check it, and pass a larger ``pool``; :func:`pool_size` is the default). Reverse-mode
    autodiff keeps every step's residuals, the maps included, so its memory grows with the
    steps (benchmarks/bench_gradients.py). The OP's motion-noise gradients are score estimates
    (:func:`jaxslam.motion.sample_with_score`), with either lookup; the SMP's and the LP's go
    through the step's own draw and need ``likelihood_lookup="bilinear"`` (the nearest-cell
    weights are piecewise constant in the pose).

    Args:
      key: the run's key.
      prepared: :func:`prepare`'s arrays.
      params: traced parameters.
      config: static settings.
      pool: static sizes of the map pools (default :func:`pool_size`).
    """
    key_init, key_steps = jax.random.split(key)
    state = init(key_init, prepared.first_ranges, prepared.sensor, params, config, prepared.initial_pose, pool=pool)
    # Not rematerialised: the maps are in the scan's carry, so a checkpoint would save nothing.
    return particle_filter.scan_filter(lambda k, s, inp: step(k, s, inp, prepared.sensor, params, config),
                                       key_steps, state, prepared.inputs, lambda info: info.log_evidence,
                                       checkpoint=False)


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
        out = filter(jax.random.key(0), prepared, noise_free, one, pool=pool)
        return jnp.where(out.state.maps.overflow, -jnp.inf, out.marginal_loglik)

    return loglik_fn


@jax.jit(static_argnames=("config",), donate_argnames=("state",))
def _run_chunk(state, keys, inputs, valid, sensor, params, config):
    def body(carry, xs):
        state, stalled = carry
        key, inp, ok = xs
        # A padding step past the end of the log, or any step after one the pool could not hold
        # (the host grows the pool and repeats from there), sees a scan with no usable beam
        # (nothing enters the maps, every weight increment is 0) and may not resample; its pose
        # draws are discarded.
        ok = ok & ~stalled
        inp = jax.tree.map(lambda a, b: jnp.where(ok, a, b), inp, _noop_inputs(inp))
        noop_params = params._replace(resample_threshold=jnp.where(ok, params.resample_threshold, 0.0))
        new_state, info = step(key, state, inp, sensor, noop_params, config)
        new_state = new_state._replace(
            poses=jnp.where(ok, new_state.poses, state.poses),
            log_weights=jnp.where(ok, new_state.log_weights, state.log_weights),
            step=jnp.where(ok, new_state.step, state.step),
            maps=new_state.maps._replace(overflow=stalled | new_state.maps.overflow),
        )
        return (new_state, stalled | info.pool_overflow), info

    (state, _), infos = jax.lax.scan(body, (state, jnp.bool_(False)), (keys, inputs, valid))
    return state, infos


def _noop_inputs(inputs: StepInputs) -> StepInputs:
    """Inputs of a padding step: no motion and only invalid (below range_min) beams."""
    invalid = jnp.full_like(inputs.ranges, -1.0)
    return StepInputs(
        motion=jnp.zeros_like(inputs.motion),
        ranges=invalid,
        future_motions=jnp.zeros_like(inputs.future_motions),
        future_ranges=jnp.full_like(inputs.future_ranges, -1.0),
        future_valid=jnp.zeros_like(inputs.future_valid),
    )


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


def backtrack_path(info: SlamInfo, final_index: int) -> np.ndarray:
    """Poses (S-1, 3) along the ancestry of particle ``final_index`` of the final set."""
    zero = np.zeros(3, np.asarray(info.proposed_poses).dtype)
    return particle_paths(info.proposed_poses, info.ancestors, zero)[final_index, 1:]


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


def local_frame_offset(log: LaserLog) -> np.ndarray:
    """(2,) float64: the translation ``run`` subtracts from ``log`` (its first odometry pose's, rounded
    to a multiple of 64 m): the origin of the filter's local frame, where the virtual grid is centred."""
    # The first pose's translation, rounded to a multiple of 64 m: a log that starts within 32 m of
    # the origin runs exactly as given, and shifting a log by a multiple of 64 m changes no bit of
    # the filter's arithmetic (the local logs are equal); |local coordinates| <= 32 m + the log's extent.
    return np.round(np.asarray(log.odometry[0, :2], dtype=np.float64) / 64.0) * 64.0 + 0.0


def _local_log(log: LaserLog, offset: np.ndarray) -> LaserLog:  # offset subtracted from x, y, float64
    if not np.any(offset):
        return log
    odometry = log.odometry.copy()
    odometry[:, :2] -= offset
    ground_truth = None
    if log.ground_truth is not None:
        ground_truth = log.ground_truth.copy()
        ground_truth[:, :2] -= offset
    return dataclasses.replace(log, odometry=odometry, ground_truth=ground_truth)


def _larger_pool(maps: PagedMaps) -> PoolSize:
    """The pools' sizes after ``maps``' pools overflowed: each at least twice the old, and room for
    what is in use plus two of the largest requests seen."""
    old = maps.pool_size
    max_new = max(2 * old.max_new_tiles, 2 * int(maps.peak_request))
    max_new_blocks = max(2 * old.max_new_blocks, 2 * int(maps.peak_block_request))
    return PoolSize(max(2 * old.capacity, int(paged_map.tiles_in_use(maps)) + 2 * max_new), max_new,
                    max(2 * old.block_capacity, int(paged_map.blocks_in_use(maps)) + 2 * max_new_blocks),
                    max_new_blocks)


def check_extent(log: LaserLog, config: SlamConfig) -> None:
    """Refuse (``ConfigError``) a log whose odometry leaves the virtual grid, before any work:
    the message names the setting to change (``map_extent``). Beams that reach past the grid's
    edge, or a path that drifts off it later, are counted (``SlamInfo.outside_samples``,
    ``poses_outside``) and reported with the same advice."""
    from jaxslam.config import ConfigError

    reach = float(np.abs(np.asarray(log.odometry[:, :2], np.float64) - local_frame_offset(log)).max(initial=0.0))
    half = config.grid.num_tiles[0] * config.grid.tile_size * config.resolution / 2.0
    if reach >= half:
        need = 2.0 * (reach + config.max_insert_range)
        raise ConfigError(f"the log's odometry reaches {reach:.1f} m from its start, beyond the map: the virtual grid "
                          f"spans +-{half:.1f} m (map_extent={config.map_extent:g} m); set --set "
                          f"map_extent={math.ceil(need / 64) * 64} or more (memory grows with the area mapped, the "
                          f"directories with the extent)")


def estimate_run_bytes(config: SlamConfig, num_beams: int) -> tuple[int, str]:
    """A rough estimate of the memory (bytes) a ``run`` with ``config`` needs at its start, and how
    it was reckoned (for a refusal message).

    The tile pool (capacity x T x T x 3 bytes, twice: a chunk's input is kept to repeat it when
    the pool overflows) and the block pool (B x S x S int32, twice) as :func:`pool_size` sizes them,
    the directories (N x DY x DX int32, twice), and scan insertion, which traces every beam with one
    sample per cell up to ``max_insert_range``: N x B x S samples of about 40 bytes. The look-ahead
    proposal adds its N x L x B float32 beam terms (B the beams used in likelihoods, ``num_beams /
    beam_stride``), twice; about 1 GB is added for XLA (compiled code, buffers) and the host.
    The pools grow with the area mapped (they are reported in ``summary.json``).
    """
    n = config.num_particles
    dy, dx = config.grid.num_blocks
    t, s = config.tile_size, config.grid.block_size
    pool_sizes = pool_size(config)
    tables = (n * dy * dx + pool_sizes.block_capacity * s * s) * 4 * 2
    pool = pool_sizes.capacity * t * t * 3 * 2
    samples = int(math.ceil(config.max_insert_range / config.resolution)) + 1
    insertion = n * num_beams * samples * 40
    how = (f"({n} particles x {dy} x {dx} blocks + {pool_sizes.block_capacity} blocks x {s} x {s} tiles) x 4 bytes "
           f"x 2 + {pool_sizes.capacity} tiles x {t} x {t} cells x 3 bytes x 2 + "
           f"{n} x {num_beams} beams x {samples} samples x 40 bytes")
    total = tables + pool + insertion + 2**30
    if config.proposal == "lp":
        beams = -(-num_beams // config.beam_stride)
        lp = n * config.num_localizers * beams * 4 * 2
        total += lp
        how += f" + {n} x {config.num_localizers} localizers x {beams} beams x 4 bytes x 2"
    return total, how + " + 1 GB for XLA"


def available_memory_bytes() -> int | None:
    """The machine's available memory (``MemAvailable`` of /proc/meminfo, bytes); None if unreadable."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


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

    The maps' pool starts at :func:`pool_size`; a chunk in which a step needed more tiles than
    the pool had is repeated from its start with a grown pool (one recompile; reported on
    stderr and in ``result.map_pool``). A log whose odometry leaves the virtual grid is refused
    first (:func:`check_extent`).

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
        :func:`pool_size`); the pool grows as needed, and its size never changes the result.
    """
    from jaxslam.io.trajectory import trajectory_per_scan  # the readers load only when a log is run

    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    t_start = time.perf_counter()
    prepared, selection, frame_offset, log = _prepare(log, config, settings)  # log: from here on, the local frame
    sensor = log.sensor
    initial_pose = jnp.asarray(prepared.initial_pose)
    key_init, key_steps = jax.random.split(key)

    inputs = prepared.inputs
    num_steps = selection.indices.size - 1
    step_keys = jax.random.split(key_steps, max(num_steps, 1))
    done = 0
    prior_info = None
    if resume is None:
        pool = pool_size(config) if initial_pool is None else PoolSize(*(int(v) for v in initial_pool))
        while True:  # the first scan alone may not fit a pool given too small
            state = init(key_init, jnp.asarray(prepared.first_ranges), sensor, params, config, initial_pose, pool=pool)
            if not bool(state.maps.overflow):
                break
            pool = _larger_pool(state.maps)
    else:
        done = int(resume.steps_done)
        if resume.num_steps != num_steps or not 0 <= done <= num_steps or (done % chunk_size and done != num_steps):
            raise ValueError(f"resume: {done} of {resume.num_steps} steps done does not fit this run "
                             f"({num_steps} steps, chunks of {chunk_size})")
        expected = (config.num_particles,) + config.grid.num_blocks
        if np.shape(resume.state.maps.directory) != expected:
            raise ValueError(f"resume: the saved map directories are {np.shape(resume.state.maps.directory)}, this "
                             f"run's are {expected} (particles, blocks)")
        state = jax.tree.map(jnp.asarray, resume.state)
        prior_info = resume.info
        step_keys = step_keys[done:]
        inputs = jax.tree.map(lambda a: a[done:], inputs)

    growths = [] if initial_pool is None or state.maps.pool_size == tuple(initial_pool) else [
        {"step": 0, **state.maps.pool_size._asdict()}]
    chunk_starts = iter(range(done, max(num_steps, 1), chunk_size))

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
    best_path = np.concatenate([np.asarray(initial_pose)[None], backtrack_path(info, best)])
    trajectory = trajectory_per_scan(log, selection.indices, best_path)
    best_path = best_path.astype(np.float64)
    if np.any(frame_offset):  # back to the world frame, in float64
        best_path[:, :2] += frame_offset
        trajectory[:, :2] += frame_offset
    total = time.perf_counter() - t_start
    timings = {
        "compile": first_chunk_seconds,
        "total": total,
        "real_time_factor": log.duration / total if total > 0 else float("inf"),
    }
    maps = state.maps
    map_pool = {
        **maps.pool_size._asdict(),
        "tiles_in_use": int(paged_map.tiles_in_use(maps)), "peak_request": int(maps.peak_request),
        "blocks_in_use": int(paged_map.blocks_in_use(maps)), "peak_block_request": int(maps.peak_block_request),
        "bytes": int(sum(np.asarray(a).nbytes for a in maps)), "growths": growths,
    }
    return SlamResult(state, info, selection, config, settings, best_path, trajectory, timings, frame_offset, map_pool)


# ---------------------------------------------------------------------------------------------
# Checkpoints of a run (written by ``on_chunk``, read back for ``resume``).

CHECKPOINT_VERSION = 3  # 2: paged maps; 3: two-level page tables


def save_checkpoint(path, progress: RunProgress, identity: dict) -> None:
    """Write ``progress`` (state, the infos so far, the steps done) and ``identity`` (JSON-able: what
    identifies the run, checked on resume) to the ``.npz`` file ``path`` atomically: into a temporary
    file in the same folder, flushed to disk, then renamed over ``path``."""
    import json

    from jaxslam.outputs import write_file_atomic

    info = progress.info() if callable(progress.info) else progress.info
    arrays = {"version": np.int64(CHECKPOINT_VERSION), "identity": np.array(json.dumps(identity, sort_keys=True)),
              "steps_done": np.int64(progress.steps_done), "num_steps": np.int64(progress.num_steps)}
    state = progress.state
    fields = {"poses": state.poses, "log_weights": state.log_weights, "step": state.step,
              **{f"maps.{name}": value for name, value in zip(PagedMaps._fields, state.maps)}}
    for name, value in fields.items():
        arrays[f"state.{name}"] = np.array(value)  # a copy: the device buffer may be donated next
    for name, value in zip(SlamInfo._fields, info):
        arrays[f"info.{name}"] = np.asarray(value)
    write_file_atomic(path, lambda f: np.savez(f, **arrays))


def load_checkpoint(path) -> tuple[RunProgress, dict]:
    """``(progress, identity)`` from a file of :func:`save_checkpoint` (NumPy arrays); ``ValueError``
    naming the file if it is not one."""
    import json
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["version"]) != CHECKPOINT_VERSION:
                raise ValueError(f"{path}: checkpoint version {int(z['version'])}, expected {CHECKPOINT_VERSION}")
            identity = json.loads(str(z["identity"]))
            maps = PagedMaps(*(z[f"state.maps.{name}"] for name in PagedMaps._fields))
            state = SlamState(z["state.poses"], z["state.log_weights"], maps, z["state.step"])
            info = SlamInfo(*(z[f"info.{name}"] for name in SlamInfo._fields))
            progress = RunProgress(int(z["steps_done"]), int(z["num_steps"]), state, info)
    except (KeyError, zipfile.BadZipFile, EOFError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a jaxslam checkpoint ({type(err).__name__}: {err})") from None
    return progress, identity
