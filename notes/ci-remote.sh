#!/usr/bin/env bash
# CI for pir2-runtime's `remote` feature (issue #9): Zenoh slow channel and action head.
# Tests bind only 127.0.0.1 (test-chosen free ports) and take ~10-20 s.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo fmt --all -- --check
cargo clippy -p pir2-runtime --features remote --all-targets -- -D warnings
RUSTDOCFLAGS="-D warnings" cargo doc -p pir2-runtime --features remote --no-deps
cargo test -p pir2-runtime --features remote
# the default build must not change
cargo test -p pir2-runtime
