"""What every proposal takes and returns.

A proposal draws one SLAM particle's next pose given its previous pose and its map
m_{t-1}, and returns the log-weight increment. All proposals share the signature

    propose(key, pose, field, inputs, sensor, params, config, step_motion=None) -> ProposalOutput

for ONE particle; ``step_motion`` is the motion model of step t (None: ``params.motion``; the
filter's slip search passes the slip component, :func:`jaxslam.slip_search.slip_motion`), while the
look-ahead's horizon keeps ``params.motion``; the RBPF vmaps it over particles. ``field`` is the particle's likelihood
field m_{t-1} (a :class:`~jaxslam.maps.PagedField`: its directory and the shared pools; a
dense (H, W) field also works where ``config.grid`` is a dense :class:`~jaxslam.grid.GridSpec`). ``inputs.ranges`` and
``inputs.future_ranges`` are already beam-subsampled (``config.beam_stride``),
and ``sensor`` matches them.
"""

from __future__ import annotations

from typing import NamedTuple

from jaxtyping import Array, Bool, Float


class StepInputs(NamedTuple):
    """One processed scan and, for the look-ahead, the scans after it."""

    motion: Float[Array, "3"]
    """Odometry motion [dx, dy, dtheta] from the previous processed scan (its robot frame)."""
    ranges: Float[Array, "B"]
    """The scan z_t (m)."""
    future_motions: Float[Array, "K 3"]
    """Motions u_{t+1..t+K} (K = config.lookahead_steps; zero-sized for OP and SMP)."""
    future_ranges: Float[Array, "K B"]
    """Scans z_{t+1..t+K}."""
    future_valid: Bool[Array, "K"]
    """False past the end of the log: the horizon shrinks there, never padded with fake scans."""


class ProposalOutput(NamedTuple):
    """One particle's draw."""

    pose: Float[Array, "3"]
    """The new pose x_t."""
    log_weight_increment: Float[Array, ""]
    """log w_t - log w_{t-1}."""
    fallback: Bool[Array, ""]
    """SMP: the match failed and the odometry proposal was used. LP: no localizer kept weight."""


def step_params(params, step_motion):
    """``params`` with the motion model of step t: ``step_motion``, or ``params.motion`` when None."""
    return params if step_motion is None else params._replace(motion=step_motion)
