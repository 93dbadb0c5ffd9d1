# flowmod: `make book` runs the whole study and renders the book; `make test` checks it.
# Every target sets up what it needs first (the venv, vendored MathJax), so both work as the
# very first command on a fresh clone.

SHELL      := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

PYTHON     ?= python3
VENV       ?= .venv
PY         := $(VENV)/bin/python
PROFILE    ?= demo
DATAROOT   ?=
SET        ?=
EXECUTED   ?= build/executed
HTML       ?= build/html
MATHJAX    := build/vendor/node_modules/mathjax/es5/tex-chtml.js
STAMP      := $(VENV)/.flowmod-env-stamp
PYTEST_ARGS ?=
TEST_WORKERS ?= 2
GC         ?=
LAB_PORT   ?= 8888
LAB_KERNELS ?= $(VENV)

RUN_SET    := $(if $(DATAROOT),--set dataroot=$(DATAROOT)) $(foreach s,$(SET),--set $(s))

.PHONY: help env data run status gc book extensions selfflow test bench lint clean browser weights lab mutation flownet flownet-finetune replicate

help:  ## list the targets
	@echo "flowmod: optical-flow motion detection, reproduced"
	@echo
	@grep -E '^[a-z]+:.*## ' $(MAKEFILE_LIST) | sed -E 's/:.*## /\t/' | expand -t 12
	@echo
	@echo "variables: PROFILE=$(PROFILE) (smoke|classroom|demo|paper or a YAML path), DATAROOT=, SET='key=value ...', VENV=$(VENV)"

env: $(STAMP) $(MATHJAX)  ## create the venv (pinned requirements, editable flowmod) and vendor MathJax

# uv installs the pinned requirements (make env about 45 s on a fresh clone where pip took
# about 140 s), told pip's configured find-links (local wheels), and compiles their bytecode
# as pip does: where PYTHONDONTWRITEBYTECODE is set, a venv without .pyc files compiles every
# module at every import (make test 25-70 % slower). Where uv cannot, pip installs them.
UV_FLAGS = $(foreach f,$(shell $(PYTHON) -m pip config get global.find-links 2>/dev/null),--find-links $(f))

$(STAMP): environment/requirements.txt pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip uv
	$(VENV)/bin/uv pip install --quiet --native-tls --compile-bytecode --python $(PY) $(UV_FLAGS) \
	    -r environment/requirements.txt \
	  || { echo "uv could not install the requirements: pip installs them"; \
	       $(PY) -m pip install --quiet -r environment/requirements.txt; }
	$(PY) -m pip install --quiet --no-deps -e .
	$(PY) -m pip check
	@touch $@

$(MATHJAX):
	@command -v npm >/dev/null || { echo "npm is needed once to vendor MathJax (apt-get install npm)"; exit 1; }
	npm install --silent --no-audit --no-fund --prefix build/vendor mathjax@3.2.2
	@test -f $@

data: env  ## build the synthetic world of PROFILE (demo: data/demo/worlds/<id>)
	$(PY) -m flowmod.world --profile $(PROFILE) $(RUN_SET)

run: env  ## execute notebooks/NN_*.ipynb in order with params/$(PROFILE).yaml into build/executed
	$(PY) -m flowmod.runner --profile $(PROFILE) --out $(EXECUTED) $(RUN_SET)

status: env  ## per stage of PROFILE (+SET): up to date or stale, and why; runs nothing
	$(PY) -m flowmod.runner --profile $(PROFILE) --status $(RUN_SET)

gc: env  ## remove per-pair cache files no node of PROFILE (+SET) reads (other options, crop geometries; GC=--worlds: other generated worlds too)
	$(PY) -m flowmod.runner --profile $(PROFILE) --gc $(GC) $(RUN_SET)

book: run browser  ## run, then render the book into build/html (and check it in Chromium)
	$(PY) -m flowmod.report.book --executed $(EXECUTED) --out $(HTML)
	$(PY) -m flowmod.report.browser $(HTML) --screenshot build/book-screenshot.png --screenshots build/screenshots

extensions: RUN_SET += --set extension_build=true --set "extension_inputs=[residual,residual-deployed,flow+static,images,images+flow]" --set "extension_methods=[gt,dis]" --set "wide_methods=[gt,dis]"
extensions: book  ## make book with chapters 10 and 11's full matrix (every input on gt and dis; demo: 18 more models)

selfflow: RUN_SET += --set selfflow_build=true
selfflow: book  ## make book with chapter 12 training FastFlowNet in the book too (photometric and supervised; resumable)

test: env browser lint  ## lint, unit tests, notebooks on the smoke profile, the book build (TEST_WORKERS=2)
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=20 $(PYTEST_ARGS)

browser:  ## install headless Chromium for the browser check of the book (apt-get; root or sudo)
	@if [ -n "$${FLOWMOD_CHROMIUM:-}" ] || command -v chromium >/dev/null \
	    || command -v chromium-browser >/dev/null; then \
	  echo "chromium: $${FLOWMOD_CHROMIUM:-$$(command -v chromium || command -v chromium-browser)}"; \
	elif ! command -v apt-get >/dev/null; then \
	  echo "Chromium is missing and there is no apt-get: install Chromium and/or set FLOWMOD_CHROMIUM"; \
	  if [ -n "$(filter-out 0 false no,$(CI))" ]; then exit 1; fi; \
	elif [ "$$(id -u)" = 0 ]; then \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; \
	elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then \
	  sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; \
	else \
	  echo "Chromium is missing and cannot be installed here (not root, no password-less sudo):"; \
	  echo "  run \`sudo apt-get install -y chromium\`, or set FLOWMOD_CHROMIUM=/path/to/chromium;"; \
	  echo "  until then tests/test_browser.py is skipped (under CI=true it fails)"; \
	  if [ -n "$(filter-out 0 false no,$(CI))" ]; then exit 1; fi; \
	fi

weights: env  ## download RAFT's checkpoints (needs internet; never run by other targets)
	$(PY) -m flowmod.weights

lab: env  ## JupyterLab on notebooks/ with the venv's kernel: run a chapter cell by cell (LAB_PORT=8888)
	@$(PY) -m ipykernel install --prefix $(LAB_KERNELS) --name python3 --display-name 'Python 3 (flowmod)' >/dev/null  # argv: this venv's python
	JUPYTER_PATH=$(abspath $(LAB_KERNELS))/share/jupyter $(VENV)/bin/jupyter lab --notebook-dir=notebooks \
	  --no-browser --ip=127.0.0.1 --port=$(LAB_PORT) $(if $(filter 0,$(shell id -u)),--allow-root)

mutation: env  ## mutation testing of the modules whose numbers reach the book, one at a time (mutmut; PART=k runs part k, each within 45 min, PART=plan lists them; MODULES="flowmod.train ..." runs those; SAMPLE=n a seeded draw of n mutants of each, scored with its interval, SAMPLE_SEED=s another draw; not part of make test)
	$(PY) benchmarks/mutation.py $(if $(PART),--part $(PART)) $(if $(SAMPLE),--sample $(SAMPLE)) $(if $(SAMPLE_SEED),--seed $(SAMPLE_SEED)) $(MODULES)

replicate: env  ## the whole study again on a world drawn with another master seed (REPLICATE_SEED=), its effects beside the book's in benchmarks/replication.json, which chapter 14 shows (demo: about the cold book's time again; resumable)
	$(PY) -m flowmod.replicate --profile $(PROFILE) $(if $(REPLICATE_SEED),--seed $(REPLICATE_SEED)) $(RUN_SET)

flownet: env  ## train the shipped FastFlowNet weights from scratch (weights/fastflownet_synth; hours on 2 CPU cores, resumable; FROM_SHIPPED=1 trains only the phases the published file lacks)
	$(PY) -m flowmod.flow.pretrain $(if $(STEPS),--steps $(STEPS)) $(if $(FROM_SHIPPED),--from-shipped)

flownet-finetune: env  ## chapter 13's answer used once: the shipped FastFlowNet fine-tuned on each far box's mean-flow error, against a control without the term, scored on the pretraining world's validation pairs (about 45 min on 2 CPU cores, resumable; the record benchmarks/finetune.json, which chapter 13 shows)
	$(PY) -m flowmod.flow.finetune

bench: env  ## throughput and memory figures into benchmarks/results/ (never asserted)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b; done

lint: env  ## ruff, and import-linter: no import cycle, every import points down the layers
	$(PY) -m ruff check src tests benchmarks notebooks
	$(VENV)/bin/lint-imports --no-cache

clean:  ## remove generated outputs (keeps the venv and data/; `make clean-all` removes them too)
	rm -rf build/executed build/html build/.html.work \
	  build/book-src build/book-extra build/book-media \
	  build/screenshots build/book-screenshot.png runs .pytest_cache .ruff_cache

.PHONY: clean-all
clean-all: clean
	rm -rf build data $(VENV)
