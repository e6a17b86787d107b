# make demo   set up .venv (first time: a few minutes) and simulate a shipped example photo with the shipped checkpoint
# make test   set up .venv and run the default test tier
VENV := .venv
STAMP := $(VENV)/.physgm-installed

.PHONY: setup demo test test-slow lint
setup: $(STAMP)
$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh
	touch $(STAMP)

demo: setup
	$(VENV)/bin/python simulate.py input=examples/jelly_cube.png

test: setup
	$(VENV)/bin/python -m pytest

test-slow: setup
	$(VENV)/bin/python -m pytest -m slow

lint: setup
	$(VENV)/bin/ruff check src tests train.py simulate.py examples scripts
	$(VENV)/bin/ruff format --check src tests train.py simulate.py examples scripts
