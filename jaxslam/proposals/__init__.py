"""The proposal distributions of the RBPF, by name.

:data:`PROPOSALS` is the one table of them: the filter draws with ``PROPOSALS[config.proposal]``,
``SlamConfig`` accepts its names, and the command line offers them. A new proposal is one
module with a ``propose`` function of the signature in :mod:`jaxslam.proposals.base`, and one
row here.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from jaxslam.proposals import lookahead, odometry, scan_match
from jaxslam.proposals.base import ProposalOutput, StepInputs


class Proposal(NamedTuple):
    """A proposal of the RBPF."""

    propose_fn: Callable[..., ProposalOutput]
    """``propose_fn(key, pose, field, inputs, sensor, params, config, step_motion=None) -> ProposalOutput`` for one
    particle (the filter vmaps it; :mod:`jaxslam.proposals.base`)."""
    looks_ahead: bool
    """Whether each step needs the next ``config.horizon`` scans (``StepInputs.future_*``)."""
    summary: str
    """What it draws from, in a few words (the command line's help)."""


PROPOSALS: dict[str, Proposal] = {
    "op": Proposal(odometry.propose, False, "odometry: the motion model"),
    "smp": Proposal(scan_match.propose, False,
                    "scan matching (GMapping's proposal): a Gaussian round each mode of the window posterior"),
    "lp": Proposal(lookahead.propose, True, "look-ahead: L localizers run k scans ahead in each particle's map"),
}
"""The proposals by name (``SlamConfig.proposal``)."""

__all__ = ["PROPOSALS", "Proposal", "ProposalOutput", "StepInputs"]
