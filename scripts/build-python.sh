#!/usr/bin/env bash
# One command for the Python package `pir2` (bindings/python, pyo3 + maturin):
# builds the wheel from a fresh clone into bindings/python/target/wheels/ (or --out DIR).
# Needs a Rust toolchain (cargo) and Python >= 3.10; maturin comes from PyPI into a private
# venv (.venv-python/ at the repository root, or $PIR2_PY_VENV), created on first use.
#
# Usage: scripts/build-python.sh [--test] [--out DIR]
#   --test   also install the wheel (with numpy and pytest) into that venv and run
#            bindings/python/tests
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv=${PIR2_PY_VENV:-"$root/.venv-python"}
out="$root/bindings/python/target/wheels"
run_tests=0
while [ $# -gt 0 ]; do
  case "$1" in
    --test) run_tests=1 ;;
    --out) out=$2; shift ;;
    *) echo "unknown option $1" >&2; exit 2 ;;
  esac
  shift
done
py=${PYTHON:-python3}
if [ ! -x "$venv/bin/python" ]; then
  echo "[build-python] creating venv $venv"
  "$py" -m venv "$venv"
fi
if ! "$venv/bin/python" -m maturin --version >/dev/null 2>&1; then
  "$venv/bin/python" -m pip install -q --upgrade pip
  "$venv/bin/python" -m pip install -q "maturin>=1.5,<2"
fi
rm -f "$out"/pir2-*.whl
"$venv/bin/python" -m maturin build --release -m "$root/bindings/python/Cargo.toml" --out "$out"
wheel=$(ls "$out"/pir2-*.whl)
echo "[build-python] wheel: $wheel"
if [ "$run_tests" = 1 ]; then
  "$venv/bin/python" -m pip install -q --force-reinstall "$wheel" pytest
  # Run from the tests folder so `import pir2` finds the installed wheel, not the sources.
  (cd "$root/bindings/python/tests" && "$venv/bin/python" -m pytest -q -p no:cacheprovider .)
fi
