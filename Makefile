# Two commands do all setup: `make demo` and `make test`. Both create .venv when missing and
# (re)install the project into it whenever pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test typecheck bench docs docs-serve clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test,torch]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m dqskin.cli demo

test: $(STAMP)
	$(PY) -m ruff check .
	$(MAKE) --no-print-directory typecheck
	$(PY) -m pytest -q

# mypy sees the top-level kernels/ folder as dqskin.kernels through this link (pyproject's
# [tool.mypy] mypy_path); the editable install's import hook is invisible to it.
typecheck: $(STAMP)
	mkdir -p build/typecheck/dqskin
	ln -sfn ../../../kernels build/typecheck/dqskin/kernels
	$(PY) -m mypy

bench: $(STAMP)
	$(PY) tools/bench.py
	$(PY) tools/bench_compare.py

docs: $(STAMP)
	$(PY) -m mkdocs build --strict

docs-serve: $(STAMP)
	$(PY) -m mkdocs serve

clean:
	rm -rf $(VENV) build site *.egg-info
