#!/usr/bin/env bash
# CI fragment for the native backends of pir2-backends (features `ort`, `tch`).
# Run by .ci/run after scripts/setup-native.sh, from the repository root.
# PIR2_NATIVE_ENV overrides the env file (e.g. .native/env.sh (of the main checkout) from a worktree).
# Sessions are single-threaded; libtorch needs LD_LIBRARY_PATH (set by env.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source "${PIR2_NATIVE_ENV:-.native/env.sh}"
# --no-deps: lint this crate only (path dependencies are linted by their own CI step).
cargo clippy -p pir2-backends --no-deps --all-targets --features ort,tch -- -D warnings
cargo test -p pir2-backends --features ort,tch
# The default build (candle only) must still pass without any native library.
env -u ORT_DYLIB_PATH -u LIBTORCH cargo test -p pir2-backends --test conformance
# Latency smoke run in the test profile (prints the side-by-side table; no timing asserts).
# Real numbers: cargo bench -p pir2-backends --features ort,tch --bench latency
PIR2_BENCH_ITERS=20 cargo test -p pir2-backends --features ort,tch --bench latency
