# make demo : set up everything on a fresh Debian machine, then run the main job.
# make test : the same set-up, then the whole test suite.
# make bench: the same set-up, then the speed benchmarks of bench/ with their defaults (figures: BENCHMARKS.md).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@bash scripts/setup_system.sh
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	@touch $(STAMP)

demo: setup
	$(BIN)/tsnav demo

test: setup
	$(BIN)/python -m pytest -q tests

# bench_detect.py is left out: it needs a built world and a detector checkpoint (--data, --checkpoint; BENCHMARKS.md)
bench: setup
	@for f in bench/*.py; do \
	  if [ "$$f" = bench/bench_detect.py ]; then echo "== $$f skipped: needs --data WORLD --checkpoint DETECTOR"; continue; fi; \
	  echo "== $$f"; $(BIN)/python $$f || exit 1; done

clean:
	rm -rf $(VENV) out runs
