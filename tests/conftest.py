"""Shared test fixtures: where the real third-party data lives, Qt offscreen."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

ROOT = Path(__file__).resolve().parents[1]


def real_data_dir() -> Path | None:
    """``$CARAPOST_REAL_DATA`` or the first ``shared/data/real`` found above the checkout."""
    env = os.environ.get("CARAPOST_REAL_DATA")
    if env and Path(env).is_dir():
        return Path(env)
    for parent in [ROOT, *ROOT.parents]:
        cand = parent / "shared" / "data" / "real"
        if cand.is_dir():
            return cand
    return None


@pytest.fixture(scope="session")
def real_data() -> Path:
    d = real_data_dir()
    if d is None:
        pytest.skip("real third-party data not found (set CARAPOST_REAL_DATA)")
    return d
