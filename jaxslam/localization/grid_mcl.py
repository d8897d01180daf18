"""Monte Carlo localization in an occupancy grid (a map ``jaxslam map`` wrote), with the
endpoint (likelihood-field) model, recovery from a lost pose and an adaptive particle count.

The map: :func:`prepare_map` turns a map_server grid (:func:`jaxslam.io.maps.read_map`'s
occupancy probabilities) into the squared cell distance to the nearest occupied cell (the
``hit_dist2`` field the SLAM filters score scans in, built with the same kernel,
:func:`jaxslam.occupancy.field_kernel`) and the list of free cells, in a local frame
(:func:`jaxslam.laserlog.frame_offset_of` of the map's centre) so that float32 keeps its
precision; the poses go back to the world frame with :func:`jaxslam.laserlog.to_world`.

A step (:func:`step`) moves every particle by the odometry motion model
(:func:`jaxslam.motion.sample`), weighs it by the scan with the SLAM filters' endpoint model
(:data:`jaxslam.sensor_model.ENDPOINT`), normalises with the core shared by every filter
(:func:`jaxslam.particle_filter.reweight_and_resample`), and resamples when the ESS is low or
when particles are to be redrawn:

- recovery (Augmented MCL, Thrun, Burgard & Fox, Table 8.3; AMCL's ``recovery_alpha_slow`` /
  ``recovery_alpha_fast``): a slow and a fast exponential average of the mean likelihood;
  while the fast one is below the slow one, a share ``1 - w_fast / w_slow`` of the resampled
  particles is redrawn uniformly over the free cells. The mean likelihood is taken per beam
  (the geometric mean of the weighted particles' per-beam likelihood), so that scans with more
  or fewer returns compare, and the first scan starts both averages (no warm-up from 0, during
  which a slow rate would keep recovery off for 1 / alpha_slow scans); ``alpha_slow = 0`` turns
  recovery off.
- adaptive count (KLD sampling, Fox 2003, as AMCL) with static shapes: the arrays hold
  ``max_particles``; the first ``num_active`` are the particles, the rest carry log-weight
  -inf and are never drawn. At a resampling, ``max_particles`` are drawn (systematic) in random
  order, the recovery's share of them redrawn, and the count is the first n with
  ``n >= max(bound(k(n)), min_particles)`` (all N if none), k(n) the number of histogram bins
  (``bin_xy`` x ``bin_xy`` x ``bin_theta``) the first n occupy and
  ``bound(k) = (k - 1) / (2 epsilon) (1 - 2 / (9 (k - 1)) + sqrt(2 / (9 (k - 1))) z)^3``.
  Redrawn particles fill bins, so recovery raises the count, as in AMCL.

Shape of the code as :mod:`jaxslam.localization.mcl`: a static :class:`GridMclConfig`, traced
:class:`GridMclParams`, named :class:`GridMclState` / :class:`GridMclInfo`; ``init_tracked`` /
``init_global`` / ``step`` / ``filter`` are pure, ``filter`` one ``lax.scan`` over the scans
(inputs from :func:`jaxslam.localization.mcl.log_inputs`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jaxslam import motion as motion_model
from jaxslam import particle_filter, resampling
from jaxslam.geometry import wrap_angle
from jaxslam.grid import GridSpec, cell_to_world, flat_index
from jaxslam.laser import SensorSpec, subsample_beams, valid_returns
from jaxslam.laserlog import frame_offset_of
from jaxslam.likelihood_field import FIELD_LOOKUPS, LikelihoodParams
from jaxslam.localization.mcl import MclInfo, ScanInputs
from jaxslam.map_view import MapView
from jaxslam.motion import MotionParams, motion_params
from jaxslam.occupancy import FAR, field_kernel, splat_field
from jaxslam.sensor_model import ENDPOINT

OCCUPIED_PROBABILITY = 0.65
"""A cell is occupied (a wall the beams end at) above this probability (map_server's ``occupied_thresh``)."""
FREE_PROBABILITY = 0.196
"""A cell is free (where the robot can be) below this probability (map_server's ``free_thresh``)."""


@dataclasses.dataclass(frozen=True)
class GridMclConfig:
    """Static settings (shapes and code paths). Hashable; changing it recompiles."""

    max_particles: int = 5000
    """N, the size of the particle arrays: the most particles the filter holds."""
    min_particles: int = 100
    """The fewest particles KLD sampling keeps."""
    kld: bool = True
    """Adapt the particle count by KLD sampling; False: always ``max_particles``."""
    beam_stride: int = 2
    """Use every ``beam_stride``-th beam of a scan in the likelihood."""
    bin_xy: float = 0.5
    """KLD histogram bin side in position (m)."""
    bin_theta: float = math.radians(10.0)
    """KLD histogram bin width in heading (rad)."""
    lookup: str = "nearest"
    """How an endpoint reads the field: one of :data:`jaxslam.likelihood_field.FIELD_LOOKUPS`."""

    def __post_init__(self):
        if self.max_particles < 1:
            raise ValueError("GridMclConfig: max_particles must be >= 1")
        if not 1 <= self.min_particles <= self.max_particles:
            raise ValueError("GridMclConfig: min_particles must be in 1..max_particles")
        if self.beam_stride < 1:
            raise ValueError("GridMclConfig: beam_stride must be >= 1")
        if not (self.bin_xy > 0 and self.bin_theta > 0):
            raise ValueError("GridMclConfig: bin_xy and bin_theta must be > 0")
        if self.lookup not in FIELD_LOOKUPS:
            raise ValueError(f"GridMclConfig: lookup must be one of {FIELD_LOOKUPS}")


class GridMclParams(NamedTuple):
    """Traced numbers: changing them never recompiles."""

    motion: MotionParams
    """Odometry noise coefficients."""
    likelihood: LikelihoodParams
    """Endpoint model: sigma (m), z_hit, z_rand and the gain on the summed beams."""
    resample_threshold: Float[Array, ""]
    """Resample when ESS < resample_threshold * num_active (0: only to redraw particles)."""
    alpha_slow: Float[Array, ""]
    """Rate of the slow average of the mean likelihood (AMCL's recovery_alpha_slow); 0: no recovery."""
    alpha_fast: Float[Array, ""]
    """Rate of the fast average (AMCL's recovery_alpha_fast), > alpha_slow."""
    kld_epsilon: Float[Array, ""]
    """KLD sampling's bound on the K-L divergence between the sample and the posterior."""
    kld_z: Float[Array, ""]
    """The standard normal's upper 1 - delta quantile (2.326: delta = 0.01)."""


def make_params(motion: MotionParams | None = None, likelihood: LikelihoodParams | None = None,
                resample_threshold=0.5, alpha_slow=0.001, alpha_fast=0.1, kld_epsilon=0.05,
                kld_z=2.326) -> GridMclParams:
    """A :class:`GridMclParams` with float32 leaves; None picks the defaults: the odometry noise
    of :func:`jaxslam.localization.mcl.make_params`, and the endpoint model with sigma 0.2 m (AMCL's
    sigma_hit), z_hit 0.9, z_rand 0.1, gain 0.5."""
    f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    if likelihood is None:
        likelihood = LikelihoodParams(f32(0.2), f32(0.9), f32(0.1), f32(0.5))
    return GridMclParams(
        motion_params(0.05, 0.02, 0.05, 0.05, 0.01, 0.005) if motion is None else motion,
        likelihood, f32(resample_threshold), f32(alpha_slow), f32(alpha_fast), f32(kld_epsilon), f32(kld_z))


class LocalizationMap(NamedTuple):
    """A grid map as the filter reads it, in the local frame (:func:`prepare_map`)."""

    field: MapView
    """The likelihood field: squared cell distance (uint8) to the nearest occupied cell, ``FAR``
    beyond the field radius, on the local-frame grid (its spec static)."""
    free_xy: Float[Array, "F 2"]
    """Centres (m, local frame) of the free cells: where particles are drawn uniformly."""


def prepare_map(probability: Float[np.ndarray, "H W"], spec: GridSpec, field_radius: int = 12
                ) -> tuple[LocalizationMap, np.ndarray]:
    """The filter's map of an occupancy grid, and the (2,) float64 offset of its local frame.

    Args:
      probability: (H, W) occupancy probabilities, rows bottom-up (as :func:`jaxslam.io.maps.read_map`
        returns them): occupied above :data:`OCCUPIED_PROBABILITY`, free below :data:`FREE_PROBABILITY`.
      spec: the grid in the world frame.
      field_radius: cells (1..15) within which the field holds the distance to an occupied cell
        (12: 0.6 m, three of the default sigma, at 5 cm cells).

    Returns:
      ``(map, frame_offset)``: world = local + ``frame_offset`` (:func:`jaxslam.laserlog.to_world`).
    Raises ValueError for a map with no free or no occupied cell.
    """
    probability = np.asarray(probability)
    if probability.shape != spec.shape:
        raise ValueError(f"prepare_map: the grid is {probability.shape}, the spec says {spec.shape}")
    if not 1 <= field_radius <= 15:
        raise ValueError(f"prepare_map: field_radius must be in 1..15 (squared, it fits uint8), got {field_radius}")
    occupied = np.argwhere(probability > OCCUPIED_PROBABILITY)
    free = np.argwhere(probability < FREE_PROBABILITY)
    if occupied.shape[0] == 0 or free.shape[0] == 0:
        raise ValueError(f"the map has {occupied.shape[0]} occupied and {free.shape[0]} free cells: "
                         f"localization needs both")
    x0, y0, x1, y1 = (*spec.origin, spec.extent[1], spec.extent[3])
    frame_offset = frame_offset_of(np.array([[(x0 + x1) / 2, (y0 + y1) / 2, 0.0]]))
    local = GridSpec(spec.shape, spec.resolution, (spec.origin[0] - frame_offset[0], spec.origin[1] - frame_offset[1]))
    offsets, d2 = field_kernel(field_radius)
    splat = flat_index(local, jnp.asarray(occupied[:, None, :] + offsets[None], jnp.int32))
    hit_dist2 = splat_field(jnp.full((local.num_cells,), FAR, jnp.uint8), splat, jnp.asarray(d2))
    free_xy = cell_to_world(local, jnp.asarray(free, jnp.int32)).astype(jnp.float32)
    return LocalizationMap(MapView(local, hit_dist2.reshape(local.shape)), free_xy), frame_offset


class GridMclState(NamedTuple):
    """The particle set: the first ``num_active`` of ``max_particles`` slots."""

    poses: Float[Array, "N 3"]
    """Pose of each particle [x, y, theta] (m, m, rad), local frame; the inactive slots hold
    finite poses that weigh nothing."""
    log_weights: Float[Array, "N"]
    """Normalised log-weights of the active particles (logsumexp = 0); -inf in the inactive slots."""
    num_active: Int[Array, ""]
    """The number of particles: slots 0 .. num_active - 1."""
    log_w_slow: Float[Array, ""]
    """log of the slow average of the mean per-beam likelihood (-inf before the first scan with a
    return; that scan's value starts both averages)."""
    log_w_fast: Float[Array, ""]
    """log of the fast average of the mean per-beam likelihood."""
    step: Int[Array, ""]
    """Steps taken since init."""


class GridMclInfo(NamedTuple):
    """Diagnostics of one step (stacked over time by :func:`filter`)."""

    mcl: MclInfo
    """The weight update and resampling as MCL reports them: ESS, whether resampled, the weighted
    mean pose (m, m, rad; local frame) and covariance, log-evidence (nats), degenerate, and the
    ancestors (-1 for a particle redrawn over the free cells)."""
    spread: Float[Array, ""]
    """RMS distance (m) of the particles from the mean position: sqrt(var x + var y)."""
    num_active: Int[Array, ""]
    """The particle count after the step (its resampling's KLD count)."""
    redrawn_share: Float[Array, ""]
    """The share of the resampled particles redrawn uniformly over the free cells, 1 - w_fast / w_slow
    clipped to [0, 1] (0: no recovery this step)."""


def uniform_free_poses(key: PRNGKeyArray, grid: LocalizationMap, num: int) -> Float[Array, "num 3"]:
    """``num`` poses uniform over the free cells (uniform inside a cell) and the heading circle."""
    k_cell, k_xy, k_theta = jax.random.split(key, 3)
    cell = jax.random.randint(k_cell, (num,), 0, grid.free_xy.shape[0])
    jitter = (jax.random.uniform(k_xy, (num, 2)) - 0.5) * grid.field.resolution
    theta = jax.random.uniform(k_theta, (num, 1), minval=-jnp.pi, maxval=jnp.pi)
    return jnp.concatenate([grid.free_xy[cell] + jitter, theta], axis=1)


def _state(poses: Float[Array, "N 3"]) -> GridMclState:
    n = poses.shape[0]
    ninf = jnp.asarray(-jnp.inf, jnp.float32)
    return GridMclState(poses.astype(jnp.float32), jnp.full((n,), -jnp.log(n), jnp.float32),
                        jnp.asarray(n, jnp.int32), ninf, ninf, jnp.zeros((), jnp.int32))


def init_tracked(key: PRNGKeyArray, pose: Float[Array, "3"], pose_std: Float[Array, "3"],
                 config: GridMclConfig) -> GridMclState:
    """``max_particles`` particles from a Gaussian around ``pose`` (local frame) with per-axis
    std ``pose_std`` (m, m, rad)."""
    noise = jax.random.normal(key, (config.max_particles, 3)) * jnp.asarray(pose_std, jnp.float32)
    poses = jnp.asarray(pose, jnp.float32) + noise
    return _state(poses.at[:, 2].set(wrap_angle(poses[:, 2])))


def init_global(key: PRNGKeyArray, grid: LocalizationMap, config: GridMclConfig) -> GridMclState:
    """``max_particles`` particles uniform over the map's free cells and every heading."""
    return _state(uniform_free_poses(key, grid, config.max_particles))


def scan_log_likelihoods(grid: LocalizationMap, poses: Float[Array, "N 3"], ranges: Float[Array, "B"],
                         sensor: SensorSpec, params: GridMclParams, config: GridMclConfig) -> Float[Array, "N"]:
    """``gain * sum_b log(z_hit exp(-d_b^2 / (2 sigma^2)) + z_rand)`` of one scan at N poses (nats;
    every ``beam_stride``-th of the B beams; :data:`jaxslam.sensor_model.ENDPOINT`)."""
    lik_sensor, lik_ranges = subsample_beams(sensor, ranges, config.beam_stride)
    return ENDPOINT.log_likelihoods_fn(grid.field, poses, lik_ranges, lik_sensor, params.likelihood, config.lookup)


def occupied_bins(poses: Float[Array, "N 3"], grid_spec: GridSpec, config: GridMclConfig) -> Int[Array, "N"]:
    """k(n) for n = 1 .. N: the number of distinct KLD histogram bins (``bin_xy`` x ``bin_xy`` x
    ``bin_theta``) the first n poses occupy (positions clipped to a bin beyond the map)."""
    x0, x1, y0, y1 = grid_spec.extent
    nx = int(math.ceil((x1 - x0) / config.bin_xy)) + 2
    ny = int(math.ceil((y1 - y0) / config.bin_xy)) + 2
    nt = int(math.ceil(2 * math.pi / config.bin_theta))
    ix = jnp.clip(jnp.floor((poses[:, 0] - x0) / config.bin_xy) + 1, 0, nx - 1).astype(jnp.int32)
    iy = jnp.clip(jnp.floor((poses[:, 1] - y0) / config.bin_xy) + 1, 0, ny - 1).astype(jnp.int32)
    it = jnp.clip(jnp.floor((wrap_angle(poses[:, 2]) + jnp.pi) / config.bin_theta), 0, nt - 1).astype(jnp.int32)
    bins = (ix * ny + iy) * nt + it
    order = jnp.argsort(bins, stable=True)  # within a bin, the earliest pose first
    sorted_bins = bins[order]
    first = jnp.concatenate([jnp.ones((1,), bool), sorted_bins[1:] != sorted_bins[:-1]])
    is_first = jnp.zeros(bins.shape, jnp.int32).at[order].set(first.astype(jnp.int32))
    return jnp.cumsum(is_first)


def kld_bound(k: Int[Array, "..."], epsilon: Float[Array, ""], z: Float[Array, ""]) -> Float[Array, "..."]:
    """Fox 2003's sample count for k occupied bins: ``(k - 1) / (2 epsilon) (1 - 2 / (9 (k - 1))
    + sqrt(2 / (9 (k - 1))) z)^3`` (Wilson-Hilferty's chi-square quantile); 1 for k <= 1."""
    km1 = jnp.maximum(k.astype(jnp.float32) - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    bound = km1 / (2.0 * epsilon) * (1.0 - a + jnp.sqrt(a) * z) ** 3
    return jnp.where(k > 1, bound, 1.0)


def kld_count(poses: Float[Array, "N 3"], grid_spec: GridSpec, params: GridMclParams,
              config: GridMclConfig) -> Int[Array, ""]:
    """How many of ``poses`` (a random-order draw) to keep: Fox's stopping rule, the first n with
    ``n >= max(kld_bound(k(n)), min_particles)`` (:func:`occupied_bins`); all N if none."""
    n = jnp.arange(1, poses.shape[0] + 1)
    bound = kld_bound(occupied_bins(poses, grid_spec, config), params.kld_epsilon, params.kld_z)
    enough = n >= jnp.maximum(bound, config.min_particles)
    return jnp.where(jnp.any(enough), jnp.argmax(enough) + 1, poses.shape[0]).astype(jnp.int32)


def _exp_average(log_avg, log_value, alpha):
    """log of ``avg + alpha (value - avg)``, in logs (AMCL's w_slow / w_fast update); the value
    itself when there is no average yet (``log_avg`` -inf)."""
    return jnp.where(jnp.isfinite(log_avg), jnp.logaddexp(jnp.log1p(-alpha) + log_avg, jnp.log(alpha) + log_value),
                     log_value)


def step(key: PRNGKeyArray, state: GridMclState, inputs: ScanInputs, grid: LocalizationMap,
         sensor: SensorSpec, params: GridMclParams, config: GridMclConfig) -> tuple[GridMclState, GridMclInfo]:
    """One step: move every particle, weigh it by the scan, update the recovery averages, and
    resample (KLD count, a share redrawn over the free cells) when the ESS is low or particles
    are to be redrawn.

    Args:
      key: PRNG key (split into motion, resampling, order and redraw keys).
      state: the particle set at the previous scan.
      inputs: the odometry motion since the previous scan (robot frame) and this scan's (B,) ranges (m).
      grid: the map (:func:`prepare_map`).
      sensor: the laser.
      params: traced numbers.
      config: static settings.
    """
    n_max = config.max_particles
    k_motion, k_resample, k_order, k_redraw, k_poses = jax.random.split(key, 5)
    active = jnp.arange(n_max) < state.num_active
    poses = motion_model.sample(k_motion, state.poses, inputs.motion, params.motion)
    log_lik = jnp.where(active, scan_log_likelihoods(grid, poses, inputs.ranges, sensor, params, config), -jnp.inf)
    # Weigh, normalise and measure only (threshold 0): the resampling below keeps the count.
    update = particle_filter.reweight_and_resample(k_resample, poses, state.log_weights, log_lik,
                                                   jnp.zeros((), jnp.float32), "systematic")
    uniform = jnp.where(active, -jnp.log(state.num_active.astype(jnp.float32)), -jnp.inf)
    log_weights = jnp.where(update.degenerate, uniform, update.log_weights)

    # Recovery: the weighted geometric mean of the per-beam likelihood, averaged slow and fast.
    lik_sensor, lik_ranges = subsample_beams(sensor, inputs.ranges, config.beam_stride)
    counted = jnp.sum(valid_returns(lik_ranges, lik_sensor)).astype(jnp.float32)
    informative = (counted > 0) & ~update.degenerate
    log_w_avg = update.log_evidence / jnp.maximum(params.likelihood.gain * counted, 1e-12)
    recover = params.alpha_slow > 0
    log_w_slow = jnp.where(informative & recover, _exp_average(state.log_w_slow, log_w_avg, params.alpha_slow),
                           state.log_w_slow)
    log_w_fast = jnp.where(informative & recover, _exp_average(state.log_w_fast, log_w_avg, params.alpha_fast),
                           state.log_w_fast)
    share = jnp.where(recover & jnp.isfinite(log_w_slow) & jnp.isfinite(log_w_fast),
                      jnp.clip(1.0 - jnp.exp(log_w_fast - log_w_slow), 0.0, 1.0), 0.0)

    resample = (update.ess < params.resample_threshold * state.num_active) | (share > 0)

    def resampled(_):
        # N systematic draws in random order, a share of them redrawn over the free cells; KLD
        # keeps the first n (redrawn particles fill bins: recovery raises the count, as AMCL's).
        ancestors = jax.random.permutation(k_order, resampling.systematic(k_resample, log_weights, n_max))
        redraw = jax.random.uniform(k_redraw, (n_max,)) < share
        drawn = jnp.where(redraw[:, None], uniform_free_poses(k_poses, grid, n_max), poses[ancestors])
        count = kld_count(drawn, grid.field.spec, params, config) if config.kld else jnp.asarray(n_max, jnp.int32)
        kept = jnp.arange(n_max) < count
        return (drawn, jnp.where(kept, -jnp.log(count.astype(jnp.float32)), -jnp.inf), count,
                jnp.where(redraw, -1, ancestors))

    new_poses, new_log_weights, count, ancestors = jax.lax.cond(
        resample, resampled, lambda _: (poses, log_weights, state.num_active, jnp.arange(n_max, dtype=jnp.int32)),
        None)
    cov = update.pose_covariance
    weighed = MclInfo.of(update)._replace(resampled=resample, ancestors=ancestors)
    info = GridMclInfo(weighed, jnp.sqrt(jnp.maximum(cov[0, 0] + cov[1, 1], 0.0)), count, share)
    return GridMclState(new_poses, new_log_weights, count, log_w_slow, log_w_fast, state.step + 1), info


step_jit = jax.jit(step, static_argnames=("config",))
""":func:`step`, jitted (``config`` static)."""


@functools.partial(jax.jit, static_argnames=("config",))
def filter(key: PRNGKeyArray, state: GridMclState, inputs: ScanInputs, grid: LocalizationMap,
           sensor: SensorSpec, params: GridMclParams, config: GridMclConfig) -> particle_filter.FilterOutput:
    """Grid MCL over a whole log as one pure function: :func:`step` over (T, ...) stacked
    ``inputs`` (:func:`jaxslam.localization.mcl.log_inputs`) in one ``lax.scan``.

    Returns:
      ``FilterOutput(state, info, marginal_loglik)``: the final particles, the (T, ...) stacked
      :class:`GridMclInfo` and the sum of the steps' ``log_evidence`` (nats).
    """
    return particle_filter.scan_filter(
        lambda k, s, inp: step(k, s, inp, grid, sensor, params, config), key, state, inputs,
        lambda info: info.mcl.log_evidence)


def pose_in_map(grid_spec: GridSpec, pose) -> bool:
    """Whether the (x, y) of ``pose`` (m, float64) lies inside the grid (in the grid's frame)."""
    x0, x1, y0, y1 = grid_spec.extent
    x, y = (float(v) for v in np.asarray(pose, np.float64)[:2])
    return x0 <= x < x1 and y0 <= y < y1
