# Two entry points for a fresh machine: `make serve` (the main job) and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: serve test lint train bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -c constraints.txt -e '.[test]'
	touch $(STAMP)

## serve: set up and run the service (API + worker + embedded Redis) on MCAM_HOST:MCAM_PORT (127.0.0.1:8000)
serve: $(STAMP)
	$(BIN)/mcam serve

## test: set up and run lint and the whole test suite
test: $(STAMP)
	@command -v chromium >/dev/null || (apt-get update -qq && apt-get install -y -qq chromium >/dev/null) || echo "chromium not installable: browser test will be skipped"
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n auto --maxprocesses 4 --dist loadfile

lint: $(STAMP)
	$(BIN)/ruff check .

## train: reproduce the shipped learned decoders (resumable; CPU is fine, slow)
train: $(STAMP)
	$(BIN)/mcam train all

bench: $(STAMP)
	$(BIN)/python -m bench.accuracy

clean:
	rm -rf $(VENV) build *.egg-info
