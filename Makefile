# The few commands people type. Every target works from a fresh clone: the venv is created (or reused)
# by .ci/env.sh, outside the clone, keyed by the dependency list.
VENV ?= $(shell bash .ci/env.sh)
PY := $(VENV)/bin/python
EXT_SUFFIX = $(shell $(PY) -c "import sysconfig; print(sysconfig.get_config_var('EXT_SUFFIX'))")

.PHONY: install dev run test test-rust test-py lint fmt bench bench-slam

## install: build the extension (release: fat LTO) and install evgs into the venv, editable
install:
	$(PY) -m pip install -q --no-build-isolation --no-deps -e .

## dev: quick optimised in-place build of evgs._core for development (thin LTO)
dev:
	cargo build --profile fast --features extension-module
	cp target/fast/libevgs.so python/evgs/_core$(EXT_SUFFIX)

## run: the main job on the built-in default sequence
run: install
	$(VENV)/bin/evgs run --seq synthetic/orbit_ambient

## test: all tests, Rust and Python
test: install test-rust test-py

test-rust:
	cargo test --quiet

test-py:
	$(PY) -m pytest -q; rc=$$?; if [ $$rc -eq 5 ]; then echo "pytest: no tests collected"; rc=0; fi; exit $$rc

lint:
	cargo fmt --check
	cargo clippy --all-targets --quiet -- -D warnings
	cargo clippy --features python --quiet -- -D warnings
	$(VENV)/bin/ruff check python tests benches
	$(VENV)/bin/ruff format --check python tests benches

fmt:
	cargo fmt
	$(VENV)/bin/ruff format python tests benches
	$(VENV)/bin/ruff check --fix python tests benches

## bench: criterion benches (Rust) and the Python side-by-side bench scripts
bench: install
	cargo bench
	for f in benches/*.py; do $(PY) $$f; done

## bench-slam: the SLAM suite (every synthetic preset × seeds 0 1 2; hours on 2 cores), e.g.
## make bench-slam BENCH_ARGS="--presets docking_good --seeds 0 --frames 20"
bench-slam: install
	$(VENV)/bin/evgs bench slam $(BENCH_ARGS)
