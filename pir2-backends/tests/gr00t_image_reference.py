"""Python reference of GR00T N1.7's eval-time image transform, with the libraries GR00T uses
(albumentations + OpenCV from PyPI): the golden test tests/gr00t_image.rs runs it.

usage: gr00t_image_reference.py IMAGE.png OUT_DIR [SHORTEST_EDGE CROP_FRACTION [LETTERBOX]]

Writes OUT_DIR/input.rgb (the decoded frame, HWC u8 RGB) and OUT_DIR/output.rgb (the image
GR00T's VLM processor receives, HWC u8 RGB) and prints the two shapes as JSON.

The calls are those of GR00T N1.7's eval pipeline (NVIDIA/Isaac-GR00T at commit
c5437fa66982969177d20d432eca5b4d966dfbbe, gr00t/model/gr00t_n1d7/image_augmentations.py,
`build_image_transformations_albumentations`, the eval `A.Compose` of lines 480-487):
1. `LetterBoxPad()` (class at lines 324-371): for a non-square frame,
   `cv2.copyMakeBorder(top = pad_h // 2, bottom = pad_h - pad_h // 2, left = pad_w // 2,
   right = pad_w - pad_w // 2, cv2.BORDER_CONSTANT, value = 0)`, `pad = max(h, w) - side`;
2. `A.SmallestMaxSize(max_size = shortest_image_edge, interpolation = cv2.INTER_AREA)`;
3. `FractionalCenterCrop(crop_fraction)` (class at lines 257-321): crop
   `max(1, int(h * f)) x max(1, int(w * f))` at `((h - ch) // 2, (w - cw) // 2)`;
4. `A.SmallestMaxSize` as in 2.
GR00T applies step 1 unconditionally (the `letter_box_transform` processor argument is stored
but never read: gr00t/model/gr00t_n1d7/processing_gr00t_n1d7.py lines 266-267 and 293).
LETTERBOX = 0 leaves step 1 out (what honouring `letter_box_transform = false` would do, as
LeRobot's port of the processor does): a non-square frame then stays non-square.
The VLM processor then only rescales and normalises (mean = std = 0.5) a square image, which
the Rust test applies to this output.
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
letterbox = (sys.argv[5] != "0") if len(sys.argv) > 5 else True

bgr = cv2.imread(path, cv2.IMREAD_COLOR)
if bgr is None:
    sys.exit(f"cannot read {path}")
rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
h, w = rgb.shape[:2]

img = rgb
if letterbox and h != w:
    side = max(h, w)
    ph, pw = side - h, side - w
    img = cv2.copyMakeBorder(
        rgb, ph // 2, ph - ph // 2, pw // 2, pw - pw // 2, cv2.BORDER_CONSTANT, value=0
    )
resize = A.SmallestMaxSize(max_size=edge, interpolation=cv2.INTER_AREA, p=1.0)
img = resize(image=img)["image"]
H, W = img.shape[:2]
ch, cw = max(1, int(H * fraction)), max(1, int(W * fraction))
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
