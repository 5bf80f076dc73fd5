#!/usr/bin/env bash
# CI fragment for the GR00T-N1.7 xArm6 + XHand stack (pir2-backends feature `gr00t`).
# Run from the repository root after scripts/setup-native.sh; `source .native/env.sh` provides
# ORT_DYLIB_PATH (ONNX Runtime 1.31) and PIR2_PYTHON (a venv with `onnx`, used by the tests to
# write the tiny synthetic graphs). PIR2_NATIVE_ENV overrides the env file.
# The end-to-end test runs the real-time driver for 2 s at 25 Hz on the xArm6/XHand emulators;
# the whole suite is bounded (< ~30 s once built).
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source "${PIR2_NATIVE_ENV:-.native/env.sh}"
rustfmt --check --edition 2021 pir2-backends/src/gr00t/*.rs pir2-backends/tests/gr00t.rs \
  pir2-backends/tests/gr00t_split_backbone.rs
# Lib + the gr00t test target (other test targets belong to the backends/ortch owners).
cargo clippy -p pir2-backends --lib --test gr00t --test gr00t_export --test gr00t_split_backbone --features gr00t -- -D warnings
# Docs: fail on any rustdoc warning inside the gr00t module. (`-D warnings` on the whole crate
# currently trips over lib.rs's `tch::TchModel` link when feature `tch` is off, which is not ours.)
doc_log=$(cargo doc -p pir2-backends --features gr00t --no-deps 2>&1)
echo "$doc_log"
if echo "$doc_log" | grep -q -- "--> pir2-backends/src/gr00t/"; then
  echo "rustdoc warnings in src/gr00t" >&2
  exit 1
fi
# The crate's unit tests (candle, ONNX export, gr00t) and the gr00t integration tests; the
# split backbone (GR00T's vit/llm export glued in Rust) against its fused composition.
cargo test -p pir2-backends --features gr00t --lib --test gr00t --test gr00t_split_backbone -- --test-threads=1
# The ONNX export of a fine-tuned N1.7 head against candle (ONNX Runtime, the reference
# fixture `alt` with a nonzero delay table), < 1 s.
cargo test -p pir2-backends --features gr00t --test gr00t_export
# `pir2 train gr00t` end to end (candle, CPU; needs no ONNX Runtime at run time): a synthetic
# N1.7-shaped checkpoint, dataset and backbone features; resume bit-identity; input errors.
cargo test -p pir2-cli --features gr00t --test gr00t_train
# A relative end-effector pose (xyz_rot6d) through pir2 train gr00t on a widened synthetic
# checkpoint; relative poses against scipy's Rotation (PIR2_PYTHON with scipy), ~2 s.
cargo test -p pir2-cli --features gr00t --test gr00t_train_pose
# Issue 20's chain: synthetic N1.7 checkpoint → pir2 train gr00t (2 steps) → pir2 export --gr00t
# → pir2 run gr00t-xarm-xhand --emulate (25 ticks), and the export's input errors (~5 s).
cargo test -p pir2-cli --features gr00t --test gr00t_export -- --test-threads=1
# `pir2 features gr00t` (needs the `ffmpeg` program and PyAV, Pillow, pyarrow in PIR2_PYTHON):
# pir2's decoded frames vs PyAV's on the committed AV1/H.264 fixture, and the features file end
# to end (the backbone on the decoded frames, deployment agreement, resume, accepted by pir2
# train gr00t); an image-typed camera (PNG/JPEG in the data file) vs Pillow.
cargo test -p pir2-cli --features gr00t --test gr00t_features -- --test-threads=1
