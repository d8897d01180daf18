"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# The command line caches compilations in ~/.cache/jaxslam/jax (jaxslam.compile_cache); the tests
# that call it, in this process or in a child, leave the user's cache alone unless told otherwise.
os.environ.setdefault("JAXSLAM_CACHE_DIR", "off")

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
