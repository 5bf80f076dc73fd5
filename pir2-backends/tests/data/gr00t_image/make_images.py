"""Writes the committed test images of the GR00T image golden test (tests/gr00t_image.rs).

Deterministic synthetic camera-like frames (gradients, a checkerboard, rings, thin stripes and
a small seeded noise patch) in the shapes the test needs: a 640x480 landscape frame (UVC
default), a 360x480 portrait frame, a 200x150 frame (enlarged by the resizes) and a 512x512
square (an integer shrink). Run once with numpy + OpenCV; the PNGs are committed.
"""
import sys

import cv2
import numpy as np


def frame(h, w, seed):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 127 + 120 * np.sin(x / w * 6.0 + seed)
    g = 255 * y / max(h - 1, 1)
    b = 127 + 120 * np.cos(np.hypot(x - w / 2, y - h / 2) / 9.0)
    img = np.stack([r, g, b], axis=-1)
    # Checkerboard (8 px) in the top-left quarter, thin vertical stripes bottom-right.
    cb = ((x // 8 + y // 8) % 2 == 0) & (x < w / 2) & (y < h / 2)
    img[cb] = [250, 250, 250]
    st = (x % 3 == 0) & (x > w * 0.6) & (y > h * 0.6)
    img[st] = [10, 40, 200]
    rng = np.random.default_rng(seed)
    ph, pw = min(40, h // 4), min(40, w // 4)
    img[h // 2 : h // 2 + ph, w // 4 : w // 4 + pw] = rng.integers(0, 256, (ph, pw, 3))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


out = sys.argv[1] if len(sys.argv) > 1 else "."
for name, (h, w), seed in [
    ("wide_640x480", (480, 640), 1),
    ("tall_360x480", (480, 360), 2),
    ("small_200x150", (150, 200), 3),
    ("square_512", (512, 512), 4),
]:
    rgb = frame(h, w, seed)
    cv2.imwrite(f"{out}/{name}.png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
