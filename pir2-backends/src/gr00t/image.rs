//! Camera image preprocessing for the backbone, as GR00T N1.7 does it at inference.
//!
//! GR00T N1.7's processor (its albumentations path, on by default for N1.7) turns each camera
//! frame (HWC `u8` RGB) into the image its VLM processor receives:
//!
//! 1. **letterbox**: pad to a square with black (value 0), the frame centred; an odd extra
//!    row/column goes to the bottom/right;
//! 2. **resize** the shorter side to `shortest_edge` (256) with OpenCV's `INTER_AREA`
//!    (albumentations' `SmallestMaxSize`; the other side `round(side · scale)`);
//! 3. **centre crop** `⌊side · crop_fraction⌋` (0.95: 243 of 256) at offset
//!    `⌊(side − crop)/2⌋`;
//! 4. **resize** the shorter side back to `shortest_edge` with `INTER_AREA`.
//!
//! (NVIDIA/Isaac-GR00T at commit c5437fa66982969177d20d432eca5b4d966dfbbe,
//! `gr00t/model/gr00t_n1d7/image_augmentations.py`: the eval `A.Compose` of
//! `build_image_transformations_albumentations`, lines 480–487, with `LetterBoxPad`, lines
//! 324–371, and `FractionalCenterCrop`, lines 257–321.)
//!
//! GR00T letterboxes **unconditionally**: both of its pipelines start with the pad (the
//! torchvision one too, line 585), and the processor's `letter_box_transform` argument, which
//! a checkpoint's `processor_config.json` carries (`false` by default), is stored and never
//! read (`gr00t/model/gr00t_n1d7/processing_gr00t_n1d7.py`, lines 266–267 and 293, "stored but
//! not actively used"). So pir2's `image.letterbox` is on by default whatever that file says,
//! and a 640×480 camera gives GR00T's 256 × 256 image.
//!
//! The VLM's image processor (Qwen3-VL, via Cosmos-Reason2) then rescales by 1/255 and
//! normalises with mean = std = 0.5 per channel; a 256 × 256 image is already a multiple of
//! its 32-pixel merged patch and at its minimum pixel count, so it is not resized again.
//! Views and frames are ordered time-major, view-minor (index `t·V + v`).
//!
//! [`resize_area`] reproduces OpenCV's `INTER_AREA` for `u8` images: its box average for an
//! integer shrink, exact cell weights for another shrink (both scales ≥ 1), OpenCV's area-mode bilinear weights in 11-bit fixed point
//! when enlarging, with the rounding of its vectorised vertical pass. The golden test (`tests/gr00t_image.rs`) compares the whole pipeline with
//! albumentations + OpenCV from PyPI on committed images, to within 1/255 per pixel, with and
//! without the letterbox.
//!
//! With `letterbox = false` (an opt-out GR00T does not have: what honouring
//! `letter_box_transform = false` would mean, as LeRobot's port of the processor does), steps
//! 2–4 run on the frame as it is, and a non-square frame stays non-square (640×480 → 340×256).
//! [`gr00t_n17_transform`] computes that image; the backbone input
//! ([`super::preprocess_image`]) refuses it, because the VLM processor would then resize it to
//! multiples of its 32-pixel merged patch (bicubic) and the image would take another number of
//! tokens than `prompt.image_tokens`, neither of which pir2 implements.

use crate::error::{Error, Result};

/// An HWC `u8` RGB image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rgb {
    /// Height.
    pub h: usize,
    /// Width.
    pub w: usize,
    /// `h · w · 3` bytes, row-major, RGB.
    pub data: Vec<u8>,
}

impl Rgb {
    /// Check and wrap `data` (HWC RGB, `h · w · 3` bytes, non-empty).
    pub fn new(h: usize, w: usize, data: Vec<u8>) -> Result<Self> {
        if h == 0 || w == 0 || h.checked_mul(w).and_then(|n| n.checked_mul(3)) != Some(data.len()) {
            return Err(Error::input(
                "camera image (HWC u8 RGB)",
                format!("{h}×{w}×3 bytes, non-empty"),
                format!("{} bytes", data.len()),
            ));
        }
        Ok(Rgb { h, w, data })
    }
}

/// Pad to a square with black, the image centred (GR00T's letterbox).
pub fn letterbox(img: &Rgb) -> Rgb {
    let side = img.h.max(img.w);
    if img.h == img.w {
        return img.clone();
    }
    let (top, left) = ((side - img.h) / 2, (side - img.w) / 2);
    let mut data = vec![0u8; side * side * 3];
    for y in 0..img.h {
        let src = &img.data[y * img.w * 3..(y + 1) * img.w * 3];
        let o = ((y + top) * side + left) * 3;
        data[o..o + img.w * 3].copy_from_slice(src);
    }
    Rgb {
        h: side,
        w: side,
        data,
    }
}

/// Crop `(h, w)` at `(y, x)`.
pub fn crop(img: &Rgb, y: usize, x: usize, h: usize, w: usize) -> Rgb {
    let mut data = Vec::with_capacity(h * w * 3);
    for r in y..y + h {
        data.extend_from_slice(&img.data[(r * img.w + x) * 3..(r * img.w + x + w) * 3]);
    }
    Rgb { h, w, data }
}

/// Resize so the shorter side is `edge` (albumentations' `SmallestMaxSize` with `INTER_AREA`;
/// the other side rounds half to even, as Python's `round`).
pub fn smallest_max_size(img: &Rgb, edge: usize) -> Rgb {
    let scale = edge as f64 / img.h.min(img.w) as f64;
    let (h, w) = (
        ((img.h as f64 * scale).round_ties_even() as usize).max(1),
        ((img.w as f64 * scale).round_ties_even() as usize).max(1),
    );
    resize_area(img, h, w)
}

/// Source taps and weights of one output coordinate when shrinking by `scale = src/dst ≥ 1`
/// (OpenCV's area table: the cell `[d·scale, (d+1)·scale)` clipped to the source).
fn area_taps(dst: usize, src: usize, scale: f64) -> Vec<Vec<(usize, f64)>> {
    (0..dst)
        .map(|d| {
            let fs1 = d as f64 * scale;
            let fs2 = fs1 + scale;
            let cell = scale.min(src as f64 - fs1);
            let s2 = (fs2.floor() as usize).min(src - 1);
            let s1 = (fs1.ceil() as usize).min(s2);
            let mut taps = Vec::new();
            if s1 as f64 - fs1 > 1e-3 {
                taps.push((s1 - 1, (s1 as f64 - fs1) / cell));
            }
            for s in s1..s2 {
                taps.push((s, 1.0 / cell));
            }
            if fs2 - s2 as f64 > 1e-3 {
                taps.push((s2, (fs2 - s2 as f64).min(1.0).min(cell) / cell));
            }
            taps
        })
        .collect()
}

/// OpenCV's fixed-point scale of interpolation coefficients (`INTER_RESIZE_COEF_BITS` = 11).
const COEF_SCALE: i32 = 1 << 11;

/// Taps of one output coordinate when enlarging with `INTER_AREA` (OpenCV's area-mode
/// linear weights, `scale = src/dst < 1`): source index and its 11-bit weight, twice.
fn area_linear_taps(dst: usize, src: usize, scale: f64) -> Vec<[(usize, i32); 2]> {
    let inv = 1.0 / scale;
    (0..dst)
        .map(|d| {
            let mut s = (d as f64 * scale).floor() as isize;
            let mut f = ((d + 1) as f64 - (s + 1) as f64 * inv) as f32;
            f = if f <= 0.0 { 0.0 } else { f - f.floor() };
            if s < 0 {
                f = 0.0;
                s = 0;
            }
            if s as usize >= src - 1 {
                f = 0.0;
                s = src as isize - 1;
            }
            let s = s as usize;
            let w0 = ((1.0 - f) * COEF_SCALE as f32).round_ties_even() as i32;
            [(s, w0), ((s + 1).min(src - 1), COEF_SCALE - w0)]
        })
        .collect()
}

/// Resize to `h × w` as OpenCV's `cv2.resize(…, interpolation=cv2.INTER_AREA)` does for a
/// `u8` RGB image (see the module docs).
pub fn resize_area(img: &Rgb, h: usize, w: usize) -> Rgb {
    if (h, w) == (img.h, img.w) {
        return img.clone();
    }
    let (sy, sx) = (img.h as f64 / h as f64, img.w as f64 / w as f64);
    let mut data = vec![0u8; h * w * 3];
    let (iy, ix) = (img.h / h, img.w / w);
    if iy * h == img.h && ix * w == img.w {
        // Integer shrink: OpenCV's box average (2 × 2: `(sum + 2) >> 2`; otherwise the sum
        // times `1/area` in f32, rounded half to even).
        let area = (iy * ix) as u32;
        let inv = 1.0f32 / area as f32;
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let mut sum = 0u32;
                    for yy in y * iy..(y + 1) * iy {
                        for xx in x * ix..(x + 1) * ix {
                            sum += u32::from(img.data[(yy * img.w + xx) * 3 + c]);
                        }
                    }
                    data[(y * w + x) * 3 + c] = if area == 4 && iy == 2 {
                        ((sum + 2) >> 2) as u8
                    } else {
                        (sum as f32 * inv).round_ties_even().min(255.0) as u8
                    };
                }
            }
        }
    } else if sy >= 1.0 && sx >= 1.0 {
        let (ty, tx) = (area_taps(h, img.h, sy), area_taps(w, img.w, sx));
        let mut row = vec![0f64; w * 3];
        for (y, ty) in ty.iter().enumerate() {
            row.fill(0.0);
            for &(ys, wy) in ty {
                let src = &img.data[ys * img.w * 3..(ys + 1) * img.w * 3];
                for (x, tx) in tx.iter().enumerate() {
                    for &(xs, wx) in tx {
                        for c in 0..3 {
                            row[x * 3 + c] += wy * wx * f64::from(src[xs * 3 + c]);
                        }
                    }
                }
            }
            for (o, v) in data[y * w * 3..(y + 1) * w * 3].iter_mut().zip(&row) {
                *o = v.round_ties_even().clamp(0.0, 255.0) as u8;
            }
        }
    } else {
        let (ty, tx) = (
            area_linear_taps(h, img.h, sy),
            area_linear_taps(w, img.w, sx),
        );
        // Horizontal pass in i32 (11-bit weights · pixels); vertical pass as OpenCV's
        // vectorised `u8` path computes it: each row sum shifted right by 4, multiplied by
        // its 11-bit weight keeping the high 16 bits, summed, then `(t + 2) >> 2`.
        let horizontal = |ys: usize| -> Vec<i32> {
            let src = &img.data[ys * img.w * 3..(ys + 1) * img.w * 3];
            let mut out = vec![0i32; w * 3];
            for (x, [(x0, w0), (x1, w1)]) in tx.iter().enumerate() {
                for c in 0..3 {
                    out[x * 3 + c] =
                        w0 * i32::from(src[x0 * 3 + c]) + w1 * i32::from(src[x1 * 3 + c]);
                }
            }
            out
        };
        let rows: Vec<Vec<i32>> = (0..img.h).map(horizontal).collect();
        for (y, [(y0, w0), (y1, w1)]) in ty.iter().enumerate() {
            for i in 0..w * 3 {
                let t = (((rows[*y0][i] >> 4) * w0) >> 16) + (((rows[*y1][i] >> 4) * w1) >> 16);
                data[y * w * 3 + i] = ((t + 2) >> 2).clamp(0, 255) as u8;
            }
        }
    }
    Rgb { h, w, data }
}

/// GR00T N1.7's eval-time image transform (steps 1–4 of the module docs): the `u8` image its
/// VLM processor receives. Without `letterbox_first`, steps 2–4 only: a non-square frame gives
/// a non-square image (its shorter side `shortest_edge`).
pub fn gr00t_n17_transform(
    img: &Rgb,
    letterbox_first: bool,
    shortest_edge: usize,
    crop_fraction: f64,
) -> Result<Rgb> {
    if shortest_edge == 0 || !(crop_fraction > 0.0 && crop_fraction <= 1.0) {
        return Err(Error::Gr00tConfig(format!(
            "image.shortest_edge = {shortest_edge} must be > 0 and image.crop_fraction = \
             {crop_fraction} in (0, 1]"
        )));
    }
    let square = if letterbox_first {
        letterbox(img)
    } else {
        img.clone()
    };
    let resized = smallest_max_size(&square, shortest_edge);
    let (ch, cw) = (
        ((resized.h as f64 * crop_fraction) as usize).max(1),
        ((resized.w as f64 * crop_fraction) as usize).max(1),
    );
    let cropped = crop(&resized, (resized.h - ch) / 2, (resized.w - cw) / 2, ch, cw);
    Ok(smallest_max_size(&cropped, shortest_edge))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(h: usize, w: usize) -> Rgb {
        let data = (0..h * w * 3).map(|i| (i * 7 % 256) as u8).collect();
        Rgb::new(h, w, data).unwrap()
    }

    #[test]
    fn letterbox_centres_the_frame_with_the_odd_pixel_at_the_bottom() {
        let img = Rgb::new(1, 2, vec![10, 11, 12, 20, 21, 22]).unwrap();
        let sq = letterbox(&img);
        assert_eq!((sq.h, sq.w), (2, 2));
        // Pad 1 row: top 0, bottom 1.
        assert_eq!(&sq.data[..6], &[10, 11, 12, 20, 21, 22]);
        assert_eq!(&sq.data[6..], &[0; 6]);
        let tall = letterbox(&ramp(5, 2));
        assert_eq!((tall.h, tall.w), (5, 5));
        // Pad 3 columns: left 1, right 2.
        assert_eq!(&tall.data[..3], &[0, 0, 0]);
        assert_eq!(&tall.data[3..9], &ramp(5, 2).data[..6]);
    }

    #[test]
    fn integer_shrink_averages_blocks_and_identity_is_a_copy() {
        let img = Rgb::new(2, 2, vec![0, 0, 0, 10, 10, 10, 20, 20, 20, 30, 30, 30]).unwrap();
        let one = resize_area(&img, 1, 1);
        assert_eq!(one.data, vec![15, 15, 15]);
        assert_eq!(resize_area(&img, 2, 2), img);
    }

    #[test]
    fn enlarging_a_flat_image_keeps_it_flat_and_shapes_follow_the_shorter_side() {
        let img = Rgb::new(3, 4, vec![77; 36]).unwrap();
        let big = smallest_max_size(&img, 9);
        assert_eq!((big.h, big.w), (9, 12));
        assert!(big.data.iter().all(|&v| v == 77));
        let out = gr00t_n17_transform(&ramp(48, 64), true, 32, 0.95).unwrap();
        assert_eq!((out.h, out.w), (32, 32));
        // Without the letterbox a 4:3 frame stays 4:3 (shorter side 32).
        let out = gr00t_n17_transform(&ramp(48, 64), false, 32, 0.95).unwrap();
        assert_eq!((out.h, out.w), (32, 43));
        // A square frame: the letterbox is the identity.
        let sq = ramp(40, 40);
        assert_eq!(
            gr00t_n17_transform(&sq, false, 32, 0.95).unwrap(),
            gr00t_n17_transform(&sq, true, 32, 0.95).unwrap()
        );
    }

    #[test]
    fn a_bad_buffer_is_refused_by_name() {
        let e = Rgb::new(2, 2, vec![0; 11]).unwrap_err();
        assert!(e.to_string().contains("HWC u8 RGB"), "{e}");
        assert!(Rgb::new(0, 2, vec![]).is_err());
    }
}
