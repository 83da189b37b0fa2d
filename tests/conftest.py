"""Shared fixtures. Data from ../shared/data is optional for users: tests that need it skip with a
reason when it is missing, except under CI (CI=true), where missing data is a failure."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))


def shared_data(*parts) -> Path:
    """Path under ../shared/data; skip (or fail under CI=true) when it is missing."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        msg = f"shared test data missing: {p}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + " (CI=true: shared data is required)")
        pytest.skip(msg)
    return p


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def small_profile():
    from nrhdr_core import profile
    return profile.default(64, 80, seed=3)
