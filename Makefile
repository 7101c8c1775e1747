# Two commands for a fresh machine (see README):  make demo   and   make test
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml requirements.lock
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# The CPU build of torch lies on local disk; install the pin first so nothing pulls a CUDA build.
	$(BIN)/pip install -q torch==2.13.0
	# Every other package at its locked version (the same on every machine and cluster node), then
	# gopre itself without resolving anything again.
	$(BIN)/pip install -q -r requirements.lock
	$(BIN)/pip install -q --no-deps -e .
	# Compile the CPU kernels once into numba's cache beside the sources (about 2 min on 2 cores, two parts at once), so the
	# first sweep starts at once and the test suite's workers do not each compile them.
	$(BIN)/python -m pipeline.experiment.warmup
	touch $(STAMP)

.PHONY: env lock demo test test-fast reproduce lint docs e2e latex texlive mutate bench postgres
env: $(STAMP)

# Re-lock after changing pyproject.toml's dependencies: resolve them in a fresh venv, freeze it.
lock:
	rm -rf .lock-venv && $(PY) -m venv .lock-venv
	.lock-venv/bin/pip install -q --upgrade pip && .lock-venv/bin/pip install -q torch==2.13.0
	.lock-venv/bin/pip install -q -e '.[dev]'
	{ sed -n '/^#/p' requirements.lock; .lock-venv/bin/pip freeze --exclude-editable | \
		sed 's/^torch==\([0-9.]*\)+.*/torch==\1/'; } > requirements.lock.new && mv requirements.lock.new requirements.lock
	rm -rf .lock-venv

# The demo sweep (gopre, fisherrf, random, coverage on the generated scene) on local Ray with
# MLflow tracking, then its report in reports/demo/.
demo: $(STAMP)
	$(BIN)/gopre-run experiment=demo
	$(BIN)/gopre-report outputs/demo --out reports/demo

# The whole suite in pytest-xdist processes, one per core (TEST_WORKERS); the tests that start Ray run
# one after another in one of them, those that start servers and job arrays in one (tests/conftest.py).
# Each process runs its tests at one thread, its share of the cores. One process more than the cores
# was measured slower (2026-12-08: 20 min 58 s against 20 min 04 s, 7% more CPU seconds, and a Ray
# test lost its round progress under the load).
TEST_WORKERS ?= $(shell python3 -c 'import os; print(len(os.sched_getaffinity(0)))')
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup

# Every published digit re-run to its last digit: each episode of reports/reproduce/episodes.json
# and the README's demo table, those the suite leaves out for their time (the full bonsai episode,
# 6 min; the sparse one and the demo table, 2.4 min each) included. CI runs it after `make test`.
reproduce: $(STAMP)
	GOPRE_REPRODUCE_ALL=1 $(BIN)/python -m pytest -q -n auto tests/test_reproduce.py

# Lint and types (CI runs it before the tests): ruff's pyflakes/pycodestyle rules, the layer contracts
# (import-linter), and mypy over the package (pyproject.toml: its config and the modules still on the
# baseline). No import cycle inside a package is a test (tests/test_import_cycles.py).
lint: $(STAMP)
	$(BIN)/ruff check pipeline tests tools examples
	$(BIN)/lint-imports
	$(BIN)/mypy
	$(BIN)/hadolint docker/Dockerfile

# The documentation site (docs/, mkdocs.yml) into site/, strict: a broken link, a missing page or
# an API docstring mkdocstrings cannot read is an error (CI runs it).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict -q

# The quick loop: every module with its oracles, without the tests marked slow (real-data fits,
# Ray/MLflow integration sweeps, kill-and-resume episodes). The full suite is `make test`.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadgroup -m "not slow"

# The viewer's browser tests (tests/test_view.py, marker e2e): the system Chromium, installed from
# the Debian packages when missing (`make test` runs them whenever a browser is present).
e2e: $(STAMP)
	command -v chromium >/dev/null || { $$( [ "$$(id -u)" = 0 ] || echo sudo ) apt-get update -qq && \
		$$( [ "$$(id -u)" = 0 ] || echo sudo ) apt-get install -y -qq chromium; }
	$(BIN)/python -m pytest -q -m e2e

# The LaTeX tables' compile test (tests/test_report.py: no error, no overfull line, and the marks
# read off the PDF's fonts) needs pdflatex: Debian's texlive-latex-recommended (about a minute,
# `make texlive`; .ci/run installs it); `make test` skips it with the reason otherwise.
texlive:
	command -v pdflatex >/dev/null || { $$( [ "$$(id -u)" = 0 ] || echo sudo ) apt-get update -qq && \
		$$( [ "$$(id -u)" = 0 ] || echo sudo ) apt-get install -y -qq --no-install-recommends texlive-latex-recommended; }

latex: $(STAMP) texlive
	$(BIN)/python -m pytest -q tests/test_report.py -k pdflatex

# Mutation testing of the core's formulas ([tool.mutmut] in pyproject.toml: which modules, which
# oracle tests); resumable. The mutated modules are the torch path, so the compiled backend is off
# here (mutmut forks its workers, and the torch path is the oracle the compiled kernels are tested
# against in tests/test_compiled.py); `$(BIN)/mutmut results` lists the survivors, `mutmut show NAME` one diff.
# All modules take hours on 2 cores; MUTANTS narrows the run to mutant-name globs and re-runs them,
# e.g. `make mutate MUTANTS='pipeline.splat.project.x_conic_2d*'`.
MUTANTS ?=
mutate: $(STAMP)
	$(BIN)/pip install -q 'mutmut==3.8.1'
	GOPRE_SHARED_DATA=$(abspath ../shared/data) GOPRE_TEST_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
		GOPRE_DISABLE_COMPILED=1 \
		$(BIN)/mutmut run --max-children 2 $(MUTANTS)
	$(BIN)/python tools/mutation_summary.py

# PostgreSQL for the tracking-server tests (tests/test_tracking_server.py): Debian's postgresql
# package, installed when initdb is missing (`make test` runs those tests whenever it is present).
postgres:
	command -v initdb >/dev/null || ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || { \
		$$( [ "$$(id -u)" = 0 ] || echo sudo ) apt-get update -qq && \
		$$( [ "$$(id -u)" = 0 ] || echo sudo ) apt-get install -y -qq --no-install-recommends postgresql; }

bench: $(STAMP)
	$(BIN)/python -m pipeline.bench render
