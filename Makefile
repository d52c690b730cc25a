# The two set-up commands are `make demo` and `make test`; each creates or refreshes .venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# numba's worker threads busy-wait by default; on small shared VMs that stalls everything.
export OMP_WAIT_POLICY ?= passive
export OPENBLAS_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: venv test lint demo bench study-target-pose studies-quick clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks

# Two workers, each test file on one of them (module fixtures are built once).
test: $(STAMP) lint
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

demo: $(STAMP)
	$(BIN)/pelvicnav demo --out demo-output

bench: $(STAMP)
	mkdir -p benchmarks/results
	$(BIN)/python -m benchmarks.run --out benchmarks/results

# The full leave-one-out target-pose study on the real atlas (about 1.5 min on 2 cores).
study-target-pose: $(STAMP)
	$(BIN)/pelvicnav study target-pose --out studies-output/target-pose --workers 2

# Every study's --quick version, one after the other on one shared cluster (a worker per core)
# (pelvicnav.studies.quick; goal: 2 min together, see docs/studies.md).
QUICK := studies-output/quick
studies-quick: $(STAMP)
	rm -rf $(QUICK)
	$(BIN)/python -m pelvicnav.studies.quick $(QUICK)

clean:
	rm -rf $(VENV) demo-output studies-output .pytest_cache .ruff_cache .hypothesis
