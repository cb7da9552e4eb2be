# Two entry points (see README): `make run` and `make test`.
# Both create .venv with the project installed from requirements.lock (exact versions with their
# hashes, PyPI only), then do their job.  `make lock` refreshes the lock; `make test-latest` runs
# the tests against the newest releases instead, so that a breaking release is noticed.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CORES  ?= 2
LOCK   := requirements.lock
LOCK_CLUSTER := requirements-cluster.lock

.PHONY: run test test-all test-cluster test-latest lock samples bench elastic-table lint report clean

# The build backend (setuptools) is in the lock too: the project is installed without build
# isolation, so nothing unpinned is fetched.
$(BIN)/.installed: pyproject.toml $(LOCK)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --require-hashes -r $(LOCK)
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $@

# --keep-going: a tip that fails costs the others nothing; the summary then lists the tips that
# finished and says for the failed one which job failed and why (Snakefile `onerror`).
# After a run that was killed: `unlock-stale` first removes its lock (never that of a run still
# running), and --rerun-incomplete reruns the jobs it was running.
run: $(BIN)/.installed          ## run the whole pipeline on data_samples/ -> results/summary.csv
	$(BIN)/python -m pipeline unlock-stale
	$(BIN)/snakemake --cores $(CORES) --keep-going --rerun-incomplete; status=$$?; \
	  if [ -f results/summary.csv ]; then echo; echo "== results/summary.csv =="; cat results/summary.csv; fi; \
	  exit $$status

# A second arithmetic path: OpenBLAS's generic kernels and numpy without its AVX2/AVX-512 loops
# (names it does not know are ignored).  The TEM fit must give the same result on any x86-64
# CPU, so its tests run again there: a tolerance that holds on one path only fails here.
ALT_ARITHMETIC := OPENBLAS_CORETYPE=Prescott NPY_DISABLE_CPU_FEATURES=X86_V3,X86_V4,AVX512_ICL,AVX512_SPR
TEM_TESTS := tests/test_tem_offset_loops.py tests/test_tem_silhouette_fit.py tests/test_tem_profiles.py tests/test_fits.py tests/test_tem_faint_layer.py tests/test_tem_fringe.py tests/test_tem_outer_layer.py tests/test_tem_saturation.py tests/test_tem_model_error.py

# The style checks first (seconds): a test run is not started on code the tools refuse.
test: $(BIN)/.installed         ## the style checks (make lint), the default (fast) test suite, then the TEM tests on a second arithmetic path
	$(MAKE) --no-print-directory lint
	$(BIN)/pytest
	$(ALT_ARITHMETIC) $(BIN)/pytest $(TEM_TESTS)

test-all: $(BIN)/.installed     ## include the slow tests
	$(BIN)/pytest -m "slow or not slow"

# Not part of `make test`: a single-node SLURM on localhost (scripts/slurm_local.sh; needs root and
# Debian's packages, which the first line installs where it can) runs the sample through
# profiles/slurm, with and without job accounting, and provokes a job over its memory, one over
# its time and a cancelled one (~15 min). Without root or the packages the tests skip, saying why.
test-cluster: $(BIN)/.installed ## the SLURM profile on a local single-node SLURM (root, Debian packages)
	-scripts/slurm_local.sh install --accounting
	$(BIN)/python -m pip install --quiet --require-hashes -r $(LOCK_CLUSTER)
	$(BIN)/pytest -rs -v tests_cluster

# Not part of `make test` (CI's gate is the locked install): the default suite in a separate
# .venv-latest with the newest release of every dependency, after a list of what is newer than
# the lock.  Run it on a schedule (README "Installing"); when it fails, a release broke something.
test-latest:                    ## the default suite against the newest releases (not the lock)
	rm -rf .venv-latest
	$(PYTHON) -m venv .venv-latest
	.venv-latest/bin/python -m pip install --quiet --upgrade pip setuptools
	.venv-latest/bin/python -m pip install --quiet --upgrade --upgrade-strategy eager -e ".[test]"
	.venv-latest/bin/python scripts/lock_drift.py $(LOCK)
	.venv-latest/bin/pytest

# Refresh both lock files with uv (installed into .venv-lock): the newest versions that satisfy
# pyproject.toml, resolved for every platform and Python >= 3.11 with as few version splits as
# possible (so the versions CI tests on Linux/CPython 3.11 are the ones everyone installs), every
# file's sha256.  The cluster lock keeps the main lock's versions and adds the SLURM plugin.
# `make lock LOCK_UPGRADE=` keeps the current pins where pyproject.toml allows them (to add a
# dependency without moving the others).
UV_VERSION := 0.13.8
LOCK_UPGRADE ?= --upgrade
UV_COMPILE = .venv-lock/bin/uv pip compile pyproject.toml .venv-lock/build-system-requires.txt --quiet --generate-hashes \
	--universal --fork-strategy fewest --python-version 3.11 --custom-compile-command "make lock"
lock:                           ## refresh requirements.lock and requirements-cluster.lock (then make test)
	test -x .venv-lock/bin/uv || { $(PYTHON) -m venv .venv-lock && .venv-lock/bin/python -m pip install --quiet "uv==$(UV_VERSION)"; }
	$(PYTHON) -c "import tomllib; print(*tomllib.load(open('pyproject.toml', 'rb'))['build-system']['requires'], sep='\n')" > .venv-lock/build-system-requires.txt
	$(UV_COMPILE) $(LOCK_UPGRADE) --extra test -o $(LOCK)
	cp $(LOCK) $(LOCK_CLUSTER)
	$(UV_COMPILE) --extra test --extra cluster -o $(LOCK_CLUSTER)

samples: $(BIN)/.installed      ## regenerate data_samples/ and config/tips/ from the seeded generator
	$(BIN)/python -m pipeline make-samples --out data_samples --config-dir config/tips

bench: $(BIN)/.installed        ## print the run-time vs error tables
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

elastic-table: $(BIN)/.installed  ## rebuild pipeline/mechanics/data/elastic_pulloff_table.npz (~5 min; commit it)
	OMP_NUM_THREADS=1 $(BIN)/python -m pipeline.mechanics.build_elastic_table

report: $(BIN)/.installed       ## HTML report of a finished run (all figures and CSVs)
	$(BIN)/snakemake --report results/report.html

# ruff ([tool.ruff] in pyproject.toml), snakefmt ([tool.snakefmt]) and Snakemake's own linter.
lint: $(BIN)/.installed         ## the style checks: ruff format --check, ruff check, snakefmt --check, snakemake --lint
	$(BIN)/ruff format --check .
	$(BIN)/ruff check .
	$(BIN)/snakefmt --check Snakefile workflow_rules
	$(BIN)/snakemake --lint

clean:
	rm -rf results .snakemake
