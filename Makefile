# detcal: `make run` sets up and serves; `make test` sets up and runs the test suite.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

BENCH_VENV ?= .bench-venv
BENCH_STAMP := $(BENCH_VENV)/.installed-stamp

.PHONY: install browser postgres run test lint bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[all,dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(VENV)/bin/detcal serve --bootstrap

lint: install
	$(PY) -m ruff check .

# The dashboard test drives Debian's headless Chromium; install it once if it is missing.
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  echo "installing Debian chromium for the dashboard test"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }

# The store tests also run on a throwaway Postgres cluster (tests/app/pg.py); install Debian's
# server once if it is missing. Its binaries live in /usr/lib/postgresql/<ver>/bin, off PATH.
postgres:
	@command -v pg_ctl >/dev/null 2>&1 || ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1 || { \
	  echo "installing Debian postgresql for the store tests"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null; }

test: install browser postgres
	$(PY) -m ruff check .
	$(PY) -m pytest -q

# Benchmarks compare against reference implementations (netcal, nuscenes-devkit) that are
# installed only into their own environment, never into .venv.
$(BENCH_STAMP): pyproject.toml constraints.txt bench/requirements-reference.txt bench/requirements-reference-devkit.txt
	$(PYTHON) -m venv $(BENCH_VENV)
	$(BENCH_VENV)/bin/pip install --quiet --upgrade pip
	$(BENCH_VENV)/bin/pip install --quiet -c constraints.txt -e '.[all,dev]' -r bench/requirements-reference.txt
	$(BENCH_VENV)/bin/pip install --quiet -c constraints.txt --no-deps nuscenes-devkit==1.2.0
	$(BENCH_VENV)/bin/pip install --quiet -c constraints.txt -r bench/requirements-reference-devkit.txt
	touch $(BENCH_STAMP)

bench: $(BENCH_STAMP)
	$(BENCH_VENV)/bin/python -m bench

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
