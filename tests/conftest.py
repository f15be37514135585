"""Shared fixtures. Real recordings come from ``../shared/data`` beside the checkout; tests that
need them skip with a reason when it is absent (a user's fresh clone has no ``../shared``)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real sensor recordings not found at {SHARED_DATA} (they live beside the checkout, never in it)")
    return SHARED_DATA
