#!/usr/bin/env bash
# One entry point for newcomers and CI.
#   ./run.sh demo [sp-demo options]   set everything up, then train baseline vs SP on a bundled scene
#   ./run.sh test [pytest options]    set everything up, then run the test suite
#   ./run.sh setup                    only create / update the virtual environment
# The virtual environment lives in $SP_VENV (default: .venv inside this checkout, one per checkout,
# so a second clone or CI never re-points another checkout's environment); it is created once and
# reused: later runs reinstall only when pyproject.toml or the checkout path changes.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="${SP_VENV:-$here/.venv}"
python="${PYTHON:-python3}"

case "$(uname -m)" in
  # torchvision from PyPI needs the matching torch; on x86_64 that is the CUDA build (runs on CPU).
  x86_64) torch_spec="${SP_TORCH_SPEC:-torch==2.14.1 torchvision==0.29.1}" ;;
  *)      torch_spec="${SP_TORCH_SPEC:-torch==2.9.1 torchvision==0.24.1}" ;;
esac

system_libs() {
  # open3d (nerfstudio's `ns-export pointcloud`) loads libusb-1.0, which minimal Debian images lack.
  # (grep without -q: with pipefail, -q's early exit fails ldconfig with SIGPIPE)
  if ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then return; fi
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[sp-plugins] installing libusb-1.0-0 (needed by open3d for ns-export pointcloud)"
    { apt-get install -y -qq libusb-1.0-0 || { apt-get update -qq && apt-get install -y -qq libusb-1.0-0; }; } >/dev/null 2>&1 \
      || echo "[sp-plugins] warning: could not install libusb-1.0-0; ns-export pointcloud will not work" >&2
  else
    echo "[sp-plugins] note: libusb-1.0 is missing; ns-export pointcloud (open3d) needs it: sudo apt-get install libusb-1.0-0" >&2
  fi
}

setup() {
  system_libs
  if [ ! -x "$venv/bin/python" ]; then
    echo "[sp-plugins] creating a virtual environment in $venv"
    mkdir -p "$(dirname "$venv")"
    "$python" -m venv "$venv"
  fi
  local stamp="$venv/.sp-plugins-stamp"
  local want
  want="$(cat "$here/pyproject.toml" | sha256sum | cut -d' ' -f1) $torch_spec $here"
  if [ "$(cat "$stamp" 2>/dev/null || true)" != "$want" ]; then
    echo "[sp-plugins] installing (first time: about 5-6 minutes and 8 GB, mostly torch and nerfstudio)"
    "$venv/bin/python" -m pip install -q --upgrade pip
    # shellcheck disable=SC2086
    "$venv/bin/python" -m pip install -q $torch_spec
    "$venv/bin/python" -m pip install -q -e "$here[dev]"
    echo "$want" > "$stamp"
  fi
}

cmd="${1:-demo}"
[ $# -gt 0 ] && shift
case "$cmd" in
  setup) setup ;;
  demo)  setup; exec "$venv/bin/sp-demo" "$@" ;;
  test)  setup; cd "$here"; exec "$venv/bin/python" -m pytest -q "$@" ;;
  *) echo "usage: $0 {demo|test|setup} [options]" >&2; exit 2 ;;
esac
