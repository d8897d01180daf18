"""SE(2) poses as ``(..., 3)`` arrays ``[x, y, theta]``.

x and y are in metres, theta in radians wrapped to (-pi, pi]. Every function
broadcasts over leading axes and works on both JAX and NumPy inputs (it uses
``jax.numpy``; NumPy callers get JAX arrays back).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def wrap_angle(theta: Float[Array, "..."]) -> Float[Array, "..."]:
    """Wrap angles (rad) to the half-open interval (-pi, pi]."""
    return jnp.pi - jnp.mod(jnp.pi - theta, 2.0 * jnp.pi)


def wrap_angle_np(theta) -> np.ndarray:
    """:func:`wrap_angle` on the host in float64 NumPy (the JAX version computes in float32).

    Angles already in (-pi, pi] are returned bit for bit. For readers, writers, the simulator's
    path builders and other host code where float32 would cost precision.
    """
    theta = np.asarray(theta, np.float64)
    inside = (theta > -np.pi) & (theta <= np.pi)
    return np.where(inside, theta, np.pi - np.mod(np.pi - theta, 2.0 * np.pi))


def between_np(a, b) -> np.ndarray:
    """:func:`between` on the host in float64 NumPy, for host code (metrics, trajectory
    smoothing) where poses far from the origin would lose precision in float32."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle_np(b[..., 2] - a[..., 2])], axis=-1)


def compose_np(a, b) -> np.ndarray:
    """:func:`compose` on the host in float64 NumPy (``a (+) b``, heading wrapped), for host
    code (log writers, odometry edits) where poses far from the origin would lose precision in
    float32."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle_np(a[..., 2] + b[..., 2])], axis=-1)


def rotation_np(theta) -> np.ndarray:
    """(..., 2, 2) float64 rotation matrices by ``theta`` (rad, any shape): a vector in the turned
    frame, times it, is the same vector in the frame it was turned from."""
    c, s = np.cos(np.asarray(theta, np.float64)), np.sin(np.asarray(theta, np.float64))
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def between_jacobians_np(a, b) -> tuple[np.ndarray, np.ndarray]:
    """The Jacobians (..., 3, 3) float64 of :func:`between_np` ``(a, b)`` with respect to ``a`` and
    to ``b`` ((..., 3) poses): the pose graph's edges and the refinement's odometry steps."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    jac_a = np.zeros(a.shape + (3,))
    jac_a[..., 0, 0], jac_a[..., 0, 1], jac_a[..., 0, 2] = -c, -s, -s * dx + c * dy
    jac_a[..., 1, 0], jac_a[..., 1, 1], jac_a[..., 1, 2] = s, -c, -c * dx - s * dy
    jac_a[..., 2, 2] = -1.0
    jac_b = np.zeros(a.shape + (3,))
    jac_b[..., 0, 0], jac_b[..., 0, 1], jac_b[..., 1, 0], jac_b[..., 1, 1], jac_b[..., 2, 2] = c, s, -s, c, 1.0
    return jac_a, jac_b


def chain_np(start, steps) -> np.ndarray:
    """(T + 1, 3) float64 poses ``x_0 = start`` (3,), ``x_{i+1} = x_i (+) steps[i]`` ((T, 3)
    relative poses), composed in closed form with no loop: the heading is the running sum of the
    rotations, and each translation is turned by the heading of the pose it starts from."""
    start, steps = np.asarray(start, np.float64), np.asarray(steps, np.float64).reshape(-1, 3)
    headings = start[2] + np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    c, s = np.cos(headings[:-1]), np.sin(headings[:-1])
    turned = np.stack([c * steps[:, 0] - s * steps[:, 1], s * steps[:, 0] + c * steps[:, 1]], axis=-1)
    xy = start[:2] + np.concatenate([np.zeros((1, 2)), np.cumsum(turned, axis=0)])
    return np.concatenate([xy, wrap_angle_np(headings)[:, None]], axis=1)


def make_pose(x, y, theta) -> Float[Array, "... 3"]:
    """Stack x, y (m) and theta (rad, wrapped) into a pose array."""
    x, y, theta = jnp.broadcast_arrays(jnp.asarray(x), jnp.asarray(y), jnp.asarray(theta))
    return jnp.stack([x, y, wrap_angle(theta)], axis=-1)


def compose(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """``a (+) b``: the pose ``b``, given in the frame of ``a``, in the frame ``a`` lives in."""
    c, s = jnp.cos(a[..., 2]), jnp.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return jnp.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """The pose ``a^-1`` with ``compose(a, inverse(a)) == 0``."""
    c, s = jnp.cos(a[..., 2]), jnp.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return jnp.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def between(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """``a^-1 (+) b``: the pose ``b`` expressed in the frame of ``a`` (relative motion a -> b)."""
    c, s = jnp.cos(a[..., 2]), jnp.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    return jnp.stack(
        [c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1
    )


def transform_points(pose: Float[Array, "... 3"], points: Float[Array, "... P 2"]) -> Float[Array, "... P 2"]:
    """Map points (m) given in the frame of ``pose`` into the frame ``pose`` lives in."""
    c, s = jnp.cos(pose[..., 2])[..., None], jnp.sin(pose[..., 2])[..., None]
    px, py = points[..., 0], points[..., 1]
    x = pose[..., 0][..., None] + c * px - s * py
    y = pose[..., 1][..., None] + s * px + c * py
    return jnp.stack([x, y], axis=-1)


def interpolate(a: Float[Array, "... 3"], b: Float[Array, "... 3"], fraction) -> Float[Array, "... 3"]:
    """Pose a fraction (0 at ``a``, 1 at ``b``) of the way along the relative motion ``a -> b``.

    The translation and the (wrapped) rotation of ``between(a, b)`` are scaled linearly;
    used to read odometry at a scan's timestamp between two odometry messages.
    """
    fraction = jnp.asarray(fraction)[..., None]
    return compose(a, between(a, b) * fraction)


def pose_errors(estimated: Float[Array, "... 3"], truth: Float[Array, "... 3"]
                ) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """Position error (m) and absolute heading error (rad, wrapped) of poses against the truth."""
    position = jnp.hypot(estimated[..., 0] - truth[..., 0], estimated[..., 1] - truth[..., 1])
    return position, jnp.abs(wrap_angle(estimated[..., 2] - truth[..., 2]))


def weighted_mean_and_covariance(
    poses: Float[Array, "N 3"], weights: Float[Array, "N"]
) -> tuple[Float[Array, "3"], Float[Array, "3 3"]]:
    """Weighted mean pose (circular mean for theta) and covariance of a particle set.

    ``weights`` are normalised (sum 1). Angle residuals are wrapped about the mean, so a
    cloud straddling theta = pi has a small spread, not a huge one.
    """
    xy = weights @ poses[:, :2]
    theta = jnp.arctan2(weights @ jnp.sin(poses[:, 2]), weights @ jnp.cos(poses[:, 2]))
    mean = jnp.concatenate([xy, theta[None]])
    residual = poses - mean
    residual = residual.at[:, 2].set(wrap_angle(residual[:, 2]))
    cov = (residual * weights[:, None]).T @ residual
    return mean, cov
