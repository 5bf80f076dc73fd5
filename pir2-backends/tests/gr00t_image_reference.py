"""Python reference of GR00T N1.7's eval-time image transform, with the libraries GR00T uses
(albumentations + OpenCV from PyPI): the golden test tests/gr00t_image.rs runs it.

usage: gr00t_image_reference.py IMAGE.png OUT_DIR [SHORTEST_EDGE CROP_FRACTION]

Writes OUT_DIR/input.rgb (the decoded frame, HWC u8 RGB) and OUT_DIR/output.rgb (the image
GR00T's VLM processor receives, HWC u8 RGB) and prints the two shapes as JSON.

Steps (GR00T N1.7 processor, albumentations path, eval): pad to a square with black, the
frame centred (odd pixel bottom/right); albumentations SmallestMaxSize(shortest_edge,
INTER_AREA); centre crop int(side * fraction) at offset (side - crop) // 2; SmallestMaxSize
again. The VLM processor then only rescales and normalises (mean = std = 0.5), which the
Rust test applies to this output.
"""
import json
import os
import sys

import albumentations as A
import cv2
import numpy as np

path, out = sys.argv[1], sys.argv[2]
edge = int(sys.argv[3]) if len(sys.argv) > 3 else 256
fraction = float(sys.argv[4]) if len(sys.argv) > 4 else 0.95

bgr = cv2.imread(path, cv2.IMREAD_COLOR)
if bgr is None:
    sys.exit(f"cannot read {path}")
rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
h, w = rgb.shape[:2]

side = max(h, w)
ph, pw = side - h, side - w
img = cv2.copyMakeBorder(
    rgb, ph // 2, ph - ph // 2, pw // 2, pw - pw // 2, cv2.BORDER_CONSTANT, value=0
)
resize = A.SmallestMaxSize(max_size=edge, interpolation=cv2.INTER_AREA, p=1.0)
img = resize(image=img)["image"]
H, W = img.shape[:2]
ch, cw = int(H * fraction), int(W * fraction)
y0, x0 = (H - ch) // 2, (W - cw) // 2
img = np.ascontiguousarray(img[y0 : y0 + ch, x0 : x0 + cw])
img = resize(image=img)["image"]
assert img.dtype == np.uint8, img.dtype

os.makedirs(out, exist_ok=True)
rgb.tofile(os.path.join(out, "input.rgb"))
np.ascontiguousarray(img).tofile(os.path.join(out, "output.rgb"))
print(
    json.dumps(
        {
            "input": [h, w],
            "output": list(img.shape[:2]),
            "albumentations": A.__version__,
            "opencv": cv2.__version__,
        }
    )
)
