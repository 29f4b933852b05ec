# make demo : set up everything on a fresh Debian machine, then run the main job.
# make test : the same set-up, then the whole test suite.
# make test-fast: the same set-up, then the tests that build no world and train for no more than seconds
#            (pytest -m "not slow", at most two minutes on 2 cores); make test and CI run everything.
# make lint : ruff check and ruff format --check over src, tests and bench (rules in pyproject.toml); .ci/run runs
#             it before the tests (`ruff format src tests bench` formats).
# make bench: the same set-up, then the speed benchmarks of bench/ with their defaults (figures: BENCHMARKS.md).
# make docs : render the generated pages again (docs/COMMANDS.md from the CLI; docs/RESULTS.md and README.md's
#             Table I from docs/results/ and the model cards); tests/project/test_docs_pages.py fails while one is stale.
PY ?= python3
# The exact torch build set-up installs before the package: 2.13.0 is the small CPU build that lies on this
# disk (pip takes it from there). pyproject.toml only declares the range the code works with (torch>=2.1), so
# `pip install -e .` beside a researcher's own torch (a CUDA build, say) keeps it; a plain range asked for with
# no torch installed would pull a CUDA build of several GB. `make TORCH= test` keeps whatever torch is there.
TORCH ?= torch==2.13.0
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-fast lint bench docs clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@bash scripts/setup_system.sh
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	@if [ -n "$(TORCH)" ]; then $(BIN)/pip install -q '$(TORCH)'; fi
	$(BIN)/pip install -q -e '.[test]'
	@touch $(STAMP)

demo: setup
	$(BIN)/tsnav demo

test: setup
	$(BIN)/python -m pytest -q tests

test-fast: setup
	$(BIN)/python -m pytest -q -m "not slow" tests

lint: setup
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench

# left out: bench_detect.py needs a built world and a detector checkpoint (--data, --checkpoint); bench_gym.py and
# bench_frame_read.py a built world (--data); bench_frames_disk.py a scratch folder and builds rooms for minutes
# (--out). Their commands are in BENCHMARKS.md.
NEEDS_ARGS := bench/bench_detect.py bench/bench_gym.py bench/bench_frame_read.py bench/bench_frames_disk.py
bench: setup
	@for f in bench/*.py; do \
	  case " $(NEEDS_ARGS) " in *" $$f "*) echo "== $$f skipped: needs arguments (BENCHMARKS.md)"; continue;; esac; \
	  echo "== $$f"; $(BIN)/python $$f || exit 1; done

docs: setup
	$(BIN)/python -m tsnav.cli_reference
	$(BIN)/python -m tsnav.report.results_page

clean:
	rm -rf $(VENV) out runs
