# One command sets up and runs each job: `make demo` (the research's flight test in SITL, moving and static,
# with their report) and `make test` (the suite).
PYTHON ?= python3
DATA_DIR ?= ../shared/data
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: coded-demo demo test lint bench bench-smoke arm64-check clean

# Python keeps what it compiles (__pycache__, not in git). A host that turns that off (PYTHONDONTWRITEBYTECODE, as
# the development machine does) has every agent, MPI rank and command the suite starts compile NAC's modules again.
# The venv is installed by uv (pip installs uv in 10 s, uv the rest in 5 s: 17 s from nothing against 48 s with
# pip alone), without byte-compiling: modules compile on first import. Where uv cannot be had, pip does it all.
unexport PYTHONDONTWRITEBYTECODE
NO_DEPS = $$($(BIN)/python -c "import sys; toml = __import__('tomllib' if sys.version_info >= (3, 11) else 'tomli'); \
    print(' '.join(toml.load(open('pyproject.toml', 'rb'))['tool']['nac']['test-no-deps']))")

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	if $(BIN)/python -m pip install -q uv && \
	    $(BIN)/uv pip install --python $(BIN)/python -q -e '.[mpich,test]' && \
	    $(BIN)/uv pip install --python $(BIN)/python -q --no-deps $(NO_DEPS); then :; else \
	    $(BIN)/python -m pip install -q --no-compile -e '.[mpich,test]' && \
	    $(BIN)/python -m pip install -q --no-compile --no-deps $(NO_DEPS); \
	fi
	touch $(STAMP)

demo: $(STAMP)
	@test -f "$${NAC_DATA_DIR:-$(DATA_DIR)}/forestfires.csv" || $(BIN)/nac-onboard data fetch
	NAC_DATA_DIR=$${NAC_DATA_DIR:-$(DATA_DIR)} $(BIN)/python -m sitl.experiment.demo

# The same straggler flight with the uncoded and the gradient-coded linear regression, and their comparison.
coded-demo: $(STAMP)
	@test -f "$${NAC_DATA_DIR:-$(DATA_DIR)}/forestfires.csv" || $(BIN)/nac-onboard data fetch
	NAC_DATA_DIR=$${NAC_DATA_DIR:-$(DATA_DIR)} $(BIN)/python -m sitl.experiment.demo --pair coded \
	    --out runs/coded-demo-$$(date +%Y%m%dT%H%M%S)

# The suite in three processes on the two cores (many of its tests wait on a simulated flight or a child process:
# three keep both cores busy, 274 s against 319 s with two), then the tests that measure rates and times against a
# bound, or look at the host's namespaces, on a quiet machine (marked `exclusive`). They leave one core idle most of
# the time (104 % of one core over their 250 s, measured): the long tests that judge nothing against a clock and
# touch nothing outside namespaces of their own (marked `niced`: the offline install, the docs' checks, ten unit modules that only
# compute, and the coded tasks' MPI runs with a killed or slow worker, which judge results) run beside them in the kernel's idle class (SCHED_IDLE: any other task that wakes
# takes the core at once; at nice 19 alone, they slowed the exclusive tests by 30 s in all) and idle I/O class,
# taking only what the exclusive tests leave. A test that waits on a simulated clock is not for this: starved, the
# documented commands' copter disarmed between two commands. Their output follows the exclusive tests'. Last, alone,
# the tests that time tens of microseconds of wall time (marked `quiet`: on this VM a wake-up on a CPU running any
# other task, even one in the idle class, costs some 40 us more).
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -m "not exclusive and not niced and not quiet" -n 3 --dist worksteal --durations=20
	@beside=$$(mktemp -d); \
	chrt --idle 0 ionice -c 3 nice -n 19 $(BIN)/python -m pytest -m niced -p no:cacheprovider \
	    --basetemp "$$beside/tmp" --durations=5 \
	    > "$$beside/log" 2>&1 & niced=$$!; \
	$(BIN)/python -m pytest -m exclusive --durations=20 tests/integration; exclusive=$$?; \
	wait $$niced; niced=$$?; echo "---- the niced tests, run beside the exclusive ones at idle priority ----"; \
	cat "$$beside/log"; rm -rf "$$beside"; \
	$(BIN)/python -m pytest -m quiet -p no:cacheprovider tests/integration; quiet=$$?; \
	[ $$exclusive -eq 0 ] && [ $$niced -eq 0 ] && [ $$quiet -eq 0 ]

# The lint rules are ruff's, set in pyproject.toml (pycodestyle, pyflakes, isort, bugbear, naming...). The code
# keeps its own line wrapping: `ruff format` would rewrite some 4,500 lines for no change in behaviour.
lint: $(STAMP)
	$(BIN)/ruff check .

# Every script in benchmarks/, for real (minutes) or with --smoke (the same code at tiny sizes, seconds each).
BENCHMARKS := $(filter-out _%,$(notdir $(basename $(wildcard benchmarks/*.py))))

bench: $(STAMP)
	set -e; for b in $(BENCHMARKS); do $(BIN)/python benchmarks/$$b.py; done

bench-smoke: $(STAMP)
	set -e; for b in $(BENCHMARKS); do $(BIN)/python benchmarks/$$b.py --smoke; done

# NAC on an arm64 companion's userland under qemu: wheelhouse here, offline install there, doctor, a compute run
# (root; minutes). Its result is recorded in docs/deploy-arm64.md.
arm64-check:
	@command -v debootstrap >/dev/null && test -x /usr/bin/qemu-aarch64-static || \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -q debootstrap qemu-user-static binfmt-support >/dev/null
	deploy/arm64-check.sh

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
