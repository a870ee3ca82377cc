#!/usr/bin/env bash
# Everything a session with a GPU runs, in one go: build the CUDA backend, the backend-parametrised tests on cuda,
# a training smoke test with resume, and the GPU benchmark. Prints one summary and writes the results to
# $GPU_CHECK_OUT (default benchmarks/results/gpu-check): summary.txt, the logs and the benchmark JSON.
#
#   bash scripts/gpu-check.sh [DATA]
#
# DATA: a small scene for the training smoke test (e.g. `splatzoo synth sweater --out DATA --width 256`);
# made here when omitted and open3d is installed, skipped (and reported) otherwise.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${GPU_CHECK_OUT:-benchmarks/results/gpu-check}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-$(nproc)}
PY=${PYTHON:-python3}
declare -A STATUS
step() {  # step NAME COMMAND...: run, log to $OUT/NAME.log, record pass/fail
  local name=$1; shift
  echo "== $name: $*"
  local t0=$SECONDS
  if "$@" >"$OUT/$name.log" 2>&1; then STATUS[$name]="ok ($((SECONDS - t0)) s)"; else STATUS[$name]="FAILED ($((SECONDS - t0)) s, see $OUT/$name.log)"; fi
  tail -n 5 "$OUT/$name.log"
}

step env bash -c "nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; $PY -c 'import torch; print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name())'; nvcc --version | tail -1"
step build $PY -c "from splatzoo.rasterizers import native; native.load('cuda'); native.load('cpu'); print('built')"
step tests $PY -m pytest -q -p no:cacheprovider tests/test_native.py tests/test_reference.py tests/test_antialias.py -k "cuda and not emulated" -rs
DATA=${1:-}
if [ -z "$DATA" ] && $PY -c "import open3d" 2>/dev/null; then
  DATA="$OUT/data-sweater"
  [ -d "$DATA" ] || $PY -m splatzoo.cli synth sweater --out "$DATA" --width 256 --height 256 --views 24 >"$OUT/synth.log" 2>&1
fi
if [ -n "$DATA" ]; then
  rm -rf "$OUT/smoke"
  step train_resume $PY scripts/gpu_smoke.py "$DATA" "$OUT/smoke"
else
  STATUS[train_resume]="not run: no DATA and no open3d to make one"
fi
step bench $PY benchmarks/bench_rasterizer.py --backends cuda --json "$OUT/bench.json"
step bench_gpu $PY benchmarks/bench_rasterizer.py --gpu --backends cuda --antialias off,on --json "$OUT/bench_gpu.json"
# the zoo's members side by side (2dgs, beta, gabor, neural-gabor's 6 waves, textured 4x4), anti-aliased as they train
step bench_kinds $PY benchmarks/bench_rasterizer.py --backends cuda --waves 0,0b,4,6,0t4 --antialias on --json "$OUT/bench_kinds.json"

{
  echo "gpu-check $(date -u +%Y-%m-%dT%H:%MZ) on $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)"
  for k in env build tests train_resume bench bench_gpu bench_kinds; do printf '%-14s %s\n' "$k" "${STATUS[$k]:-not run}"; done
  grep -E "passed|failed" "$OUT/tests.log" | tail -1
  tail -n 1 "$OUT/train_resume.log" 2>/dev/null
} | tee "$OUT/summary.txt"
! grep -q FAILED "$OUT/summary.txt"
