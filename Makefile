# make test   set up .venv (first time: a few minutes) and run the default test tier
VENV := .venv
STAMP := $(VENV)/.physgm-installed

.PHONY: setup test test-slow lint
setup: $(STAMP)
$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh
	touch $(STAMP)

test: setup
	$(VENV)/bin/python -m pytest

test-slow: setup
	$(VENV)/bin/python -m pytest -m slow

lint: setup
	$(VENV)/bin/ruff check src tests train.py simulate.py
