"""jaxslam: vectorized particle filters for robot mapping and localization, in JAX.

The public API, re-exported by name; submodules hold the rest: the SLAM filter
(``jaxslam.rbpf``, pure; its proposals in ``jaxslam.proposals``, its laser models in
``jaxslam.sensor_model``; islands of it over devices in ``jaxslam.islands``, on the driver in
``jaxslam.island_runs``), SLAM on a whole
log from the host (``jaxslam.slam.run``; several runs over devices: ``slam.run_batch``),
localization (``jaxslam.localization``: MCL and the door filter), the log readers (``jaxslam.io``) and
the simulator (``jaxslam.sim``, not imported here).
"""

from jaxslam import binary_bayes, geometry, grid, laser, likelihood_field, motion, occupancy, particle_filter
from jaxslam import island_runs, islands, localization, proposals, rbpf, resampling, scan_matching, sensor_model, slam
from jaxslam.config import ConfigError, RunSettings, SlamConfig, SlamParams, build_setup, default_params, params_from_dict
from jaxslam.grid import GridSpec
from jaxslam.laser import SensorSpec, make_sensor, uniform_beams
from jaxslam.laserlog import LaserLog, LogError, select_updates
from jaxslam.occupancy import GridMap
from jaxslam.rbpf import SlamInfo, SlamState
from jaxslam.slam import SlamResult

__version__ = "0.1.0"

__all__ = [
    "ConfigError", "GridMap", "GridSpec", "LaserLog", "LogError", "RunSettings", "SensorSpec", "SlamConfig",
    "SlamInfo", "SlamParams", "SlamResult", "SlamState", "binary_bayes", "build_setup", "default_params",
    "geometry", "grid", "island_runs", "islands", "laser", "likelihood_field", "localization", "make_sensor", "motion", "occupancy", "params_from_dict",
    "particle_filter", "proposals", "rbpf", "resampling", "scan_matching", "select_updates", "sensor_model", "slam",
    "uniform_beams",
]
