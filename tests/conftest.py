"""Fixtures of every test: the real-data folder, the one Mitsuba fixture, and the effect registry restored
after each test (a test that registers an effect must not change the catalogue of the tests after it)."""

import os
import sys
from pathlib import Path

import pytest

from detector.effects import base as effects_base

#: ../shared/realdata next to the project; NEWTSIM_REALDATA names another place (a git worktree elsewhere)
REALDATA = Path(os.environ.get("NEWTSIM_REALDATA") or Path(__file__).resolve().parents[1].parent / "shared" / "realdata")
sys.path.append(str(Path(__file__).parent))  # tests/helpers.py (after the packages: tests/detector is no package)


@pytest.fixture
def realdata() -> Path:
    if not REALDATA.is_dir():
        pytest.skip(f"real data folder {REALDATA} not found (../shared/realdata next to the project)")
    return REALDATA


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the llvm variant: the one place tests select it (DESIGN.md convention 6)."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'newtsim[optics]')")
    from optics.llvm import init_mitsuba

    return init_mitsuba()


@pytest.fixture(autouse=True)
def _restore_registry():
    """Whatever a test registers (plugins, examples/custom_effect.py) is gone after it."""
    saved = dict(effects_base._REGISTRY)
    yield
    effects_base._REGISTRY.clear()
    effects_base._REGISTRY.update(saved)


#: modules whose validation cases are computed once per run across the pytest-xdist workers
#: (helpers.shared_row): their tests are spread over the workers one by one
SHARED_ROW_MODULES = ("test_diagnose_hidden.py", "test_diagnose_unseen.py")


def pytest_configure(config):
    """On a pytest-xdist worker, BLAS runs on one thread: ``make test`` gives each core one worker, and
    OpenBLAS's own threads on top of it (two per worker on two cores) made the diagnoses' few-row,
    million-column products several times slower (the machine oversubscribed). The subprocesses the tests
    start (the command line) inherit the same limit through the environment."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    from threadpoolctl import threadpool_limits

    config._newtsim_blas_limit = threadpool_limits(limits=1, user_api="blas")


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup`` grouped by test file (SHARED_ROW_MODULES: by test). pytest-xdist 3.8 marks a group
    by writing ``@group`` into ``item._nodeid``, which pytest 9 no longer reads (the node id lives in
    ``_id``): the marks of pytest_collection_modifyitems below were silently lost and every test was
    scheduled alone, so a module's module-scoped renders were made again each time its tests came back to
    a worker after another module's. This scheduler finds the file in the node id itself; the units are
    sent largest (most tests) first, so the one-test validation cases come last and fill the workers' tails."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class FileGroups(LoadGroupScheduling):
        def _split_scope(self, nodeid: str) -> str:
            group = super()._split_scope(nodeid)
            if group != nodeid:  # an ``@group`` suffix (a pytest that keeps xdist's node id)
                return group
            path = nodeid.split("::", 1)[0]
            return nodeid if Path(path).name in SHARED_ROW_MODULES else path

    return FileGroups(config, log)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` (long statistical runs, full-size frames, optimisations) run only when asked:
    ``pytest -m slow`` or NEWTSIM_SLOW=1 (``make test-slow``); the default run stays well under 30 minutes.

    Under pytest-xdist (``make test``: ``-n 2 --dist loadgroup``) the tests of a module stay on one worker (its
    module-scoped renders are made once), except the modules of SHARED_ROW_MODULES, whose cases are shared
    between the workers on disk and so are spread over them (the scheduling itself: pytest_xdist_make_scheduler
    above)."""
    for item in items:
        if item.path.name not in SHARED_ROW_MODULES:
            item.add_marker(pytest.mark.xdist_group(item.path.name))
    expr = config.getoption("markexpr", "") or ""
    if "slow" in expr.replace("not slow", "") or os.environ.get("NEWTSIM_SLOW"):
        return
    skip = pytest.mark.skip(reason="slow: run `pytest -m slow` or set NEWTSIM_SLOW=1 (make test-slow)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
