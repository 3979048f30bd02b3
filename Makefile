# Two commands for users: `make demo` and `make test`. Both create .venv (python3 3.10-3.12) when missing and
# install everything pinned for CPU (constraints-cpu.txt), then the torchvision shim (willags_ns/engine/tvshim.py).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.willags-installed
DEMO_DIR ?= demo_outputs

.PHONY: demo test test-timing install sysdeps lint bench clean-venv

# open3d (imported by `ns-export` and nerfstudio's .ply loading) needs Debian's libusb-1.0-0; the viewer's browser
# test (tests/test_viewer_browser.py) needs Debian's chromium (it speaks the DevTools protocol itself, so no
# chromium-driver / selenium). Checked on every run (cheap); installed with apt when missing and we may (root);
# otherwise the command to run is printed.
sysdeps:
	@ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 (needed by open3d: ns-export, .ply seed points)"; \
	    (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || (apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null)) \
	      || echo "warning: could not install libusb-1.0-0; ns-export will fail (sudo apt-get install libusb-1.0-0)"; \
	  else echo "warning: libusb-1.0-0 missing; ns-export needs it: sudo apt-get install libusb-1.0-0"; fi; }
	@command -v chromium >/dev/null || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing chromium (the viewer panel's browser test drives it headless)"; \
	    (apt-get install -y -q chromium >/dev/null 2>&1 || (apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null)) \
	      || echo "warning: could not install chromium; the browser test will skip (sudo apt-get install chromium)"; \
	  else echo "note: chromium missing; the viewer's browser test skips (sudo apt-get install chromium)"; fi; }

$(STAMP): pyproject.toml constraints-cpu.txt Makefile
	@$(PY) -c 'import sys; v=sys.version_info[:2]; sys.exit(0 if (3,10)<=v<=(3,12) else "willags needs python 3.10-3.12, got %d.%d (set PY=python3.X)" % v)'
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -c constraints-cpu.txt torch==2.13.0 torchvision==0.28.0
	$(BIN)/python -m pip install -c constraints-cpu.txt -e '.[dev]'
	$(BIN)/python -m willags_ns.engine.tvshim install
	@touch $(STAMP)

install: $(STAMP) sysdeps

demo: $(STAMP) sysdeps
	$(BIN)/python -m willags_ns.scripts.demo --output-dir $(DEMO_DIR)

test: $(STAMP) sysdeps
	$(BIN)/python -m pytest -q -ra

# The tests that race another process or a clock (marker `timing`), RUNS times in a row; BUSY=N keeps N other
# processes spinning on the cores meanwhile (a loaded machine). Stops at the first failing run.
RUNS ?= 5
BUSY ?= 0
test-timing: $(STAMP) sysdeps
	@pids=""; for i in $$(seq 1 $(BUSY)); do (while :; do :; done) & pids="$$pids $$!"; done; \
	trap 'kill $$pids 2>/dev/null' EXIT; \
	for i in $$(seq 1 $(RUNS)); do \
	  echo "timing tests, run $$i of $(RUNS) ($(BUSY) busy processes)"; \
	  $(BIN)/python -m pytest -q -m timing -p no:cacheprovider || { echo "run $$i of $(RUNS) failed"; exit 1; }; \
	done; echo "timing tests: $(RUNS) of $(RUNS) runs passed ($(BUSY) busy processes)"

lint: $(STAMP)
	$(BIN)/ruff check willags_ns tests benchmarks
	$(BIN)/ruff format --check willags_ns tests benchmarks

# the speed suite on this machine's GPU (python -m benchmarks speed --help); BENCH_ARGS=--quick: a CPU smoke test
bench: $(STAMP)
	$(BIN)/python -m benchmarks speed $(BENCH_ARGS)

clean-venv:
	rm -rf $(VENV)
