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

# make bench: a smoke run of the benchmarks, not their figures: quick runs on the embedded data
# (stages/data/taf-bw, with IAMP_TAF_BW unset for them), each a few seconds on 2 cores, stopping at the first
# that fails: dense (6 vehicles, 3 timed frames), codec (6 vehicles, 5 frames), state_estimator (both
# embedded recordings), markov_stage (numpy, 1 and 10 pairs), markov_kernel (hybrid chain, 2 and 3 pairs),
# relations_timing, stage_timing, corridor_coverage (K729), scenario_traffic and hostile's fuzz section
# (200 payloads). The full-size runs (minutes to hours, some need the full data or a GPU): each script's docstring.
BENCH_DATA := stages/data/taf-bw
BENCH_RUNS := \
	"dense.py --vehicles 6 --frames 3 --warmup 1 --segments 1" \
	"codec.py --per-schema 20 --vehicles 6 --frames 5 --repeat 1" \
	"state_estimator.py --data $(BENCH_DATA)" \
	"markov_stage.py --pairs 1,10 --repeats 2 --backends numpy" \
	"markov_kernel.py --hybrid-only --pairs 2,3 --repeats 1" \
	"relations_timing.py --data $(BENCH_DATA) --repeat 5" \
	"stage_timing.py --data $(BENCH_DATA) --repeats 3" \
	"corridor_coverage.py --data $(BENCH_DATA) --recording k729_2022-03-16" \
	"scenario_traffic.py" \
	"hostile.py --section fuzz --n 200"

bench: $(STAMP)
	@for b in $(BENCH_RUNS); do echo "== bench/$$b"; env -u IAMP_TAF_BW $(BIN)/python bench/$$b || exit 1; done

clean:  # runs/ holds the user's recordings: left alone (remove it by hand)
	rm -rf $(VENV) build *.egg-info
