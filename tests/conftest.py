"""Shared test set-up: the repo root on sys.path and where the real data lives."""

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
sys.path.insert(0, str(REPO))


@pytest.fixture(scope="session")
def data_dir():
    """The folder of real volumes and meshes (../shared/data beside the repo)."""
    if not DATA.is_dir():
        pytest.fail(f"real data folder not found: {DATA}")
    return DATA
