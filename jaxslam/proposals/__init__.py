"""The proposal distributions of the RBPF, by name.

:data:`PROPOSALS` is the one table of them. Each row is a :class:`Proposal` its module defines:
its draw, its static settings (``config.num_localizers``), its traced numbers
(``params.lookahead``), its command-line flags, the future scans it reads, whether it gets the
slip search and what memory it adds. ``SlamConfig``, ``build_setup``, the command line and the
memory check read them from the table. A new proposal is one module that builds a
:class:`Proposal`, and one row here, or a call to :func:`jaxslam.config.register_proposal` (which is how
``tests/test_proposal_registry.py`` maps with a proposal defined in the test).
"""

from __future__ import annotations

from jaxslam.proposals import lookahead, odometry, scan_match
from jaxslam.proposals.base import Flag, ParamGroup, Proposal, ProposalOutput, Setting, StepInputs

PROPOSALS: dict[str, Proposal] = {
    "op": odometry.PROPOSAL,
    "smp": scan_match.PROPOSAL,
    "lp": lookahead.PROPOSAL,
}
"""The proposals by name (``SlamConfig.proposal``)."""


def _owned(kind: str) -> dict:
    out = {}
    for name, proposal in PROPOSALS.items():
        items = proposal.settings if kind == "settings" else proposal.flags if kind == "flags" else (
            () if proposal.params is None else (proposal.params,))
        for item in items:
            key = item.flag if kind == "flags" else item.name
            if key in out and out[key] is not item:
                raise ValueError(f"proposal {name!r}: {kind[:-1]} {key!r} is taken by another proposal")
            out[key] = item
    return out


def proposal_settings() -> dict[str, Setting]:
    """Every registered proposal's static settings, by name."""
    return _owned("settings")


def proposal_param_groups() -> dict[str, ParamGroup]:
    """Every registered proposal's traced numbers, by group name."""
    return _owned("groups")


def proposal_flags() -> dict[str, Flag]:
    """Every registered proposal's command-line flags, by flag."""
    return _owned("flags")


def add_proposal(name: str, proposal: Proposal, reserved: frozenset[str]) -> None:
    """Add ``proposal`` to :data:`PROPOSALS` as ``name`` (:func:`jaxslam.config.register_proposal`,
    which passes ``SlamConfig``'s and ``SlamParams``' own names as ``reserved``). Refuses a name
    taken by another proposal (adding the same row again is a no-op), and a setting, group or flag
    that another proposal owns or that is ``reserved``."""
    if not isinstance(proposal, Proposal):
        raise TypeError(f"add_proposal: expected a Proposal, got {type(proposal).__name__}")
    if name in PROPOSALS:
        if PROPOSALS[name] is not proposal:
            raise ValueError(f"add_proposal: {name!r} is taken by another proposal")
        return
    clashes = [s.name for s in proposal.settings if s.name in reserved]
    clashes += [] if proposal.params is None or proposal.params.name not in reserved else [proposal.params.name]
    if clashes:
        raise ValueError(f"add_proposal: {name!r} owns {clashes}, names of SlamConfig or SlamParams")
    PROPOSALS[name] = proposal
    try:
        for kind in ("settings", "groups", "flags"):
            _owned(kind)
    except ValueError:
        del PROPOSALS[name]
        raise


__all__ = ["Flag", "PROPOSALS", "ParamGroup", "Proposal", "ProposalOutput", "Setting", "StepInputs",
           "add_proposal", "proposal_flags", "proposal_param_groups", "proposal_settings"]
