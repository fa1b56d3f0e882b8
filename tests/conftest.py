"""Shared test helpers: small sensors, the real-data folder."""

from pathlib import Path

import pytest

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


@pytest.fixture
def realdata() -> Path:
    if not REALDATA.is_dir():
        pytest.skip(f"real data folder {REALDATA} not found (../shared/realdata next to the project)")
    return REALDATA
