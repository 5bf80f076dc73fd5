#!/usr/bin/env bash
# Does `pir2-cli --features gr00t,cuda` build? The last step of .ci/run (no GPU needed).
#
# candle's CUDA backend compiles its kernels with NVIDIA's `nvcc` in candle-kernels' build
# script. PyPI's CUDA 13 wheel `nvidia-cuda-nvcc` ships nvcc (the CUDA 12 wheel has only
# `ptxas`); with the runtime headers and CCCL (CUB/Thrust/libcu++, which the kernels include)
# that is all a build needs: cuBLAS, cuRAND and NVRTC are loaded by cudarc at run time, so
# they are not installed here (about 900 MB saved). Without an `nvcc` on PATH this installs the
# three wheels into .native/venv-nvcc (about 370 MB).
#
# `cargo check` runs candle-kernels' build script, so every CUDA kernel (the static objects and
# the PTX) is compiled by nvcc, and pir2 is type-checked against candle's and cudarc's CUDA API.
# Nothing is linked or run on a GPU.
#
# cudarc 0.19's build script knows CUDA up to 13.4, so the 13.5 toolkit is declared as 13.4
# (same driver API); CUDA_COMPUTE_CAP picks the target architecture where no GPU can be queried.
#
#   scripts/cuda-build-check.sh        # from the repository root or anywhere
set -euo pipefail
cd "$(dirname "$0")/.."
t0=$SECONDS
if ! command -v nvcc >/dev/null 2>&1; then
    venv=.native/venv-nvcc
    if [ ! -x "$venv/bin/python" ]; then
        "${PYTHON:-python3}" -m venv "$venv"
    fi
    "$venv/bin/pip" -q install "nvidia-cuda-nvcc==13.5.37" "nvidia-cuda-runtime==13.5.37" \
        "nvidia-cuda-cccl==13.3.5.0.6"
    cu="$("$venv/bin/python" -c 'import nvidia, os; print(os.path.join(nvidia.__path__[0], "cu13"))')"
    [ -x "$cu/bin/nvcc" ] || { echo "cuda-build-check: no nvcc in $cu/bin after the install" >&2; exit 1; }
    export PATH="$cu/bin:$PATH" CUDA_ROOT="$cu" CUDA_PATH="$cu" CUDA_TOOLKIT_ROOT_DIR="$cu"
    export CUDARC_CUDA_VERSION="${CUDARC_CUDA_VERSION:-13040}"
fi
export CUDA_COMPUTE_CAP="${CUDA_COMPUTE_CAP:-80}"
echo "cuda-build-check: $(nvcc --version | tail -1), compute capability $CUDA_COMPUTE_CAP"
if cargo check -p pir2-cli --features gr00t,cuda; then
    echo "cuda-build-check: pir2-cli --features gr00t,cuda compiles ($((SECONDS - t0)) s)"
else
    echo "cuda-build-check: pir2-cli --features gr00t,cuda FAILED to compile after $((SECONDS - t0)) s" >&2
    exit 1
fi
