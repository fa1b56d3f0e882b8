# newtsim: two commands on a fresh Debian machine (as root, or with sudo):
#   make demo   installs everything, renders the built-in showcase scene -> out/demo.fits + out/demo.png,
#               then runs one compare/diagnose round on a frame with a hidden effect -> out/round_*
#   make test   installs everything and runs the test suite
#   make bench  every benchmark against its reference, recorded in benchmarks/history/ (bench-quick: CI's check)
VENV    ?= .venv
PYTHON  ?= python3
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed

.PHONY: install demo test test-slow bench bench-quick clean

$(STAMP): pyproject.toml scripts/system-deps.sh
	sh scripts/system-deps.sh
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[optics,test]'
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(VENV)/bin/newtsim demo -o out

# the suite on TEST_WORKERS processes (pytest-xdist): a test file stays on one process (its module fixtures made
# once), except the validation cases shared on disk (tests/conftest.py SHARED_ROW_MODULES)
TEST_WORKERS ?= 2

test: install
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup

test-slow: install
	NEWTSIM_SLOW=1 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup

# every benchmark with its reference in the same run: benchmarks/history/<date>_<commit>.json (ratios, peak memory,
# machine, commit, date) and one line appended to benchmarks/history/history.jsonl (commit it with the landing)
bench: install
	$(PY) -m pip install -q -e '.[bench]'
	$(PY) benchmarks/run.py --record

# the quick subset (about a minute; CI): fails when a ratio is worse than the last stored one by more than the margin
bench-quick: install
	$(PY) benchmarks/run.py --quick --check

clean:
	rm -rf $(VENV) out .pytest_cache
