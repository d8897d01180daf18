"""Odometry motion model, GMapping-style: sample and log-density.

The odometry motion ``u = [dx, dy, dtheta]`` (robot frame of the previous pose)
is perturbed by independent Gaussian noise in that frame:

    sigma_x  = srr |dx| + sxy |dy| + srt |dtheta| + min_translation_std
    sigma_y  = srr |dy| + sxy |dx| + srt |dtheta| + min_translation_std
    sigma_th = stt |dtheta| + str sqrt(dx^2 + dy^2) + min_rotation_std

and the new pose is ``x_{t-1} (+) (u + noise)``. The names follow GMapping's
parameters (srr: translation error per metre of translation, srt: translation
error per radian of rotation, str: rotation error per metre of translation,
stt: rotation error per radian of rotation, sxy = 0.3 srr as in GMapping); the
minimum stds keep the density finite for a robot standing still.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from jaxslam.geometry import between, compose, wrap_angle

LOG_2PI = 1.8378770664093453


class MotionParams(NamedTuple):
    """Traced noise coefficients (a view of the filter's ``Params``)."""

    srr: Float[Array, ""]
    """Translation std per metre of translation (m/m)."""
    srt: Float[Array, ""]
    """Translation std per radian of rotation (m/rad)."""
    str: Float[Array, ""]
    """Rotation std per metre of translation (rad/m)."""
    stt: Float[Array, ""]
    """Rotation std per radian of rotation (rad/rad)."""
    min_translation_std: Float[Array, ""]
    """Std floor of each translation component (m)."""
    min_rotation_std: Float[Array, ""]
    """Std floor of the rotation (rad)."""


def motion_params(srr, srt, str_, stt, min_translation_std=0.0, min_rotation_std=0.0) -> MotionParams:
    """The one constructor of :class:`MotionParams`: float32 scalars (``str_`` is the field
    ``str``). Every value must be a finite number >= 0 (checked when it is concrete, not when it
    is traced), else ``ValueError`` names it."""
    values = (srr, srt, str_, stt, min_translation_std, min_rotation_std)
    for name, value in zip(MotionParams._fields, values):
        if isinstance(value, jax.core.Tracer):
            continue
        x = np.asarray(value, np.float64) if not isinstance(value, (str, bytes)) else None
        if x is None or x.shape != () or not np.isfinite(x) or x < 0:
            raise ValueError(f"motion_params: {name} must be a finite number >= 0, got {value!r}")
    return MotionParams(*(jnp.asarray(v, jnp.float32) for v in values))


def noise_std(motion: Float[Array, "... 3"], params: MotionParams) -> Float[Array, "... 3"]:
    """Std of the noise on [dx, dy, dtheta] for an odometry motion."""
    ax, ay, ath = jnp.abs(motion[..., 0]), jnp.abs(motion[..., 1]), jnp.abs(motion[..., 2])
    sxy = 0.3 * params.srr
    sx = params.srr * ax + sxy * ay + params.srt * ath + params.min_translation_std
    sy = params.srr * ay + sxy * ax + params.srt * ath + params.min_translation_std
    sth = params.stt * ath + params.str * jnp.hypot(motion[..., 0], motion[..., 1]) + params.min_rotation_std
    return jnp.stack([sx, sy, sth], axis=-1)


def sample(key: PRNGKeyArray, pose: Float[Array, "... 3"], motion: Float[Array, "3"],
           params: MotionParams) -> Float[Array, "... 3"]:
    """Draw ``x_t ~ p(x_t | x_{t-1} = pose, u = motion)`` for each pose (leading axes broadcast)."""
    std = noise_std(motion, params)
    noise = jax.random.normal(key, pose.shape, pose.dtype) * std
    return compose(pose, motion + noise)


def sample_with_score(key: PRNGKeyArray, pose: Float[Array, "... 3"], motion: Float[Array, "3"],
                      params: MotionParams) -> tuple[Float[Array, "... 3"], Float[Array, "..."]]:
    """:func:`sample`'s draw (the same values for the same key) for learning the noise by the score.

    Returns ``(new_pose, score_term)``: ``new_pose`` carries no gradient, and ``score_term`` is 0
    in value with gradient ``grad_params log p(new_pose | pose, motion)``. Added to a particle's
    log-weight it makes autodiff of the filter's log-likelihood the Fisher-identity (score)
    estimate (Poyiadjis, Doucet & Singh 2011) instead of a pathwise one. A pathwise gradient
    moves the pose against a map that does not move with it (the maps are not differentiable in
    the poses that built them), so it is far noisier than the score and points the wrong way
    (the figures: docs/design.md, "Motion-noise gradients by the score"). A zero std (no noise)
    gives a zero term.
    """
    std = noise_std(motion, params)
    eps = jax.random.normal(key, pose.shape, pose.dtype)
    drawn_std = jax.lax.stop_gradient(std)
    new_pose = compose(jax.lax.stop_gradient(pose), motion + eps * drawn_std)
    # log N(eps * s0; 0, s^2) up to a constant; its derivative at s = s0 is (eps^2 - 1) / s0.
    # Double where: a zero std must give neither a NaN value nor a NaN gradient.
    noisy = std > 0
    safe_std = jnp.where(noisy, std, 1.0)
    safe_drawn = jnp.where(noisy, drawn_std, 1.0)
    log_p = jnp.where(noisy, -0.5 * (eps * safe_drawn / safe_std) ** 2 - jnp.log(safe_std), 0.0)
    return new_pose, jnp.sum(log_p - jax.lax.stop_gradient(log_p), axis=-1)


def log_density(new_pose: Float[Array, "... 3"], pose: Float[Array, "... 3"], motion: Float[Array, "3"],
                params: MotionParams) -> Float[Array, "..."]:
    """log p(x_t = new_pose | x_{t-1} = pose, u = motion) (density in m^-2 rad^-1)."""
    std = noise_std(motion, params)
    residual = between(pose, new_pose) - motion
    residual = residual.at[..., 2].set(wrap_angle(residual[..., 2]))
    z = residual / std
    return jnp.sum(-0.5 * z**2 - jnp.log(std) - 0.5 * LOG_2PI, axis=-1)


def world_gaussian(pose: Float[Array, "3"], motion: Float[Array, "3"], params: MotionParams
                   ) -> tuple[Float[Array, "3"], Float[Array, "3 3"]]:
    """p(x_t | x_{t-1} = pose, u = motion) as a Gaussian in world coordinates: mean
    ``pose (+) motion`` and covariance R diag(std^2) R^T (R the rotation by the pose's heading on
    x, y; the heading's variance alone on theta). Exact: x_t is linear in the noise."""
    std = noise_std(motion, params)
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    rotation = jnp.stack([jnp.stack([c, -s, zero]), jnp.stack([s, c, zero]), jnp.stack([zero, zero, one])])
    return compose(pose, motion), (rotation * std**2) @ rotation.T


def path_log_density(path: Float[Array, "T 3"], motions: Float[Array, "T-1 3"],
                     params: MotionParams) -> Float[Array, ""]:
    """log p(x_1..x_{T-1} | x_0, u): the motion model's log-density of a known path given the
    odometry motions between its poses (``motions[t]`` from ``path[t]`` to ``path[t + 1]``).

    Maximised over the noise terms (:func:`jaxslam.learning.fit`) on a log with ground truth, it
    gives the motion model's own optimum for that log: what a filter that learns the noise from
    the scans can at best recover. It need not be the simulator's values: the simulator takes
    each step's std at the true motion, the model at the odometry reading, and that alone moves
    the optimum of ``str`` and ``stt`` (the figures:
    docs/design.md, "Tempering and learning").
    """
    return jnp.sum(log_density(path[1:], path[:-1], motions, params))
