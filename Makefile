# proxpose: `make run` starts the service, `make test` runs the test suite.
# Both create .venv on first use (python3 -m venv + the exact versions of requirements.lock).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv test run lint lock system-deps clean

venv: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -r requirements.lock
	$(BIN)/pip install --quiet --no-deps -e .
	touch $(STAMP)

# Re-resolve the ranges of pyproject.toml (every extra) in a scratch venv and pin what pip chose:
# run after changing a dependency, then `make test` and commit both files.
lock:
	rm -rf .lock-venv
	$(PYTHON) -m venv .lock-venv
	.lock-venv/bin/pip install --quiet --upgrade pip
	.lock-venv/bin/pip install --quiet '.[dev]'
	( echo "# Exact versions of every dependency (all extras), from 'make lock'; install with"; \
	  echo "#   pip install -r requirements.lock && pip install --no-deps -e ."; \
	  .lock-venv/bin/pip freeze --exclude-editable | grep -v '^proxpose' ) > requirements.lock
	rm -rf .lock-venv

# Optional system packages: LLVM >= 16 lets Mitsuba use its fast llvm variant (otherwise it
# falls back to scalar_rgb), Chromium drives the browser tests. Installed only when we are
# root with apt-get; skipped silently elsewhere.
system-deps:
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  missing=""; \
	  ls /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1 || missing="$$missing libllvm19"; \
	  command -v chromium >/dev/null || missing="$$missing chromium"; \
	  if [ -n "$$missing" ]; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null) \
	      || echo "note: could not install$$missing; continuing"; \
	  fi; \
	fi

# Two pytest processes, a test file each at a time (its module fixtures shared as before): the
# service tests mostly wait on subprocesses while the engine tests render, so the suite takes
# ~8.5 min here instead of ~14 (a 2-core VM, 2026-12-07).
test: venv system-deps
	$(BIN)/python -m pytest -n 2 --dist loadfile

run: venv
	$(BIN)/proxpose serve

lint: venv
	$(BIN)/ruff check schemas worker service tests
	$(BIN)/ruff format --check schemas worker service tests
	$(BIN)/mypy schemas service

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
