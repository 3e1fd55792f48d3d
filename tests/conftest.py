"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real data folder beside the repository (``../shared/data``): CMU BVH, holosoma climb.

    Fails (never skips) when it is missing, so a broken checkout cannot pass silently.
    """
    if not (SHARED_DATA / "cmu").is_dir() or not (SHARED_DATA / "holosoma_climb").is_dir():
        pytest.fail(
            f"shared test data not found at {SHARED_DATA}: expected the folders cmu/ and "
            "holosoma_climb/ there (the 'shared' folder beside the repository)"
        )
    return SHARED_DATA
