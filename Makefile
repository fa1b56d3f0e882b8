# newtsim: two commands on a fresh Debian machine (as root, or with sudo):
#   make demo   installs everything, renders the built-in showcase scene -> out/demo.fits + out/demo.png,
#               then runs one compare/diagnose round on a frame with a hidden effect -> out/round_*
#   make test   installs everything and runs the test suite
VENV    ?= .venv
PYTHON  ?= python3
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed

.PHONY: install demo test test-slow bench clean

$(STAMP): pyproject.toml scripts/system-deps.sh
	sh scripts/system-deps.sh
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[optics,test]'
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(VENV)/bin/newtsim demo -o out

test: install
	$(PY) -m pytest -q

test-slow: install
	NEWTSIM_SLOW=1 $(PY) -m pytest -q

bench: install
	$(PY) -m pip install -q -e '.[bench]'
	$(PY) benchmarks/bench_detector_fullframe.py
	$(PY) benchmarks/bench_optics_trace.py

clean:
	rm -rf $(VENV) out .pytest_cache
