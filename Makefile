# Two commands for users: `make demo` and `make test`. Both create .venv (python3 3.10-3.12) when missing and
# install everything pinned for CPU (constraints-cpu.txt), then the torchvision shim (willags_ns/tvshim.py).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.willags-installed
DEMO_DIR ?= demo_outputs

.PHONY: demo test install lint bench clean-venv

$(STAMP): pyproject.toml constraints-cpu.txt Makefile
	@$(PY) -c 'import sys; v=sys.version_info[:2]; sys.exit(0 if (3,10)<=v<=(3,12) else "willags needs python 3.10-3.12, got %d.%d (set PY=python3.X)" % v)'
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -c constraints-cpu.txt torch==2.13.0 torchvision==0.28.0
	$(BIN)/python -m pip install -c constraints-cpu.txt -e '.[dev]'
	$(BIN)/python -m willags_ns.tvshim install
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m willags_ns.scripts.demo --output-dir $(DEMO_DIR)

test: $(STAMP)
	$(BIN)/python -m pytest -q -ra

lint: $(STAMP)
	$(BIN)/ruff check willags_ns tests benchmarks
	$(BIN)/ruff format --check willags_ns tests benchmarks

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_rasterize.py

clean-venv:
	rm -rf $(VENV)
