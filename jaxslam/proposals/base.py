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

A proposal is one :class:`Proposal` row (:data:`jaxslam.proposals.PROPOSALS`), which carries what it
owns besides its draw: its static settings (:class:`Setting`, read as ``config.<name>``), its traced
numbers (:class:`ParamGroup`, read as ``params.<group>``), its command-line flags (:class:`Flag`),
how many future scans it reads, whether it searches the window posterior (and so gets the slip
search) and what memory it adds.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

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


class Setting(NamedTuple):
    """A static setting a proposal owns: a ``SlamConfig`` name (it sets shapes or code paths, so
    changing it recompiles), read as ``config.<name>`` and set by name in ``build_setup``."""

    name: str
    """Its flat name (``num_localizers``); unique over the registered proposals and
    ``SlamConfig``'s own fields."""
    default: Any
    """Its default; its type is the setting's type (int, float or str), checked as ``SlamConfig``'s
    own fields are."""
    check: Callable[[Any], bool]
    """Whether a value of that type is accepted."""
    accepted: str
    """What is accepted, in words (the refusal's message)."""
    doc: str
    """What it sets, with units."""


class ParamGroup(NamedTuple):
    """The traced numbers a proposal owns: a group of ``SlamParams``, read as
    ``params.<name>.<field>`` and set by the dotted name ``<name>.<field>``."""

    name: str
    """The group's name (``lookahead``); unique over the registered proposals and ``SlamParams``'
    own groups."""
    numbers: type
    """A ``NamedTuple`` of float32 scalars, one field per number."""
    defaults: dict[str, float]
    """Every field's default."""
    ranges: dict[str, tuple[Callable[[float], bool], str]]
    """Every field's physical range: (predicate, what is accepted in words)."""


class Flag(NamedTuple):
    """A command-line flag of a proposal's setting or number (``--localizers``)."""

    flag: str
    """The flag (``--localizers``)."""
    name: str
    """The ``build_setup`` name it sets (``num_localizers``, ``lookahead.alpha``)."""
    type: type
    """int or float."""
    help: str
    """What it sets, in a few words (``--help`` adds the default)."""
    minimum: int | None = None
    """An int flag's least value, checked with the flag's name before any work (None: the setting's
    own check names it)."""


def _never(config) -> bool:
    return False


def _no_future_scans(config) -> int:
    return 0


def _no_extra_memory(config, num_beams: int) -> tuple[int, str]:
    return 0, ""


class Proposal(NamedTuple):
    """A proposal of the RBPF: its draw and what it owns (one row of :data:`jaxslam.proposals.PROPOSALS`)."""

    propose_fn: Callable[..., ProposalOutput]
    """``propose_fn(key, pose, field, inputs, sensor, params, config, step_motion=None) -> ProposalOutput``
    for one particle (the filter vmaps it; the module docstring)."""
    summary: str
    """What it draws from, in a few words (the command line's help)."""
    settings: tuple[Setting, ...] = ()
    """Its static settings (``SlamConfig`` names)."""
    params: ParamGroup | None = None
    """Its traced numbers (a ``SlamParams`` group), or None."""
    flags: tuple[Flag, ...] = ()
    """The command-line flags of its settings and numbers."""
    future_scans_fn: Callable[[Any], int] = _no_future_scans
    """``future_scans_fn(config) -> K``: the future scans each step carries (``StepInputs.future_*``)."""
    searches_window_fn: Callable[[Any], bool] = _never
    """``searches_window_fn(config) -> bool``: whether it searches the window posterior, and so gets
    the filter's slip search (:mod:`jaxslam.slip_search`)."""
    memory_fn: Callable[[Any, int], tuple[int, str]] = _no_extra_memory
    """``memory_fn(config, num_beams) -> (bytes, how)``: the memory its draw adds to a run's
    estimate (:func:`jaxslam.resources.estimate_run_bytes`), with the arithmetic in words."""
