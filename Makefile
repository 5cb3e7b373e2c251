# Two entry points (see README.md):
#   make run    set up .venv if needed, then run the default pipeline on the embedded scenario
#   make test   set up .venv if needed, then run the test suite
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# torch first, pinned: on these machines the CPU wheel comes from local disk. Installing the
# project first would let pip resolve a plain "torch" to the newest CUDA build (several GB).
TORCH_REQ ?= torch==2.13.0
ARGS ?=

.PHONY: setup run test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet "$(TORCH_REQ)"
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	$(BIN)/python -c "import torch, zenoh, lanelet2, mcap, viser, msgpack, scipy, foxglove; print('setup ok: torch', torch.__version__)"
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/python launch.py $(ARGS)

test: $(STAMP)
	@# the viewer's browser test needs Debian's chromium; install it when missing and we may (root)
	@if [ ! -x /usr/bin/chromium ] && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "make test: installing chromium for the viewer's browser test"; \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
			|| echo "make test: could not install chromium; the browser test will fail"; \
	fi
	$(BIN)/python -m pytest -q -p no:cacheprovider $(ARGS)

bench: $(STAMP)
	for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) runs build *.egg-info
