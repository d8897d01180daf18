"""The traced numbers of the RBPF (:class:`SlamParams`): a pytree of float32 scalars, so changing
them never recompiles and they can be differentiated.

Built from dotted names (``motion.srr``, ``lookahead.alpha``) by :func:`params_from_dict`, each
checked against its physical range before any work. ``SlamParams`` holds its own groups (motion,
likelihood, insertion, scan matcher) and each registered proposal's group
(:data:`jaxslam.proposals.PROPOSALS`; the LP's ``lookahead``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxslam.checks import ConfigError, check_float
from jaxslam.likelihood_field import LikelihoodParams
from jaxslam.motion import MotionParams, motion_params
from jaxslam.occupancy import InsertionParams
from jaxslam.proposals import proposal_param_groups


class ScanMatchParams(NamedTuple):
    """Traced numbers of the window posterior (the SMP's and the LP's), its match score and the
    refinement's matcher."""

    linear_step: Float[Array, ""]
    """Spacing (m) in x, y of the 27-pose stencil each window-posterior mode's Gaussian and mass
    come from; also the refinement's hill climber's first step."""
    angular_step: Float[Array, ""]
    """The stencil's spacing (rad) in theta; also the refinement's climber's first step."""
    min_score: Float[Array, ""]
    """Mean per-beam match quality (0..1) under which the match counts as failed (fall back to OP)."""
    min_std_fraction: Float[Array, ""]
    """Floor of the std of the likelihood's Gaussian fitted on the stencil, as a fraction of its
    spacing, before the product with the motion prior (sets particle diversity where the scan is sharp)."""
    window_sigmas: Float[Array, ""]
    """Half-side of the window posterior's window in each axis, in the step's motion-noise stds."""
    window_min_xy: Float[Array, ""]
    """... but at least this (m) in x and y ..."""
    window_min_theta: Float[Array, ""]
    """... and this (rad) in heading."""
    slip_trigger: Float[Array, ""]
    """The slip search runs at a step when the heaviest particle's posterior probability that the
    step's odometry slipped is above this (its window posterior's evidence under the slip
    component against the usual motion model; 1 never runs it). The odometry is common to every
    particle, so one particle can tell. See :func:`jaxslam.slip_search.slip_log_odds`."""
    slip_probability: Float[Array, ""]
    """epsilon, the prior probability that a step's odometry slipped: the motion model is then the
    mixture (1 - epsilon) p(x | x_{t-1}, u_t) + epsilon N(x_{t-1} (+) u_t, diag(slip stds^2))."""
    slip_std_xy: Float[Array, ""]
    """The slip component's std (m) in x and y, whatever the step's motion: a slip's size does
    not scale with the distance driven."""
    slip_std_theta: Float[Array, ""]
    """... and in heading (rad)."""


class SlamParams(NamedTuple):
    """Traced numbers of the RBPF. Changing them never recompiles; differentiable."""

    motion: MotionParams
    """Odometry noise."""
    likelihood: LikelihoodParams
    """Endpoint (likelihood-field) model."""
    insertion: InsertionParams
    """Occupancy log-odds increments and clamps."""
    scan_match: ScanMatchParams
    """Scan matcher and SMP."""
    resample_threshold: Float[Array, ""]
    """SLAM particles are resampled when ESS < this * N (GMapping: 0.5)."""
    proposals: dict[str, Any]
    """The numbers the proposals own, by group (:data:`jaxslam.proposals.PROPOSALS`; the LP's
    ``LookaheadParams`` under "lookahead"), read as attributes: ``params.lookahead.alpha``."""

    def __getattr__(self, name):
        # Only called when the usual lookup fails: a proposal's group.
        groups = self.proposals
        if name in groups:
            return groups[name]
        raise AttributeError(f"'SlamParams' object has no attribute {name!r}")

    def with_group(self, name: str, numbers) -> "SlamParams":
        """These parameters with a proposal's group replaced (``params.with_group("lookahead",
        params.lookahead._replace(alpha=a))``); ``_replace`` for the groups."""
        if name not in self.proposals:
            raise KeyError(f"SlamParams has no proposal group {name!r}; groups: {sorted(self.proposals)}")
        return self._replace(proposals={**self.proposals, name: numbers})


_OWN_GROUPS = ("motion", "likelihood", "insertion", "scan_match")


def _flatten_params_with_keys(params: SlamParams):
    # The proposals' groups sit beside the own ones (before resample_threshold, where the LP's
    # was a field): a leaf's key path is its dotted name ("lookahead.alpha", as build_setup
    # takes it), so learning's parameter names need no rule of their own.
    names = tuple(sorted(params.proposals))
    children = [(jax.tree_util.GetAttrKey(name), getattr(params, name)) for name in _OWN_GROUPS]
    children += [(jax.tree_util.GetAttrKey(name), params.proposals[name]) for name in names]
    children.append((jax.tree_util.GetAttrKey("resample_threshold"), params.resample_threshold))
    return children, names


def _unflatten_params(names, children) -> SlamParams:
    own = len(_OWN_GROUPS)
    return SlamParams(*children[:own], resample_threshold=children[-1],
                      proposals=dict(zip(names, children[own:-1])))


jax.tree_util.register_pytree_with_keys(
    SlamParams, _flatten_params_with_keys, _unflatten_params,
    lambda params: ([child for _, child in _flatten_params_with_keys(params)[0]], tuple(sorted(params.proposals))))


_DEFAULTS: dict[str, float] = {
    # GMapping's ROS defaults for the odometry noise.
    "motion.srr": 0.1, "motion.srt": 0.2, "motion.str": 0.1, "motion.stt": 0.2,
    "motion.min_translation_std": 0.01, "motion.min_rotation_std": 0.005,
    "likelihood.sigma": 0.05, "likelihood.z_hit": 0.9, "likelihood.z_rand": 0.05,
    "likelihood.gain": 0.1, "likelihood.see_through": 0.05, "likelihood.free_margin": 0.15,
    "insertion.logodds_occupied": 0.85, "insertion.logodds_free": -0.4,
    "insertion.logodds_min": -4.0, "insertion.logodds_max": 4.0,
    "insertion.no_return_free_range": 5.0,
    "scan_match.linear_step": 0.05, "scan_match.angular_step": 0.05, "scan_match.min_score": 0.15,
    "scan_match.min_std_fraction": 0.1,
    "scan_match.window_sigmas": 3.0, "scan_match.window_min_xy": 0.1, "scan_match.window_min_theta": 0.1,
    "scan_match.slip_trigger": 0.5, "scan_match.slip_probability": 0.01, "scan_match.slip_std_xy": 0.3,
    "scan_match.slip_std_theta": 0.35,
    "resample_threshold": 0.5,
}
"""The defaults of ``SlamParams``' own numbers (:func:`param_defaults` adds the proposals')."""


def default_params(**overrides: float) -> SlamParams:
    """``SlamParams`` with defaults, overridden by dotted names (``**{"motion.srr": 0.05}``)
    or underscored ones (``motion__srr=0.05``)."""
    return params_from_dict({k.replace("__", "."): v for k, v in overrides.items()})


def _at_least(lo):
    return lambda v: v >= lo


def _above(lo):
    return lambda v: v > lo


_PARAM_RANGES: dict[str, tuple[Any, str]] = {
    # name: (predicate on the value, what is accepted). Every value must also be a finite number.
    **{f"motion.{f}": (_at_least(0.0), ">= 0") for f in ("srr", "srt", "str", "stt", "min_translation_std",
                                                          "min_rotation_std")},
    "likelihood.sigma": (_above(0.0), "> 0 (m)"),
    "likelihood.z_hit": (_at_least(0.0), ">= 0"),
    "likelihood.z_rand": (_above(0.0), "> 0 (it keeps log-likelihoods finite)"),
    "likelihood.gain": (_above(0.0), "> 0"),
    "likelihood.see_through": (lambda v: 0.0 < v <= 1.0, "in (0, 1] (a probability; 1 adds no evidence)"),
    "likelihood.free_margin": (_at_least(0.0), ">= 0 (m)"),
    "insertion.logodds_occupied": (_above(0.0), "> 0 (a hit makes a cell more likely occupied)"),
    "insertion.logodds_free": (lambda v: v < 0, "< 0 (a beam passing through makes a cell more likely free)"),
    "insertion.logodds_min": (lambda v: v < 0, "< 0 (the lower clamp must let a cell turn free)"),
    "insertion.logodds_max": (_above(0.0), "> 0 (the upper clamp must let a cell turn occupied)"),
    "insertion.no_return_free_range": (_at_least(0.0), ">= 0 (m)"),
    "scan_match.linear_step": (_above(0.0), "> 0 (m)"),
    "scan_match.angular_step": (_above(0.0), "> 0 (rad)"),
    # Above 1 is allowed and used (tests): no match reaches it, so the SMP always falls back to the OP.
    "scan_match.min_score": (_at_least(0.0), ">= 0 (a mean per-beam fit in [0, 1]; above 1 every match fails)"),
    "scan_match.min_std_fraction": (_at_least(0.0), ">= 0"),
    "scan_match.window_sigmas": (_above(0.0), "> 0"),
    "scan_match.window_min_xy": (_above(0.0), "> 0 (m)"),
    "scan_match.window_min_theta": (_above(0.0), "> 0 (rad)"),
    "scan_match.slip_trigger": (lambda v: 0.0 <= v <= 1.0, "in [0, 1] (a probability; 1 never searches)"),
    "scan_match.slip_probability": (lambda v: 0.0 <= v < 1.0, "in [0, 1) (0: a slip is never drawn)"),
    "scan_match.slip_std_xy": (_above(0.0), "> 0 (m)"),
    "scan_match.slip_std_theta": (_above(0.0), "> 0 (rad)"),
    # Above 1 is allowed and used (tests, "above 1 always does"): ESS <= N, so every step resamples.
    "resample_threshold": (_at_least(0.0), ">= 0 (a fraction of N: 0 never resamples, above 1 always)"),
}
"""The physical range of ``SlamParams``' own numbers, checked by :func:`params_from_dict`
(:func:`param_ranges` adds the proposals')."""


def param_defaults() -> dict[str, float]:
    """Every dotted parameter with its default: ``SlamParams``' own and the registered proposals'."""
    return {**_DEFAULTS, **{f"{group.name}.{f}": v for group in proposal_param_groups().values()
                            for f, v in group.defaults.items()}}


def param_ranges() -> dict[str, tuple[Any, str]]:
    """Every dotted parameter's physical range: (predicate, what is accepted)."""
    return {**_PARAM_RANGES, **{f"{group.name}.{f}": r for group in proposal_param_groups().values()
                                for f, r in group.ranges.items()}}


def params_from_dict(values: dict[str, Any]) -> SlamParams:
    """Build ``SlamParams`` from dotted names; anything missing keeps its default.

    Every value must be a finite number (a string that parses as one, as ``--set`` gives, is
    fine; a bool is not) in its physical range (:data:`_PARAM_RANGES`: noise >= 0, sigma > 0,
    log-odds signs, steps > 0, ...). Unknown names and bad values raise ``ConfigError`` naming
    the parameter, the value and what is accepted.
    """
    if not isinstance(values, dict):
        raise ConfigError(f"parameters must be a dict of dotted names and numbers, got {values!r}")
    defaults = param_defaults()
    unknown = sorted(set(values) - set(defaults), key=str)
    if unknown:
        raise ConfigError(f"unknown parameter(s) {unknown}; known: {sorted(defaults)}")
    merged = {**defaults, **values}
    for name, value in merged.items():
        if isinstance(value, str):
            try:
                value = float(value.strip())
            except ValueError:
                raise ConfigError(f"parameter {name} must be a number, got {value!r}") from None
        merged[name] = check_float(f"parameter {name}", value)
    for name, (ok, accepted) in param_ranges().items():
        if not ok(merged[name]):
            raise ConfigError(f"parameter {name} must be {accepted}, got {merged[name]!r}")

    def group(cls, prefix):
        return cls(**{f: jnp.float32(merged[f"{prefix}.{f}"]) for f in cls._fields})

    return SlamParams(
        motion=motion_params(*(merged[f"motion.{f}"] for f in MotionParams._fields)),
        likelihood=group(LikelihoodParams, "likelihood"),
        insertion=group(InsertionParams, "insertion"),
        scan_match=group(ScanMatchParams, "scan_match"),
        resample_threshold=jnp.float32(merged["resample_threshold"]),
        proposals={name: group(g.numbers, name) for name, g in proposal_param_groups().items()},
    )


def params_to_dict(params: SlamParams) -> dict[str, float]:
    """Flat dotted-name view of ``SlamParams`` (for summaries and config files)."""
    out = {}
    groups = {name: getattr(params, name) for name in SlamParams._fields if name != "proposals"}
    for name, value in {**groups, **params.proposals}.items():
        if hasattr(value, "_fields"):
            out.update({f"{name}.{f}": float(getattr(value, f)) for f in value._fields})
        else:
            out[name] = float(value)
    return out
