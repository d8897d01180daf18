"""Monte Carlo localization on a known segment map, with the beam model by ray casting.

Each of N particles is a pose with a log-weight. A step moves every particle by
the odometry motion model (:func:`jaxslam.motion.sample`), casts the scan's beams
from it into the map (:func:`jaxslam.segment_map.expected_ranges`, exact), scores the
measured ranges with the beam model (:mod:`jaxslam.localization.beam_model`), and
reweighs and resamples selectively (ESS below ``resample_threshold * N``) with the core
shared by every filter (:func:`jaxslam.particle_filter.reweight_and_resample`).

Shape of the code: a static :class:`MclConfig` (particle count, beam stride,
resampler; changing it recompiles), traced :class:`MclParams`, named
:class:`MclState` / :class:`MclInfo`; ``init_tracked`` / ``init_global`` /
``step`` / ``filter`` are pure, and ``filter`` is one ``lax.scan`` over the scans.
MCL serves localization only (a known map); the door filter in
:mod:`jaxslam.localization.doors` builds on it.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import motion as motion_model
from jaxslam import particle_filter, resampling
from jaxslam.geometry import between, wrap_angle
from jaxslam.laser import SensorSpec, subsample_beams
from jaxslam.laserlog import LaserLog, frame_offset_of, to_local
from jaxslam.localization.beam_model import BeamModelParams, beam_model_log_likelihood, make_beam_model_params
from jaxslam.motion import MotionParams, motion_params
from jaxslam.segment_map import expected_ranges


@dataclasses.dataclass(frozen=True)
class MclConfig:
    """Static settings (shapes and code paths). Hashable; changing it recompiles."""

    num_particles: int = 1000
    """N, the number of particles."""
    beam_stride: int = 1
    """Use every ``beam_stride``-th beam of a scan in the likelihood."""
    resampler: str = "systematic"
    """Resampling scheme: one of :data:`jaxslam.resampling.RESAMPLERS`."""

    def __post_init__(self):
        if self.num_particles < 1:
            raise ValueError("MclConfig: num_particles must be >= 1")
        if self.beam_stride < 1:
            raise ValueError("MclConfig: beam_stride must be >= 1")
        if self.resampler not in resampling.RESAMPLERS:
            raise ValueError(f"MclConfig: resampler must be one of {sorted(resampling.RESAMPLERS)}")


class MclParams(NamedTuple):
    """Traced numbers: changing them never recompiles; they can be differentiated."""

    motion: MotionParams
    """Odometry noise coefficients."""
    beam: BeamModelParams
    """Beam model mixture weights, sigma_hit (m), lambda_short (1/m)."""
    likelihood_gain: Float[Array, ""]
    """Multiplier of every beam's log-likelihood (< 1 tempers the over-confidence of
    treating neighbouring beams as independent)."""
    resample_threshold: Float[Array, ""]
    """Resample when ESS < resample_threshold * N (0: never, 1: every step)."""


def make_params(motion: MotionParams | None = None, beam: BeamModelParams | None = None,
                likelihood_gain=0.5, resample_threshold=0.5) -> MclParams:
    """An :class:`MclParams` with float32 leaves; None picks the defaults (the assumed odometry
    noise ``motion_params(0.05, 0.02, 0.05, 0.05, 0.01, 0.005)``)."""
    return MclParams(
        motion_params(0.05, 0.02, 0.05, 0.05, 0.01, 0.005) if motion is None else motion,
        make_beam_model_params() if beam is None else beam,
        jnp.asarray(likelihood_gain, jnp.float32),
        jnp.asarray(resample_threshold, jnp.float32),
    )


class MclState(NamedTuple):
    """The particle set."""

    poses: Float[Array, "N 3"]
    """Pose of each particle [x, y, theta] (m, m, rad)."""
    log_weights: Float[Array, "N"]
    """Normalised log-weights (logsumexp = 0)."""
    step: Int[Array, ""]
    """Steps taken since init."""


class MclInfo(NamedTuple):
    """Diagnostics of one step (stacked over time by :func:`filter`)."""

    ess: Float[Array, ""]
    """Effective sample size after the weight update, before resampling."""
    resampled: Bool[Array, ""]
    """Whether the particles were resampled at the end of the step."""
    mean_pose: Float[Array, "3"]
    """Weighted mean pose after the weight update (circular mean in theta)."""
    pose_covariance: Float[Array, "3 3"]
    """Weighted covariance of the poses (theta residuals wrapped)."""
    log_evidence: Float[Array, ""]
    """log sum_i w_{t-1,i} p(z_t | x_t,i): the log-likelihood increment of the step (-inf
    when ``degenerate``)."""
    degenerate: Bool[Array, ""]
    """Every particle's weight was -inf (or NaN) this step; the weights were reset to uniform."""
    ancestors: Int[Array, "N"]
    """After the step, particle i descends from moved particle ``ancestors[i]``."""

    @classmethod
    def of(cls, update: particle_filter.WeightUpdate) -> "MclInfo":
        """The info of a :class:`~jaxslam.particle_filter.WeightUpdate`."""
        return cls(update.ess, update.resampled, update.mean_pose, update.pose_covariance, update.log_evidence,
                   update.degenerate, update.ancestors)


class ScanInputs(NamedTuple):
    """What one step consumes (stacked (T, ...) for :func:`filter`)."""

    motion: Float[Array, "3"]
    """Odometry motion [dx, dy, dtheta] since the previous scan, in the previous robot frame."""
    ranges: Float[Array, "B"]
    """Measured ranges (m)."""


def init_tracked(key: PRNGKeyArray, pose: Float[Array, "3"], pose_std: Float[Array, "3"],
                 config: MclConfig) -> MclState:
    """Particles drawn from a Gaussian around ``pose`` with per-axis std ``pose_std`` (m, m, rad)."""
    pose = jnp.asarray(pose, jnp.float32)
    noise = jax.random.normal(key, (config.num_particles, 3)) * jnp.asarray(pose_std, jnp.float32)
    poses = pose + noise
    poses = poses.at[:, 2].set(wrap_angle(poses[:, 2]))
    return _uniform_state(poses)


def init_global(key: PRNGKeyArray, regions: Float[Array, "R 4"], config: MclConfig,
                heading_range: tuple[float, float] = (-np.pi, np.pi)) -> MclState:
    """Particles uniform over a union of axis-aligned boxes and a heading interval.

    Args:
      key: PRNG key.
      regions: (R, 4) boxes [xmin, ymin, xmax, ymax] (m) of free space (or of the region
        the robot is known to be in); a box is chosen with probability proportional to its
        area, so that the density is uniform over the union (boxes should not overlap).
      config: the particle count.
      heading_range: (lo, hi) headings (rad), uniform; the full circle by default.
    """
    regions = jnp.asarray(regions, jnp.float32).reshape(-1, 4)
    area = (regions[:, 2] - regions[:, 0]) * (regions[:, 3] - regions[:, 1])
    k_box, k_xy, k_theta = jax.random.split(key, 3)
    n = config.num_particles
    box = jax.random.categorical(k_box, jnp.log(area), shape=(n,))
    u = jax.random.uniform(k_xy, (n, 2))
    lo, hi = regions[box, :2], regions[box, 2:]
    xy = lo + u * (hi - lo)
    theta = jax.random.uniform(k_theta, (n,), minval=heading_range[0], maxval=heading_range[1])
    return _uniform_state(jnp.concatenate([xy, wrap_angle(theta)[:, None]], axis=1))


def _uniform_state(poses):
    n = poses.shape[0]
    return MclState(poses.astype(jnp.float32), jnp.full((n,), -jnp.log(n), jnp.float32),
                    jnp.zeros((), jnp.int32))


def scan_log_likelihood(segments: Float[Array, "M 4"], pose: Float[Array, "3"], ranges: Float[Array, "B"],
                        sensor: SensorSpec, params: MclParams, active: Bool[Array, "M"] | None = None,
                        beam_stride: int = 1) -> Float[Array, ""]:
    """``gain * sum_b log p(z_b | x, map)`` of one scan (all B beams given; the stride is applied here)."""
    lik_sensor, lik_ranges = subsample_beams(sensor, ranges, beam_stride)
    expected, _ = expected_ranges(segments, pose, lik_sensor, active)
    per_beam = beam_model_log_likelihood(expected, lik_ranges, sensor.range_max, params.beam)
    return params.likelihood_gain * jnp.sum(per_beam)


def step(key: PRNGKeyArray, state: MclState, inputs: ScanInputs, segments: Float[Array, "M 4"],
         sensor: SensorSpec, params: MclParams, config: MclConfig,
         active: Bool[Array, "M"] | None = None) -> tuple[MclState, MclInfo]:
    """One MCL step: move every particle, weigh it by the scan, resample if the ESS is low.

    Args:
      key: PRNG key (split into motion and resampling keys).
      state: the particle set at the previous scan.
      inputs: the odometry motion since the previous scan and this scan's (B,) ranges.
      segments: (M, 4) map segments (m).
      sensor: the laser.
      params: traced numbers.
      config: static settings.
      active: optional (M,) mask of the segments present (transparent when False).
    """
    k_motion, k_resample = jax.random.split(key)
    poses = motion_model.sample(k_motion, state.poses, inputs.motion, params.motion)
    log_lik = jax.vmap(lambda p: scan_log_likelihood(segments, p, inputs.ranges, sensor, params, active,
                                                     config.beam_stride))(poses)
    update = particle_filter.reweight_and_resample(k_resample, poses, state.log_weights, log_lik,
                                                   params.resample_threshold, config.resampler)
    return MclState(poses[update.ancestors], update.new_log_weights, state.step + 1), MclInfo.of(update)


step_jit = jax.jit(step, static_argnames=("config",))
""":func:`step`, jitted (``config`` static)."""


@functools.partial(jax.jit, static_argnames=("config",))
def filter(key: PRNGKeyArray, state: MclState, inputs: ScanInputs, segments: Float[Array, "M 4"],
           sensor: SensorSpec, params: MclParams, config: MclConfig,
           active: Bool[Array, "M"] | None = None) -> particle_filter.FilterOutput:
    """MCL over a whole log as one pure function: :func:`step` over (T, ...) stacked ``inputs``
    in one ``lax.scan`` (per-step keys split from ``key``). Jittable, vmappable over keys,
    params and same-length logs; differentiable (score gradients through resampling, each step
    rematerialised under reverse mode).

    Returns:
      ``FilterOutput(state, info, marginal_loglik)``: the final particles, the (T, ...) stacked
      :class:`MclInfo` and the sum of the steps' ``log_evidence``.
    """
    return particle_filter.scan_filter(
        lambda k, s, inp: step(k, s, inp, segments, sensor, params, config, active), key, state, inputs,
        lambda info: info.log_evidence)


def log_inputs(log: LaserLog) -> ScanInputs:
    """The (T, ...) inputs of a log: odometry motions (row 0 is zero: the first scan is
    weighed at the initial particles) and ranges, as float32 JAX arrays."""
    odom = to_local(log.odometry, frame_offset_of(log.odometry))  # float32 below: in the local frame
    motions = np.zeros_like(odom)
    motions[1:] = np.asarray(between(odom[:-1], odom[1:]), np.float64)
    return ScanInputs(jnp.asarray(motions, jnp.float32), jnp.asarray(log.ranges, jnp.float32))
