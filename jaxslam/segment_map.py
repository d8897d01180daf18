"""Segment maps: walls and doors as line segments, and exact ray casting against them.

The map model of the localization filters (:mod:`jaxslam.localization`) and of the
simulator (:mod:`jaxslam.sim`): a map is an (M, 4) array of segments [x1, y1, x2, y2]
(m), optionally with an (M,) mask of the segments present (an open door is transparent).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxslam.laser import SensorSpec, laser_rays

_EPS = 1e-9


def raycast(
    segments: Float[Array, "M 4"],
    origins: Float[Array, "... 2"],
    angles: Float[Array, "..."],
    max_range: float | Float[Array, ""],
    active: Bool[Array, "M"] | None = None,
) -> tuple[Float[Array, "..."], Int[Array, "..."]]:
    """Distance along each ray to the first segment it hits.

    Args:
      segments: (M, 4) rows [x1, y1, x2, y2] in metres.
      origins: ray origins (m), broadcast against ``angles``.
      angles: ray directions (rad, world frame).
      max_range: rays that hit nothing closer get this range.
      active: optional (M,) mask; inactive segments (an open door, say) are transparent.

    Returns:
      ``(ranges, hit)``: ranges (m) clipped to ``max_range``, and the index of the segment
      hit first (-1 when nothing is hit within ``max_range``). Exact: no ray marching.
    """
    segments = jnp.asarray(segments, jnp.float32)
    origins = jnp.asarray(origins, jnp.float32)
    angles = jnp.asarray(angles, jnp.float32)
    shape = jnp.broadcast_shapes(origins.shape[:-1], angles.shape)
    origins = jnp.broadcast_to(origins, shape + (2,))[..., None, :]  # (..., 1, 2)
    d = jnp.stack([jnp.cos(angles), jnp.sin(angles)], axis=-1)
    d = jnp.broadcast_to(d, shape + (2,))[..., None, :]  # (..., 1, 2)
    a = segments[:, :2]
    e = segments[:, 2:] - a  # (M, 2)
    ap = a - origins  # (..., M, 2)
    denom = d[..., 0] * e[:, 1] - d[..., 1] * e[:, 0]  # cross(d, e)
    e_len = jnp.hypot(e[:, 0], e[:, 1])
    # Tolerances relative to the segment's length, above float32 resolution: a ray parallel to
    # a segment (sin < 1e-6) never hits it, nor does a ray starting on a segment's line.
    ok = jnp.abs(denom) > 1e-6 * e_len
    cross_ap_e = ap[..., 0] * e[:, 1] - ap[..., 1] * e[:, 0]
    on_line = jnp.abs(cross_ap_e) <= 1e-5 * e_len
    safe = jnp.where(ok, denom, 1.0)
    t = cross_ap_e / safe  # distance along the ray
    s = (ap[..., 0] * d[..., 1] - ap[..., 1] * d[..., 0]) / safe  # position on the segment
    hit = ok & ~on_line & (t > _EPS) & (s >= 0.0) & (s <= 1.0)
    if active is not None:
        hit = hit & active
    t = jnp.where(hit, t, jnp.inf)
    first = jnp.argmin(t, axis=-1)
    best = jnp.min(t, axis=-1)
    found = best < max_range
    return jnp.where(found, best, max_range), jnp.where(found, first, -1).astype(jnp.int32)


def expected_ranges(segments: Float[Array, "M 4"], pose: Float[Array, "3"], sensor: SensorSpec,
                    active: Bool[Array, "M"] | None = None, max_range=None) -> tuple[Float[Array, "B"], Int[Array, "B"]]:
    """The ranges (m) the map predicts for every beam of a scan taken at robot ``pose``, and
    the segment each beam hits first (-1: none within ``max_range``, default ``range_max``)."""
    origin, angles = laser_rays(pose, sensor)
    return raycast(segments, origin, angles, sensor.range_max if max_range is None else max_range, active)
