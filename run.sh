#!/usr/bin/env bash
# One entry point for newcomers and CI.
#   ./run.sh demo [sp-demo options]   set everything up, then train baseline vs SP on a bundled scene
#   ./run.sh test [pytest options]    set everything up, then run the test suite
#   ./run.sh docs                     set everything up, build the docs site (warnings are errors), print index.html's path
#   ./run.sh setup                    only create / update the virtual environments
#   ./run.sh setup-sdfstudio          only create / update the sdfstudio environment (see below)
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

system_browser() {
  # tests/nerfstudio/test_viewer_browser.py opens nerfstudio's web viewer in the system's chromium (driven by
  # Playwright from the dev extra, which never downloads a browser of its own); without it that test is
  # skipped with the reason, and with CI=true it fails. Not for `demo`: about 300 MB that sp-demo never uses.
  if command -v chromium >/dev/null; then return; fi
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[sp-plugins] installing chromium (the browser test opens nerfstudio's viewer in it; about 300 MB)"
    { DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium \
      || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }; } >/dev/null 2>&1 \
      || echo "[sp-plugins] warning: could not install chromium; the browser test will be skipped (with CI=true it fails)" >&2
  else
    echo "[sp-plugins] note: chromium is missing; the browser test is skipped without it: sudo apt-get install chromium" >&2
  fi
}

# torch and its CUDA wheels (about 3 GB) are installed by one environment at a time: where pip keeps its downloads
# (its http cache), the first install downloads them and the second installs from the cache, instead of both
# downloading them at once. The main environment goes first (the main suite is the longer one): `./run.sh test`
# takes the lock before it starts the sdfstudio set-up beside it (hold_torch_lock) and lets go once the main
# environment has torch (release_torch_lock). The lock is a file on descriptor 9; without flock, no lock.
torch_lock="${TMPDIR:-/tmp}/sp-plugins-torch-install.lock"
torch_lock_held=0
hold_torch_lock() {
  command -v flock >/dev/null || return 0
  exec 9>"$torch_lock"
  flock 9
  torch_lock_held=1
}
release_torch_lock() {
  if [ "$torch_lock_held" = 1 ]; then flock -u 9; exec 9>&-; torch_lock_held=0; fi
}
install_torch() {
  # shellcheck disable=SC2086
  if [ "$torch_lock_held" = 1 ] || ! command -v flock >/dev/null; then
    "$1" -m pip install -q $torch_spec
  else
    ( flock 9 && "$1" -m pip install -q $torch_spec ) 9>"$torch_lock"
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
    # not --no-compile: where PYTHONDONTWRITEBYTECODE is set (this CI machine), the byte code pip writes is the
    # only byte code there is; without it every process compiled nerfstudio and torch again (a run 2x slower)
    install_torch "$venv/bin/python"
    release_torch_lock
    "$venv/bin/python" -m pip install -q -e "$here[nerfstudio,nerfbaselines,sweeps,dev,docs]"
    echo "$want" > "$stamp"
  fi
}

# sdfstudio (a second host) installs as a package named `nerfstudio`, so it gets its own environment:
# $SP_SDFSTUDIO_VENV (default .venv-sdfstudio inside this checkout), built from $SP_SDFSTUDIO_SRC (a source
# tree or a .tar.gz of one; default ../shared/hosts/sdfstudio-370902a.tar.gz beside the checkout). Without a
# source it says how to get one and skips. The stamp is written only after every step succeeded, so a failed
# build is never taken for a working one (the tests skip the host until the stamp exists).
sdf_venv="${SP_SDFSTUDIO_VENV:-$here/.venv-sdfstudio}"
sdf_src="${SP_SDFSTUDIO_SRC:-$here/../shared/hosts/sdfstudio-370902a.tar.gz}"
sdf_stamp="$sdf_venv/.sp-sdfstudio-stamp"

sdf_get_one="get one: git clone https://github.com/autonomousvision/sdfstudio && SP_SDFSTUDIO_SRC=\$PWD/sdfstudio ./run.sh setup-sdfstudio"

setup_sdfstudio() {
  if [ ! -e "$sdf_src" ]; then
    echo "[sp-plugins] sdfstudio: no source at $sdf_src; no sdfstudio environment (its tests are reported as skipped; with CI=true the run fails)." >&2
    echo "[sp-plugins]   $sdf_get_one" >&2
    return 0
  fi
  local src_id want
  if [ -d "$sdf_src" ]; then
    src_id="$(cd "$sdf_src" && { git rev-parse HEAD 2>/dev/null || find . -name '*.py' -newer pyproject.toml | wc -l; })"
  else
    src_id="$(sha256sum "$sdf_src" | cut -d' ' -f1)"
  fi
  want="$(sha256sum "$here/pyproject.toml" | cut -d' ' -f1) $torch_spec $here $(cd "$(dirname "$sdf_src")" && pwd)/$(basename "$sdf_src") $src_id"
  if [ "$(cat "$sdf_stamp" 2>/dev/null || true)" = "$want" ]; then return 0; fi
  echo "[sp-plugins] sdfstudio: building its environment in $sdf_venv (first time: about 3-5 minutes)"
  rm -f "$sdf_stamp"
  [ -x "$sdf_venv/bin/python" ] || "$python" -m venv "$sdf_venv"
  local log="$sdf_venv/setup.log"
  if ! {
    "$sdf_venv/bin/python" -m pip install -q --upgrade pip &&
    install_torch "$sdf_venv/bin/python" &&
    "$sdf_venv/bin/python" -m pip install -q --no-deps "$sdf_src" &&
    "$sdf_venv/bin/python" -m pip install -q -e "$here[sdfstudio,dev]" &&
    "$sdf_venv/bin/python" -c "import sp_plugins.sdfstudio.detect as h; h.require_sdfstudio()" &&
    # opt-in hook: sdfstudio's own ns-train / ns-eval / ns-extract-mesh see our patches and methods
    "$sdf_venv/bin/python" -m sp_plugins.sdfstudio.hook install
  } >"$log" 2>&1; then
    tail -n 20 "$log" >&2
    echo "[sp-plugins] sdfstudio: building its environment failed (log: $log); it stays unusable until a build succeeds" >&2
    return 1
  fi
  echo "$want" > "$sdf_stamp"
}

# ./run.sh test [pytest options] [paths]: the main suite in $venv and tests/sdfstudio in the sdfstudio
# environment (the main run then leaves them out: SP_SDFSTUDIO_TESTS=separate, see
# tests/sdfstudio/conftest.py). Paths go to the run they belong to; options go to both. The exit
# status is the worse of the two (pytest's 5, "no tests collected", counts only if both had none).
# Without the sdfstudio environment (no source, see setup_sdfstudio) the sdfstudio tests are collected
# by the main run and reported there as skipped, with the reason; in CI (CI=true) that fails the run
# instead: a CI that cannot run a host's tests must not look green.
run_tests() {
  cd "$here"
  local opts=() main_paths=() sdf_paths=() a
  for a in "$@"; do
    if [ "${a#-}" = "$a" ] && [ -e "${a%%::*}" ]; then
      case "$(realpath -m "${a%%::*}")" in
        "$here/tests/sdfstudio"*) sdf_paths+=("$a") ;;
        *) main_paths+=("$a") ;;
      esac
    else
      opts+=("$a")
    fi
  done
  local main_rc=5 sdf_rc=5 run_main=0 run_sdf=0 sdf_log="" sdf_pid=""
  if [ ${#main_paths[@]} -gt 0 ] || [ ${#sdf_paths[@]} -eq 0 ]; then run_main=1; fi
  if [ ${#sdf_paths[@]} -gt 0 ] || [ ${#main_paths[@]} -eq 0 ]; then run_sdf=1; fi
  local sdf_missing="" sdf_beside=0
  if [ "$run_sdf" = 1 ] && [ "$run_main" = 1 ] && { [ -e "$sdf_src" ] || [ -f "$sdf_stamp" ]; }; then
    # built (when needed) and tested in the background, beside the main install and suite (below)
    sdf_beside=1
    export SP_SDFSTUDIO_TESTS=separate
  elif [ "$run_sdf" = 1 ]; then
    setup_sdfstudio
    if [ ! -f "$sdf_stamp" ]; then
      sdf_missing="no sdfstudio environment at $sdf_venv (no source at $sdf_src to build it from; $sdf_get_one)"
      run_sdf=0
      if [ "${CI:-}" = true ]; then
        echo "[sp-plugins] error: CI=true and the sdfstudio tests cannot run: $sdf_missing" >&2
        sdf_rc=1
      else
        # the main run collects them and reports them as skipped, with this reason
        [ ${#sdf_paths[@]} -gt 0 ] && { run_main=1; main_paths+=("${sdf_paths[@]}"); }
        export SP_SDFSTUDIO_MISSING="$sdf_missing"
      fi
    else
      export SP_SDFSTUDIO_TESTS=separate
    fi
  fi
  if [ "$run_sdf" = 1 ]; then
    # the two suites share nothing but the CPU: each runs one torch thread (tests/conftest.py), so on
    # two or more cores they run side by side; the sdfstudio report is printed after the main one.
    # The two environments are also installed side by side: a fresh clone's installs (one core each,
    # mostly unpacking wheels) take about as long as each other, so the main suite starts one install
    # earlier. A failed sdfstudio build fails the run (its log's tail is in the report).
    [ ${#sdf_paths[@]} -gt 0 ] || sdf_paths=(tests/sdfstudio)
    sdf_log="$(mktemp "${TMPDIR:-/tmp}/sp-sdfstudio-tests.XXXXXX")"
    if [ "$sdf_beside" = 1 ]; then
      echo "[sp-plugins] sdfstudio: setting up its environment and running its tests in the background (reported after the main suite)"
      [ "$run_main" = 1 ] && hold_torch_lock  # the main environment installs torch first
      ( exec 9>&-; torch_lock_held=0; setup_sdfstudio && exec "$sdf_venv/bin/python" -m pytest -q ${opts[@]+"${opts[@]}"} "${sdf_paths[@]}" ) >"$sdf_log" 2>&1 &
      sdf_pid=$!
    else
      echo "[sp-plugins] sdfstudio tests, in $sdf_venv"
      sdf_rc=0; "$sdf_venv/bin/python" -m pytest -q ${opts[@]+"${opts[@]}"} "${sdf_paths[@]}" || sdf_rc=$?
      rm -f "$sdf_log"; sdf_log=""
    fi
  fi
  if [ "$run_main" = 1 ]; then
    # a failed install ends this script (set -e): the sdfstudio run beside it ends with it
    [ -n "$sdf_pid" ] && trap "pkill -P $sdf_pid 2>/dev/null; kill $sdf_pid 2>/dev/null || true" EXIT
    setup
    release_torch_lock  # (setup lets go once torch is in; here when it had nothing to install)
    system_browser
    trap - EXIT
    # the main suite is spread over SP_TEST_WORKERS processes (default: the cores, at most 8; 1 = one
    # process), a test file per worker at a time so its module fixtures are built once
    local workers="${SP_TEST_WORKERS:-$(nproc 2>/dev/null || echo 1)}" xdist=()
    [ "$workers" -gt 8 ] && workers=8
    if [ "$workers" -gt 1 ] && "$venv/bin/python" -c "import xdist" 2>/dev/null; then xdist=(-n "$workers" --dist loadfile --no-loadscope-reorder); fi
    # CI=true: the 25 slowest tests listed after the summary (what bounds the suite's wall time)
    local slowest=(); [ "${CI:-}" = true ] && slowest=(--durations=25)
    main_rc=0; "$venv/bin/python" -m pytest -q ${xdist[@]+"${xdist[@]}"} ${slowest[@]+"${slowest[@]}"} ${opts[@]+"${opts[@]}"} ${main_paths[@]+"${main_paths[@]}"} || main_rc=$?
  fi
  if [ -n "$sdf_pid" ]; then
    sdf_rc=0; wait "$sdf_pid" || sdf_rc=$?
    echo "[sp-plugins] sdfstudio tests, in $sdf_venv (ran beside the main suite)"
    cat "$sdf_log"; rm -f "$sdf_log"
  fi
  if [ -n "$sdf_missing" ] && [ "${CI:-}" = true ]; then
    echo "[sp-plugins] error: CI=true and the sdfstudio tests did not run: $sdf_missing" >&2
  fi
  if [ "$main_rc" = 5 ] && [ "$sdf_rc" = 5 ]; then return 5; fi
  [ "$main_rc" = 5 ] && main_rc=0
  [ "$sdf_rc" = 5 ] && sdf_rc=0
  if [ "$main_rc" != 0 ]; then return "$main_rc"; fi
  return "$sdf_rc"
}

cmd="${1:-demo}"
[ $# -gt 0 ] && shift
case "$cmd" in
  setup) setup; system_browser; setup_sdfstudio ;;
  setup-sdfstudio) setup_sdfstudio ;;
  demo)  setup; exec "$venv/bin/sp-demo" "$@" ;;
  test)  run_tests "$@" ;;
  docs)  setup
         # the docs site (Sphinx + furo + MyST; tests/docs/test_docs_site.py builds it the same way in the suite)
         "$venv/bin/python" -m sphinx -W --keep-going -q -b html "$here/docs" "$here/docs/_build/html" "$@"
         echo "[sp-plugins] docs: $here/docs/_build/html/index.html" ;;
  *) echo "usage: $0 {demo|test|docs|setup} [options]" >&2; exit 2 ;;
esac
