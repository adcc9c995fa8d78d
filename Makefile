# One entry point for set-up, tests, demo and benchmarks. Everything a fresh machine needs is installed here.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Keep DDS discovery on this machine (tests and demo never talk to the network).
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export MPLBACKEND ?= Agg

.PHONY: install lock test lint demo bench bags bags-check paper-sim clean

install: $(STAMP)

# constraints.txt pins every resolved dependency, so a fresh machine gets what CI tested; `make lock` refreshes it.
$(STAMP): setup.py package.xml constraints.txt
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "Python >= 3.11 needed, found " + sys.version'
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip setuptools wheel -c constraints.txt
	$(PY) -m pip install --quiet -e '.[ros,test]' -c constraints.txt
	touch $(STAMP)

# Re-resolve the dependencies from setup.py in a scratch venv (newest versions the registries offer) and pin them.
lock:
	rm -rf .venv-lock
	$(PYTHON) -m venv .venv-lock
	.venv-lock/bin/python -m pip install --quiet --upgrade pip setuptools wheel
	.venv-lock/bin/python -m pip install --quiet -e '.[ros,test]'
	(echo '# Resolved dependency versions for `make install` (pip -c). Refresh: `make lock`, then run `make test`.'; \
	 .venv-lock/bin/python -m pip freeze --all --exclude-editable | grep -v '^#') > constraints.txt
	rm -rf .venv-lock

lint: install
	$(VENV)/bin/ruff check .

test: install lint
	$(VENV)/bin/python -m pytest -q test

# The live pipeline on the simulated rig (DESIGN.md §6): every node a separate process over DDS; runs the
# papers' stadium loop, stops by itself and writes demo_out/ (TUM files, ATE/RPE, plot, latency, logs).
demo: install
	$(VENV)/bin/fixego demo --out demo_out

paper-sim: install
	$(VENV)/bin/fixego paper-sim --out docs/paper_sim

bench: install
	$(VENV)/bin/python -m fixego_ros.bench --out bench

# The shipped test bags (bags/paper, bags/walk) from their seeded recipe in fixego_ros/bags/shipped.py.
bags: install
	$(PY) -m fixego_ros.bags.shipped --force

bags-check: install
	$(PY) -m fixego_ros.bags.shipped --check

clean:
	rm -rf $(VENV) build install log .pytest_cache
