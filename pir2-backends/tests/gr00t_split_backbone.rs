//! The backbone from GR00T's own split export (`vit_fp32.onnx` + `llm_fp32.onnx` + the token
//! table in `model.safetensors`), glued in Rust, against the fused composition of the same
//! maps (`pir2_backends::gr00t::testing::write_split_backbone`: tiny stand-ins with the
//! export's input/output names, made with `$PIR2_PYTHON` after `source .native/env.sh`).
//!
//! The fused graph does the glue as ONNX ops (patching, embedding lookup, image-token
//! scatter) and holds the multimodal positions computed in Python by the public rule, so a
//! wrong patch order, scatter order, position id or deepstack wiring on the Rust side makes
//! the two differ.
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};

use pir2_backends::gr00t::testing::{
    add_bpe_tokenizer, python_from_env, write_split_backbone, write_tiny_checkpoint, D_VL,
};
use pir2_backends::gr00t::{
    load_tokenizer, CheckpointFiles, EmbodimentConfig, Gr00tBackbone, EMBED_TOKENS_KEY,
};
use pir2_backends::ort::OrtOptions;
use pir2_backends::Error;
use pir2_runtime::View;

const PROMPT: &str = "Catch the book!";

/// A tiny checkpoint with the BPE tokenizer, two 16-px camera views cut into 4-px patches
/// merged 2×2 (4 tokens per view), and the split backbone stand-ins (`variant` breaks the
/// LLM); `edit` changes the embodiment before the graphs are made.
fn split_fixture(
    name: &str,
    variant: &str,
    edit: impl FnOnce(&mut EmbodimentConfig),
) -> (PathBuf, Vec<Vec<i64>>) {
    let dir = std::env::temp_dir().join(format!("pir2-gr00t-split-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let python = python_from_env().unwrap();
    write_tiny_checkpoint(&dir, "", &python).unwrap();
    add_bpe_tokenizer(&dir).unwrap();
    let path = dir.join("embodiment.toml");
    let mut cfg = EmbodimentConfig::load(&path).unwrap();
    cfg.prompt.chat.images = 2;
    cfg.prompt.image_tokens = 8;
    cfg.vision.patch_size = 4;
    cfg.vision.temporal_patch_size = 2;
    cfg.vision.merge_size = 2;
    edit(&mut cfg);
    std::fs::write(&path, cfg.to_toml().unwrap()).unwrap();
    let pos = write_split_backbone(&dir, PROMPT, variant, &python).unwrap();
    (dir, pos)
}

/// A copy of the split checkpoint `dir` as a fused one: `fused_backbone.onnx` becomes
/// `onnx/backbone.onnx`, the split files are left out.
fn fused_copy(dir: &Path, name: &str) -> PathBuf {
    let out = dir.with_file_name(format!(
        "{}-{name}",
        dir.file_name().unwrap().to_string_lossy()
    ));
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(out.join("onnx")).unwrap();
    for f in std::fs::read_dir(dir).unwrap() {
        let p = f.unwrap().path();
        let n = p.file_name().unwrap().to_string_lossy().to_string();
        if p.is_file() && n != "model.safetensors" && n != "fused_backbone.onnx" {
            std::fs::copy(&p, out.join(&n)).unwrap();
        }
    }
    for f in std::fs::read_dir(dir.join("onnx")).unwrap() {
        let p = f.unwrap().path();
        let n = p.file_name().unwrap().to_string_lossy().to_string();
        if !n.starts_with("vit_") && !n.starts_with("llm_") {
            std::fs::copy(&p, out.join("onnx").join(&n)).unwrap();
        }
    }
    std::fs::copy(
        dir.join("fused_backbone.onnx"),
        out.join("onnx/backbone.onnx"),
    )
    .unwrap();
    out
}

fn load(dir: &Path) -> pir2_backends::Result<Gr00tBackbone> {
    let files = CheckpointFiles::in_dir(dir);
    let cfg = files.embodiment_config()?;
    let tok = load_tokenizer(&files, &cfg.prompt)?;
    Gr00tBackbone::load(
        &files,
        &cfg.image,
        &cfg.prompt,
        &cfg.vision,
        tok.as_ref(),
        PROMPT,
        Some((D_VL, PathBuf::from("dit.onnx"))),
        &OrtOptions::default(),
    )
}

fn views() -> [View; 2] {
    let view = |v: u8, (h, w): (usize, usize)| View {
        image: (0..h * w * 3)
            .map(|i| v.wrapping_add((i % 251) as u8).wrapping_mul(3))
            .collect(),
        hw: (h, w),
    };
    [view(10, (48, 64)), view(90, (32, 32))]
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn split_backbone_equals_the_fused_composition() {
    let (dir, py_pos) = split_fixture("equal", "", |_| {});
    let fused_dir = fused_copy(&dir, "fused");
    let mut split = load(&dir).unwrap();
    let mut fused = load(&fused_dir).unwrap();
    assert!(split.is_split() && !fused.is_split());
    // The positions fed to the LLM are those of the public rule (Python), and they are not
    // plain text positions (the images are 2×2 grids).
    let t = split.sequence().ids.len();
    assert_eq!(split.position_ids().unwrap(), py_pos.concat().as_slice());
    assert_ne!(py_pos[1], py_pos[2], "image tokens carry 2-D positions");
    let frame = views();
    let a = split.encode_views(&frame).unwrap().to_vec();
    let b = fused.encode_views(&frame).unwrap().to_vec();
    assert_eq!(a.len(), t * D_VL);
    let d = max_diff(&a, &b);
    assert!(d < 1e-4, "split and fused backbones differ by {d}");
    // The two views are distinguished: swapping them changes the features.
    let swapped = [frame[1].clone(), frame[0].clone()];
    let c = split.encode_views(&swapped).unwrap().to_vec();
    assert!(max_diff(&a, &c) > 1e-2, "view order reaches the features");
    // A sharded checkpoint: the index names the shard holding the table.
    std::fs::rename(
        dir.join("model.safetensors"),
        dir.join("model-00002-of-00002.safetensors"),
    )
    .unwrap();
    let key = EMBED_TOKENS_KEY;
    let index = serde_json::json!({
        "metadata": {},
        "weight_map": { key: "model-00002-of-00002.safetensors",
                        "action_head.vlln.bias": "model-00001-of-00002.safetensors" },
    });
    std::fs::write(dir.join("model.safetensors.index.json"), index.to_string()).unwrap();
    let mut sharded = load(&dir).unwrap();
    let e = sharded.encode_views(&frame).unwrap().to_vec();
    assert_eq!(e, a);
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&fused_dir).ok();
}

/// `set_prompt` (a new task for an already loaded backbone, as `pir2 gr00t features` does
/// between episodes) gives bit for bit what a backbone loaded with that prompt gives: the
/// split form re-reads the token-table rows and recomputes the positions.
#[test]
fn a_new_prompt_equals_a_backbone_loaded_with_it() {
    let (dir, _) = split_fixture("prompt", "", |_| {});
    let files = CheckpointFiles::in_dir(&dir);
    let cfg = files.embodiment_config().unwrap();
    let tok = load_tokenizer(&files, &cfg.prompt).unwrap();
    let other = "Put the ball in the bowl";
    let load_with = |prompt: &str| {
        Gr00tBackbone::load(
            &files,
            &cfg.image,
            &cfg.prompt,
            &cfg.vision,
            tok.as_ref(),
            prompt,
            None,
            &OrtOptions::default(),
        )
        .unwrap()
    };
    let frame = views();
    let px: Vec<(&[u8], (usize, usize))> =
        frame.iter().map(|v| (v.image.as_slice(), v.hw)).collect();
    let mut bb = load_with(PROMPT);
    assert!(bb.is_split());
    let a = bb.backbone_embeddings(&px).unwrap().to_vec();
    let mut fresh = load_with(other);
    let want = fresh.backbone_embeddings(&px).unwrap().to_vec();
    bb.set_prompt(&files, &cfg.prompt, tok.as_ref(), other)
        .unwrap();
    assert_eq!(bb.sequence(), fresh.sequence());
    assert_eq!(bb.position_ids(), fresh.position_ids());
    let b = bb.backbone_embeddings(&px).unwrap().to_vec();
    assert!(
        b.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits()),
        "set_prompt differs from a fresh load"
    );
    assert!(max_diff(&a, &b) > 1e-3, "the prompt reaches the features");
    bb.set_prompt(&files, &cfg.prompt, tok.as_ref(), PROMPT)
        .unwrap();
    assert_eq!(bb.backbone_embeddings(&px).unwrap(), a.as_slice());
    // The deployment output is the backbone's with vlln and the VL self-attention on top.
    let deployed = bb.encode_views(&frame).unwrap().to_vec();
    assert_eq!(deployed.len(), a.len());
    assert!(max_diff(&deployed, &a) > 1e-3);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn backbone_file_sets_are_one_form_or_one_error() {
    let (dir, _) = split_fixture("files", "", |_| {});
    let files = CheckpointFiles::in_dir(&dir);
    // Both forms: one error naming the three graphs.
    std::fs::copy(dir.join("fused_backbone.onnx"), &files.backbone).unwrap();
    let e = load(&dir).unwrap_err();
    assert!(matches!(e, Error::BackboneFiles { .. }), "{e}");
    let e = e.to_string();
    assert!(
        e.contains("backbone.onnx") && e.contains("vit_fp32.onnx") && e.contains("llm_fp32.onnx"),
        "{e}"
    );
    std::fs::remove_file(&files.backbone).unwrap();
    // Half a split set: the missing file is named.
    let llm = dir.join("onnx/llm_fp32.onnx");
    std::fs::rename(&llm, dir.join("llm.bak")).unwrap();
    let e = load(&dir).unwrap_err().to_string();
    assert!(e.contains("llm_fp32.onnx") && e.contains("missing"), "{e}");
    std::fs::rename(dir.join("llm.bak"), &llm).unwrap();
    // No checkpoint weights: the table's files are named.
    std::fs::rename(dir.join("model.safetensors"), dir.join("m.bak")).unwrap();
    let e = load(&dir).unwrap_err().to_string();
    assert!(
        e.contains("model.safetensors") && e.contains("token-embedding"),
        "{e}"
    );
    std::fs::rename(dir.join("m.bak"), dir.join("model.safetensors")).unwrap();
    // A table name the checkpoint does not hold: file and key named.
    let path = dir.join("embodiment.toml");
    let mut cfg = EmbodimentConfig::load(&path).unwrap();
    cfg.vision.embed_tokens_key = "model.embed_tokens.weight".into();
    std::fs::write(&path, cfg.to_toml().unwrap()).unwrap();
    let e = load(&dir).unwrap_err().to_string();
    assert!(
        e.contains("model.safetensors") && e.contains("model.embed_tokens.weight"),
        "{e}"
    );
    // Patch rows of another width than the ViT takes: the file, the input and both values.
    cfg.vision = Default::default();
    cfg.vision.patch_size = 4;
    cfg.vision.temporal_patch_size = 1;
    std::fs::write(&path, cfg.to_toml().unwrap()).unwrap();
    let e = load(&dir).unwrap_err().to_string();
    assert!(
        e.contains("vit_fp32.onnx")
            && e.contains("pixel_values")
            && e.contains("96")
            && e.contains("48"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn llm_with_a_wrong_input_name_or_width_is_refused_by_name() {
    let (dir, _) = split_fixture("name", "wrong_name", |_| {});
    let e = load(&dir).unwrap_err().to_string();
    assert!(
        e.contains("llm_fp32.onnx") && e.contains("input_embeds") && e.contains("unexpected"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
    let (dir, _) = split_fixture("width", "wrong_width", |_| {});
    let e = load(&dir).unwrap_err().to_string();
    assert!(
        e.contains("llm_fp32.onnx")
            && e.contains("inputs_embeds")
            && e.contains(&format!("is {}", D_VL - 4))
            && e.contains(&format!("`D_vl` = {D_VL}")),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Replace the split stand-ins of `dir` by those of `variant` (same weights; see
/// `make_split_backbone.py`).
fn regenerate(dir: &Path, variant: &str) {
    for f in std::fs::read_dir(dir.join("onnx")).unwrap() {
        let p = f.unwrap().path();
        let n = p.file_name().unwrap().to_string_lossy().to_string();
        if n.starts_with("vit_") || n.starts_with("llm_") {
            std::fs::remove_file(p).unwrap();
        }
    }
    write_split_backbone(dir, PROMPT, variant, &python_from_env().unwrap()).unwrap();
}

/// Largest |a − b| over the largest |b| (the stand-ins' features are tanh outputs, |b| ≤ 1).
fn rel_diff(a: &[f32], b: &[f32]) -> f32 {
    max_diff(a, b) / b.iter().fold(0.0f32, |m, x| m.max(x.abs()))
}

/// GR00T's exporter writes the LLM in bfloat16 by default (`llm_bf16.onnx`: bfloat16
/// `inputs_embeds`, `deepstack_*` and `embeddings`) and the ViT so with `use_bf16=True`
/// (`vit_bf16.onnx`). pir2 takes them unchanged, converting each float tensor at the boundary
/// by its declared type: the features match the float32 composition of the same maps up to
/// bfloat16 rounding. The stand-ins compute in float32 between boundary Casts (ONNX Runtime's
/// CPU provider has no bfloat16 MatMul/Add/Tanh kernels), so the difference is the rounding
/// of the inputs (2⁻⁹ relative each) and of the output (2⁻⁹ of |y| ≤ 1), carried through four
/// tanh layers: below 2·10⁻² of the feature scale. float16 (2⁻¹¹) lands below 5·10⁻³ — and a
/// float16 file named `llm_fp32.onnx` is read as float16: the types decide, not the name.
#[test]
fn bf16_and_f16_exports_match_the_float32_composition() {
    let (dir, _) = split_fixture("bf16", "llm_bf16", |_| {});
    let fused_dir = fused_copy(&dir, "fused");
    let frame = views();
    let want = load(&fused_dir)
        .unwrap()
        .encode_views(&frame)
        .unwrap()
        .to_vec();
    for (variant, file, converted, tol) in [
        (
            "llm_bf16",
            "llm_bf16.onnx",
            "LLM inputs_embeds bfloat16",
            2e-2,
        ),
        (
            "llm_bf16,vit_bf16",
            "vit_bf16.onnx",
            "ViT pixel_values bfloat16, ViT image_embeds bfloat16",
            2e-2,
        ),
        ("llm_f16", "llm_fp32.onnx", "LLM deepstack_2 float16", 5e-3),
    ] {
        if variant != "llm_bf16" {
            regenerate(&dir, variant);
        }
        let mut bb = load(&dir).unwrap_or_else(|e| panic!("{variant}: {e}"));
        let what = bb.describe();
        assert!(
            what.contains(file) && what.contains(converted),
            "{variant}: {what}"
        );
        let got = bb.encode_views(&frame).unwrap().to_vec();
        let r = rel_diff(&got, &want);
        println!("{variant}: max |split − fused| / max |fused| = {r:.3e}");
        assert!(r < tol, "{variant}: relative difference {r} ≥ {tol}");
        assert!(
            r > 0.0,
            "{variant}: no rounding at all: the boundary is not half precision"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&fused_dir).ok();
}

/// A float input of a type pir2 does not convert (float64 `inputs_embeds`) is one error naming
/// the file, the input and the type; a bfloat16 op the provider has no kernel for is one error
/// at load naming the file, the op, the provider and the way out.
#[test]
fn unsupported_element_types_and_kernels_are_named_at_load() {
    let (dir, _) = split_fixture("types", "llm_f64", |_| {});
    let e = load(&dir).unwrap_err();
    assert!(matches!(e, Error::Gr00tContract { .. }), "{e}");
    let e = e.to_string();
    assert!(
        e.contains("llm_fp32.onnx")
            && e.contains("`inputs_embeds`")
            && e.contains("float64")
            && e.contains("bfloat16"),
        "{e}"
    );
    regenerate(&dir, "llm_bf16_matmul");
    match load(&dir) {
        Err(e @ Error::NoKernel { .. }) => {
            let e = e.to_string();
            println!("{e}");
            assert!(
                e.contains("llm_bf16.onnx")
                    && e.contains("MatMul")
                    && e.contains("CPUExecutionProvider")
                    && e.contains("--ep cuda")
                    && e.contains("use_bf16=False"),
                "{e}"
            );
        }
        // An ONNX Runtime with bfloat16 CPU kernels runs it (the MatMul is by identity).
        Ok(mut bb) => {
            let f = bb.encode_views(&views()).unwrap().to_vec();
            assert!(f.iter().all(|x| x.is_finite()));
        }
        Err(e) => panic!("not the missing-kernel error: {e}"),
    }
    std::fs::remove_dir_all(&dir).ok();
}
