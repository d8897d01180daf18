"""The settings of the RBPF, split by who reads them.

* ``SlamConfig`` holds everything that sets array shapes or picks code paths inside the
  jitted step (particle counts, horizon, map shape, beam subsampling, proposal kind): a
  frozen, hashable dataclass passed to ``jax.jit`` as a static argument; changing it
  recompiles.
* ``RunSettings`` holds what only the host-side driver reads (the update rule that selects
  the processed scans): changing it never recompiles.
* ``SlamParams`` holds the numbers (noise, gains, thresholds): a pytree of float32 arrays,
  traced, so changing it never recompiles and it can be differentiated.

All three are built from one flat dictionary of names (:func:`build_setup`): config and
settings fields by name (``num_particles``, ``linear_update``), parameters by dotted name
(``motion.srr``, ``likelihood.sigma``), as the command line's ``--set`` and config files
give them.

Everything is checked when it is built, before any work: exact types (an int field refuses 2.9
and True instead of truncating them; a string from ``--set`` that parses, "3", is fine), finite
numbers, and physical ranges (noise >= 0, sigma > 0, log-odds signs, steps > 0, ...); a bad
value raises :class:`ConfigError` naming it, its value and what is accepted.
"""

from __future__ import annotations

import dataclasses
import difflib
from typing import Any

from jaxslam.checks import ConfigError, check_float, check_int, typed_value
from jaxslam.likelihood_field import FIELD_LOOKUPS
from jaxslam.maps import PagedGridSpec
from jaxslam.params import (ScanMatchParams, SlamParams, _DEFAULTS, default_params, param_defaults,  # noqa: F401
                            param_ranges, params_from_dict, params_to_dict)
from jaxslam.proposals import PROPOSALS, Proposal, add_proposal, proposal_settings
from jaxslam.proposals.lookahead import LookaheadParams  # noqa: F401  (the LP's numbers, once defined here)
from jaxslam.resampling import RESAMPLERS
from jaxslam.sensor_model import SENSOR_MODELS

# SlamParams, its builders and the checks live in jaxslam.params and jaxslam.checks; they are
# imported here too, since ``from jaxslam.config import ...`` is how the package and its users
# reach every setting.
__all__ = ["ConfigError", "LookaheadParams", "OWN_NAMES", "RunSettings", "SETTINGS_FIELDS", "ScanMatchParams",
           "SlamConfig", "SlamParams", "build_setup", "check_float", "check_int", "config_from_dict", "config_names",
           "config_to_dict", "default_params", "default_values", "param_defaults", "param_ranges",
           "params_from_dict", "params_to_dict", "register_proposal", "unknown_names_message"]


@dataclasses.dataclass(frozen=True, init=False)
class SlamConfig:
    """Static settings of the jitted RBPF step (shapes and code paths). Hashable; changing it recompiles.

    Besides its own fields, it takes the settings the proposals own by name
    (:data:`jaxslam.proposals.PROPOSALS`: the LP's ``num_localizers``, ``horizon`` and
    ``lookahead_initial``, the SMP's ``smp_weight``), checked as its own are and read as
    attributes (``config.num_localizers``); :attr:`proposal_settings` holds those that differ from
    their defaults. ``SlamConfig(num_particles=50, num_localizers=20)`` and
    ``dataclasses.replace(config, horizon=3)`` work as for its own fields."""

    num_particles: int = 30
    """N, the number of SLAM particles (each with its own map)."""
    proposal: str = "smp"
    """Proposal distribution, a name in :data:`jaxslam.proposals.PROPOSALS`: "op" (odometry),
    "smp" (scan matching), "lp" (look-ahead)."""
    sensor_model: str = "endpoint"
    """The laser model that scores scans in the maps, a name in
    :data:`jaxslam.sensor_model.SENSOR_MODELS` ("endpoint": the likelihood field)."""
    resolution: float = 0.05
    """Map cell side (m)."""
    map_extent: float = 1280.0
    """Side (m) of the square virtual grid the maps live on, centred on the log's first pose
    (rounded; ``slam.run``'s local frame). Memory grows with the area mapped, not with this:
    a particle's map holds only the tiles it wrote (:mod:`jaxslam.maps`); its directory
    costs 4 bytes per 16 x 16 tiles of the extent (2.5 KB at the default 1.28 km and 64-cell tiles)."""
    tile_size: int = 64
    """Cells per side of a map tile: the unit particles share and copy on write."""
    max_insert_range: float = 15.0
    """Beams are inserted into the map up to this range (m); sets samples per beam. A match's
    score (which decides whether it failed, ``scan_match.min_score``) counts only beams shorter
    than it (GMapping's usable range): the map registers no endpoint farther from a pose."""
    field_radius: int = 4
    """Radius (cells) of the likelihood field around each registered endpoint."""
    likelihood_lookup: str = "nearest"
    """How a beam's endpoint reads the likelihood field in the particle weights (every proposal,
    the SMP's fitted Gaussian, the LP's localizers): "nearest" (the cell it falls in) or
    "bilinear" (interpolated between the four surrounding cells, so the likelihood is continuous
    in the pose; four gathers per beam). See ``jaxslam.likelihood_field``."""
    match_lookup: str = "bilinear"
    """The same choice for the window posterior's polish of each mode's peak (the SMP's and the
    LP's) and the refinement's hill climber and its covariances. "bilinear" (the default) lets a
    peak settle between cells instead of stopping wherever a whole cell stops improving (the
    figures: docs/design.md, "Endpoint model")."""
    beam_stride: int = 2
    """Use every ``beam_stride``-th beam in likelihoods (the map always gets all beams)."""
    free_space_samples: int = 0
    """Cells checked along each beam's free path for the free-space evidence in the SLAM weights
    (:func:`jaxslam.likelihood_field.see_through_log_likelihood`, one sample a cell from the laser
    out: ``max_insert_range / resolution`` covers every inserted beam); 0: none (the endpoint
    model alone)."""
    resampler: str = "systematic"
    """Resampling scheme: systematic, stratified, multinomial or residual."""
    match_iterations: int = 24
    """Fixed iteration budget of the refinement's hill-climbing scan matcher."""
    refine_rounds: int = 2
    """Rounds of the refinement (:func:`jaxslam.refine.refine_in_rounds`): the first localises
    every scan in the final map, each later one in the map drawn again from the processed scans
    at the last round's poses. 1: the final map only (the figures:
    docs/design.md, "Refinement")."""
    window_cells: int = 5
    """Coarse cells per axis of the window posterior (:mod:`jaxslam.window_posterior`): the
    window is cut into this cubed, each scored once."""
    window_levels: int = 4
    """Levels the window posterior refines each mode by (each halves the cells); with the
    coarse level, the polish and the fit, the proposal's sequential depth."""
    window_modes: int = 4
    """Modes the window posterior keeps: its coarse local maxima, each refined on its own."""
    window_keep: int = 3
    """Cells each mode keeps per level (each splits into 8 at the next)."""
    particle_block: int = 128
    """Particles a step processes at once in its two per-particle stages, the proposals and the
    scan insertion (a ``lax.map`` over blocks of this many, each block vmapped): their
    intermediates (the window posterior's candidate poses times beams, the insertion's beam
    samples) then cost this many particles' worth, not N's. It changes no value; larger blocks
    give a GPU more parallel work, smaller ones less memory (the figures:
    docs/design.md, "Per-particle stages run in blocks")."""
    score_lag: int | None = None
    """Which score estimate the gradient of ``rbpf.filter``'s ``marginal_loglik`` is (its value
    is the same): None, the path-space score over the final particles' ancestral paths; an int L
    >= 0, the fixed-lag smoothed score, each step's term averaged over the particles L steps
    later (:func:`jaxslam.particle_filter.fixed_lag_score`; less biased by path degeneracy:
    docs/design.md, "What a gradient of the filter is"). Mapping computes no gradient and ignores it."""
    proposal_settings: tuple[tuple[str, Any], ...] = ()
    """The proposals' own settings that differ from their defaults, as (name, value) pairs sorted
    by name (read them as attributes: ``config.num_localizers``)."""

    def __init__(self, **values):
        owned = proposal_settings()
        unknown = sorted(set(values) - {field.name for field in dataclasses.fields(self)} - set(owned))
        if unknown:
            raise ConfigError(f"SlamConfig: unknown field(s) {unknown}; known: {sorted(config_names())}")
        for field in dataclasses.fields(self):
            object.__setattr__(self, field.name, values.get(field.name, field.default))
        given = {**dict(self.proposal_settings), **{k: v for k, v in values.items() if k in owned}}
        kept = {}
        for name, value in given.items():
            if name not in owned:
                raise ConfigError(f"SlamConfig: {name!r} is no registered proposal's setting")
            value = _normalize_setting(owned[name], value)
            if value != owned[name].default:
                kept[name] = value
        object.__setattr__(self, "proposal_settings", tuple(sorted(kept.items())))
        self.__post_init__()

    def __getattr__(self, name):
        # Only called when the usual lookup fails: a proposal's setting, or its default.
        owned = proposal_settings()
        if name not in owned:
            raise AttributeError(f"'SlamConfig' object has no attribute {name!r}")
        return dict(self.__dict__.get("proposal_settings", ())).get(name, owned[name].default)

    def __post_init__(self):
        _normalize_fields(self, "SlamConfig")
        checks = [
            (self.num_particles >= 1, f"num_particles must be >= 1, got {self.num_particles}"),
            (self.proposal in PROPOSALS, f"proposal must be one of {tuple(PROPOSALS)}, got {self.proposal!r}"),
            (self.sensor_model in SENSOR_MODELS,
             f"sensor_model must be one of {tuple(SENSOR_MODELS)}, got {self.sensor_model!r}"),
            (self.resolution > 0, f"resolution must be > 0 (m), got {self.resolution}"),
            (self.map_extent > 0, f"map_extent must be > 0 (m), got {self.map_extent}"),
            (self.tile_size in (8, 16, 32, 64, 128, 256, 512, 1024),
             f"tile_size must be a power of two in 8..1024 (cells), got {self.tile_size}"),
            (self.max_insert_range > 0, f"max_insert_range must be > 0 (m), got {self.max_insert_range}"),
            (1 <= self.field_radius <= 11,
             f"field_radius must be in 1..11 (its squared distances fit uint8), got {self.field_radius}"),
            (self.likelihood_lookup in FIELD_LOOKUPS,
             f"likelihood_lookup must be one of {FIELD_LOOKUPS}, got {self.likelihood_lookup!r}"),
            (self.match_lookup in FIELD_LOOKUPS,
             f"match_lookup must be one of {FIELD_LOOKUPS}, got {self.match_lookup!r}"),
            (self.beam_stride >= 1, f"beam_stride must be >= 1, got {self.beam_stride}"),
            (self.free_space_samples >= 0, f"free_space_samples must be >= 0, got {self.free_space_samples}"),
            (self.resampler in RESAMPLERS, f"resampler must be one of {sorted(RESAMPLERS)}, got {self.resampler!r}"),
            (self.match_iterations >= 0, f"match_iterations must be >= 0, got {self.match_iterations}"),
            (self.refine_rounds >= 1, f"refine_rounds must be >= 1, got {self.refine_rounds}"),
            (self.window_cells >= 1, f"window_cells must be >= 1, got {self.window_cells}"),
            (self.window_levels >= 1, f"window_levels must be >= 1, got {self.window_levels}"),
            (1 <= self.window_modes <= self.window_cells**3,
             f"window_modes must be in 1..window_cells^3, got {self.window_modes}"),
            (self.window_keep >= 1, f"window_keep must be >= 1, got {self.window_keep}"),
            (self.particle_block >= 1, f"particle_block must be >= 1, got {self.particle_block}"),
            (self.score_lag is None or self.score_lag >= 0, f"score_lag must be None or >= 0, got {self.score_lag}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"SlamConfig: {message}")
        # Only once every field is in its own range, what is computed from several (so that
        # resolution = 0 is refused as such, not in a division by zero).
        if self.map_extent / self.resolution > 46340:
            raise ConfigError(f"SlamConfig: map_extent / resolution must be at most 46,340 cells a side (int32 cell "
                              f"indices), got {self.map_extent} m / {self.resolution} m")

    @property
    def grid(self) -> PagedGridSpec:
        """The virtual grid of the maps, in the filter's local frame (centred on its origin)."""
        return PagedGridSpec.centred((0.0, 0.0), self.map_extent, self.resolution, self.tile_size)

    @property
    def lookahead_steps(self) -> int:
        """Future scans each step carries (the proposal's ``future_scans_fn``: the LP's horizon)."""
        return PROPOSALS[self.proposal].future_scans_fn(self)


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """Host-side settings of ``slam.run``: which scans are processed. Never part of the jitted
    step, so changing them never recompiles it."""

    linear_update: float = 0.5
    """Process a scan after this much travel (m) since the last processed one. Half GMapping's
    1 m: the odometry's error, and so the cloud every proposal has to search, grows with the
    motion between processed scans (the figures: docs/design.md, "Static configuration, traced parameters")."""
    angular_update: float = 0.25
    """... or after this much rotation (rad); half GMapping's 0.5 rad."""

    def __post_init__(self):
        _normalize_fields(self, "RunSettings")  # numbers, finite
        checks = [
            (self.linear_update >= 0, f"linear_update must be >= 0 (m), got {self.linear_update}"),
            (self.angular_update >= 0, f"angular_update must be >= 0 (rad), got {self.angular_update}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"RunSettings: {message}")


def _normalize_fields(obj, where: str) -> None:
    """Check that every int, float and str field of a frozen dataclass holds exactly that type
    (an int field refuses 2.9 and True rather than truncating them; a float field refuses NaN and
    inf) and store it as the plain Python type (NumPy scalars become int / float)."""
    for field in dataclasses.fields(obj):
        if field.name == "proposal_settings":
            continue
        try:
            value = typed_value(field.name, getattr(obj, field.name), field.default)
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}") from None
        object.__setattr__(obj, field.name, value)



def _normalize_setting(setting, value):
    """A proposal's setting (:class:`jaxslam.proposals.Setting`) as its default's plain type, in
    its range; else ``ConfigError`` naming it."""
    try:
        value = typed_value(setting.name, value, setting.default)
    except ConfigError as err:
        raise ConfigError(f"SlamConfig: {err}") from None
    if not setting.check(value):
        raise ConfigError(f"SlamConfig: {setting.name} must be {setting.accepted}, got {value!r}")
    return value


def config_to_dict(config) -> dict[str, Any]:
    """Plain-data view of a ``SlamConfig`` (its fields and every registered proposal's setting, by
    name) or a ``RunSettings`` (JSON-ready)."""
    out = dataclasses.asdict(config)
    if isinstance(config, SlamConfig):
        del out["proposal_settings"]
        out.update({name: getattr(config, name) for name in proposal_settings()})
    return out


def _dataclass_from_dict(cls, values: dict[str, Any]):
    """``cls(**values)`` with strings (from ``--set``) parsed to their field's type: "3" is
    fine for an int field, "2.9" is not; numbers must already have the field's type (an int
    field refuses 2.9 and True, see ``SlamConfig.__post_init__``). Bad values raise ``ConfigError`` naming the field."""
    if not isinstance(values, dict):
        raise ConfigError(f"{cls.__name__} fields must be a dict of names and values, got {values!r}")
    kwargs = {}
    owned = proposal_settings() if cls is SlamConfig else {}
    for name, value in values.items():
        default = owned[name].default if name in owned else getattr(cls, name)
        kind = type(default)
        if isinstance(value, str) and kind is not str:
            text = value.strip()
            if default is None:  # an optional int: "none" or an integer
                kind = int
                if text.lower() == "none":
                    kwargs[name] = None
                    continue
            try:
                value = int(text) if kind is int else float(text)
            except ValueError:
                if kind is int:
                    raise ConfigError(f"config field {name} must be an integer, got {value!r}") from None
                raise ConfigError(f"config field {name} must be a number, got {value!r}") from None
        kwargs[name] = value
    return cls(**kwargs)


_OWN_CONFIG_FIELDS = tuple(f.name for f in dataclasses.fields(SlamConfig) if f.name != "proposal_settings")
SETTINGS_FIELDS = tuple(f.name for f in dataclasses.fields(RunSettings))
"""Names that set a :class:`RunSettings` field."""
OWN_NAMES = frozenset({*_OWN_CONFIG_FIELDS, *SETTINGS_FIELDS, *SlamParams._fields, "proposal_settings",
                       *(name.split(".")[0] for name in _DEFAULTS)})
"""The names a proposal may not own: ``SlamConfig``'s, ``RunSettings``' and ``SlamParams``' own."""


def register_proposal(name: str, proposal: Proposal) -> None:
    """Make ``proposal`` available as ``SlamConfig(proposal=name)``, ``--proposal name`` (in a
    parser built afterwards) and in ``build_setup``, with its settings, numbers and flags. Refuses
    (``ValueError``) a name taken by another proposal (registering the same row again is a
    no-op), and a setting, group or flag that another proposal owns or that names one of
    :data:`OWN_NAMES`."""
    add_proposal(name, proposal, OWN_NAMES)


def config_names() -> tuple[str, ...]:
    """Names that set a :class:`SlamConfig` field or a registered proposal's setting."""
    return (*_OWN_CONFIG_FIELDS, *proposal_settings())


def config_from_dict(values: dict[str, Any]) -> SlamConfig:
    """Build a ``SlamConfig`` from field names; unknown names or bad types raise ``ConfigError``."""
    names = config_names()
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"unknown config field(s) {unknown}; known: {sorted(names)}")
    return _dataclass_from_dict(SlamConfig, values)


def unknown_names_message(unknown: list[str]) -> str:
    """What ``build_setup`` says of names that are neither fields nor parameters: both kinds of
    known names, and the closest ones."""
    fields = sorted(config_names() + SETTINGS_FIELDS)
    dotted = sorted(param_defaults())
    close = {name: difflib.get_close_matches(str(name), [*fields, *dotted], n=1, cutoff=0.8) for name in unknown}
    hints = "; ".join(f"{name!r}: did you mean {found[0]!r}?" for name, found in close.items() if found)
    return (f"unknown name(s) {unknown}{' (' + hints + ')' if hints else ''}: a name is either a config or run "
            f"settings field {fields} or a dotted parameter {dotted}")


def default_values() -> dict[str, Any]:
    """Every name :func:`build_setup` takes with its default: config and run-settings fields,
    dotted parameters."""
    fields = [*dataclasses.fields(SlamConfig), *dataclasses.fields(RunSettings)]
    return {**{f.name: f.default for f in fields if f.name != "proposal_settings"},
            **{name: setting.default for name, setting in proposal_settings().items()}, **param_defaults()}


def build_setup(values: dict[str, Any]) -> tuple[SlamConfig, RunSettings, SlamParams]:
    """The config, run settings and parameters of one flat dictionary of names.

    ``values`` maps :func:`config_names` to ``SlamConfig`` fields and proposals' settings, :data:`SETTINGS_FIELDS`
    names to ``RunSettings`` fields and dotted names (``motion.srr``) to parameters; anything
    missing keeps its default. This is the one builder behind ``--set``, config files and the
    experiments' method tables. Unknown names and bad values raise ``ConfigError``.
    """
    names = config_names()
    unknown = sorted(set(values) - set(names) - set(SETTINGS_FIELDS) - set(param_defaults()), key=str)
    if unknown:
        raise ConfigError(unknown_names_message(unknown))
    config_values = {k: v for k, v in values.items() if k in names}
    settings_values = {k: v for k, v in values.items() if k in SETTINGS_FIELDS}
    param_values = {k: v for k, v in values.items() if k not in names and k not in SETTINGS_FIELDS}
    return (config_from_dict(config_values), _dataclass_from_dict(RunSettings, settings_values),
            params_from_dict(param_values))
