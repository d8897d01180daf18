"""The endpoint (likelihood-field) laser model of the SLAM filters.

The endpoint (likelihood-field) model scores a scan in a grid map with one
lookup per beam, in the map's ``hit_dist2`` field (see :mod:`jaxslam.occupancy`):

    p(z_b | x, m) = z_hit * exp(-d_b^2 / (2 sigma^2)) + z_rand,

d_b being the distance from beam b's endpoint to the nearest registered
endpoint in the map (infinite beyond the field radius, and for endpoints outside
the map). Beams without a return (r >= range_max) or shorter than range_min are
skipped. The sum over beams is multiplied by the gain (``likelihood.gain``) (< 1 tempers the
over-confidence of treating correlated beams as independent).

The expression above is the Gaussian's shape without its normalisation, which every pose and
map share; the particles' weights do not need it. A log-likelihood that is to be maximised in
``sigma`` does: :func:`endpoint_log_normalizer` is the per-scan constant that makes each beam's
term a density per metre of the endpoint's distance, ``(z_hit * exp(-d_b^2 / (2 sigma^2)) +
z_rand) / Z``, so the random floor is a density ``z_rand`` times the Gaussian's peak. Z counts
the distance in whole cells, as the field does (a registered cell has width, not a point at
distance 0): without that, every endpoint inside a registered cell is worth ``log(1 / sigma)``
and the log-likelihood rises without bound as sigma falls; without any normaliser it rises with
sigma for every d_b.

``lookup`` (static, :data:`FIELD_LOOKUPS`) says how an endpoint reads the field: "nearest"
takes the cell it falls in (one gather per beam; the likelihood is then constant while the
endpoint stays in its cell, so a pose is only resolved to about a cell), "bilinear"
interpolates the per-beam log-likelihood of the four cells whose centres surround it (four
gathers; the likelihood is continuous in the pose, so the scan matcher can settle between
cells).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, UInt8

from jaxslam.computed_once import computed_once
from jaxslam.grid import GridSpec, cell_clip_bound, world_to_cell
from jaxslam.laser import SensorSpec, beam_endpoints, laser_rays, valid_returns
from jaxslam.map_view import MapView
from jaxslam.maps import PagedField, PagedGridSpec
from jaxslam.occupancy import FAR

SEE_THROUGH_RAYS = (-2.0, 0.0, 2.0)
"""The rays a beam's free path is checked along, in cells to its side (:func:`see_through_log_likelihood`):
two cells, not one, so that a beam must pass 20 cm deep into what the map holds to count (on a box
world's map drawn at the true poses, the true pose crossed 44 times in 127 scans with one cell
and 5 with two, the least-crossed pose nearby 13 and 2)."""
SEE_THROUGH_CLEAR = 4
"""Squared cells from the nearest registered endpoint at which a ray is in clear space again
(two cells) after crossing one (:func:`see_through_log_likelihood`)."""

FIELD_LOOKUPS = ("nearest", "bilinear")
"""How an endpoint reads the likelihood field (see the module docstring)."""


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
    see_through: Float[Array, ""] | float = 0.05
    """Probability that a beam passes through a cell holding a registered endpoint before its own
    end (glass, a person gone since): the free-space evidence's per-beam factor
    (:func:`see_through_log_likelihood`; only with ``SlamConfig.free_space_samples`` > 0)."""
    free_margin: Float[Array, ""] | float = 0.15
    """Metres before a beam's end over which its path is not checked (a beam grazing a wall, the
    endpoint's own scatter)."""


def endpoint_log_likelihood(
    spec: GridSpec | PagedGridSpec,
    hit_dist2: UInt8[Array, "H W"] | PagedField,
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
    spec: GridSpec | PagedGridSpec,
    hit_dist2: UInt8[Array, "H W"] | PagedField,
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
    view = MapView(spec, hit_dist2)
    table = per_beam_log_likelihood_table(view.grid, params)
    grid = view.grid
    if lookup == "nearest":
        d2, valid = endpoint_cell_distances(spec, hit_dist2, poses, ranges, sensor)
        per_beam = table[d2.astype(jnp.int32)]
    else:
        ends, valid = beam_endpoints(poses, ranges, sensor)
        # Cell coordinates of the endpoint relative to the cell centres (cell (r, c) has its
        # centre at (c + 0.5, r + 0.5) cells from the origin): the four cells round it are
        # ``base`` and its neighbours up and right.
        xy = (ends - jnp.asarray(grid.origin, ends.dtype)) / grid.resolution - 0.5
        big = cell_clip_bound(grid)
        lower = jnp.clip(jnp.floor(xy), -big, big)
        # Position inside that square, (x, y) in [0, 1]; clipped so that the weights stay a
        # convex combination where a far-away point was clipped (all four cells are FAR there).
        frac = jnp.clip(xy - lower, 0.0, 1.0)
        base = jnp.stack([lower[..., 1], lower[..., 0]], axis=-1).astype(jnp.int32)  # (row, col)
        if view.paged:  # twelve gathers read them: compute them once
            base, frac = computed_once(lambda b, f: (b, f), base, frac)
        per_beam = 0.0
        for d_row, d_col in ((0, 0), (0, 1), (1, 0), (1, 1)):
            term = table[view.read(base + jnp.array([d_row, d_col]), FAR).astype(jnp.int32)]
            weight = ((frac[..., 1] if d_row else 1.0 - frac[..., 1])
                      * (frac[..., 0] if d_col else 1.0 - frac[..., 0]))
            per_beam = per_beam + weight * term
    return params.gain * jnp.sum(jnp.where(valid, per_beam, 0.0), axis=-1)


def endpoint_cell_log_likelihoods(
    spec: GridSpec | PagedGridSpec,
    hit_dist2: UInt8[Array, "H W"] | PagedField,
    poses: Float[Array, "L 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    params: LikelihoodParams,
    reach_xy: Float[Array, ""],
    reach_theta: Float[Array, ""],
    field_radius: int,
) -> Float[Array, "L"]:
    """The endpoint log-likelihood of a cell of poses: within ``reach_xy`` (m, in position) and
    ``reach_theta`` (rad, in heading) of each of the L ``poses`` (nats, tempered by ``params.gain``),
    for the coarse levels of the window posterior (:mod:`jaxslam.window_posterior`).

    Moving the robot by at most (reach_xy, reach_theta) moves beam b's endpoint by at most
    ``rho_b = reach_xy + reach_theta * |p_b|`` (|p_b| <= |laser offset| + r_b, its distance from
    the robot). Each beam
    is scored at the centre pose with its Gaussian widened by that reach,
    ``log(z_hit exp(-d_b^2 / (2 (sigma^2 + rho_b^2))) + z_rand)``, a ``FAR`` cell (beyond the
    field radius) counting as ``field_radius`` cells away (static). This is a blurred
    likelihood, not a bound: the bound (d_b - rho_b in place of d_b, Olson's multi-resolution
    matching read from the distance field) is flat wherever rho_b exceeds a few sigma, which at
    a coarse heading step is every beam beyond a metre or two, and the search then kept the
    cells nearest the prediction (docs/design.md, "The window posterior")."""
    view = MapView(spec, hit_dist2)
    resolution = view.resolution
    d2, valid = endpoint_cell_distances(spec, hit_dist2, poses, ranges, sensor)
    # The per-beam term depends on the beam (its reach) and the stored squared cell distance
    # (0 .. field_radius^2, or FAR): a (B, field_radius^2 + 2) table, built once for all L poses
    # (and, under vmap, per particle), replaces an exp and a log per beam and pose.
    far_index = field_radius**2 + 1
    stored = jnp.arange(far_index + 1, dtype=jnp.float32).at[far_index].set(float(field_radius**2))
    arm = jnp.hypot(sensor.laser_pose[0], sensor.laser_pose[1]) + jnp.maximum(ranges, 0.0)  # (B,) m
    reach = reach_xy + reach_theta * arm
    widened = params.sigma**2 + reach**2  # (B,) m^2
    table = jnp.log(params.z_hit * jnp.exp(-0.5 * stored * resolution**2 / widened[:, None]) + params.z_rand)
    index = jnp.where(d2 == FAR, far_index, jnp.minimum(d2.astype(jnp.int32), far_index - 1))  # (L, B)
    per_beam = jnp.take_along_axis(table, index.T, axis=1).T
    return params.gain * jnp.sum(jnp.where(valid, per_beam, 0.0), axis=-1)


NORMALIZER_CELLS = 32
"""Cells summed exactly by :func:`endpoint_log_normalizer`; the Gaussian's tail beyond them is
integrated in closed form."""


def endpoint_log_normalizer(ranges: Float[Array, "B"], sensor: SensorSpec, params: LikelihoodParams,
                            resolution: float) -> Float[Array, ""]:
    """The log normalising constant of one scan's endpoint model (nats), the same at every pose.

    ``-gain * n * log(Z)`` over the n beams that count, with

        Z = resolution * sum_{k=0}^{K-1} exp(-(k resolution)^2 / (2 sigma^2))
            + sigma sqrt(pi / 2) erfc(K resolution / (sqrt(2) sigma))
            + resolution / 2 * exp(-(K resolution)^2 / (2 sigma^2))

    (K = :data:`NORMALIZER_CELLS`; metres; the last two terms are the cells from K on): the
    field knows an endpoint's distance only to the cell, so each beam's term becomes a density
    per metre across a wall of cells of width ``resolution`` at 0, 1, 2, ... cells from it. For
    sigma well above a cell, Z is the half-normal's ``sigma sqrt(pi/2)`` plus half a cell; as
    sigma falls below a cell, Z tends to one cell, not to 0, so an endpoint inside a registered
    cell (distance 0) is worth at most ``-log(resolution)``. Exact for the nearest lookup. For
    the bilinear lookup it is an approximation that holds for sigma above a cell (the
    interpolated density's own Z falls below it under a cell: measured ratios in
    docs/design.md, "Endpoint model"). That integral tends to 0 with sigma, and
    with it the log-likelihood would again be unbounded as sigma falls; the cell count keeps
    the model well posed, and a sigma learned
    with it is comparable with a reference computed with it (not with one computed under another
    normaliser). The filters add it to their log-evidence, not to the weights (a constant there
    changes nothing but rounding).

    Args:
      ranges: (B,) one scan's ranges (m); the beams with a return count.
      sensor: the laser.
      params: the endpoint model's sigma (m) and gain.
      resolution: the map's cell size (m), static.
    """
    num_counted = jnp.sum(valid_returns(ranges, sensor)).astype(jnp.float32)
    sigma = params.sigma
    cells = resolution * jnp.arange(NORMALIZER_CELLS, dtype=jnp.float32)
    lattice = resolution * jnp.sum(jnp.exp(-0.5 * (cells / sigma) ** 2))
    # The cells from K on by Euler-Maclaurin: the integral from K cells plus half the K-th cell.
    reach = NORMALIZER_CELLS * resolution
    tail = (sigma * math.sqrt(math.pi / 2.0) * jax.scipy.special.erfc(reach / (math.sqrt(2.0) * sigma))
            + 0.5 * resolution * jnp.exp(-0.5 * (reach / sigma) ** 2))
    return -params.gain * num_counted * jnp.log(lattice + tail)


def endpoint_cell_distances(
    spec: GridSpec | PagedGridSpec,
    hit_dist2: UInt8[Array, "H W"] | PagedField,
    poses: Float[Array, "L 3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
) -> tuple[UInt8[Array, "L B"], Bool[Array, "B"]]:
    """The stored squared cell distance at every beam's endpoint for L robot poses (``FAR``
    outside the map or the field radius), and which beams count (a return within range)."""
    view = MapView(spec, hit_dist2)
    ends, valid = beam_endpoints(poses, ranges, sensor)
    cells = world_to_cell(view.grid, ends)
    if view.paged:  # three gathers read the cells: compute them once
        cells = computed_once(lambda c: c, cells)
    return view.read(cells, FAR), valid


def per_beam_log_likelihood_table(spec: GridSpec | PagedGridSpec, params: LikelihoodParams) -> Float[Array, "256"]:
    """log(z_hit * fit + z_rand) for every uint8 squared cell distance (``FAR``: fit 0)."""
    d2 = jnp.arange(FAR + 1, dtype=jnp.float32)
    fit = jnp.where(d2 == FAR, 0.0, jnp.exp(-0.5 * d2 * spec.resolution**2 / params.sigma**2))
    return jnp.log(params.z_hit * fit + params.z_rand)


def endpoint_match_score(
    spec: GridSpec | PagedGridSpec,
    hit_dist2: UInt8[Array, "H W"] | PagedField,
    pose: Float[Array, "3"],
    ranges: Float[Array, "B"],
    sensor: SensorSpec,
    sigma: Float[Array, ""],
) -> Float[Array, ""]:
    """The match quality of one scan at one pose: the mean per-beam fit in [0, 1] of the beams
    that count (0 when none counts). A beam's fit is exp(-d_b^2 / (2 sigma^2)), d_b the
    distance (m) from its endpoint to the nearest registered endpoint; 0 beyond the field
    radius and outside the map."""
    d2, valid = endpoint_cell_distances(spec, hit_dist2, pose[None], ranges, sensor)
    d2_m = d2[0].astype(jnp.float32) * (spec.resolution**2)
    fit = jnp.where(d2[0] == FAR, 0.0, jnp.exp(-0.5 * d2_m / sigma**2))
    n = jnp.sum(valid)
    return jnp.sum(jnp.where(valid, fit, 0.0)) / jnp.maximum(n, 1)


def see_through_log_likelihood(
    spec: GridSpec | PagedGridSpec,
    hit_dist2: UInt8[Array, "H W"] | PagedField,
    pose: Float[Array, "3"],
    free_lengths: Float[Array, "B"],
    sensor: SensorSpec,
    params: LikelihoodParams,
    num_samples: int,
) -> Float[Array, ""]:
    """The free-space evidence of one scan at one pose (nats): ``gain * log(see_through)`` for
    every beam whose free path crosses a cell holding a registered endpoint.

    The endpoint model scores only where beams end, so a map that holds a landmark twice (once
    where an earlier visit put it, once where a wrong pose put it now) explains every later scan
    as well as the right map does. A beam that passes through a cell the map holds occupied is
    the evidence against that map and pose. Each beam is sampled every cell from the laser out
    (``num_samples``, static), up to its free length (``occupancy.free_lengths``: its range, or
    the "no return" length) less ``params.free_margin``, and so are two rays beside it, two cells
    to either side (:data:`SEE_THROUGH_RAYS`). A ray crosses when it passes a registered cell and
    is in clear space again (:data:`SEE_THROUGH_CLEAR`) before the checked length ends; a beam
    counts, once, when all three rays cross. Two kinds of crossing are not evidence and are left
    out so: a beam that passes a wall's corner or runs along a wall clips registered cells on one
    side only, and a beam that ends inside a wall the map holds smeared meets registered cells up
    to its end, with no clear space after them. Counted, the first made the true pose cross more
    cells than poses moved towards what it sees, and the second pulled every pose towards the near
    side of a smear (the endpoint model is flat through it), which the next insertion thickened: a
    heading ratchet of 50-100 degrees over a box world's laps (docs/design.md, "Free-space evidence").
    Constant in the pose between cells, so it carries no pose gradient.

    Args:
      spec, hit_dist2: the map (dense or one particle's paged field).
      pose: (3,) robot pose.
      free_lengths: (B,) metres of each beam that the scan clears.
      sensor: the laser.
      params: the endpoint model's numbers (``see_through``, ``free_margin``, ``gain``).
      num_samples: samples per beam, one cell apart (static).
    """
    view = MapView(spec, hit_dist2)
    origin, angle = laser_rays(pose, sensor)
    direction = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)  # (B, 2)
    normal = jnp.stack([-direction[:, 1], direction[:, 0]], axis=-1)
    along = (jnp.arange(num_samples, dtype=jnp.float32) + 1.0) * view.resolution  # (S,)
    checked = along[None, :] <= (free_lengths - params.free_margin)[:, None]  # (B, S)
    index = jnp.arange(num_samples)
    crossed = jnp.ones(checked.shape[:1], bool)
    for side in SEE_THROUGH_RAYS:
        points = (origin + along[None, :, None] * direction[:, None, :]
                  + (side * view.resolution) * normal[:, None, :])  # (B, S, 2)
        d2 = view.read(world_to_cell(view.grid, points), FAR)
        # Through a registered cell and out again into clear space before the end.
        first_registered = jnp.min(jnp.where(checked & (d2 == 0), index, num_samples), axis=1)
        last_clear = jnp.max(jnp.where(checked & (d2 >= SEE_THROUGH_CLEAR), index, -1), axis=1)
        crossed = crossed & (first_registered < last_clear)
    return params.gain * jnp.log(params.see_through) * jnp.sum(crossed)
