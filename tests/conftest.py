"""Shared pytest fixtures: paths to the recordings in ../shared/data (never copied here)."""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def real_data() -> Path:
    """Folder of real sensor recordings (`../shared/data/real`); skips when absent."""
    path = SHARED_DATA / "real"
    if not path.is_dir():
        pytest.skip(f"real recordings not found at {path} (../shared/data/real is absent)")
    return path


@pytest.fixture(scope="session")
def isd_data() -> Path:
    """Folder of the labelled incipient-slip dataset (`../shared/data/isd`); skips when absent."""
    path = SHARED_DATA / "isd"
    if not path.is_dir():
        pytest.skip(f"incipient-slip dataset not found at {path} (../shared/data/isd is absent)")
    return path
