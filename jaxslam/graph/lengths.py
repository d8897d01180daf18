"""The chain's step lengths: what each scan pins, and the odometry where it pins nothing.

The chain's steps are the filter's relative poses. A scan matched in its map pins the pose
along the normals of the surfaces it sees: in a room every direction, in a corridor only across
it. Along a corridor the scan slides, and the filter's step lengths there are what its particles
drew and kept: FR-clinic's corridors come out 1.9-2.5 % long against its relations, where the
odometry's are within 0.1 %. The loops cannot see this. A loop closes a path at any scale: on
FR-clinic the kept loops' chi2 is least with the chain's lengths as they are, though 2 % shorter
steps fit the relations better.

So the final graph takes each step's translation from two edges (:func:`weighed_steps`): the
chain's, with the information the scan's structure gives (:func:`scan_structure`), and the
odometry's, with the motion model's. Where the scan pins a direction, the chain's step holds
there; along a corridor the odometry's length does. The heading stays the chain's alone
(:mod:`jaxslam.graph.drift` weighs it).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxslam.geometry import rotation_np
from jaxslam.graph.pose_graph import ODOMETRY, Edges, concat_edges
from jaxslam.laser import scan_points
from jaxslam.motion import noise_std

NORMAL_SPAN = 3
"""A point's normal is taken across the returns this many places either side: one each side
is noise at a few centimetres' spacing (FR-clinic's corridors then looked half as degenerate)."""
MAX_NORMAL_GAP = 1.0
"""Longest chord (m) across which two returns are taken as one surface: farther apart, they are
two objects, and the chord between them is no surface's tangent."""


def scan_structure(ranges: np.ndarray, sensor, max_range: float) -> np.ndarray:
    """How each scan's surfaces pin its position: the mean of ``n n^T`` over its returns' unit
    normals, in the robot frame.

    Args:
        ranges: (S, B) scans (m).
        sensor: the laser (:class:`jaxslam.laser.SensorSpec`).
        max_range: longest return used (m).

    Returns:
        (S, 2, 2) float64, symmetric, trace 1 where the scan has a surface and 0 where it has
        none. An eigenvalue is the share of the normals along its axis: about 1/2 each in a room,
        near 0 along a corridor.
    """
    ranges = np.asarray(ranges, np.float32)
    points, valid = scan_points(ranges, sensor, max_range, ranges.shape[1])
    points = points.astype(np.float64)
    chord = points[:, 2 * NORMAL_SPAN:] - points[:, :-2 * NORMAL_SPAN]
    length = np.linalg.norm(chord, axis=-1)
    surface = (valid[:, 2 * NORMAL_SPAN:] & valid[:, :-2 * NORMAL_SPAN] & valid[:, NORMAL_SPAN:-NORMAL_SPAN]
               & (length > 1e-6) & (length < MAX_NORMAL_GAP))
    normal = np.stack([-chord[..., 1], chord[..., 0]], axis=-1) / np.where(surface, length, 1.0)[..., None]
    count = surface.sum(axis=1)
    return np.einsum("spi,spj,sp->sij", normal, normal, surface) / np.maximum(count, 1)[:, None, None]


def weighed_steps(sequential: Edges, structure: np.ndarray, motions: np.ndarray, motion_params,
                  resolution: float) -> Edges:
    """The chain's edges with each step's translation weighed by what its scan pins, followed
    by the odometry's translation over the same steps.

    A scan whose surfaces face every way (``structure`` = I/2) is taken to pin its pose to half
    a map cell along each axis, and a step, the difference of two such poses, to twice that
    variance: the chain's translation information is ``4 / resolution^2`` times the second
    scan's structure. The odometry's edges carry the motion model's translation information and
    none for the heading.

    Args:
        sequential: the chain's S - 1 edges (``first`` = ``second`` - 1; the heading information
            kept as given).
        structure: (S, 2, 2) :func:`scan_structure` of every node's scan.
        motions: (S, 3) odometry motion from the previous node, in its frame (row 0 unused).
        motion_params: the filter's :class:`jaxslam.motion.MotionParams`.
        resolution: the map's cell size (m).

    Returns:
        2 (S - 1) edges: the chain's, then the odometry's (kind :data:`ODOMETRY`).
    """
    if resolution <= 0:
        raise ValueError(f"weighed_steps: resolution must be > 0 (m), got {resolution}")
    if structure.ndim != 3 or structure.shape[1:] != (2, 2) or structure.shape[0] != motions.shape[0]:
        raise ValueError(f"weighed_steps: structure must be (S, 2, 2) for the S = {motions.shape[0]} nodes' motions, "
                         f"got {structure.shape}")
    # An edge's error is taken in its measurement's frame, turned by the step's heading: the second
    # node's robot frame, where its scan's structure already is; the odometry's noise is in the first.
    heading = sequential.measurement[:, 2]
    turn = rotation_np(heading)  # second's frame -> first's
    chain_information = sequential.information.copy()
    chain_information[:, :2, :2] = structure[sequential.second] * (4.0 / resolution ** 2) + 1e-6 * np.eye(2)
    std = np.asarray(noise_std(jnp.asarray(motions[sequential.second], jnp.float32), motion_params), np.float64)
    odometry_information = np.zeros_like(sequential.information)
    odometry_information[:, :2, :2] = np.einsum("sji,sj,sjk->sik", turn, 1.0 / np.maximum(std[:, :2], 1e-6) ** 2, turn)
    odometry_measurement = np.concatenate([motions[sequential.second, :2], heading[:, None]], axis=1)
    chain = sequential._replace(information=chain_information)
    odometry = Edges(sequential.first, sequential.second, odometry_measurement, odometry_information,
                     np.full(sequential.count, ODOMETRY))
    return concat_edges(chain, odometry)
