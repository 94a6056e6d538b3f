# Two commands do all the set-up: `make demo` and `make test`; each creates .venv if needed.
# `make test` with CI=true (as .ci/run sets) also runs lint, types, docs and the wheel check.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEV_STAMP := $(VENV)/.installed-dev
DOCS_STAMP := $(VENV)/.installed-docs
TORCH := torch==2.13.0

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# the pinned torch first (the CPU build where pip's configuration offers it), so that the
	# range in pyproject.toml installs nothing more
	$(BIN)/pip install --quiet "$(TORCH)"
	$(BIN)/pip install --quiet -e ".[test,notebooks,benchmarks]"
	# the compiled small-problem path (numba, in the test extra): compiled here, once (about 2
	# minutes), never by a fit; nothing to do where the cache is current
	@echo "compiling torchpref's compiled fast path once (about 2 minutes) ..."
	$(BIN)/torchpref fast-path build --if-needed
	touch $(STAMP)

$(DEV_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $(DEV_STAMP)

$(DOCS_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -e ".[docs]"
	touch $(DOCS_STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m torchpref.demo

# `make test`: the suite without the tests marked slow (kills, browsers, long loops, the longer
# grids); `make test-slow`: only those. CI (CI=true) runs both, then the checks.
# `make fast-path`: compile the compiled path for this checkout (after its sources changed; about
# 2 minutes), or say that its cache is current (docs/speed.md, "The compiled path")
fast-path: $(STAMP)
	$(BIN)/torchpref fast-path build --if-needed

test: $(STAMP) fast-path
	$(BIN)/python -m pytest -q
ifeq ($(CI),true)
	$(MAKE) test-slow lint types docs wheel-check test-floor
endif

# every results file under benchmarks/results: fresh, stale (its measured code changed) or unstamped
results-status: $(STAMP)
	$(BIN)/python benchmarks/results_status.py

# write every figure into README.md and docs/*.md from its stamped results file (docs/figures.py);
# a stale one gets its visible note
pages: $(STAMP)
	$(BIN)/python docs/figures.py --write

# re-run every measurement the pages quote, then write the pages (docs/results.md: what each step
# costs on this project's 2-core machine, which settings are cheaper than the published runs', and
# what it leaves out: the Ax loops, which need the Ax environment, `make test-integrations`).
# Run it alone on the machine: the speed figures are CPU times.
RESULTS := benchmarks/results
results: $(STAMP) fast-path
	$(BIN)/torchpref reproduce wave --out $(RESULTS)
	$(BIN)/pip install --quiet -e ".[speed-peers]"  # botorch-rust, the speed table's second peer
	$(BIN)/python benchmarks/speed/speed_pairwise.py --sizes 20 50 100 200 500 --repeats 5 --slow-n 1000 --clock cpu --threads 1 --no-mixed --no-memory --out $(RESULTS)/speed_quiet
	$(BIN)/python benchmarks/speed/speed_fast_path.py --sizes 20 50 100 200 --person-sizes 20 50 100 200 --repeats 7 --out $(RESULTS)/fast_path
	$(BIN)/python benchmarks/studies/population.py
	$(BIN)/python benchmarks/studies/population_scale.py
	$(BIN)/python benchmarks/studies/study_twins.py
	rm -rf .cache/twins  # the twins' populations refitted on this code (about 14 minutes in all)
	OMP_NUM_THREADS=1 $(BIN)/python benchmarks/studies/twins.py --fresh --cache .cache/twins
	$(BIN)/torchpref reproduce replay --out $(RESULTS)/replay
	$(BIN)/python benchmarks/robustness/fuzz.py
	$(BIN)/python benchmarks/speed/speed_line_search.py
	@if [ -n "$$TORCHPREF_SUSHI_DATA" ]; then \
	  $(BIN)/torchpref reproduce sushi --calibration 0 --out $(RESULTS)/sushi && \
	  $(BIN)/torchpref reproduce sushi --rating-model-only --calibration 200 --out $(RESULTS)/sushi; \
	else echo "results: the SUSHI replay left out (set TORCHPREF_SUSHI_DATA to your download; docs/real_raters.md)"; fi
	$(BIN)/python benchmarks/results_status.py
	$(MAKE) pages

test-slow: $(STAMP) fast-path
	$(BIN)/python -m pytest -q -m slow

bench: $(STAMP)
	$(BIN)/python -m pytest benchmarks/ --benchmark-only -q

# ruff: lint, and the formatting check (`make format` applies it)
lint: $(DEV_STAMP)
	$(BIN)/ruff check torchpref tests benchmarks docs/conf.py
	$(BIN)/ruff format --check torchpref tests benchmarks docs/conf.py

format: $(DEV_STAMP)
	$(BIN)/ruff format torchpref tests benchmarks docs/conf.py

# mypy over the package (configuration in pyproject.toml)
types: $(DEV_STAMP)
	$(BIN)/mypy

# the site, warnings as errors; the notebooks are executed (TORCHPREF_DOCS_EXECUTE=off skips that)
docs: $(DOCS_STAMP)
	rm -rf docs/_build/html docs/_generated
	$(BIN)/sphinx-build -W --keep-going -q -b html docs docs/_build/html

# sdist + wheel, twine check, then the wheel in fresh venvs: without the plot extra the demo says
# so in one line; with it, it runs
wheel: $(DEV_STAMP)
	rm -rf dist
	$(BIN)/python -m build --outdir dist .
	$(BIN)/twine check --strict dist/*

wheel-check: wheel
	PY=$(PY) TORCH="$(TORCH)" .ci/wheel-check dist


# Issue 21: the dependency floors and the Ax / BoFire integrations, each in a venv of its own
# (Ax and BoFire pin their own botorch; neither is installed in .venv).
# `make test-floor`: the oldest supported botorch / gpytorch / linear_operator / numpy / scipy /
# tqdm (requirements-floor.txt) with torch 2.13.0; the model and BoTorch tests.
test-floor:
	$(PY) -m venv .venv-floor
	.venv-floor/bin/pip install --quiet "torch==2.13.0"
	.venv-floor/bin/pip install --quiet -e . pytest scipy -c requirements-floor.txt
	.venv-floor/bin/python -m pytest -q tests/parity/test_pairwise_contract.py tests/models/test_models.py tests/parity/test_botorch_port_model.py tests/parity/test_botorch_port_acquisition.py tests/parity/test_botorch_fit.py tests/inference/test_laplace.py

# `make upstream-tests`: BoFire's own tests, from its sdist (Ax ships its tests in its wheel).
upstream-tests:
	mkdir -p .cache/upstream
	test -f .cache/upstream/bofire-0.5.0/tests/bofire/surrogates/test_pairwise_gp.py || ( \
	  .venv-bofire/bin/pip download --quiet --no-deps --no-binary :all: bofire==0.5.0 -d .cache/upstream && \
	  tar xzf .cache/upstream/bofire-0.5.0.tar.gz -C .cache/upstream bofire-0.5.0/tests )

# `make test-integrations`: torchpref[ax] and torchpref[bofire], each with the library's own tests
# of its preference path run with PreferenceGP (tests/parity/test_upstream_suites.py) and the
# recipes of docs/ax.md (tests/integrations/test_ax_recipes.py). Not in CI: docs/install.md says why.
test-integrations:
	$(PY) -m venv .venv-ax
	.venv-ax/bin/pip install --quiet "torch==2.13.0"
	.venv-ax/bin/pip install --quiet -e ".[ax]" pytest scipy pyfakefs
	.venv-ax/bin/python -m pytest -q -rs tests/integrations/test_ax_integration.py tests/integrations/test_ax_recipes.py tests/parity/test_upstream_suites.py -k "not bofire"
	$(PY) -m venv .venv-bofire
	.venv-bofire/bin/pip install --quiet "torch==2.13.0"
	.venv-bofire/bin/pip install --quiet -e ".[bofire]" pytest scipy
	$(MAKE) upstream-tests
	.venv-bofire/bin/python -m pytest -q -rs tests/integrations/test_bofire_integration.py tests/parity/test_upstream_suites.py -k "not ax_"

clean:
	rm -rf $(VENV) .venv-floor .venv-ax .venv-bofire .cache/upstream dist build docs/_build docs/_generated docs/jupyter_execute

.PHONY: venv demo fast-path test test-slow results-status pages results bench lint format types docs wheel wheel-check clean test-floor upstream-tests test-integrations
