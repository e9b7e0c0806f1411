# RibPull: `make run` starts the service (Redis + worker + API), `make test` runs the test suite.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.ribpull-install-stamp
SAMPLE := var/samples/points.ply

.PHONY: help install web run test test-service openapi sample clean-storage migrate

help:
	@echo "make run           install (if needed) and start Redis + worker + API on http://127.0.0.1:$${PORT:-8000}"
	@echo "make test          install (if needed) and run the whole test suite"
	@echo "make test-service  only the service tests (tests/test_service_*.py)"
	@echo "make sample        write the synthetic sample ribcage to $(SAMPLE)"
	@echo "make openapi       regenerate openapi/openapi.json"
	@echo "make web           (re)vendor the web page's three.js from web/package-lock.json (npm ci)"
	@echo "make migrate       upgrade the job database (RIBPULL_DATABASE_URL, else the SQLite file) to this code's schema"

# pip install -e '.[dev]' once per pyproject.toml content (stamp = its sha256), then `ribpull warmup`:
# numba compiles the kernels into its cache (ribpull_core/**/__pycache__) instead of in the first job
install:
	@want=$$(sha256sum pyproject.toml | cut -d' ' -f1); \
	if [ -x "$(PY)" ] && [ -f "$(STAMP)" ] && [ "$$(cat $(STAMP))" = "$$want" ]; then exit 0; fi; \
	if [ ! -x "$(PY)" ]; then echo "creating $(VENV)"; $(PYTHON) -m venv $(VENV) || exit 1; fi; \
	echo "installing ribpull[dev] into $(VENV) (pyproject.toml changed or first run)"; \
	$(PY) -m pip install -e '.[dev]' || exit 1; \
	echo "$$want" > "$(STAMP)"; \
	echo "compiling the CPU kernels once (ribpull warmup), so the first job does not"; \
	$(VENV)/bin/ribpull warmup || echo "warm-up failed: the kernels will compile on first use instead"
	@$(PY) scripts/build_web.py

# the web page's three.js (web/package-lock.json -> app/web/static/vendor/; make install runs it)
web:
	@$(PY) scripts/build_web.py --force

run: install
	@[ -f $(SAMPLE) ] || $(MAKE) --no-print-directory sample || echo "(no sample written; try make sample)"
	@$(PY) scripts/serve.py

test: install
	@$(PY) -m pytest

test-service: install
	@$(PY) -m pytest tests/test_service_*.py

sample: install
	@$(PY) -c "from ribpull_core.phantom import write_phantom; p = write_phantom('var/samples'); print('wrote', p['points'])"

# Alembic revisions in app/migrations/versions/ (app/migrate.py); the API and workers refuse an old schema
migrate: install
	@$(VENV)/bin/ribpull-db upgrade

openapi: install
	@$(PY) scripts/export_openapi.py openapi/openapi.json

clean-storage:
	rm -rf var/storage
