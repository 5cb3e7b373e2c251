#!/usr/bin/env bash
# The checks of the CUDA path and of real time on a bigger machine, in one go (docs/performance.md, "Real time on more cores"
# and "On a GPU"): run on a machine with an NVIDIA GPU and this project's dependencies importable.
#
#   bash bench/gpu_checks.sh OUTDIR [DEVICE]      (DEVICE: cuda (default), or cpu to try the script anywhere)
#
# The Python it runs: $PYTHON, else the project's .venv/bin/python where there is one, else python3. With DEVICE cuda
# it stops at once (exit 2) where that Python sees no CUDA device, instead of running its 30 minutes of steps.
#
# Needs $IAMP_TAF_BW (the full TAF-BW data) for the dense recordings; without it the benches use the embedded
# scenario (they say so). Writes one log per check to OUTDIR and dense_cuda.json; prints each log's tail. Each
# check has its own time limit and a failing one does not stop the others. Asserts nothing about times.
set -u
OUT=${1:?usage: bash bench/gpu_checks.sh OUTDIR [DEVICE]}
DEV=${2:-cuda}
HERE=$(cd "$(dirname "$0")/.." && pwd)
if [ -n "${PYTHON:-}" ]; then PY=$PYTHON; elif [ -x "$HERE/.venv/bin/python" ]; then PY=$HERE/.venv/bin/python; else PY=python3; fi
if ! "$PY" -c "import stages, torch" 2>/dev/null; then
    echo "bench/gpu_checks.sh: $PY cannot import the project and torch: run 'make setup', or set PYTHON to the project's Python" >&2
    exit 2
fi
if [ "$DEV" != cpu ] && ! "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    echo "bench/gpu_checks.sh: no CUDA device here (torch.cuda.is_available() is false): nothing to check; DEVICE cpu tries the script anyway" >&2
    exit 2
fi
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
T0=$(date +%s)
step() {  # step NAME LIMIT_S TAIL_LINES COMMAND...
    local name=$1 lim=$2 tail_n=$3; shift 3
    echo "=== $name (limit ${lim}s) at +$(( $(date +%s) - T0 ))s"
    timeout "$lim" "$@" > "$OUT/$name.log" 2>&1
    echo "rc=$?"
    tail -n "$tail_n" "$OUT/$name.log"
}
nvidia-smi -L 2>&1 | head -2
echo "cpu cores: $(nproc)"
"$PY" -c "import torch; print('torch', torch.__version__, 'cuda available:', torch.cuda.is_available())"
# the CUDA tests (skipped without a GPU): the torch chain against numpy, the hybrid chain on real frames
step pytest_cuda 300 8 "$PY" -m pytest -q -p no:cacheprovider tests/stages/test_markov_torch_hybrid.py \
    tests/stages/test_markov_transitions.py tests/stages/test_markov_cuda_chain.py -k "cuda or torch" -W ignore
# the hybrid chain alone on synthetic pairs (no map, data or bus): numpy kernels against torch on CPU and on CUDA, and
# the cuda backend's one kernel
step kernel_hybrid 200 8 "$PY" bench/markov_kernel.py --hybrid-only --pairs 1,10,50,200 --repeats 5
step dense_cuda 300 16 "$PY" bench/dense.py --vehicles 6,18,72 --frames 16 --warmup 4 --modes hybrid \
    --backend torch --device "$DEV" --json "$OUT/dense_cuda.json"
# the cuda backend: the hybrid chain's whole run as one numba.cuda kernel per frame (stages/lib/markov/cuda_chain.py)
step dense_cudachain 300 16 "$PY" bench/dense.py --vehicles 6,18,72 --frames 16 --warmup 4 --modes hybrid \
    --backend cuda --device "$DEV" --json "$OUT/dense_cudachain.json"
step phases_cudachain 200 14 "$PY" bench/frame_phases.py --vehicles 18 --frames 12 --warmup 3 --segments 1 \
    --backend cuda --device "$DEV" --function stages.lib.markov.cuda_chain:speed_priority_run
step phases_cuda 200 34 "$PY" bench/frame_phases.py --vehicles 18 --frames 12 --warmup 3 --segments 1 \
    --backend torch --device "$DEV" --function stages.lib.markov.propagate:_TorchBackend.transition \
    --function stages.lib.markov.propagate:_TorchBackend.support \
    --function stages.markov_prediction.chain:_PriorityBackend._torch_priority
OMP_NUM_THREADS=1 step dense_cpu 300 16 "$PY" bench/dense.py --vehicles 18,72 --frames 16 --warmup 4 --modes hybrid
# at real time, 18 vehicles, 40 s each: unsharded, in two shards, unsharded with the chain on four threads, in four
# shards (the first run on a fresh machine also compiles every stage's kernels: give it time)
step e2e_hybrid 240 22 "$PY" bench/e2e_latency.py --vehicles 18 --duration-s 40 --no-trace
step e2e_cudachain 180 22 "$PY" bench/e2e_latency.py --vehicles 18 --duration-s 40 --no-trace \
    --set markov_prediction.backend=cuda
step e2e_sharded 180 22 "$PY" bench/e2e_latency.py --vehicles 18 --duration-s 40 --pipeline sharded \
    --expect grid_fusion/motion_grid --no-trace
step e2e_threads4 180 22 "$PY" bench/e2e_latency.py --vehicles 18 --duration-s 40 --no-trace \
    --set markov_prediction.kernel_threads=4
step e2e_sharded4 180 26 "$PY" bench/e2e_latency.py --vehicles 18 --duration-s 40 --pipeline sharded4 \
    --expect grid_fusion/motion_grid --no-trace
echo "done at +$(( $(date +%s) - T0 ))s"
