//! GR00T N1.7's camera preprocessing against the Python reference: albumentations + OpenCV
//! from PyPI (the libraries GR00T's processor uses), run by `tests/gr00t_image_reference.py`
//! with `$PIR2_PYTHON` (`source .native/env.sh`; `scripts/setup-native.sh` installs both) on
//! the committed frames in `tests/data/gr00t_image/` (written once by `make_images.py` there).
//!
//! Per frame: pir2's transform of the decoded frame must equal the reference image to within
//! one `u8` step (1/255) on every value, and `preprocess_image` must give that image
//! normalised as the VLM processor does (`(x/255 − 0.5)/0.5`, CHW). Both settings of
//! `image.letterbox`: on (GR00T N1.7's pipeline, which always pads; the default) and off (the
//! same calls without the pad: a non-square frame stays non-square, which `preprocess_image`
//! refuses by name, and a square frame gives the same image as with the pad).
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};
use std::process::Command;

use pir2_backends::gr00t::image::{gr00t_n17_transform, Rgb};
use pir2_backends::gr00t::testing::python_from_env;
use pir2_backends::gr00t::{preprocess_image, ImageConfig};

fn tests_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests")
}

/// Run the reference on `png`; returns (input frame, reference output).
fn reference(png: &str, edge: usize, fraction: f64, letterbox: bool) -> (Rgb, Rgb) {
    let out = std::env::temp_dir().join(format!(
        "pir2-gr00t-image-{}-{png}-{edge}-{letterbox}",
        std::process::id()
    ));
    let o = Command::new(python_from_env().unwrap())
        .arg(tests_dir().join("gr00t_image_reference.py"))
        .arg(
            tests_dir()
                .join("data/gr00t_image")
                .join(format!("{png}.png")),
        )
        .arg(&out)
        .arg(edge.to_string())
        .arg(fraction.to_string())
        .arg(if letterbox { "1" } else { "0" })
        .output()
        .expect("running the Python reference");
    assert!(
        o.status.success(),
        "reference failed (albumentations and opencv-python-headless installed? \
         scripts/setup-native.sh): {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let meta: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let shape = |k: &str| {
        let v = meta[k].as_array().unwrap();
        (
            v[0].as_u64().unwrap() as usize,
            v[1].as_u64().unwrap() as usize,
        )
    };
    let read = |name: &str, (h, w): (usize, usize)| {
        Rgb::new(h, w, std::fs::read(out.join(name)).unwrap()).unwrap()
    };
    let r = (
        read("input.rgb", shape("input")),
        read("output.rgb", shape("output")),
    );
    std::fs::remove_dir_all(&out).ok();
    r
}

/// pir2's transform against the reference; returns the reference output.
fn compare(png: &str, edge: usize, fraction: f64, letterbox: bool) -> (Rgb, Rgb) {
    let (input, want) = reference(png, edge, fraction, letterbox);
    let got = gr00t_n17_transform(&input, letterbox, edge, fraction).unwrap();
    assert_eq!(
        (got.h, got.w),
        (want.h, want.w),
        "{png} letterbox {letterbox}"
    );
    let diffs: Vec<u8> = got
        .data
        .iter()
        .zip(&want.data)
        .map(|(a, b)| a.abs_diff(*b))
        .collect();
    let max = *diffs.iter().max().unwrap();
    let off = diffs.iter().filter(|&&d| d > 0).count();
    eprintln!(
        "{png} edge {edge} fraction {fraction} letterbox {letterbox}: {}×{}, max |Δ| = {max}, \
         {off} of {} values differ",
        want.w,
        want.h,
        diffs.len()
    );
    assert!(max <= 1, "{png}: max |Δ| = {max} u8 steps");
    // Within one step, and almost everywhere exact.
    assert!(off * 100 <= diffs.len(), "{png}: {off} values differ");
    (input, want)
}

#[test]
fn the_transform_matches_albumentations_and_opencv_within_one_step() {
    for (png, edge, fraction) in [
        ("wide_640x480", 256, 0.95),
        ("tall_360x480", 256, 0.95),
        ("small_200x150", 256, 0.95),
        ("square_512", 256, 0.95),
        ("wide_640x480", 224, 0.9),
    ] {
        let (input, want) = compare(png, edge, fraction, true);

        // preprocess_image = that image, normalised, CHW (letterbox explicitly on, as by
        // default).
        let cfg = ImageConfig {
            letterbox: true,
            shortest_edge: edge,
            crop_fraction: fraction,
            ..ImageConfig::default()
        };
        let mut px = Vec::new();
        preprocess_image(&input.data, (input.h, input.w), &cfg, &mut px).unwrap();
        let n = edge * edge;
        assert_eq!(px.len(), 3 * n);
        for (i, rgb) in want.data.chunks_exact(3).enumerate() {
            for c in 0..3 {
                let r = (f32::from(rgb[c]) / 255.0 - 0.5) / 0.5;
                assert!(
                    (px[c * n + i] - r).abs() <= 2.0 / 255.0 + 1e-6,
                    "{png}: channel {c} pixel {i}: {} vs {r}",
                    px[c * n + i]
                );
            }
        }
    }
}

#[test]
fn without_the_letterbox_the_transform_matches_the_same_calls_minus_the_pad() {
    assert!(
        ImageConfig::default().letterbox,
        "GR00T N1.7 always letterboxes"
    );
    for (png, edge, fraction, hw) in [
        // 640×480 → 341×256 → crop 323×243 → 340×256 (what GR00T's VLM would receive if
        // the pad were left out).
        ("wide_640x480", 256, 0.95, (256, 340)),
        ("tall_360x480", 256, 0.95, (340, 256)),
        ("small_200x150", 256, 0.95, (256, 340)),
        ("square_512", 256, 0.95, (256, 256)),
        ("wide_640x480", 224, 0.9, (224, 300)),
    ] {
        let (input, want) = compare(png, edge, fraction, false);
        assert_eq!((want.h, want.w), hw, "{png}");
        let cfg = ImageConfig {
            letterbox: false,
            shortest_edge: edge,
            crop_fraction: fraction,
            ..ImageConfig::default()
        };
        let mut px = Vec::new();
        let r = preprocess_image(&input.data, (input.h, input.w), &cfg, &mut px);
        if input.h == input.w {
            // The pad is the identity on a square frame: the same input as with it.
            r.unwrap();
            let mut with = Vec::new();
            let on = ImageConfig {
                letterbox: true,
                ..cfg.clone()
            };
            preprocess_image(&input.data, (input.h, input.w), &on, &mut with).unwrap();
            assert_eq!(px, with, "{png}");
        } else {
            let e = r.unwrap_err().to_string();
            assert!(
                e.contains("image.letterbox") && e.contains("letter_box_transform"),
                "{e}"
            );
        }
    }
}
