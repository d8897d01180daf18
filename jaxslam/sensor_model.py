"""The seam between the SLAM filter and its laser model.

Everything that scores a scan in a particle's map goes through the model that
``SlamConfig.sensor_model`` names in :data:`SENSOR_MODELS`: the three proposals, the window
posterior (its cell scores, its match score and its fitted Gaussians), the trajectory refinement
and the filter's log-evidence. A model reads the map through a :class:`~jaxslam.map_view.MapView`
(paged or dense alike). A new model is one file that builds a :class:`SensorModel`, added to
:data:`SENSOR_MODELS` here, or at run time with :func:`register_sensor_model` (which is how
``tests/test_sensor_model.py`` maps the office with a model defined in the test).

The model scores the map's likelihood field (``hit_dist2``, the squared cell distance to the
nearest registered endpoint, kept by :mod:`jaxslam.maps` at insertion); what the maps
store does not change with the model.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from jaxtyping import Array, Float

from jaxslam.likelihood_field import (LikelihoodParams, endpoint_cell_log_likelihoods, endpoint_log_likelihoods,
                                      endpoint_log_normalizer, endpoint_match_score)
from jaxslam.laser import SensorSpec
from jaxslam.map_view import MapView

LogLikelihoodsFn = Callable[[MapView, Float[Array, "L 3"], Float[Array, "B"], SensorSpec, LikelihoodParams, str],
                            Float[Array, "L"]]
"""``log_likelihoods_fn(view, poses, ranges, sensor, params, lookup) -> (L,)``: log p(z | x_l, m)
(nats, tempered by ``params.gain``) of one scan at L robot poses in one map; ``lookup`` is
``SlamConfig.likelihood_lookup`` or ``match_lookup`` (static; a model may ignore it)."""
MatchScoreFn = Callable[[MapView, Float[Array, "3"], Float[Array, "B"], SensorSpec, LikelihoodParams],
                        Float[Array, ""]]
"""``match_score_fn(view, pose, ranges, sensor, params) -> ()``: how well the scan fits the map at
``pose``, in [0, 1]; a match under ``scan_match.min_score`` counts as failed."""
LogNormalizerFn = Callable[[Float[Array, "B"], SensorSpec, LikelihoodParams, float], Float[Array, ""]]
"""``log_normalizer_fn(ranges, sensor, params, resolution) -> ()``: the scan's log normalising
constant, the same at every pose (added to the log-evidence, not to the weights)."""
CellLogLikelihoodsFn = Callable[[MapView, Float[Array, "L 3"], Float[Array, "B"], SensorSpec, LikelihoodParams,
                                 Float[Array, ""], Float[Array, ""], int], Float[Array, "L"]]
"""``cell_log_likelihoods_fn(view, poses, ranges, sensor, params, reach_xy, reach_theta, field_radius) -> (L,)``:
the log-likelihood of the cell of poses within ``reach_xy`` (m) and ``reach_theta`` (rad) of
each pose, smooth at the cell's scale: what the window posterior (:mod:`jaxslam.window_posterior`)
ranks its coarse cells by."""


class SensorModel(NamedTuple):
    """A SLAM laser model: three pure, vmappable functions of one particle's map."""

    log_likelihoods_fn: LogLikelihoodsFn
    """Scores a scan at many poses (the hot loop of every proposal and of the matcher)."""
    match_score_fn: MatchScoreFn
    """The match quality that decides whether a scan match counts."""
    log_normalizer_fn: LogNormalizerFn
    """Makes the log-evidence that of a density (for fitting the model's parameters)."""
    cell_log_likelihoods_fn: CellLogLikelihoodsFn | None = None
    """What the window posterior ranks its coarse cells by; None: a model without it is scored
    at the cells' centres (nearest lookup)."""


def _endpoint_log_likelihoods(view, poses, ranges, sensor, params, lookup):
    return endpoint_log_likelihoods(view.spec, view.values, poses, ranges, sensor, params, lookup)


def _endpoint_match_score(view, pose, ranges, sensor, params):
    return endpoint_match_score(view.spec, view.values, pose, ranges, sensor, params.sigma)


def _endpoint_cell_log_likelihoods(view, poses, ranges, sensor, params, reach_xy, reach_theta, field_radius):
    return endpoint_cell_log_likelihoods(view.spec, view.values, poses, ranges, sensor, params, reach_xy,
                                         reach_theta, field_radius)


ENDPOINT = SensorModel(_endpoint_log_likelihoods, _endpoint_match_score, endpoint_log_normalizer,
                       _endpoint_cell_log_likelihoods)
"""The endpoint (likelihood-field) model of :mod:`jaxslam.likelihood_field`, GMapping's."""

SENSOR_MODELS: dict[str, SensorModel] = {"endpoint": ENDPOINT}
"""The SLAM sensor models by name (``SlamConfig.sensor_model``)."""


def register_sensor_model(name: str, model: SensorModel) -> None:
    """Make ``model`` available as ``SlamConfig(sensor_model=name)``. Refuses a name already
    taken by another model (re-registering the same model is a no-op)."""
    if not isinstance(model, SensorModel):
        raise TypeError(f"register_sensor_model: {name!r} must be a SensorModel, got {type(model).__name__}")
    if name in SENSOR_MODELS and SENSOR_MODELS[name] is not model:
        raise ValueError(f"register_sensor_model: {name!r} is taken by another model")
    SENSOR_MODELS[name] = model


def sensor_model(config) -> SensorModel:
    """The model ``config.sensor_model`` names."""
    return SENSOR_MODELS[config.sensor_model]
