# Set-up and checks from a fresh clone. `make test` and `make demo` create .venv on first use.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=

.PHONY: venv test test-fast demo lint bench clean

venv: $(STAMP)

# Re-runs only when the dependency files change; torch is pinned to the local CPU wheel by
# constraints.txt so nothing ever pulls a CUDA build.
$(STAMP): requirements.txt constraints.txt setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q -c constraints.txt -r requirements.txt
	$(PY) -m pip install --disable-pip-version-check -q --no-deps -e .
	touch $(STAMP)

lint: venv
	$(VENV)/bin/ruff check fhld_ros msg_adapters test setup.py

# the whole suite: unit tests, real DDS between processes, colcon build, slow regressions
test: venv lint
	$(VENV)/bin/pytest -q -ra --durations=15 --timeout=900 $(PYTEST_ARGS)

# unit tests only: no rclpy context, DDS, colcon or test over ~5 s (markers in setup.cfg)
test-fast: venv
	$(VENV)/bin/pytest -q -ra --durations=10 --timeout=300 -m "not ros and not slow" $(PYTEST_ARGS)

# simulate a drive, detect lanes, score them, draw out/demo/demo.png (see README)
demo: venv
	$(VENV)/bin/fhld demo --out out/demo --overwrite

bench: venv
	$(VENV)/bin/fhld bench

clean:
	rm -rf $(VENV) build install log *.egg-info .pytest_cache .ruff_cache .hypothesis
