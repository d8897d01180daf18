"""The checks every setting passes before any work: exact types and finite numbers.

A bad value raises :class:`ConfigError` naming it, its value and what is accepted
(``jaxslam.config`` and ``jaxslam.params`` use these for every field and parameter).
"""

from __future__ import annotations

import math
import numbers

import numpy as np


class ConfigError(ValueError):
    """A configuration or parameter value is invalid; the message names it."""


def _is_bool(value) -> bool:
    return isinstance(value, (bool, np.bool_)) or (getattr(value, "dtype", None) is not None
                                                   and np.dtype(value.dtype) == np.bool_)


def _scalar(value):
    """A 0-d NumPy or JAX array as its Python scalar; anything else unchanged."""
    if hasattr(value, "shape") and hasattr(value, "dtype") and not isinstance(value, (str, bytes)):
        if tuple(value.shape) == ():
            return np.asarray(value).item()
    return value


def check_int(name: str, value) -> int:
    """``value`` as an int: a Python or NumPy integer (not a bool, not a float, not even 3.0)."""
    value = _scalar(value)
    if _is_bool(value) or not isinstance(value, numbers.Integral):
        raise ConfigError(f"{name} must be an integer, got {value!r}")
    return int(value)


def check_float(name: str, value) -> float:
    """``value`` as a finite float: a Python or NumPy number (not a bool), finite in float32."""
    value = _scalar(value)
    if _is_bool(value) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{name} must be a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out) or abs(out) > float(np.finfo(np.float32).max):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    return out


def typed_value(name: str, value, default):
    """``value`` as the plain type of ``default`` (int, float, str; None: an optional int); else
    ``ConfigError`` naming ``name``."""
    kind = type(default)
    if (default is None and value is not None) or kind is int:
        return check_int(name, value)
    if kind is float:
        return check_float(name, value)
    if kind is str and not isinstance(value, str):
        raise ConfigError(f"{name} must be a string, got {value!r}")
    return value
