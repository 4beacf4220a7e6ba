# Two commands on a fresh machine (README): `make demo` and `make test`.
# Both create the virtual environment on first use; nothing is installed globally
# except the system library open3d needs (libusb-1.0-0, via apt when run as root).

PYTHON ?= python3
VENV ?= .venv
CORES ?= 2
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test test-fast lint dry-run report view figures bench-sweep bench-stability clean-results

install: $(STAMP)

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "sellip needs Python >= 3.11")'
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 (needed by open3d)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else \
	    echo "open3d needs the system library libusb-1.0-0: install it (e.g. 'sudo apt-get install libusb-1.0-0') and re-run" >&2; exit 1; \
	  fi; \
	fi
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	@touch $(STAMP)

# The main job: the whole workflow on the built-in demo capture (generated on first use).
demo: $(STAMP)
	$(BIN)/snakemake --cores $(CORES) --workflow-profile workflow/profiles/default

dry-run: $(STAMP)
	$(BIN)/snakemake -n --workflow-profile workflow/profiles/default

report: $(STAMP)
	$(BIN)/snakemake --workflow-profile workflow/profiles/default --report results/report.html

# The viewer, materials table and exports of a finished run results/RUN (docs/viewer.md; RUN=demo by default), SERVE=1 serves it.
RUN ?= demo
view: $(STAMP)
	$(BIN)/sellip view results/$(RUN) $(if $(SERVE),--serve)

# The whole suite (~27 min on 2 cores; CI runs it), ending with its 25 slowest tests. Two pytest-xdist workers (one
# per core) take whole test files (--dist loadfile: a module's fixtures run once), the files with the most slow tests
# first (tests/conftest.py): one worker fills the other's idle time (Snakemake's serial jobs, single-threaded compiles).
test: $(STAMP)
	$(BIN)/python -m pytest -n $(CORES) --dist loadfile --no-loadscope-reorder --durations=25

# The inner loop (< 3 min on 2 cores): every package's fast tests, without those marked slow.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -m "not slow"

# ruff (rules in pyproject.toml), snakefmt and Snakemake's own linter; CI runs this before the tests.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/snakefmt --check Snakefile workflow/
	$(BIN)/snakemake --lint --workflow-profile workflow/profiles/default

# The README's accuracy table regenerated and compared, number by number, within the README's tolerances
# (docs/benchmarks.md, "Paper figures by one command"). FIGURES=small: the demo (minutes on 2 cores; CI runs it);
# FIGURES=all: the sphere_ior and painted cow rows too (about 2 h more). The comparison, commit and versions: results/figures.json.
FIGURES ?= small
figures: $(STAMP)
	$(BIN)/sellip figures run --size $(FIGURES) --record results/figures.json

# The stability suite (docs/benchmarks.md): failure-mode cases run end to end -> results/bench/stability/.
bench-stability: $(STAMP)
	$(BIN)/sellip bench-stability --out results/bench/stability --cores $(CORES)

# The speed-accuracy sweep of docs/benchmarks.md at the demo's own settings (full preset; --preset quick: 320x256).
bench-sweep: $(STAMP)
	$(BIN)/sellip bench-sweep --scenes demo sphere_ior --preset full --out results/bench/sweep --cores $(CORES)

clean-results:
	rm -rf results .snakemake
