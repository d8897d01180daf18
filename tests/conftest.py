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
