# Two commands do everything on a fresh machine (Python 3.11+, nothing else installed):
#   make demo   - set up .venv and run the main job on the built-in default scene
#   make test   - set up .venv, lint (ruff), build the docs site (mkdocs --strict) and run the test suite
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: demo test test-all bench setup docs lint

# The set-up also compiles the native libraries (the shading kernels; the map fits' sparse
# Cholesky factorisation), which are otherwise compiled on first use and cached: the first render
# and the first map fit then do not wait on the C++ compiler (the factorisation's library took
# 6-7 s on two cores, inside a first 256² map fit). Where no compiler builds them, this says why,
# and the JAX stages and SuperLU serve.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e '.[test]'
	$(VENV)/bin/python -c "import diffshade._native as n, fitting._cholesky as c; n.available(); c.available()"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/diffshade demo

# The docs site (mkdocs.yml) built with --strict: a broken link, anchor, snippet or API reference
# fails the target; the site goes to site/ (ignored by git). Not --quiet: it hides the warnings
# from --strict too, and the build then passes.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/python -m mkdocs build --strict

# ruff: the lint rules and the formatting of pyproject.toml's [tool.ruff]
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test: $(STAMP) lint docs
	$(VENV)/bin/python -m pytest -n 2 -q

# every test, the slow variants too (the default run leaves them out, to keep it short on 2 cores)
test-all: $(STAMP) lint docs
	$(VENV)/bin/python -m pytest -n 2 -q -m ""

# Transparent huge pages for malloc: XLA's large per-call buffers are otherwise page-faulted in
# again on every call (measured: 12-tangent Jacobian at 512^2 80 ms instead of 170 ms).
bench: export GLIBC_TUNABLES = glibc.malloc.hugetlb=1
bench: $(STAMP)
	$(VENV)/bin/python -m pip install --quiet -e '.[bench]'
	$(VENV)/bin/python benchmarks/bench_raster.py
	$(VENV)/bin/python benchmarks/bench_render.py
	$(VENV)/bin/python benchmarks/bench_fit.py
	$(VENV)/bin/python benchmarks/bench_fit_suite.py
	$(VENV)/bin/python benchmarks/bench_deodr.py
	$(VENV)/bin/python benchmarks/bench_lights.py
