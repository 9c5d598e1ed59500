#!/usr/bin/env bash
# Installs everything the project needs on a fresh machine: Mesa's EGL/OpenGL (headless rendering
# with llvmpipe when there is no GPU) and Chromium (the tests open the report in a headless browser)
# from the system packages, then the project and its test tools into the current Python (activate a
# virtualenv first if you want one).
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}

have_egl() { "$PY" - <<'PYEOF'
import ctypes.util, sys
sys.exit(0 if ctypes.util.find_library("EGL") and ctypes.util.find_library("gbm") else 1)
PYEOF
}
missing=()
have_egl || missing+=(libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1)
command -v chromium >/dev/null 2>&1 || missing+=(chromium)
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi
"$PY" -m pip install -q -e ".[test]"
command -v pyenv >/dev/null 2>&1 && pyenv rehash || true
