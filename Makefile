# gdwm — `make help` lists targets. Everything runs from .venv, created on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
WORKDIR ?= ./gdwm-work
PYTEST_ARGS ?=

.DEFAULT_GOAL := help
.PHONY: help setup demo test test-all bench lint format clean

help: ## list targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	@# Without CUDA, pin the CPU build first: an unpinned torch pulls a multi-GB CUDA build.
	if ! command -v nvidia-smi >/dev/null 2>&1; then $(PY) -m pip install --quiet torch==2.13.0; fi
	$(PY) -m pip install --quiet -e '.[dev]'
	@# The report's browser test drives the system chromium (no browser download); never fails the setup.
	command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && { apt-get install -y -qq --no-install-recommends chromium || { apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium; }; } || echo "chromium not installed: the browser test will skip"; }
	@# Official BLEU/ROUGE-L/CIDEr tokenize with pycocoevalcap's PTBTokenizer (Java); never fails the setup.
	command -v java >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && { apt-get install -y -qq --no-install-recommends default-jre-headless || { apt-get update -qq && apt-get install -y -qq --no-install-recommends default-jre-headless; }; } || echo "java not installed: text metrics use the fallback tokenizer, labelled approximate"; }
	touch $(STAMP)

setup: $(STAMP) ## create .venv and install gdwm with dev tools

demo: setup ## journal_ablation on synthetic_mini (local Ray): the paper-layout table, HTML report, zoo (./gdwm-work)
	$(VENV)/bin/gdwm sweep sweep=journal_ablation experiment=demo workdir=$(WORKDIR)

# pytest exits 5 when it collected no test: that is a broken suite, not a pass.
define run_pytest
	rc=0; $(PY) -m pytest $(1) $(PYTEST_ARGS) || rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing on purpose"; exit 1; fi; exit $$rc
endef

test: setup ## run the test suite (everything but `slow`) on local Ray with 2 CPUs
	$(call run_pytest,)

test-all: setup ## run every test, `slow` included
	$(call run_pytest,-m "slow or not slow")

bench: setup ## run benchmarks/ and print side-by-side ratios
	$(PY) -m benchmarks

lint: setup ## ruff check + format check
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: setup ## apply ruff fixes and formatting
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

clean: ## remove the workdir and caches (keeps .venv)
	rm -rf $(WORKDIR) .pytest_cache .ruff_cache
