#!/usr/bin/env bash
# Checks too long or too heavy for CI (`.ci/run`, budget 60 min on 2 cores). Run the group an
# issue needs before resolving it, and put the summary this script prints in the issue's note.
#
#   scripts/check-extra.sh fuzz-fast    # the byte parsers: Zenoh wire, xArm and XHand frames
#   scripts/check-extra.sh fuzz-files   # the file parsers: dataset, study config, checkpoint,
#                                       # embodiment (optimised build with the checks on)
#   scripts/check-extra.sh torch        # the Python package's PyTorch side (pir2.gr00t): its tests
#                                       # and the PyTorch -> pir2 round trip (full torch, ~5 GB);
#                                       # with PIR2_ISAAC_GR00T=<Isaac-GR00T checkout>, also on
#                                       # Isaac-GR00T's own DiT classes (test_gr00t_isaac.py)
#   scripts/check-extra.sh lerobot      # examples/lerobot-flow end to end: the pir2_flow LeRobot
#                                       # plugin's tests, pir2 collect ballplate, lerobot-train
#                                       # --policy.type=pir2_flow a few hundred steps, export,
#                                       # pir2 eval on the ONNX checkpoint
#   scripts/check-extra.sh all
#
# Fuzzing: every property runs PIR2_FUZZ_CASES cases (default 10^6), in the test profile whose
# builds CI already has. Each property starts from a corpus of valid inputs and mutates it,
# besides arbitrary bytes:
#   wire       encoded requests, replies, pongs and features of every message family
#   frames     xArm commands/replies/reports and XHand frames as the protocol docs write them
#   xarm_wire  report frames of every size the official SDK accepts, split anywhere
#   reader     a small LeRobotDataset v3.0 written by `DatasetWriter` (info.json, parquet)
#   config     the ball-plate task's TOML config
#   checkpoint a candle checkpoint (config.json, stats.json, model.safetensors)
#   embodiment the xArm6 + XHand embodiment.toml
# A failure is shrunk and written to the crate's `proptest-regressions/` (commit it: CI then
# replays it first on every run).
set -euo pipefail
cd "$(dirname "$0")/.."

export PIR2_FUZZ_CASES="${PIR2_FUZZ_CASES:-1000000}"
summary=()

timed() {
    local name="$1"
    shift
    local t0=$SECONDS
    echo "--- $name ($PIR2_FUZZ_CASES cases per property) ---"
    if "$@"; then
        summary+=("$name: ok, $((SECONDS - t0)) s")
    else
        summary+=("$name: FAILED after $((SECONDS - t0)) s")
        return 1
    fi
}

fuzz_fast() {
    timed "wire (pir2-runtime remote::wire)" \
        cargo test -p pir2-runtime --features remote --lib remote::wire
    timed "frames + xarm_wire (pir2-robots)" \
        cargo test -p pir2-robots --test frames --test xarm_wire
}

fuzz_files() {
    if [ -f .native/env.sh ]; then
        # shellcheck disable=SC1091
        source .native/env.sh
    fi
    # Optimised code with the test profile's checks kept (debug assertions, overflow checks):
    # an overflow or a failed assertion still panics, and a dataset-reader case costs 2.8 ms
    # instead of about 7 unoptimised. Its own target dir, so CI's unoptimised builds are not
    # thrown away.
    local opt=(--config 'profile.dev.opt-level=2' --target-dir target/fuzz-opt)
    # The dataset reader's cases write and read files: on a memory file system (when there is
    # one) a case costs 1.7 ms instead of 2.8.
    if [ -d /dev/shm ] && [ -w /dev/shm ]; then
        export TMPDIR="${TMPDIR:-/dev/shm}"
    fi
    timed "reader + config (pir2-sim)" \
        cargo test "${opt[@]}" -p pir2-sim --test reader_fuzz --test config_fuzz
    timed "checkpoint + embodiment (pir2-backends)" \
        cargo test "${opt[@]}" -p pir2-backends --features gr00t --test checkpoint_fuzz --test embodiment_fuzz
}

torch() {
    # `pir2.gr00t` needs a torch that imports: the full torch 2.13.0 wheel with its CUDA
    # libraries (setup-native.sh installs a lean torch for libtorch only, which cannot
    # `import torch`), diffusers for the tests' N1.7-shaped head, safetensors. They go into
    # .native/venv-torch (or $PIR2_TORCH_VENV), with the package's wheel; the round trip needs
    # a pir2 built with feature gr00t and ONNX Runtime (setup-native.sh).
    local t0=$SECONDS venv=${PIR2_TORCH_VENV:-.native/venv-torch}
    [ -f .native/env.sh ] || bash scripts/setup-native.sh
    # shellcheck disable=SC1091
    source .native/env.sh
    [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
    "$venv/bin/pip" -q install "torch==2.13.0" "diffusers==0.42.1" "safetensors==0.8.0" numpy pytest
    PIR2_PY_VENV="$venv" bash scripts/build-python.sh
    "$venv/bin/pip" -q install --force-reinstall --no-deps bindings/python/target/wheels/pir2-*.whl
    cargo build -p pir2-cli --features gr00t
    local bin
    bin="$(cargo metadata --format-version 1 --no-deps | "$venv/bin/python" -c 'import json,sys; print(json.load(sys.stdin)["target_directory"])')/debug/pir2"
    # test_gr00t_isaac.py converts heads built on Isaac-GR00T's own DiT classes: it runs when
    # PIR2_ISAAC_GR00T names a checkout of NVIDIA/Isaac-GR00T (its gr00t/model/modules/dit.py
    # is loaded by path), and skips itself otherwise.
    local isaac_root="${PIR2_ISAAC_GR00T:-}" isaac
    if [ -n "$isaac_root" ] && [ -f "$isaac_root/gr00t/model/modules/dit.py" ]; then
        isaac_root="$(cd "$isaac_root" && pwd)"
        isaac="Isaac-GR00T check ran against $isaac_root"
        local rev
        if [ -e "$isaac_root/.git" ] && rev="$(git -C "$isaac_root" rev-parse --short HEAD 2>/dev/null)"; then
            isaac+=" at $rev"
        fi
    elif [ -n "$isaac_root" ]; then
        isaac="Isaac-GR00T check SKIPPED ($isaac_root has no gr00t/model/modules/dit.py)"
    else
        isaac="Isaac-GR00T check skipped (set PIR2_ISAAC_GR00T to an Isaac-GR00T checkout)"
    fi
    if (cd bindings/python/tests && PIR2_BIN="$bin" PIR2_ISAAC_GR00T="$isaac_root" \
        "$venv/bin/python" -m pytest -q -s -p no:cacheprovider \
        test_gr00t_torch.py test_gr00t_isaac.py test_gr00t_roundtrip.py); then
        summary+=("torch: pir2.gr00t tests and the PyTorch -> pir2 round trip ok; $isaac; $((SECONDS - t0)) s")
    else
        summary+=("torch: FAILED after $((SECONDS - t0)) s; $isaac")
        return 1
    fi
}

lerobot() {
    # Python: $PIR2_LEROBOT_PYTHON (an interpreter with torch, lerobot==0.4.4 and what its
    # lerobot-train imports, onnx, onnxruntime==1.31.1, pytest and the pir2 wheel; see
    # examples/lerobot-flow/README.md), or a venv .native/venv-lerobot created here with
    # `pip install lerobot==0.4.4` (which brings its own torch) and the wheel built by
    # scripts/build-python.sh. The plugin examples/lerobot-flow/lerobot_policy_pir2_flow is
    # installed into it (editable). ONNX Runtime for Rust: .native/env.sh
    # (scripts/setup-native.sh).
    local t0=$SECONDS
    if [ -f .native/env.sh ]; then
        # shellcheck disable=SC1091
        source .native/env.sh
    fi
    if [ -z "${ORT_DYLIB_PATH:-}" ]; then
        echo "lerobot: ORT_DYLIB_PATH is not set: run scripts/setup-native.sh first" >&2
        summary+=("lerobot: FAILED (no ONNX Runtime: scripts/setup-native.sh)")
        return 1
    fi
    local py="${PIR2_LEROBOT_PYTHON:-}"
    if [ -z "$py" ]; then
        local venv=.native/venv-lerobot
        if [ ! -x "$venv/bin/python" ]; then
            python3 -m venv "$venv"
            "$venv/bin/pip" -q install "lerobot==0.4.4" onnx "onnxruntime==1.31.1" pytest
        fi
        scripts/build-python.sh --out .native/wheels
        "$venv/bin/pip" -q install --force-reinstall --no-deps .native/wheels/pir2-*.whl
        py="$venv/bin/python"
    fi
    "$py" -m pip -q install --no-deps -e examples/lerobot-flow/lerobot_policy_pir2_flow
    local tests
    if ! tests="$("$py" -m pytest -q -p no:cacheprovider examples/lerobot-flow/lerobot_policy_pir2_flow/tests 2>&1 | tail -n 1)"; then
        summary+=("lerobot: FAILED plugin tests ($tests)")
        return 1
    fi
    cargo build --release -p pir2-cli --features ort
    local pir2
    pir2="$(cargo metadata --format-version 1 --no-deps | "$py" -c 'import json,sys; print(json.load(sys.stdin)["target_directory"])')/release/pir2"
    local work
    work="$(mktemp -d)"
    local steps="${PIR2_LEROBOT_STEPS:-400}" episodes="${PIR2_LEROBOT_EPISODES:-20}"
    # The dataset is local: LeRobot needs no hub access.
    if "$pir2" collect ballplate --out "$work/data" --episodes 100 --seed 0 &&
        HF_HUB_OFFLINE=1 "$py" -m lerobot.scripts.lerobot_train --policy.type=pir2_flow \
            --policy.device=cpu --policy.push_to_hub=false --dataset.repo_id=local \
            --dataset.root="$work/data" --output_dir="$work/train" --steps="$steps" \
            --batch_size=128 --num_workers=0 --save_freq="$steps" --log_freq=100 --seed=0 \
            --wandb.enable=false &&
        "$py" -m lerobot_policy_pir2_flow.export \
            --policy-path "$work/train/checkpoints/last/pretrained_model" --out "$work/onnx" &&
        "$pir2" eval ballplate --checkpoint "$work/onnx" --policy pir2 --d0 1,2,3 \
            --episodes "$episodes" --json "$work/cells.json" | tee "$work/table.md"; then
        local rates
        rates="$("$py" -c 'import json,sys; print(", ".join("%s d0=%d: %d/%d" % (c["label"], c["d0"], c["successes"], c["episodes"]) for c in json.load(open(sys.argv[1]))))' "$work/cells.json")" || {
            summary+=("lerobot: FAILED reading $work/cells.json")
            return 1
        }
        summary+=("lerobot: ok (plugin tests: $tests; lerobot-train $steps steps, 100 demos), success $rates, $((SECONDS - t0)) s")
        rm -rf "$work"
    else
        summary+=("lerobot: FAILED after $((SECONDS - t0)) s (outputs in $work)")
        return 1
    fi
}

status=0
case "${1:-all}" in
fuzz-fast) fuzz_fast || status=1 ;;
fuzz-files) fuzz_files || status=1 ;;
torch) torch || status=1 ;;
lerobot) lerobot || status=1 ;;
all)
    fuzz_fast || status=1
    fuzz_files || status=1
    torch || status=1
    lerobot || status=1
    ;;
*)
    echo "usage: $0 [fuzz-fast|fuzz-files|torch|lerobot|all]" >&2
    exit 2
    ;;
esac

echo "=== check-extra summary ==="
printf '%s\n' "${summary[@]}"
exit $status
