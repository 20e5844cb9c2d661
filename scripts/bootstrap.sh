#!/usr/bin/env bash
# Set up simart-pipeline on a fresh Debian/Ubuntu machine, then run the demo or the tests.
#   bash scripts/bootstrap.sh demo   # system packages, .venv, the package; then `simart run scenes/demo`
#   bash scripts/bootstrap.sh test   # the same set-up; then the test suite
# Idempotent: every step checks first and does only what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
mode="${1:-demo}"
case "$mode" in demo|test|setup) ;; *) echo "usage: $0 demo|test|setup" >&2; exit 2;; esac

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "need root or sudo to install system packages" >&2; exit 1; }
  SUDO="sudo"
fi

# --- system packages -------------------------------------------------------------------------
# drjit's LLVM backend (Sionna RT on the CPU) needs libLLVM >= 17; LLVM 14/15 abort with
# "Cannot select ... fmaximum". Debian 12 and Ubuntu 24.04 ship libllvm19.
have_pkg() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
need=()
llvm_ok=""
for v in 19 18 17 20; do have_pkg "libllvm$v" && llvm_ok="libllvm$v" && break; done
for p in python3 python3-venv git; do have_pkg "$p" || need+=("$p"); done
# The browser test (tests/test_browser_ui.py) drives Debian's Chromium through Playwright (no
# browser download); Ubuntu's chromium is a snap, which containers lack: set SIMART_CHROMIUM there.
want_chromium=""
if [ "$mode" = test ] && ! have_pkg chromium && [ -z "${SIMART_CHROMIUM:-}" ]; then want_chromium=1; fi
if [ ${#need[@]} -gt 0 ] || [ -z "$llvm_ok" ] || [ -n "$want_chromium" ]; then
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -q
  if [ -n "$want_chromium" ]; then
    if apt-cache show chromium >/dev/null 2>&1; then need+=(chromium)
    else echo "no Debian chromium package here: the browser test will fail; install a Chromium and set SIMART_CHROMIUM" >&2
    fi
  fi
  if [ -z "$llvm_ok" ]; then
    for v in 19 18 17; do
      if apt-cache show "libllvm$v" >/dev/null 2>&1; then need+=("libllvm$v"); break; fi
    done
  fi
  if [ ${#need[@]} -gt 0 ]; then
    $SUDO apt-get install -y -q --no-install-recommends "${need[@]}"
  fi
fi

# --- Python environment ------------------------------------------------------------------------
PY="${PYTHON:-python3}"
"$PY" -c 'import sys; assert sys.version_info >= (3, 10), sys.version' \
  || { echo "Python >= 3.10 is needed (found $("$PY" --version))" >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
# Extras: test (the suite's own readers), cluster (dagster-k8s: tests/test_cluster.py validates the
# Kubernetes deployment against its schemas, docs/cluster.md). The stamp names them, so adding one
# reinstalls.
extras="test,cluster"
stamp=.venv/.simart-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ "$(cat "$stamp")" != "$extras" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[$extras]"
  echo "$extras" > "$stamp"
fi
.venv/bin/simart preflight

case "$mode" in
  demo)
    exec .venv/bin/simart run scenes/demo ;;
  test)
    set +e
    .venv/bin/python -m pytest -q tests
    rc=$?
    # pytest's 5 means no test ran: that is a failure here, never a pass.
    [ "$rc" -eq 5 ] && { echo "no test ran" >&2; exit 1; }
    exit "$rc" ;;
  setup) ;;
esac
