"""The one test fixture that selects Mitsuba's variant (DESIGN.md convention 6)."""

import pytest


@pytest.fixture(scope="session")
def mi():
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'newtsim[optics]')")
    from optics.llvm import init_mitsuba

    return init_mitsuba()
