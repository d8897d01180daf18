"""jaxslam: vectorized particle filters for robot mapping and localization, in JAX."""

__version__ = "0.1.0"
