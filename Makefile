# The README's two commands: `make run` and `make test`. Both bootstrap .venv from nothing.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: run test test-fleet lint bench experiments clean help

help:
	@echo "make run    start a server, run the paper simulation and the multi-robot demo against it"
	@echo "make test   lint, type-check and run the test suite (all but the fleet matrix)"
	@echo "make test-fleet  the replicated fleet's whole partition and endpoint matrix (~8 min)"
	@echo "make bench  benchmarks and experiments (figures into experiments/results/)"

# Re-install (and rebuild the compiled kernel) only when the packaging or the kernel source
# changes; a second call costs nothing.
$(STAMP): pyproject.toml setup.py service/mcsm/core/_kernel.c
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,eval,viz]'
	@touch $(STAMP)

run: $(STAMP)
	$(PY) -m mcsm_client.demo

lint: $(STAMP)
	$(PY) -m ruff check service clients tests benchmarks experiments
	$(PY) -m mypy --strict service/mcsm clients/mcsm_client

test: lint
	$(PY) -m pytest -q -m "not fleet"

test-fleet: $(STAMP)
	$(PY) -m pytest -q --durations=5 tests/service/test_partitions.py tests/service/test_fleet_endpoints.py

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
