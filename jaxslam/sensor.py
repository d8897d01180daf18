"""Laser sensor description and likelihoods.

The endpoint (likelihood-field) model scores a scan in a grid map with one
lookup per beam, in the map's ``hit_dist2`` field (see :mod:`jaxslam.grid`):

    p(z_b | x, m) = z_hit * exp(-d_b^2 / (2 sigma^2)) + z_rand,

d_b being the distance from beam b's endpoint to the nearest registered
endpoint in the map (infinite beyond the field radius, and for endpoints outside
the map). Beams without a return (r >= range_max) or shorter than range_min are
skipped. The sum over beams is multiplied by ``likelihood_gain`` (< 1 tempers the
over-confidence of treating correlated beams as independent).

``lookup`` (static, :data:`FIELD_LOOKUPS`) says how an endpoint reads the field: "nearest"
takes the cell it falls in (one gather per beam; the likelihood is then constant while the
endpoint stays in its cell, so a pose is only resolved to about a cell), "bilinear"
interpolates the per-beam log-likelihood of the four cells whose centres surround it (four
gathers; the likelihood is continuous in the pose, so the scan matcher can settle between
cells).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax.scipy.special import ndtr as _ndtr
from jaxtyping import Array, Bool, Float, UInt8

from jaxslam.grid import FAR, GridSpec, cell_clip_bound, flat_index, world_to_cell
from jaxslam.motion import _LOG_2PI

FIELD_LOOKUPS = ("nearest", "bilinear")
"""How an endpoint reads the likelihood field (see the module docstring)."""



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
    d2, valid = endpoint_cell_distances(spec, hit_dist2, pose[None], ranges, sensor)
    d2_m = d2[0].astype(jnp.float32) * (spec.resolution**2)
    fit = jnp.where(d2[0] == FAR, 0.0, jnp.exp(-0.5 * d2_m / sigma**2))
    return fit, valid


def endpoint_log_likelihood(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: LikelihoodParams,
    lookup: str = "nearest",
) -> Float[Array, ""]:
    """log p(z | x, m) of one scan at one robot pose in one map, in nats.

    ``gain * sum_b log(z_hit * fit_b + z_rand)`` over the beams that count (see
    :func:`endpoint_fit`), each beam's term read from the field by ``lookup`` (static,
    :data:`FIELD_LOOKUPS`). vmap it over poses and maps, or call
    :func:`endpoint_log_likelihoods` for many poses in one map.
    """
    return endpoint_log_likelihoods(spec, hit_dist2, pose[None], ranges, sensor, params, lookup)[0]


def endpoint_log_likelihoods(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    poses: Float[Array, "L 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: LikelihoodParams,
    lookup: str = "nearest",
) -> Float[Array, "L"]:
    """:func:`endpoint_log_likelihood` of one scan at L robot poses in one map (nats).

    The hot loop of every proposal, so it is fused: the beam endpoints are computed once
    in the robot frame (B trig calls, shared by all poses and, under vmap, by all SLAM
    particles), after which a pose costs one rotation per beam; and the per-beam term only
    depends on the stored squared cell distance (uint8), so it is read from a 256-entry
    table (:func:`per_beam_log_likelihood_table`) instead of evaluating exp and log per beam.
    With ``lookup="bilinear"`` the terms of the four surrounding cells are interpolated.
    """
    if lookup not in FIELD_LOOKUPS:
        raise ValueError(f"lookup must be one of {FIELD_LOOKUPS}, got {lookup!r}")
    table = per_beam_log_likelihood_table(spec, params)
    if lookup == "nearest":
        d2, valid = endpoint_cell_distances(spec, hit_dist2, poses, ranges, sensor)
        per_beam = table[d2.astype(jnp.int32)]
    else:
        ends, valid = beam_endpoints(poses, ranges, sensor)
        # Cell coordinates of the endpoint relative to the cell centres (cell (r, c) has its
        # centre at (c + 0.5, r + 0.5) cells from the origin): the four cells round it are
        # ``base`` and its neighbours up and right.
        xy = (ends - jnp.asarray(spec.origin, ends.dtype)) / spec.resolution - 0.5
        big = cell_clip_bound(spec)
        lower = jnp.clip(jnp.floor(xy), -big, big)
        # Position inside that square, (x, y) in [0, 1]; clipped so that the weights stay a
        # convex combination where a far-away point was clipped (all four cells are FAR there).
        frac = jnp.clip(xy - lower, 0.0, 1.0)
        base = jnp.stack([lower[..., 1], lower[..., 0]], axis=-1).astype(jnp.int32)  # (row, col)
        per_beam = 0.0
        for d_row, d_col in ((0, 0), (0, 1), (1, 0), (1, 1)):
            term = table[_field_at_cells(spec, hit_dist2, base + jnp.array([d_row, d_col])).astype(jnp.int32)]
            weight = ((frac[..., 1] if d_row else 1.0 - frac[..., 1])
                      * (frac[..., 0] if d_col else 1.0 - frac[..., 0]))
            per_beam = per_beam + weight * term
    return params.gain * jnp.sum(jnp.where(valid, per_beam, 0.0), axis=-1)


def beam_endpoints(
    poses: Float[Array, "L 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
) -> tuple[Float[Array, "L B 2"], Bool[Array, "B"]]:
    """World (x, y) in metres of every beam's endpoint for L robot poses, and which beams
    count (a return within range). The endpoints are computed once in the robot frame (B
    trig calls), after which a pose costs one rotation per beam."""
    valid = (ranges < sensor.range_max) & (ranges >= sensor.range_min)
    beam_x = ranges * jnp.cos(sensor.beam_angles)  # (B,) endpoints in the laser frame (m)
    beam_y = ranges * jnp.sin(sensor.beam_angles)
    lc, ls = jnp.cos(sensor.laser_pose[2]), jnp.sin(sensor.laser_pose[2])
    robot_x = sensor.laser_pose[0] + lc * beam_x - ls * beam_y  # laser -> robot frame, once per scan
    robot_y = sensor.laser_pose[1] + ls * beam_x + lc * beam_y
    c, s = jnp.cos(poses[:, 2:3]), jnp.sin(poses[:, 2:3])  # (L, 1)
    ends = jnp.stack([poses[:, 0:1] + c * robot_x - s * robot_y,
                      poses[:, 1:2] + s * robot_x + c * robot_y], axis=-1)  # (L, B, 2)
    return ends, valid


def _field_at_cells(spec: GridSpec, hit_dist2: UInt8[Array, "H W"], cells) -> UInt8[Array, "..."]:
    """The field at (row, col) cells; ``FAR`` outside the map."""
    return hit_dist2.reshape(-1).at[flat_index(spec, cells)].get(mode="fill", fill_value=FAR)


def endpoint_cell_distances(
    spec: GridSpec,
    hit_dist2: UInt8[Array, "H W"],
    poses: Float[Array, "L 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
) -> tuple[UInt8[Array, "L B"], Bool[Array, "B"]]:
    """The stored squared cell distance at every beam's endpoint for L robot poses (``FAR``
    outside the map or the field radius), and which beams count (a return within range)."""
    ends, valid = beam_endpoints(poses, ranges, sensor)
    return _field_at_cells(spec, hit_dist2, world_to_cell(spec, ends)), valid


def per_beam_log_likelihood_table(spec: GridSpec, params: LikelihoodParams) -> Float[Array, "256"]:
    """log(z_hit * fit + z_rand) for every uint8 squared cell distance (``FAR``: fit 0)."""
    d2 = jnp.arange(FAR + 1, dtype=jnp.float32)
    fit = jnp.where(d2 == FAR, 0.0, jnp.exp(-0.5 * d2 * spec.resolution**2 / params.sigma**2))
    return jnp.log(params.z_hit * fit + params.z_rand)


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




class BeamModelParams(NamedTuple):
    """Traced numbers of the beam model (Thrun, Burgard & Fox, Probabilistic Robotics, 6.3).

    The four weights are normalised by their sum inside :func:`beam_model_log_likelihood`.
    """

    z_hit: Float[Array, ""]
    """Weight of the measurement-noise Gaussian around the expected range."""
    z_short: Float[Array, ""]
    """Weight of the exponential of unexpected obstacles (people) in front of the expected one."""
    z_max: Float[Array, ""]
    """Weight of the point mass at range_max (no return)."""
    z_rand: Float[Array, ""]
    """Weight of the uniform density of unexplained readings on [0, range_max)."""
    sigma_hit: Float[Array, ""]
    """Std (m) of the hit Gaussian."""
    lambda_short: Float[Array, ""]
    """Rate (1/m) of the short exponential."""


def make_beam_model_params(z_hit=0.8, z_short=0.1, z_max=0.05, z_rand=0.05, sigma_hit=0.1,
                           lambda_short=0.5) -> BeamModelParams:
    """A :class:`BeamModelParams` of float32 scalars."""
    f = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    return BeamModelParams(f(z_hit), f(z_short), f(z_max), f(z_rand), f(sigma_hit), f(lambda_short))


def beam_model_log_likelihood(
    expected_ranges: Float[Array, "... B"],
    ranges: Float[Array, "... B"],
    range_max: Float[Array, ""],
    params: BeamModelParams,
) -> Float[Array, "... B"]:
    """Per-beam log p(z_b | expected range) of the classic beam model mixture, in nats.

    A reading is a mixed measure: a density (1/m) on [0, range_max) and a point mass at
    range_max (every ``r >= range_max`` is "no return"). With the weights normalised to sum 1:

      hit:   N(r; expected, sigma_hit^2) truncated to [0, range_max]   (density)
      short: lambda e^(-lambda r) / (1 - e^(-lambda expected)) for r <= expected   (density)
      rand:  1 / range_max                                              (density)
      max:   1 at r >= range_max                                        (probability)

    A "no return" reading scores log z_max alone; a return scores
    log(z_hit hit + z_short short + z_rand rand). Computed in log space, finite for any
    finite input (expected ranges are clipped to [0, range_max]).

    Args:
      expected_ranges: (..., B) ranges (m) the map predicts (ray casting), broadcast with ``ranges``.
      ranges: (..., B) measured ranges (m).
      range_max: the sensor's maximum range (m).
      params: mixture weights, sigma_hit (m) and lambda_short (1/m).

    Returns:
      (..., B) float32 log-likelihoods (log of 1/m for returns, log of a probability for
      no-return readings).
    """
    range_max = jnp.asarray(range_max, jnp.float32)
    expected = jnp.clip(jnp.asarray(expected_ranges, jnp.float32), 0.0, range_max)
    r = jnp.asarray(ranges, jnp.float32)
    total = params.z_hit + params.z_short + params.z_max + params.z_rand
    log_w_hit = jnp.log(params.z_hit / total)
    log_w_short = jnp.log(params.z_short / total)
    log_w_max = jnp.log(params.z_max / total)
    log_w_rand = jnp.log(params.z_rand / total)
    sigma = params.sigma_hit
    # Hit: the Gaussian's mass inside [0, range_max] renormalises it .
    upper = _ndtr((range_max - expected) / sigma)
    lower = _ndtr(-expected / sigma)
    log_mass = jnp.log(jnp.maximum(upper - lower, 1e-30))
    z = (r - expected) / sigma
    log_hit = -0.5 * z**2 - jnp.log(sigma) - 0.5 * _LOG_2PI - log_mass
    # Short: an exponential truncated to [0, expected]; impossible beyond the expected range
    # and when the expected range is 0 (nothing can stand in front of it).
    lam = params.lambda_short
    norm_short = -jnp.expm1(-lam * expected)  # 1 - e^(-lambda expected), exact for small values
    short_ok = (r <= expected) & (norm_short > 0)
    log_short = jnp.where(
        short_ok, jnp.log(lam) - lam * r - jnp.log(jnp.where(short_ok, norm_short, 1.0)), -jnp.inf)
    log_rand = -jnp.log(range_max)
    log_return = jnp.logaddexp(jnp.logaddexp(log_w_hit + log_hit, log_w_short + log_short),
                               log_w_rand + log_rand)
    return jnp.where(r >= range_max, log_w_max + jnp.zeros_like(log_return), log_return)


