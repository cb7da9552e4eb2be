# Two entry points (see README): `make run` and `make test`.
# Both create .venv with the project installed (PyPI only), then do their job.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CORES  ?= 2

.PHONY: run test test-all test-cluster samples bench elastic-table lint report clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $@

run: $(BIN)/.installed          ## run the whole pipeline on data_samples/ -> results/summary.csv
	$(BIN)/snakemake --cores $(CORES)
	@echo; echo "== results/summary.csv =="; cat results/summary.csv

# A second arithmetic path: OpenBLAS's generic kernels and numpy without its AVX2/AVX-512 loops
# (names it does not know are ignored).  The TEM fit must give the same result on any x86-64
# CPU, so its tests run again there: a tolerance that holds on one path only fails here.
ALT_ARITHMETIC := OPENBLAS_CORETYPE=Prescott NPY_DISABLE_CPU_FEATURES=X86_V3,X86_V4,AVX512_ICL,AVX512_SPR
TEM_TESTS := tests/test_tem_silhouette_fit.py tests/test_tem_profiles.py tests/test_fits.py

test: $(BIN)/.installed         ## the default (fast) test suite, then the TEM tests on a second arithmetic path
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
	$(BIN)/python -m pip install --quiet -e ".[test,cluster]"
	$(BIN)/pytest -rs -v tests_cluster

samples: $(BIN)/.installed      ## regenerate data_samples/ and config/tips/ from the seeded generator
	$(BIN)/python -m pipeline make-samples --out data_samples --config-dir config/tips

bench: $(BIN)/.installed        ## print the run-time vs error tables
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

elastic-table: $(BIN)/.installed  ## rebuild pipeline/mechanics/data/elastic_pulloff_table.npz (~5 min; commit it)
	OMP_NUM_THREADS=1 $(BIN)/python -m pipeline.mechanics.build_elastic_table

report: $(BIN)/.installed       ## HTML report of a finished run (all figures and CSVs)
	$(BIN)/snakemake --report results/report.html

lint: $(BIN)/.installed
	$(BIN)/snakemake --lint

clean:
	rm -rf results .snakemake
