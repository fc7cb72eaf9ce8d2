# Two commands on a fresh machine (Python >= 3.11):
#   make demo   install everything, render 4,000 frames, look at them, train the CPU preset, evaluate
#   make test   install everything, lint (ruff, mypy) and run the test suite (what CI runs, with make docs)
# tests/test_readme.py runs the demo recipe at small size (DEMO_N, DEMO_TRAIN) so it cannot drift.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO   ?= data/demo
RUN    ?= runs/demo
WORKERS ?= $(shell nproc 2>/dev/null || echo 2)
DEMO_N ?= 4000
DEMO_TRAIN ?=

.PHONY: install demo test test-all lint format docs bench clean-demo

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -e ".[dev]"
	$(BIN)/python -c "import timm, torch, torchvision, h5py, cv2, astropy; print('imports ok: torch', torch.__version__, 'timm', timm.__version__)"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/skygen render --n $(DEMO_N) --workers $(WORKERS) --out $(DEMO)
	$(BIN)/skygen inspect $(DEMO)
	$(BIN)/skygen preview $(DEMO) --out $(DEMO)/preview.png
	$(BIN)/skygen validate $(DEMO)
	$(BIN)/fusion train --data $(DEMO) --out $(RUN) --config configs/cpu.yaml --force $(DEMO_TRAIN)
	$(BIN)/fusion evaluate --checkpoint $(RUN)/best.pt --data $(DEMO) --split test --out $(RUN)/eval-test
	@echo "dataset: $(DEMO) (preview: $(DEMO)/preview.png)  run: $(RUN)  report: $(RUN)/eval-test/eval-test.md"

test: lint
	$(BIN)/python -m pytest -q -m "not gpu"

# ruff (lint + formatting) over the code, mypy over the public API (pyproject.toml's [tool.ruff], [tool.mypy])
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

format: $(STAMP)
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

# the documentation site (mkdocs.yml), warnings as errors; HTML in site/
DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): $(STAMP) pyproject.toml
	$(BIN)/python -m pip install -e ".[docs]"
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

test-all: $(STAMP)
	RUN_SLOW=1 $(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/render_bench.py

clean-demo:
	rm -rf $(DEMO) $(RUN)
