"""jaxslam: vectorized particle filters for robot mapping and localization, in JAX.

The public API, re-exported by name; submodules (``jaxslam.rbpf``, ``jaxslam.sim``,
``jaxslam.io``, ...) hold the rest.
"""

from jaxslam import binary_bayes, geometry, grid, motion, resampling, sensor
from jaxslam import doors, mcl, rbpf
from jaxslam.config import ConfigError, SlamConfig, SlamParams, default_params, params_from_dict
from jaxslam.grid import GridMap, GridSpec
from jaxslam.laserlog import LaserLog, LogError, select_updates
from jaxslam.rbpf import SlamInfo, SlamResult, SlamState
from jaxslam.sensor import SensorSpec, make_sensor, uniform_beams

__version__ = "0.1.0"

__all__ = [
    "ConfigError", "GridMap", "doors", "mcl", "GridSpec", "LaserLog", "LogError", "SensorSpec", "SlamConfig", "SlamInfo",
    "SlamParams", "SlamResult", "SlamState", "binary_bayes", "default_params", "geometry", "grid",
    "make_sensor", "motion", "params_from_dict", "rbpf", "resampling", "select_updates", "sensor",
    "uniform_beams",
]
