"""Shared test fixtures."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

# Most of the suite's time is XLA compiling (measured: a 40-scan SMP run is 51 s of compiling and
# 1 s of filtering). One test session caches its compilations in one folder (JAX's persistent
# cache), so that a program is compiled once for the session, not once by each xdist worker, by
# each test module (each module's in-memory caches are dropped when it ends, below), by the
# notebooks' kernels and by each command-line process. The folder is made here, in the first
# process that loads this file (the workers and the children inherit the variables), and removed
# when that process ends; JAXSLAM_TEST_CACHE_DIR names a folder to keep instead, "off" runs without.
# The command line's own cache (jaxslam.compile_cache, ~/.cache/jaxslam/jax) points at the same
# folder, so the user's cache is left alone.
_SESSION_CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ and "JAXSLAM_CACHE_DIR" not in os.environ:
    _wanted = os.environ.get("JAXSLAM_TEST_CACHE_DIR", "")
    if _wanted.lower() in ("off", "0", "none", "false", "no"):
        os.environ["JAXSLAM_CACHE_DIR"] = "off"
    else:
        _folder = _wanted or tempfile.mkdtemp(prefix="jaxslam-test-cache-")
        _SESSION_CACHE = None if _wanted else _folder
        os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ["JAXSLAM_CACHE_DIR"] = _folder
os.environ.setdefault("JAXSLAM_CACHE_DIR", "off")


def pytest_unconfigure(config):
    """The session's cache folder goes with the process that made it (the workers made none)."""
    if _SESSION_CACHE is not None:
        shutil.rmtree(_SESSION_CACHE, ignore_errors=True)

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("JAXSLAM_DATA", REPO_ROOT.parent / "shared" / "data"))


@pytest.fixture
def shared_data() -> Path:
    """The folder of real datasets (../shared/data); the test is skipped when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real datasets not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_functions():
    """Each test module's compiled functions and cached constants are dropped when it ends. An
    xdist worker otherwise keeps every executable it ever built: about 6 GB a worker by the end
    of the suite, which a 24 GB CI machine running two workers and the notebooks' kernels did not
    survive (a worker died in the last minutes of the 2026-11-26 run)."""
    yield
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
