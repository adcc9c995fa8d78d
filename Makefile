# One entry point for set-up, tests, demo and benchmarks. Everything a fresh machine needs is installed here.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Keep DDS discovery on this machine (tests and demo never talk to the network).
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export MPLBACKEND ?= Agg

.PHONY: install test lint demo bench paper-sim clean

install: $(STAMP)

$(STAMP): setup.py package.xml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "Python >= 3.11 needed, found " + sys.version' 
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip setuptools wheel
	$(PY) -m pip install --quiet -e '.[ros,test]'
	touch $(STAMP)

lint: install
	$(VENV)/bin/ruff check .

test: install lint
	$(VENV)/bin/python -m pytest -q test

# Until the live pipeline lands (issue: KLT flow node, estimator node, live pipeline) the demo runs the
# papers' numerical experiments on a reduced number of trials and writes report.json + PNGs to demo_out/.
demo: install
	$(VENV)/bin/fixego paper-sim --out demo_out --trials 50 --trials-seq 10

paper-sim: install
	$(VENV)/bin/fixego paper-sim --out docs/paper_sim

bench: install
	$(VENV)/bin/python -m fixego_ros.bench --out bench

clean:
	rm -rf $(VENV) build install log .pytest_cache
