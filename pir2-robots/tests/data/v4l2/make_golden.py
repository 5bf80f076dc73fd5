"""Write the golden fixtures of pir2-robots' V4L2 pixel conversions (run once; the outputs
are committed next to this script). Needs numpy and opencv-python-headless (the venv of
scripts/setup-native.sh has both):

    python make_golden.py            # writes into this script's folder

- yuyv_32x8.yuyv / yuyv_32x8.rgb: a 32x8 YUYV frame (seeded random bytes; the first row
  sweeps the extremes of Y, U and V) and OpenCV's cv2.cvtColor(..., COLOR_YUV2RGB_YUYV) of it.
- mjpeg_48x32.jpg / mjpeg_48x32_nodht.jpg / mjpeg_48x32.rgb: a 48x32 4:2:2 JPEG written by
  OpenCV's encoder (standard Huffman tables), the same JPEG with its DHT segments removed
  (as UVC cameras send MJPEG), and OpenCV's decode of the full JPEG as RGB.
"""

import os
import sys

import cv2
import numpy as np

OUT = os.path.dirname(os.path.abspath(__file__))


def yuyv():
    w, h = 32, 8
    rng = np.random.default_rng(19)
    frame = rng.integers(0, 256, size=(h, w * 2), dtype=np.uint8)
    # Row 0: every combination of extreme/mid values for Y (two per pair), U and V.
    extremes = [0, 15, 16, 128, 235, 240, 255]
    row = []
    for k in range(w // 2):
        y0 = extremes[k % 7]
        y1 = extremes[(k + 3) % 7]
        u = extremes[(k * 2) % 7]
        v = extremes[(k * 5 + 1) % 7]
        row += [y0, u, y1, v]
    frame[0] = np.array(row, dtype=np.uint8)
    rgb = cv2.cvtColor(frame.reshape(h, w, 2), cv2.COLOR_YUV2RGB_YUYV)
    assert rgb.shape == (h, w, 3)
    frame.tofile(os.path.join(OUT, "yuyv_32x8.yuyv"))
    rgb.tofile(os.path.join(OUT, "yuyv_32x8.rgb"))


def strip_dht(jpeg: bytes) -> bytes:
    out = bytearray(jpeg[:2])
    i = 2
    while True:
        assert jpeg[i] == 0xFF
        marker = jpeg[i + 1]
        if marker == 0xDA:
            out += jpeg[i:]
            return bytes(out)
        n = int.from_bytes(jpeg[i + 2:i + 4], "big")
        if marker != 0xC4:
            out += jpeg[i:i + 2 + n]
        i += 2 + n


def mjpeg():
    w, h = 48, 32
    yy, xx = np.mgrid[0:h, 0:w]
    bgr = np.zeros((h, w, 3), dtype=np.uint8)
    bgr[..., 0] = (xx * 5) % 256
    bgr[..., 1] = (yy * 7 + xx) % 256
    bgr[..., 2] = np.where((xx // 8 + yy // 8) % 2 == 0, 220, 30)
    ok, enc = cv2.imencode(
        ".jpg",
        bgr,
        [
            cv2.IMWRITE_JPEG_QUALITY, 85,
            cv2.IMWRITE_JPEG_OPTIMIZE, 0,
            cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
        ],
    )
    assert ok
    jpeg = enc.tobytes()
    nodht = strip_dht(jpeg)
    assert b"\xff\xc4" not in nodht[:nodht.index(b"\xff\xda")]
    rgb = cv2.cvtColor(cv2.imdecode(enc, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert rgb.shape == (h, w, 3)
    open(os.path.join(OUT, "mjpeg_48x32.jpg"), "wb").write(jpeg)
    open(os.path.join(OUT, "mjpeg_48x32_nodht.jpg"), "wb").write(nodht)
    rgb.tofile(os.path.join(OUT, "mjpeg_48x32.rgb"))


if __name__ == "__main__":
    yuyv()
    mjpeg()
    print("opencv", cv2.__version__, "numpy", np.__version__, file=sys.stderr)
