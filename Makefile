# The README's two commands: `make run` and `make test`. Both bootstrap .venv from nothing.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: run test test-fleet lint bench experiments clean help wheel-check

help:
	@echo "make run    start a server, run the paper simulation and the multi-robot demo against it"
	@echo "make test   lint, type-check and run the test suite (all but the fleet matrix)"
	@echo "make test-fleet  the replicated fleet's whole partition and endpoint matrix (~8 min)"
	@echo "make bench  benchmarks and experiments (figures into experiments/results/)"
	@echo "make wheel-check  build the wheel, install it in a fresh venv, run it (CI runs it)"

# Re-install (and rebuild the compiled kernel) only when the packaging or the kernel source
# changes; a second call costs nothing.
# The first build takes a minute or more (downloads, the C kernel): each step says what it does
# and pip shows what it fetches.
$(STAMP): pyproject.toml setup.py $(wildcard service/mcsm/core/_*.c service/mcsm/core/*.h)
	@echo "make: setting up $(VENV) (once; about a minute the first time)"
	@test -x $(PY) || { echo "make: [1/4] creating $(VENV)"; $(PYTHON) -m venv $(VENV); }
	@echo "make: [2/4] upgrading pip"
	@$(PY) -m pip install --quiet --upgrade pip
	@echo "make: [3/4] installing mcsm with extras test, eval, viz, ros and building its C kernel"
	@{ $(PY) -m pip install --progress-bar off -e '.[test,eval,viz,ros]'; echo $$? > $(VENV)/.rc; } \
		| grep --line-buffered -E '^(Collecting|Building|Installing|Successfully)' || true
	@test "$$(cat $(VENV)/.rc)" = 0 || { echo "make: pip install failed (see above)"; exit 1; }
	@echo "make: [4/4] building tf2_msgs/TFMessage for mcsm ros2 (cached in ~/.cache/mcsm)"
	@$(PY) -m mcsm_client.ros2.tf2 >/dev/null
	@touch $(STAMP)
	@echo "make: $(VENV) is ready"

run: $(STAMP)
	$(PY) -m mcsm_client.demo

lint: $(STAMP)
	$(PY) -m ruff check service clients tests benchmarks experiments
	$(PY) -m mypy --strict service/mcsm clients/mcsm_client

# PyPI's ROS wheels (the ros extra) make every Python of the venv re-exec itself once to set
# LD_LIBRARY_PATH (ros_wheels_bootstrapper.pth, about 70 ms a process): the suite sets it once.
ROS_ENV = LD_LIBRARY_PATH="$$(_ROS_WHEELS_BOOTSTRAP_COMPLETE=1 $(PY) -c 'import ros_wheels_bootstrapper as b; print(b.get_ros_paths())')" _ROS_WHEELS_BOOTSTRAP_COMPLETE=1

# The suite waits on subprocesses and sockets more than it computes: two pytest-xdist workers,
# each taking whole test files (module fixtures are built once), finish it sooner even on 2
# shared cores. PYTEST_WORKERS=0 runs it in one process.
PYTEST_WORKERS ?= 2
test: lint
	$(ROS_ENV) $(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile -m "not fleet"

test-fleet: $(STAMP)
	$(ROS_ENV) $(PY) -m pytest -q --durations=5 tests/service/test_partitions.py tests/service/test_fleet_endpoints.py

wheel-check: $(STAMP)
	$(PY) tests/install/check_wheel.py

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
