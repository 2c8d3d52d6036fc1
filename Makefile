# cvslam: every target sets itself up on a machine with only Python >= 3.11.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.install-stamp
SHARED_DATA ?= $(if $(CVSLAM_SHARED_DATA),$(CVSLAM_SHARED_DATA),../shared/data)
DEMO_DIR ?= runs/demo

.PHONY: install test lint bench demo clean check-report fuzz batch all-datasets summary wheel-test

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11) and "cvslam needs Python >= 3.11")'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# one worker per core, each test file on one worker (its module fixtures built once)
test: install
	$(BIN)/python -m pytest -q -n auto --dist loadfile

lint: install
	$(BIN)/ruff check cvslam_cli tests
	$(BIN)/ruff format --check cvslam_cli tests

bench: install
	$(BIN)/python -m pytest -q -s tests/benchmarks -p no:cacheprovider -o addopts=""

demo: install
	@bash scripts/demo.sh "$(BIN)/cvslam" "$(SHARED_DATA)" "$(DEMO_DIR)"

clean:
	rm -rf $(VENV) runs datasets/generated .pytest_cache .ruff_cache

# Build the wheel, install it in a fresh venv and run the demo scenario with it (~70 s;
# `make test` only checks the wheel's contents).
wheel-test: install
	CVSLAM_WHEEL_TEST=1 $(BIN)/python -m pytest -q -p no:cacheprovider tests/test_wheel.py

# Render the demo's report in headless Chromium and check every image loaded (needs chromium).
check-report: install
	$(BIN)/python scripts/check_report.py $(DEMO_DIR)/run/eval/report.html

# The MCAP reader's fuzz test over many damaged variants (40 run in `make test`);
# `make fuzz FUZZ_VARIANTS=3000`, seed from CVSLAM_FUZZ_SEED (default 2026).
FUZZ_VARIANTS ?= 600
fuzz: install
	CVSLAM_FUZZ_VARIANTS=$(FUZZ_VARIANTS) $(BIN)/python -m pytest -q -s -p no:cacheprovider tests/io/test_mcap_fuzz.py

# ---------------------------------------------------------------------------- datasets
# One recipe per dataset in $(DATASETS_DIR) (datasets/README.md). `make runs/NAME/eval/report.html`
# builds one, `make batch` (= all-datasets) every one, `make -j N batch` N at a time (each
# recipe writes only its own run and generated folders); `make summary` compares them. A
# second `make batch` has nothing to do; after a recipe changes, its stages skip what is up to
# date. CVSLAM / INSTALL: another cvslam command, and what it needs first (the tests use this).
DATASETS_DIR  ?= datasets
RUNS_DIR      ?= runs
GENERATED_DIR ?= $(DATASETS_DIR)/generated
CVSLAM        ?= $(BIN)/cvslam
INSTALL       ?= $(STAMP)
RECIPES  := $(sort $(wildcard $(DATASETS_DIR)/*.yaml))
DATASETS := $(patsubst $(DATASETS_DIR)/%.yaml,%,$(RECIPES))
REPORTS  := $(patsubst %,$(RUNS_DIR)/%/eval/report.html,$(DATASETS))

$(RUNS_DIR)/%/eval/report.html: $(DATASETS_DIR)/%.yaml | $(INSTALL)
	$(CVSLAM) batch --serial --runs $(RUNS_DIR) --generated $(GENERATED_DIR) $<

batch all-datasets: $(REPORTS)

summary: $(REPORTS)
	$(CVSLAM) summary $(patsubst %,$(RUNS_DIR)/%,$(DATASETS)) -o $(RUNS_DIR)/summary
