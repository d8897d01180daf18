"""Laser sensor description and likelihoods.

The endpoint (likelihood-field) model scores a scan in a grid map with one
lookup per beam, in the map's ``hit_dist2`` field (see :mod:`jaxslam.grid`):

    p(z_b | x, m) = z_hit * exp(-d_b^2 / (2 sigma^2)) + z_rand,

d_b being the distance from beam b's endpoint to the nearest registered
endpoint in the map (infinite beyond the field radius, and for endpoints outside
the map). Beams without a return (r >= range_max) or shorter than range_min are
skipped. The sum over beams is multiplied by ``likelihood_gain`` (< 1 tempers the
over-confidence of treating correlated beams as independent).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, UInt8

from jaxslam.geometry import compose
from jaxslam.grid import FAR, GridSpec, flat_index, world_to_cell


class SensorSpec(NamedTuple):
    """A planar laser scanner (a pytree of arrays: traced, not static)."""

    beam_angles: Float[Array, "B"]
    """Angle of each beam in the laser frame (rad), counter-clockwise from the laser's x axis."""
    range_min: Float[Array, ""]
    """Ranges below this (m) are invalid readings."""
    range_max: Float[Array, ""]
    """Ranges at or above this (m) mean "no return"."""
    laser_pose: Float[Array, "3"]
    """Pose [x, y, theta] of the laser in the robot frame (m, m, rad)."""


def make_sensor(beam_angles, range_min=0.0, range_max=30.0, laser_pose=(0.0, 0.0, 0.0)) -> SensorSpec:
    """A :class:`SensorSpec` with float32 arrays."""
    return SensorSpec(
        jnp.asarray(beam_angles, jnp.float32),
        jnp.asarray(range_min, jnp.float32),
        jnp.asarray(range_max, jnp.float32),
        jnp.asarray(laser_pose, jnp.float32),
    )


def uniform_beams(num_beams: int, fov: float = jnp.pi) -> Float[Array, "B"]:
    """``num_beams`` angles spanning ``fov`` radians centred on the laser's x axis, both ends included."""
    return jnp.linspace(-fov / 2, fov / 2, num_beams, dtype=jnp.float32)


def subsample_beams(sensor: SensorSpec, ranges: Float[Array, "... B"], stride: int):
    """Every ``stride``-th beam (static stride), for the likelihood; the map gets all beams."""
    if stride == 1:
        return sensor, ranges
    return sensor._replace(beam_angles=sensor.beam_angles[::stride]), ranges[..., ::stride]


class LikelihoodParams(NamedTuple):
    """Traced numbers of the endpoint model (a view of the filter's ``Params``)."""

    sigma: Float[Array, ""]
    """Std (m) of the endpoint's distance to the nearest obstacle."""
    z_hit: Float[Array, ""]
    """Weight of the Gaussian term."""
    z_rand: Float[Array, ""]
    """Floor for unexplained beams (people, glass, unmapped space); > 0 keeps logs finite."""
    gain: Float[Array, ""]
    """Multiplier of the summed log-likelihood."""


def endpoint_fit(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    sigma: Float[Array, ""],
) -> tuple[Float[Array, "B"], Bool[Array, "B"]]:
    """Per-beam fit ``exp(-d_b^2 / (2 sigma^2))`` in [0, 1] of a scan at ``pose``, and which beams count.

    d_b is the distance (m) from beam b's endpoint to the nearest registered endpoint in
    the map; the fit is 0 beyond the field radius and outside the map. Beams without a
    return or below range_min do not count.
    """
    origin = compose(pose, sensor.laser_pose)
    angle = origin[2] + sensor.beam_angles
    ends = origin[:2] + ranges[:, None] * jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)
    idx = flat_index(spec, world_to_cell(spec, ends))
    d2 = hit_dist2.reshape(-1).at[idx].get(mode="fill", fill_value=FAR)
    d2_m = d2.astype(jnp.float32) * (spec.resolution**2)
    fit = jnp.where(d2 == FAR, 0.0, jnp.exp(-0.5 * d2_m / sigma**2))
    valid = (ranges < sensor.range_max) & (ranges >= sensor.range_min)
    return fit, valid


def endpoint_log_likelihood(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: LikelihoodParams,
) -> Float[Array, ""]:
    """log p(z | x, m) of one scan at one robot pose in one map, in nats.

    ``gain * sum_b log(z_hit * fit_b + z_rand)`` over the beams that count (see
    :func:`endpoint_fit`). vmap it over poses (particles, localizers) and maps.
    """
    fit, valid = endpoint_fit(spec, hit_dist2, pose, ranges, sensor, params.sigma)
    per_beam = jnp.log(params.z_hit * fit + params.z_rand)
    return params.gain * jnp.sum(jnp.where(valid, per_beam, 0.0))


def match_score(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    sigma: Float[Array, ""],
) -> Float[Array, ""]:
    """Mean per-beam fit (0..1) of the beams that count; 0 when none counts."""
    fit, valid = endpoint_fit(spec, hit_dist2, pose, ranges, sensor, sigma)
    n = jnp.sum(valid)
    return jnp.sum(jnp.where(valid, fit, 0.0)) / jnp.maximum(n, 1)
