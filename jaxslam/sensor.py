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
from jaxtyping import Array, Float, UInt8

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


def endpoint_log_likelihood(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: LikelihoodParams,
) -> Float[Array, ""]:
    """log p(z | x, m) of one scan at one robot pose in one map (``spec`` a GridSpec).

    vmap it over poses (particles, localizers) and maps. Endpoints outside the map
    score ``log(z_rand)``.
    """
    origin = compose(pose, sensor.laser_pose)
    angle = origin[2] + sensor.beam_angles
    ends = origin[:2] + ranges[:, None] * jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)
    idx = flat_index(spec, world_to_cell(spec, ends))
    d2 = hit_dist2.reshape(-1).at[idx].get(mode="fill", fill_value=FAR)
    d2_m = d2.astype(jnp.float32) * (spec.resolution**2)
    gauss = jnp.where(d2 == FAR, 0.0, jnp.exp(-0.5 * d2_m / params.sigma**2))
    per_beam = jnp.log(params.z_hit * gauss + params.z_rand)
    valid = (ranges < sensor.range_max) & (ranges >= sensor.range_min)
    return params.gain * jnp.sum(jnp.where(valid, per_beam, 0.0))
