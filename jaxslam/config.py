"""The static ``SlamConfig`` and the traced ``SlamParams`` of the RBPF.

``SlamConfig`` holds everything that sets array shapes or picks code paths
(particle counts, horizon, map shape, beam subsampling, proposal kind): it is a
frozen, hashable dataclass passed to ``jax.jit`` as a static argument, and
changing it recompiles. ``SlamParams`` holds the numbers (noise, gains,
thresholds): a pytree of float32 arrays, traced, so changing it never recompiles
and it can be differentiated.

Both can be written and read as flat dictionaries with dotted names
(``motion.srr``, ``likelihood.sigma``) for the command line and config files.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxslam.grid import LIKELIHOOD_FIELDS, GridSpec, InsertionParams
from jaxslam.motion import MotionParams
from jaxslam.resampling import RESAMPLERS
from jaxslam.sensor import FIELD_LOOKUPS, LikelihoodParams

PROPOSALS = ("op", "smp", "lp")


class ConfigError(ValueError):
    """A configuration or parameter value is invalid; the message names it."""


@dataclasses.dataclass(frozen=True)
class SlamConfig:
    """Static settings of the RBPF (shapes and code paths). Hashable; changing it recompiles."""

    num_particles: int = 30
    """N, the number of SLAM particles (each with its own map)."""
    proposal: str = "smp"
    """Proposal distribution: "op" (odometry), "smp" (scan matching), "lp" (look-ahead)."""
    resolution: float = 0.05
    """Map cell size (m), used when ``grid`` is None."""
    map_padding: float = 8.0
    """Metres added around the odometry's extent when the grid is sized from a log."""
    grid: GridSpec | None = None
    """The map's shape and placement; None sizes it from the log (see ``map_padding``)."""
    max_insert_range: float = 15.0
    """Beams are inserted into the map up to this range (m); sets samples per beam."""
    field_radius: int = 4
    """Radius (cells) of the likelihood field around each registered endpoint."""
    likelihood_field: str = "endpoints"
    """What the likelihood field measures distances to: "endpoints" (every endpoint ever
    registered, a scatter-min per beam) or "occupied" (the cells whose log-odds is above 0, so
    endpoints that later beams see through stop counting, as in GMapping; the field is
    recomputed in a window round each inserted scan). See ``jaxslam.grid.insert_scan``."""
    likelihood_lookup: str = "nearest"
    """How a beam's endpoint reads the likelihood field in the particle weights (every proposal,
    the SMP's fitted Gaussian, the LP's localizers): "nearest" (the cell it falls in) or
    "bilinear" (interpolated between the four surrounding cells, so the likelihood is continuous
    in the pose; four gathers per beam). See ``jaxslam.sensor``."""
    match_lookup: str = "bilinear"
    """The same choice for the hill-climbing scan matcher (the SMP's and LP-SM's match, and the
    refinement's matches and their covariances). "bilinear" (the default) lets the matcher
    settle between cells instead of stopping wherever a whole cell stops improving: on Intel,
    ACES and MIT CSAIL it is as accurate or more (docs/tuning.md, "Reading the field between
    cells"). "nearest" is what the datasets and box-world tables were measured with."""
    beam_stride: int = 2
    """Use every ``beam_stride``-th beam in likelihoods (the map always gets all beams)."""
    linear_update: float = 1.0
    """Process a scan after this much travel (m) since the last processed one (GMapping)."""
    angular_update: float = 0.5
    """... or after this much rotation (rad)."""
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
    lookahead_weight: str = "filter"
    """The LP's SLAM weight. "filter" (DESIGN.md step 5): the evidence of scan t, with the
    selection correction (``lookahead.selection_correction``), so the particles target the
    filtering posterior. "lookahead": the particles target the posterior given the k scans ahead
    too (block sampling, Doucet, Briers and Senecal 2006): the increment is the localizer filter's
    log p(z_{t+k} | x_{t-1}, z_{t:t+k-1}), and the pose drawn by the look-ahead is not corrected
    back; the SLAM resampling then sees k scans ahead."""

    def __post_init__(self):
        checks = [
            (self.num_particles >= 1, "num_particles must be >= 1"),
            (self.proposal in PROPOSALS, f"proposal must be one of {PROPOSALS}, got {self.proposal!r}"),
            (self.resolution > 0, "resolution must be > 0"),
            (self.map_padding >= 0, "map_padding must be >= 0"),
            (self.max_insert_range > 0, "max_insert_range must be > 0"),
            (1 <= self.field_radius <= 11, "field_radius must be in 1..11 (its squared distances fit uint8)"),
            (self.likelihood_field in LIKELIHOOD_FIELDS,
             f"likelihood_field must be one of {LIKELIHOOD_FIELDS}, got {self.likelihood_field!r}"),
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
            (self.lookahead_weight in ("filter", "lookahead"),
             f"lookahead_weight must be 'filter' or 'lookahead', got {self.lookahead_weight!r}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"SlamConfig: {message}")

    @property
    def lookahead_steps(self) -> int:
        """Future scans each step carries: the horizon for LP, none otherwise."""
        return self.horizon if self.proposal == "lp" else 0


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
    match_share: Float[Array, ""]
    """``lookahead_initial="scan_match"`` only: the share in [0, 1] of the time-t localizers drawn
    around the scan-matched pose; the others are drawn from the motion model, as in the paper's
    LP, and every g is weighted against the mixture of the two (so the estimate stays unbiased).
    1 (default): all from the match; a match that slid along a weak structure then leaves no
    localizer near the truth, which the odometry-drawn share keeps."""
    selection_correction: Float[Array, ""]
    """How much of the selection correction the SLAM weight keeps, in [0, 1]. The increment is
    log mean_i exp(g_i) + c (g_J - logsumexp(g) - log p_J): c = 1 (default) is the DESIGN's
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
    "lookahead.match_share": 1.0, "lookahead.selection_correction": 1.0,
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
    if not 0.0 <= merged["lookahead.match_share"] <= 1.0:
        raise ConfigError(f"parameter lookahead.match_share must be in [0, 1], got {merged['lookahead.match_share']}")
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


def config_to_dict(config: SlamConfig) -> dict[str, Any]:
    """Plain-data view of a ``SlamConfig`` (JSON-ready)."""
    out = dataclasses.asdict(config)
    return out


def config_from_dict(values: dict[str, Any]) -> SlamConfig:
    """Build a ``SlamConfig`` from field names; unknown names or bad types raise ``ConfigError``."""
    fields = {f.name: f for f in dataclasses.fields(SlamConfig)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(f"unknown config field(s) {unknown}; known: {sorted(fields)}")
    kwargs = {}
    for name, value in values.items():
        if name == "grid":
            kwargs[name] = None if value is None else GridSpec(tuple(value["shape"]), value["resolution"], tuple(value["origin"]))
            continue
        default = getattr(SlamConfig, name)
        try:
            kwargs[name] = type(default)(value) if not isinstance(default, str) else str(value)
        except (TypeError, ValueError):
            raise ConfigError(f"config field {name} must be a {type(default).__name__}, got {value!r}") from None
    return SlamConfig(**kwargs)
