"""The settings of the RBPF, split by who reads them.

* ``SlamConfig`` holds everything that sets array shapes or picks code paths inside the
  jitted step (particle counts, horizon, map shape, beam subsampling, proposal kind): a
  frozen, hashable dataclass passed to ``jax.jit`` as a static argument; changing it
  recompiles.
* ``RunSettings`` holds what only the host-side driver reads (the update rule that selects
  the processed scans, and how a grid is sized from a log): changing it never recompiles.
* ``SlamParams`` holds the numbers (noise, gains, thresholds): a pytree of float32 arrays,
  traced, so changing it never recompiles and it can be differentiated.

All three are built from one flat dictionary of names (:func:`build_setup`): config and
settings fields by name (``num_particles``, ``linear_update``), parameters by dotted name
(``motion.srr``, ``likelihood.sigma``), as the command line's ``--set`` and config files
give them.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxslam.grid import GridSpec
from jaxslam.likelihood_field import FIELD_LOOKUPS, LikelihoodParams
from jaxslam.motion import MotionParams
from jaxslam.occupancy import InsertionParams
from jaxslam.resampling import RESAMPLERS

PROPOSALS = ("op", "smp", "lp")


class ConfigError(ValueError):
    """A configuration or parameter value is invalid; the message names it."""


@dataclasses.dataclass(frozen=True)
class SlamConfig:
    """Static settings of the jitted RBPF step (shapes and code paths). Hashable; changing it recompiles."""

    num_particles: int = 30
    """N, the number of SLAM particles (each with its own map)."""
    proposal: str = "smp"
    """Proposal distribution: "op" (odometry), "smp" (scan matching), "lp" (look-ahead)."""
    grid: GridSpec | None = None
    """The map's shape and placement; None: ``rbpf.run`` sizes it from the log
    (``RunSettings.resolution`` and ``map_padding``)."""
    max_insert_range: float = 15.0
    """Beams are inserted into the map up to this range (m); sets samples per beam."""
    field_radius: int = 4
    """Radius (cells) of the likelihood field around each registered endpoint."""
    likelihood_lookup: str = "nearest"
    """How a beam's endpoint reads the likelihood field in the particle weights (every proposal,
    the SMP's fitted Gaussian, the LP's localizers): "nearest" (the cell it falls in) or
    "bilinear" (interpolated between the four surrounding cells, so the likelihood is continuous
    in the pose; four gathers per beam). See ``jaxslam.likelihood_field``."""
    match_lookup: str = "bilinear"
    """The same choice for the hill-climbing scan matcher (the SMP's and LP-SM's match, and the
    refinement's matches and their covariances). "bilinear" (the default) lets the matcher
    settle between cells instead of stopping wherever a whole cell stops improving: on Intel,
    ACES and MIT CSAIL it is as accurate or more (docs/results.md). "nearest" is what the
    box-world tables were measured with."""
    beam_stride: int = 2
    """Use every ``beam_stride``-th beam in likelihoods (the map always gets all beams)."""
    resampler: str = "systematic"
    """Resampling scheme: systematic, stratified, multinomial or residual."""
    match_iterations: int = 24
    """Fixed iteration budget of the hill-climbing scan matcher."""
    num_localizers: int = 100
    """L, localizer particles per SLAM particle in the look-ahead proposal."""
    horizon: int = 5
    """k, the look-ahead horizon in processed scans (0: the LP's weights reduce to an average)."""
    lookahead_initial: str = "odometry"
    """Where the LP draws its L time-t localizers: "odometry" (the motion model, as in the paper)
    or "scan_match" (a Gaussian fitted around the scan-matched pose, importance-corrected)."""

    def __post_init__(self):
        checks = [
            (self.num_particles >= 1, "num_particles must be >= 1"),
            (self.proposal in PROPOSALS, f"proposal must be one of {PROPOSALS}, got {self.proposal!r}"),
            (self.max_insert_range > 0, "max_insert_range must be > 0"),
            (1 <= self.field_radius <= 11, "field_radius must be in 1..11 (its squared distances fit uint8)"),
            (self.likelihood_lookup in FIELD_LOOKUPS,
             f"likelihood_lookup must be one of {FIELD_LOOKUPS}, got {self.likelihood_lookup!r}"),
            (self.match_lookup in FIELD_LOOKUPS,
             f"match_lookup must be one of {FIELD_LOOKUPS}, got {self.match_lookup!r}"),
            (self.beam_stride >= 1, "beam_stride must be >= 1"),
            (self.resampler in RESAMPLERS, f"resampler must be one of {sorted(RESAMPLERS)}"),
            (self.match_iterations >= 0, "match_iterations must be >= 0"),
            (self.num_localizers >= 1, "num_localizers must be >= 1"),
            (self.horizon >= 0, "horizon must be >= 0"),
            (self.lookahead_initial in ("odometry", "scan_match"),
             f"lookahead_initial must be 'odometry' or 'scan_match', got {self.lookahead_initial!r}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"SlamConfig: {message}")

    @property
    def lookahead_steps(self) -> int:
        """Future scans each step carries: the horizon for LP, none otherwise."""
        return self.horizon if self.proposal == "lp" else 0


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """Host-side settings of ``rbpf.run``: which scans are processed and how a grid is sized
    from a log. Never part of the jitted step, so changing them never recompiles it."""

    linear_update: float = 1.0
    """Process a scan after this much travel (m) since the last processed one (GMapping)."""
    angular_update: float = 0.5
    """... or after this much rotation (rad)."""
    resolution: float = 0.05
    """Map cell size (m) of a grid sized from the log (``SlamConfig.grid`` None)."""
    map_padding: float = 8.0
    """Metres added around the odometry's extent when the grid is sized from the log."""

    def __post_init__(self):
        checks = [
            (self.linear_update >= 0, "linear_update must be >= 0"),
            (self.angular_update >= 0, "angular_update must be >= 0"),
            (self.resolution > 0, "resolution must be > 0"),
            (self.map_padding >= 0, "map_padding must be >= 0"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"RunSettings: {message}")


class ScanMatchParams(NamedTuple):
    """Traced numbers of the scan matcher and the scan-matching proposal."""

    linear_step: Float[Array, ""]
    """Initial step (m) of the hill climber; also the SMP's sampling stencil spacing in x, y."""
    angular_step: Float[Array, ""]
    """Initial step (rad) of the hill climber and the stencil spacing in theta."""
    min_score: Float[Array, ""]
    """Mean per-beam match quality (0..1) under which the match counts as failed (fall back to OP)."""
    min_std_fraction: Float[Array, ""]
    """Floor of the SMP Gaussian's std, as a fraction of the stencil spacing (sets particle diversity)."""
    start_noise: Float[Array, ""]
    """The SMP's hill climber starts from a draw of the motion model with its stds times this
    (GMapping: 1, each particle matches from its own odometry sample, so particles that share a
    map can land in different optima); 0 starts every particle from the odometry prediction."""


class LookaheadParams(NamedTuple):
    """Traced numbers of the look-ahead proposal."""

    alpha: Float[Array, ""]
    """Defensive share in [0, 1): 0 is the paper's Eq. 10; > 0 makes the weights unbiased."""
    resample_threshold: Float[Array, ""]
    """Localizers are resampled inside the horizon when their ESS < this * L."""
    localizer_gain: Float[Array, ""]
    """Likelihood gain inside the localizer filter (its weights a, g and so the selection).
    1 uses each scan's own sharpness, as the SMP's fit does. The SLAM weight increment is
    then scaled by ``likelihood.gain / localizer_gain`` (the tempered evidence), so setting
    it equal to ``likelihood.gain`` tempers the localizers and leaves the increment as is."""
    selection_correction: Float[Array, ""]
    """How much of the selection correction the SLAM weight keeps, in [0, 1]. The increment is
    log mean_i exp(g_i) + c (g_J - logsumexp(g) - log p_J): c = 1 (default) is the design's
    g_J - log L - log p_J, unbiased for alpha > 0 but noisy, since it depends on which sample
    was drawn; c = 0 weighs every SLAM particle by its evidence estimate alone, unbiased for
    every alpha (the paper's 0 included) and independent of the draw, so the look-ahead then
    only chooses the pose. Values in between temper the correction like the likelihood gain."""


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
    lookahead: LookaheadParams
    """Look-ahead proposal."""
    resample_threshold: Float[Array, ""]
    """SLAM particles are resampled when ESS < this * N (GMapping: 0.5)."""


_DEFAULTS: dict[str, float] = {
    # GMapping's ROS defaults for the odometry noise.
    "motion.srr": 0.1, "motion.srt": 0.2, "motion.str": 0.1, "motion.stt": 0.2,
    "motion.min_translation_std": 0.01, "motion.min_rotation_std": 0.005,
    "likelihood.sigma": 0.05, "likelihood.z_hit": 0.9, "likelihood.z_rand": 0.05,
    "likelihood.gain": 0.1,
    "insertion.logodds_occupied": 0.85, "insertion.logodds_free": -0.4,
    "insertion.logodds_min": -4.0, "insertion.logodds_max": 4.0,
    "insertion.no_return_free_range": 5.0,
    "scan_match.linear_step": 0.05, "scan_match.angular_step": 0.05, "scan_match.min_score": 0.15,
    "scan_match.min_std_fraction": 0.1, "scan_match.start_noise": 1.0,
    "lookahead.alpha": 0.5, "lookahead.resample_threshold": 0.5, "lookahead.localizer_gain": 1.0,
    "lookahead.selection_correction": 1.0,
    "resample_threshold": 0.5,
}


def default_params(**overrides: float) -> SlamParams:
    """``SlamParams`` with defaults, overridden by dotted names (``**{"motion.srr": 0.05}``)
    or underscored ones (``motion__srr=0.05``)."""
    return params_from_dict({k.replace("__", "."): v for k, v in overrides.items()})


def params_from_dict(values: dict[str, Any]) -> SlamParams:
    """Build ``SlamParams`` from dotted names; unknown names raise ``ConfigError``."""
    unknown = sorted(set(values) - set(_DEFAULTS))
    if unknown:
        raise ConfigError(f"unknown parameter(s) {unknown}; known: {sorted(_DEFAULTS)}")
    merged = {**_DEFAULTS, **values}
    for name, value in merged.items():
        try:
            merged[name] = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"parameter {name} must be a number, got {value!r}") from None
    if not 0.0 <= merged["lookahead.alpha"] < 1.0:
        raise ConfigError(f"parameter lookahead.alpha must be in [0, 1), got {merged['lookahead.alpha']}")
    if not 0.0 <= merged["lookahead.selection_correction"] <= 1.0:
        raise ConfigError("parameter lookahead.selection_correction must be in [0, 1], "
                          f"got {merged['lookahead.selection_correction']}")
    if merged["lookahead.localizer_gain"] <= 0:
        raise ConfigError(f"parameter lookahead.localizer_gain must be > 0, got {merged['lookahead.localizer_gain']}")
    if merged["likelihood.z_rand"] <= 0:
        raise ConfigError("parameter likelihood.z_rand must be > 0 (it keeps log-likelihoods finite)")

    def group(cls, prefix):
        return cls(**{f: jnp.float32(merged[f"{prefix}.{f}"]) for f in cls._fields})

    return SlamParams(
        motion=group(MotionParams, "motion"),
        likelihood=group(LikelihoodParams, "likelihood"),
        insertion=group(InsertionParams, "insertion"),
        scan_match=group(ScanMatchParams, "scan_match"),
        lookahead=group(LookaheadParams, "lookahead"),
        resample_threshold=jnp.float32(merged["resample_threshold"]),
    )


def params_to_dict(params: SlamParams) -> dict[str, float]:
    """Flat dotted-name view of ``SlamParams`` (for summaries and config files)."""
    out = {}
    for name in SlamParams._fields:
        value = getattr(params, name)
        if hasattr(value, "_fields"):
            out.update({f"{name}.{f}": float(getattr(value, f)) for f in value._fields})
        else:
            out[name] = float(value)
    return out


def config_to_dict(config) -> dict[str, Any]:
    """Plain-data view of a ``SlamConfig`` or ``RunSettings`` (JSON-ready)."""
    return dataclasses.asdict(config)


def _dataclass_from_dict(cls, values: dict[str, Any]):
    """``cls(**values)`` with every value converted to its field's type; bad types raise ``ConfigError``."""
    kwargs = {}
    for name, value in values.items():
        if name == "grid":
            kwargs[name] = None if value is None else GridSpec(tuple(value["shape"]), value["resolution"],
                                                               tuple(value["origin"]))
            continue
        default = getattr(cls, name)
        try:
            kwargs[name] = type(default)(value) if not isinstance(default, str) else str(value)
        except (TypeError, ValueError):
            raise ConfigError(f"config field {name} must be a {type(default).__name__}, got {value!r}") from None
    return cls(**kwargs)


CONFIG_FIELDS = tuple(f.name for f in dataclasses.fields(SlamConfig))
"""Names that set a :class:`SlamConfig` field."""
SETTINGS_FIELDS = tuple(f.name for f in dataclasses.fields(RunSettings))
"""Names that set a :class:`RunSettings` field."""


def config_from_dict(values: dict[str, Any]) -> SlamConfig:
    """Build a ``SlamConfig`` from field names; unknown names or bad types raise ``ConfigError``."""
    unknown = sorted(set(values) - set(CONFIG_FIELDS))
    if unknown:
        raise ConfigError(f"unknown config field(s) {unknown}; known: {sorted(CONFIG_FIELDS)}")
    return _dataclass_from_dict(SlamConfig, values)


def build_setup(values: dict[str, Any]) -> tuple[SlamConfig, RunSettings, SlamParams]:
    """The config, run settings and parameters of one flat dictionary of names.

    ``values`` maps :data:`CONFIG_FIELDS` names to ``SlamConfig`` fields, :data:`SETTINGS_FIELDS`
    names to ``RunSettings`` fields and dotted names (``motion.srr``) to parameters; anything
    missing keeps its default. This is the one builder behind ``--set``, config files and the
    experiments' method tables. Unknown names and bad values raise ``ConfigError``.
    """
    config_values = {k: v for k, v in values.items() if k in CONFIG_FIELDS}
    settings_values = {k: v for k, v in values.items() if k in SETTINGS_FIELDS}
    param_values = {k: v for k, v in values.items() if k not in CONFIG_FIELDS and k not in SETTINGS_FIELDS}
    return (config_from_dict(config_values), _dataclass_from_dict(RunSettings, settings_values),
            params_from_dict(param_values))
