"""Simulated laser scans and odometry in a :class:`~jaxslam.sim.world.SegmentWorld`.

Scans are exact ray casts (:func:`jaxslam.segment_map.expected_ranges`) plus Gaussian range
noise. Odometry is the true path with GMapping-style noise
(:func:`jaxslam.motion.noise_std`) added to every true relative motion, so it
drifts like a real robot's and the filter's motion model is nearly the generating model
(:func:`noisy_odometry` says where they differ).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from jaxslam.driver import run_in_chunks
from jaxslam.geometry import between, chain_np
from jaxslam.laser import SensorSpec
from jaxslam.laserlog import LaserLog
from jaxslam.motion import MotionParams, noise_std
from jaxslam.segment_map import expected_ranges
from jaxslam.sim.world import SegmentWorld

# Scans cast per vmapped batch: bounds the (batch, B, M) intermediates of the ray
# caster (~14 MB each at B=180, M=100) while keeping enough work per batch.
_SCAN_BATCH = 128


def _scan(key, segments, pose, sensor, range_noise_std, max_range, active):
    """One noisy scan; the body that :func:`simulate_scan` and :func:`simulate_scans` share."""
    exact, hit = expected_ranges(segments, pose, sensor, active, max_range)
    noisy = exact + range_noise_std * jax.random.normal(key, exact.shape, exact.dtype)
    noisy = jnp.clip(noisy, 0.0, sensor.range_max)
    # A beam that hits nothing reads exactly range_max: the log's "no return".
    return jnp.where(hit >= 0, noisy, sensor.range_max)


def _max_range(sensor: SensorSpec, max_range) -> Float[Array, ""]:
    if max_range is None:
        return sensor.range_max
    return jnp.minimum(jnp.asarray(max_range, jnp.float32), sensor.range_max)


def simulate_scan(
    key: PRNGKeyArray,
    world: SegmentWorld,
    pose: Float[Array, "3"],
    sensor: SensorSpec,
    range_noise_std: float,
    max_range: float | None = None,
    active: Bool[Array, "M"] | None = None,
) -> Float[Array, "B"]:
    """One simulated laser scan from the robot at ``pose``.

    Args:
      key: PRNG key for the range noise.
      world: the segments to cast against.
      pose: (3,) robot pose [x, y, theta] (m, m, rad); the laser sits at
        ``sensor.laser_pose`` on the robot.
      sensor: beam angles and range limits.
      range_noise_std: std (m) of the zero-mean Gaussian noise added to every return.
      max_range: distance (m) up to which obstacles are detected; defaults to, and is
        capped at, ``sensor.range_max``.
      active: optional (M,) bool mask; inactive segments (open doors) are transparent.

    Returns:
      (B,) float32 ranges (m). A beam that hits a segment within ``max_range`` reads the
      true distance plus noise, clipped to [0, range_max] (so a noisy return just short of
      range_max can read as "no return", as on a real laser); a beam that hits nothing
      reads exactly ``sensor.range_max``.
    """
    segments = jnp.asarray(world.segments)
    active = jnp.ones(segments.shape[0], dtype=bool) if active is None else jnp.asarray(active)
    return _batch_jit(key[None], jnp.asarray(segments), jnp.asarray(pose, jnp.float32)[None], sensor,
                      jnp.float32(range_noise_std), _max_range(sensor, max_range), active[None])[0]


@jax.jit
def _batch_jit(keys, segments, poses, sensor, range_noise_std, max_range, active):
    """A batch of scans: (S,) keys, (S, 3) poses, (S, M) masks -> (S, B) ranges."""
    scan = jax.vmap(_scan, in_axes=(0, None, 0, None, None, None, 0))
    return scan(keys, segments, poses, sensor, range_noise_std, max_range, active)


def simulate_scans(
    key: PRNGKeyArray,
    world: SegmentWorld,
    poses: Float[Array, "T 3"],
    sensor: SensorSpec,
    range_noise_std: float,
    max_range: float | None = None,
    active: Bool[Array, "M"] | Bool[Array, "T M"] | None = None,
) -> np.ndarray:
    """Scans from every pose of a path, vmapped over batches of scans.

    Row ``i`` is ``simulate_scan(jax.random.fold_in(key, i), world, poses[i], ...)``, so a
    log's first scans do not depend on its length.
    ``active`` is None, one (M,) mask for all scans, or a (T, M) mask per scan (doors
    that open and close). Other arguments as in :func:`simulate_scan`.

    Returns:
      (T, B) float32 NumPy ranges (m).
    """
    poses = np.asarray(poses, np.float32).reshape(-1, 3)
    num_scans = poses.shape[0]
    num_segments = world.num_segments
    active = np.ones(num_segments, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    if active.shape not in ((num_segments,), (num_scans, num_segments)):
        raise ValueError(f"simulate_scans: active has shape {active.shape}, expected "
                         f"({num_scans}, {num_segments}) or ({num_segments},)")
    active = np.broadcast_to(active, (num_scans, num_segments))
    # Fixed-size batches, the last one padded: one compilation per world and sensor whatever
    # the path's length, and bounded memory for long logs.
    segments = jnp.asarray(world.segments)
    noise, reach = jnp.float32(range_noise_std), _max_range(sensor, max_range)
    indices = np.arange(num_scans, dtype=np.uint32)

    def chunk_fn(_, xs, valid):
        batch_indices, batch_poses, batch_active = xs
        keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, batch_indices)
        return None, _batch_jit(keys, segments, batch_poses, sensor, noise, reach, batch_active)

    return run_in_chunks(chunk_fn, (indices, poses, active), num_scans, _SCAN_BATCH).outputs


@jax.jit
def _noisy_motions(key, true_poses, params):
    """(T-1, 3) true relative motions plus their noise."""
    motions = between(true_poses[:-1], true_poses[1:])
    noise = jax.random.normal(key, motions.shape, motions.dtype) * noise_std(motions, params)
    return motions + noise


def noisy_odometry(key: PRNGKeyArray, true_poses, params: MotionParams) -> np.ndarray:
    """Odometry that drifts: the true relative motions plus GMapping-style noise, composed.

    For each step i, the true motion ``u_i = between(x_i, x_{i+1})`` (robot frame of x_i) gets
    independent Gaussian noise with std ``motion.noise_std(u_i, params)`` on [dx, dy, dtheta],
    and the noisy motions are composed from the first true pose. This is nearly the generative
    form of :func:`jaxslam.motion.sample`, which takes the std at the odometry reading rather
    than at the true motion: on a nearly straight step the reading's sideways and turning parts
    are pure noise, so the model's std is the wider, and on the simulated office the model's own
    optimum for the known true path (:func:`jaxslam.motion.path_log_density`) is about 0.84x the
    simulated ``str`` and 1.32x ``stt`` (docs/design.md, "Tempering and learning"). A
    filter that composes k simulation steps into one update (update selection) over-estimates
    the noise by about sqrt(k), since independent per-step errors add in variance while the
    model's std adds linearly.

    Args:
      key: PRNG key for the motion noise.
      true_poses: (T, 3) true poses [x, y, theta] (m, m, rad).
      params: noise coefficients; all zeros gives the true path back.

    Returns:
      (T, 3) float64 odometry poses; row 0 is the first true pose.
    """
    true_poses = np.asarray(true_poses, dtype=np.float64).reshape(-1, 3)
    noisy = np.asarray(_noisy_motions(key, true_poses.astype(np.float32), params), dtype=np.float64)
    return chain_np(true_poses[0], noisy)


def simulate_log(
    key: PRNGKeyArray,
    world: SegmentWorld,
    true_poses,
    sensor: SensorSpec,
    motion_params: MotionParams,
    range_noise_std: float,
    dt: float = 0.1,
    max_range: float | None = None,
    active=None,
    source: str = "<simulated>",
) -> LaserLog:
    """A complete simulated :class:`~jaxslam.laserlog.LaserLog` along a true path.

    Args:
      key: PRNG key; split into one key for the scans and one for the odometry.
      world: the segments the laser sees.
      true_poses: (T, 3) true robot poses (m, m, rad), one per scan.
      sensor: the laser.
      motion_params: odometry noise (see :func:`noisy_odometry`).
      range_noise_std: range noise std (m) (see :func:`simulate_scan`).
      dt: seconds between scans; timestamps are ``i * dt``.
      max_range, active: as in :func:`simulate_scans`.
      source: the log's name in error messages.

    Returns:
      The log: timestamps (T,), noisy odometry (T, 3), ranges (T, B), ground_truth (T, 3).
    """
    true_poses = np.asarray(true_poses, dtype=np.float64).reshape(-1, 3)
    scan_key, odometry_key = jax.random.split(key)
    ranges = simulate_scans(scan_key, world, true_poses, sensor, range_noise_std, max_range, active)
    odometry = noisy_odometry(odometry_key, true_poses, motion_params)
    timestamps = np.arange(true_poses.shape[0], dtype=np.float64) * dt
    return LaserLog(timestamps, odometry, np.asarray(ranges), sensor, true_poses, source)
