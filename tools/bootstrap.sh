#!/usr/bin/env bash
# Set up placerec on a fresh Debian machine and run one job.
#   bash tools/bootstrap.sh demo   # the main job: configs/demo.yaml on the built-in simulator
#   bash tools/bootstrap.sh test   # the test suite
# It creates ./.venv (Python >= 3.10, 3.11 preferred), installs placerec with the extras the job needs and the
# system library open3d needs (libusb-1.0-0: installed with apt-get when run as root, else the command is printed);
# the test job also installs the viewer and browser extras and Debian's chromium (the report's browser tests).
# Re-running is cheap: the install is skipped while pyproject.toml is unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."
job="${1:-}"; shift || true
case "$job" in demo|test) ;; *) echo "usage: bash tools/bootstrap.sh demo|test [extra args]" >&2; exit 2 ;; esac

# 1. the system library open3d loads
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[bootstrap] installing libusb-1.0-0 (needed by open3d)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null
  else
    echo "[bootstrap] open3d needs libusb-1.0-0; run: sudo apt-get install -y libusb-1.0-0" >&2
    exit 1
  fi
fi

# the tests open reports in a real browser: Debian's chromium, driven by playwright (whose own browser download
# needs a network placerec does not assume)
if [ "$job" = test ] && ! command -v chromium >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[bootstrap] installing chromium (the report's browser tests)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null
  else
    echo "[bootstrap] the browser tests need chromium; run: sudo apt-get install -y chromium (they are skipped without it)" >&2
  fi
fi

# 2. a local venv
PY=""
for cand in python3.11 python3.12 python3.10 python3; do
  if command -v "$cand" >/dev/null && "$cand" -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then PY="$cand"; break; fi
done
[ -n "$PY" ] || { echo "[bootstrap] need Python >= 3.10 (apt-get install python3 python3-venv)" >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  echo "[bootstrap] creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi

# 3. packages (skipped when pyproject.toml is unchanged since the last successful install)
extras="dev,ouster,ros,dask,slam,superpoint"
# the tests read Rerun recordings back, open reports in a browser and run SuperPoint's onnxruntime backend; the
# demo needs none of them (the viewer is a 170 MB wheel)
if [ "$job" = test ]; then extras="$extras,viewer,browser,onnxruntime"; fi
stamp=".venv/.placerec-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1) $extras"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[bootstrap] installing placerec[$extras] into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[$extras]"
  # the peers: map-closures pins an old typer/click that ouster-sdk's pins exclude, so they are installed without
  # their dependencies (their Python API needs only numpy and pydantic, which placerec already has)
  .venv/bin/python -m pip install -q --no-deps "map-closures>=2.2" "pyhbst>=0.2.0"
  echo "$want" > "$stamp"
fi
.venv/bin/placerec --version

# 4. the job
if [ "$job" = test ]; then
  set +e
  .venv/bin/python -m pytest "$@"
  rc=$?
  set -e
  if [ "$rc" = 5 ]; then echo "[bootstrap] pytest collected no tests" >&2; exit 1; fi
  exit "$rc"
else
  .venv/bin/placerec run configs/demo.yaml "$@"
fi
