# gdwm — `make help` lists targets. Everything runs from .venv, created on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
WORKDIR ?= ./gdwm-work
PYTEST_ARGS ?=

.DEFAULT_GOAL := help
.PHONY: help setup lock demo test test-all bench lint format clean

help: ## list targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

# Installs come from a lock (locks/, `make lock`): exact versions with sha256 hashes, one lock per platform; the
# venv's stamp names the lock it was made from. LOCK=locks/NAME.txt picks another (e.g. the CPU lock on a GPU box).
LOCK ?= locks/$(shell $(PYTHON) platform/gdwm/environment/lock.py name).txt
LOCKS ?= cpu-linux-x86_64-py311 cuda-linux-x86_64-py311 mlflow-linux-x86_64-py311
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu

$(STAMP): pyproject.toml $(wildcard $(LOCK))
	@test -f $(LOCK) || { echo "make setup: no lock for this machine ($(LOCK) is missing; locks/ has $(notdir $(wildcard locks/*.txt))): run 'make lock LOCKS=$(basename $(notdir $(LOCK)))' where uv reaches PyPI, commit it, then make setup" >&2; exit 2; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@# the lock's pip first (hash-checked too): what installs the rest, with the cache of a recent pip
	awk '/^pip==/{p=1} p&&/^ *#/{exit} p' $(LOCK) > $(VENV)/pip.lock && $(PY) -m pip install --quiet --require-hashes --no-deps -r $(VENV)/pip.lock
	@# torch's CPU build is not on PyPI: take it from PyTorch's index unless pip already finds it (a local wheelhouse).
	extra=""; torch=$$(grep -o '^torch==[^ ;]*+cpu' $(LOCK) || true); \
	if [ -n "$$torch" ] && ! $(PY) -m pip install --quiet --dry-run --no-deps "$$torch" >/dev/null 2>&1; then extra="--extra-index-url $(TORCH_CPU_INDEX)"; fi; \
	$(PY) -m pip install --quiet --require-hashes -r $(LOCK) $$extra
	@# an egg-info an older editable build left in the checkout would shadow the installed metadata (entry points)
	rm -rf *.egg-info
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	$(PY) platform/gdwm/environment/lock.py sync $(LOCK)
	@# The report's browser test drives the system chromium (no browser download); never fails the setup.
	command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && { apt-get install -y -qq --no-install-recommends chromium || { apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium; }; } || echo "chromium not installed: the browser test will skip"; }
	@# Official BLEU/ROUGE-L/CIDEr tokenize with pycocoevalcap's PTBTokenizer (Java); never fails the setup.
	command -v java >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && { apt-get install -y -qq --no-install-recommends default-jre-headless || { apt-get update -qq && apt-get install -y -qq --no-install-recommends default-jre-headless; }; } || echo "java not installed: text metrics use the fallback tokenizer, labelled approximate"; }
	@# A team's store (MLflow on PostgreSQL) in the tests: they start PostgreSQL as the unprivileged user the package
	@# creates; never fails the setup.
	command -v initdb >/dev/null || ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && { apt-get install -y -qq --no-install-recommends postgresql || { apt-get update -qq && apt-get install -y -qq --no-install-recommends postgresql; }; } || echo "postgresql not installed: the team-store tests will skip"; }
	echo "$(abspath $(LOCK))" > $(STAMP)

setup: $(STAMP) ## create .venv and install gdwm with dev tools, exactly as locks/ says (pip --require-hashes)

lock: ## refresh locks/ from pyproject.toml and locks/*.in (uv pip compile; LOCKS=NAME... for some)
	@# needs no lock for this machine: a machine without one makes it here (uv resolves for any platform)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -c 'import uv' 2>/dev/null || $(PY) -m pip install --quiet uv
	$(PY) platform/gdwm/environment/lock.py compile $(LOCKS)

demo: setup ## journal_ablation on synthetic_mini (local Ray): the paper-layout table, HTML report, zoo (./gdwm-work)
	$(VENV)/bin/gdwm sweep sweep=journal_ablation experiment=demo workdir=$(WORKDIR)

# pytest exits 5 when it collected no test: that is a broken suite, not a pass.
define run_pytest
	rc=0; $(PY) -m pytest $(1) $(PYTEST_ARGS) || rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing on purpose"; exit 1; fi; exit $$rc
endef

# Every test, on both cores of the 2-core box the suite is sized for: pytest-xdist workers take whole files (and files
# sharing a session fixture together), the longest first (tests/conftest.py). TEST_WORKERS=1 runs them one by one.
TEST_WORKERS ?= 2
XDIST = $(if $(filter-out 0 1,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder,-p no:xdist)

test: setup ## run every test (the long end-to-end ones too) on local Ray, 2 pytest workers
	$(call run_pytest,$(XDIST))

test-all: test ## the same as make test (there is no other tier)

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
