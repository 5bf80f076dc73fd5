#!/usr/bin/env bash
# One command for the native pieces behind cargo features:
#   MuJoCo 3.17.0 (feature `mujoco`), ONNX Runtime 1.31.1 (feature `ort`), libtorch 2.13.0 (feature `tch`),
#   and the LeapCubeReorient scene from the `playground==0.2.0` wheel (Apache-2.0).
# Everything comes from PyPI into a private venv under .native/ (nothing is downloaded from elsewhere),
# with the Python references of the native tests (onnx, scipy, Pillow, pyarrow, tokenizers, jinja2, albumentations +
# opencv-python-headless, av, xarm-python-sdk), and the `ffmpeg` program (apt) that decodes
# datasets' camera videos.
# It writes .native/env.sh; `source .native/env.sh` before building/running with those features.
# Idempotent: a second run only checks.
#
# Usage: scripts/setup-native.sh [--no-torch] [--full-torch]
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
native="$root/.native"
venv="$native/venv"
want_torch=1
full_torch=0
for a in "$@"; do
  case "$a" in
    --no-torch) want_torch=0 ;;
    --full-torch) full_torch=1 ;;
    *) echo "unknown option $a" >&2; exit 2 ;;
  esac
done
mkdir -p "$native"
py=${PYTHON:-python3}
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup-native] creating venv $venv"
  "$py" -m venv "$venv" 2>/dev/null || { apt-get update -qq && apt-get install -y -qq python3-venv >/dev/null && "$py" -m venv "$venv"; }
fi
pip="$venv/bin/pip"
"$pip" -q install --upgrade pip >/dev/null 2>&1 || true
have() { "$venv/bin/python" - "$1" "$2" <<'PY' 2>/dev/null
import sys, importlib.metadata as m
sys.exit(0 if m.version(sys.argv[1]) == sys.argv[2] else 1)
PY
}
have mujoco 3.17.0 || "$pip" -q install "mujoco==3.17.0"
have onnxruntime 1.31.1 || "$pip" -q install "onnxruntime==1.31.1"
# `onnx` + numpy: the GR00T tests write their tiny synthetic graphs with them.
"$venv/bin/python" -c "import onnx, numpy" 2>/dev/null || "$pip" -q install onnx numpy
# scipy: its `Rotation` is the reference of the relative end-effector poses
# (pir2-cli/tests/gr00t_train_pose.rs); Isaac-GR00T's pose code builds on it.
have scipy 1.17.1 || "$pip" -q install "scipy==1.17.1"
# Hugging Face `tokenizers` + Jinja2: the Python reference of the GR00T tokenizer golden test
# (pir2-backends/tests/gr00t_tokenizer.rs).
have tokenizers 0.23.3 || "$pip" -q install "tokenizers==0.23.3"
have jinja2 3.1.6 || "$pip" -q install "jinja2==3.1.6"
# albumentations + OpenCV: the Python reference of GR00T N1.7's image preprocessing
# (pir2-backends/tests/gr00t_image.rs), the libraries GR00T's processor uses.
have albumentations 2.0.8 || "$pip" -q install "albumentations==2.0.8"
have opencv-python-headless 4.14.0.94 || "$pip" -q install "opencv-python-headless==4.14.0.94"
# PyAV (LeRobot's video decoding backend): the Python reference of `pir2 gr00t features`'s
# frame decoding (pir2-cli/tests/gr00t_features.rs). 18.1.0: the last release for Python 3.11.
have av 18.1.0 || "$pip" -q install "av==18.1.0"
# Pillow + pyarrow: the Python reference of image-typed camera features (PNG/JPEG bytes in the
# data files, decoded by LeRobot with Pillow) in pir2-cli/tests/gr00t_features.rs, which also
# writes its image dataset with pyarrow.
have pillow 13.0.0 || "$pip" -q install "pillow==13.0.0"
have pyarrow 26.0.1 || "$pip" -q install "pyarrow==26.0.1"
# The `ffmpeg` program: `pir2 gr00t features` decodes the datasets' camera videos with it
# (AV1, LeRobot's default codec, and H.264). Debian/Ubuntu package `ffmpeg`.
if ! command -v ffmpeg >/dev/null 2>&1; then
  echo "[setup-native] installing ffmpeg (apt)"
  { apt-get update -qq && apt-get install -y -qq ffmpeg >/dev/null; } \
    || echo "[setup-native] could not install ffmpeg: install it (apt-get install ffmpeg) for pir2 gr00t features" >&2
fi
# UFACTORY's official xArm SDK: the real client of the xArm emulator in the native tests.
have xarm-python-sdk 1.18.4 || "$pip" -q install "xarm-python-sdk==1.18.4"
if [ "$want_torch" = 1 ]; then
  if ! have torch 2.13.0; then
    if [ "$full_torch" = 1 ]; then
      "$pip" -q install "torch==2.13.0"
    else
      # Lean install: enough for libtorch from Rust (tch); `import torch` needs --full-torch.
      "$pip" -q install --no-deps "torch==2.13.0" "nvidia-cuda-runtime==13.0.96" "nvidia-cuda-cupti==13.0.85"
    fi
  fi
fi
site=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')

# MuJoCo: an absolute dir with an unversioned libmujoco.so symlink.
mjdir="$native/mujoco"
mkdir -p "$mjdir"
mjlib=$(ls "$site"/mujoco/libmujoco.so.* 2>/dev/null | head -1)
[ -n "$mjlib" ] || { echo "[setup-native] libmujoco.so.* not found in the mujoco wheel" >&2; exit 1; }
ln -sf "$mjlib" "$mjdir/libmujoco.so"
ln -sf "$mjlib" "$mjdir/$(basename "$mjlib")"

# ONNX Runtime shared library from the wheel.
ortlib=$(ls "$site"/onnxruntime/capi/libonnxruntime.so* 2>/dev/null | head -1)
[ -n "$ortlib" ] || { echo "[setup-native] libonnxruntime.so not found in the onnxruntime wheel" >&2; exit 1; }

# Leap-cube scene from the playground wheel (not committed: installed here).
scene="$native/leap_cube"
if [ ! -f "$scene/scene_mjx_cube.xml" ]; then
  tmp=$(mktemp -d)
  "$pip" -q download --no-deps -d "$tmp" "playground==0.2.0" >/dev/null
  whl=$(ls "$tmp"/playground-0.2.0-*.whl | head -1)
  "$venv/bin/python" - "$whl" "$scene" <<'PY'
import sys, zipfile, os
whl, out = sys.argv[1], sys.argv[2]
pre = "mujoco_playground/_src/manipulation/leap_hand/xmls/"
with zipfile.ZipFile(whl) as z:
    for n in z.namelist():
        if n.startswith(pre) and not n.endswith("/"):
            dst = os.path.join(out, n[len(pre):])
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            with open(dst, "wb") as f:
                f.write(z.read(n))
PY
  rm -rf "$tmp"
fi

{
  echo "# generated by scripts/setup-native.sh"
  echo "export PIR2_NATIVE='$native'"
  echo "export MUJOCO_DYNAMIC_LINK_DIR='$mjdir'"
  echo "export ORT_DYLIB_PATH='$ortlib'"
  echo "export PIR2_LEAP_CUBE_DIR='$scene'"
  echo "export PIR2_PYTHON='$venv/bin/python'"
  if [ "$want_torch" = 1 ]; then
    echo "export LIBTORCH='$site/torch'"
    echo "export LIBTORCH_BYPASS_VERSION_CHECK=1"
    echo "export LD_LIBRARY_PATH='$mjdir:$site/torch/lib'\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
  else
    echo "export LD_LIBRARY_PATH='$mjdir'\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
  fi
} > "$native/env.sh"
echo "[setup-native] ok: source $native/env.sh"
