//! Test support: a tiny synthetic GR00T checkpoint and a synthetic camera.
//!
//! [`write_tiny_checkpoint`] writes a checkpoint directory whose ONNX graphs have the export
//! contract's exact input/output names and shapes but tiny sizes (`D_in` = [`D_IN`], `D_vl` =
//! [`D_VL`], `T` = [`TOKENS`], crop 16, `H` = 50); the graphs are small random maps made by
//! the embedded `make_graphs.py` ([`MAKE_GRAPHS_PY`]) with a Python that has `onnx`
//! (`$PIR2_PYTHON` after `source .native/env.sh`). They are not GR00T: they exist so the
//! stack (contract checks, action head, backbone, the real-time driver, the CLI) can be run end
//! to end without weights. Used by `pir2-backends/tests/gr00t.rs` and the `pir2-cli` tests.
//! [`add_bpe_tokenizer`] gives such a checkpoint a small BPE `tokenizer.json` (the format of
//! GR00T's VLM tokenizer) in place of its `vocab.txt`. [`write_split_backbone`] replaces its
//! fused `backbone.onnx` with stand-ins of GR00T's split export (`vit_fp32.onnx`,
//! `llm_fp32.onnx`, the token table in `model.safetensors`) and writes their fused
//! composition next to them.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::{Clock, SlowFrame, SlowSource, View};

use super::config::{CheckpointFiles, EmbodimentConfig};
use super::tokenizer::build_sequence;
use super::weights::{write_f32, DELAY_EMBEDDING, POSITION_EMBEDDING};
use crate::error::{Error, Result};

/// `D_in` of the synthetic graphs (action-token width).
pub const D_IN: usize = 32;
/// `D_vl` of the synthetic backbone (feature width).
pub const D_VL: usize = 24;
/// Backbone tokens `T` of the tiny embodiment (4 image + 4 text).
pub const TOKENS: usize = 8;
/// The graph generator (`make_graphs.py OUTDIR [VARIANT]`).
pub const MAKE_GRAPHS_PY: &str = include_str!("make_graphs.py");
/// Vocabulary of the synthetic checkpoint (covers the paper's four prompts).
pub const VOCAB: &str = "<pad>\n<unk>\n<image>\ncatch\nthe\nbook\nput\nin\nbasket\nbox\nbooks\n\
                         ball\nbowl\nand\non\ncutting\nboard\nthem\n";

/// A small byte-level BPE `tokenizer.json` shaped like the Qwen3-VL tokenizer of GR00T
/// N1.7's VLM (NFC, regex split with look-ahead, byte-level mapping, the chat template's
/// special tokens after the 400 learned ones), trained by [`BPE_FIXTURE_PY`].
pub const BPE_TOKENIZER_JSON: &str = include_str!("testdata/tokenizer.json");
/// Its `tokenizer_config.json` (pad token and a Jinja chat template, for the Python reference).
pub const BPE_TOKENIZER_CONFIG: &str = include_str!("testdata/tokenizer_config.json");
/// The script that trained the BPE fixture and computes the Python reference ids
/// (`bpe_fixture.py train OUTDIR` / `bpe_fixture.py encode DIR`, with `tokenizers` and
/// `jinja2` from PyPI).
pub const BPE_FIXTURE_PY: &str = include_str!("testdata/bpe_fixture.py");
/// `prompt.text_tokens` of the tiny embodiment once it has the BPE tokenizer: room for the
/// chat template and the paper's prompts.
pub const BPE_TEXT_TOKENS: usize = 24;

/// Give the synthetic checkpoint in `dir` the BPE tokenizer: writes [`BPE_TOKENIZER_JSON`]
/// as `tokenizer.json` (used instead of `vocab.txt` from then on) and
/// [`BPE_TOKENIZER_CONFIG`], and sets `prompt.text_tokens` of its `embodiment.toml` to
/// [`BPE_TEXT_TOKENS`].
pub fn add_bpe_tokenizer(dir: &Path) -> Result<()> {
    let write = |name: &str, text: &str| {
        let p = dir.join(name);
        std::fs::write(&p, text).map_err(io("writing", &p))
    };
    write("tokenizer.json", BPE_TOKENIZER_JSON)?;
    write("tokenizer_config.json", BPE_TOKENIZER_CONFIG)?;
    let path = dir.join("embodiment.toml");
    let mut cfg = EmbodimentConfig::load(&path)?;
    cfg.prompt.text_tokens = BPE_TEXT_TOKENS;
    write("embodiment.toml", &cfg.to_toml()?)
}

/// The Python interpreter with `onnx` (`$PIR2_PYTHON`, set by `.native/env.sh`).
pub fn python_from_env() -> Result<PathBuf> {
    std::env::var_os("PIR2_PYTHON")
        .map(PathBuf::from)
        .ok_or_else(|| {
            Error::Fixture(
                "PIR2_PYTHON is not set: run `source .native/env.sh` (scripts/setup-native.sh) \
                 first"
                    .into(),
            )
        })
}

/// The paper's xArm6 + XHand embodiment with a tiny image (16 px) and prompt (4 + 4 tokens).
pub fn tiny_embodiment() -> EmbodimentConfig {
    let mut c = EmbodimentConfig::xarm6_xhand();
    c.image.shortest_edge = 16;
    c.image.resize = 16;
    c.image.crop = 16;
    c.prompt.image_tokens = 4;
    c.prompt.text_tokens = 4;
    c
}

/// A GR00T `statistics.json` for `cfg` with plausible ranges, and `relative_action`
/// statistics of shape `[H, D]` for its relative action groups; `drop` (e.g.
/// `"state.fingertip_forces.min"`, `"relative_action.arm_joints.max"`) leaves one statistic
/// out.
pub fn statistics_json(cfg: &EmbodimentConfig, drop: Option<&str>) -> String {
    let mut emb = serde_json::Map::new();
    for (m, groups) in [("state", &cfg.state), ("action", &cfg.action)] {
        let mut gm = serde_json::Map::new();
        for g in groups.iter() {
            let (lo, hi) = match (m, g.name.as_str()) {
                ("action", "arm_joints") => (-0.1, 0.1),
                ("action", _) => (0.2, 0.6),
                (_, "hand_torques") => (-300.0, 300.0),
                (_, "fingertip_forces") => (-20.0, 20.0),
                _ => (-3.2, 3.2),
            };
            let mut s = serde_json::Map::new();
            for (k, v) in [("min", lo), ("max", hi), ("mean", 0.0), ("std", 1.0)] {
                if drop == Some(&format!("{m}.{}.{k}", g.name)) {
                    continue;
                }
                s.insert(k.into(), serde_json::json!(vec![v; g.dim]));
            }
            gm.insert(g.name.clone(), s.into());
        }
        emb.insert(m.into(), gm.into());
    }
    // Relative groups: per chunk slot, widening with the slot (2 mrad per slot).
    let mut rel = serde_json::Map::new();
    for g in cfg.action.iter().filter(|g| g.relative) {
        let row = |p: usize, sign: f64| vec![sign * 0.002 * (p + 1) as f64; g.dim];
        let table = |sign: f64| (0..cfg.horizon).map(|p| row(p, sign)).collect::<Vec<_>>();
        let mut s = serde_json::Map::new();
        for (k, v) in [
            ("min", table(-1.0)),
            ("max", table(1.0)),
            ("mean", table(0.0)),
            ("std", table(0.5)),
        ] {
            if drop != Some(&format!("relative_action.{}.{k}", g.name)) {
                s.insert(k.into(), serde_json::json!(v));
            }
        }
        rel.insert(g.name.clone(), s.into());
    }
    if !rel.is_empty() {
        emb.insert("relative_action".into(), rel.into());
    }
    serde_json::json!({ &cfg.embodiment_tag: emb }).to_string()
}

/// Make the action groups `groups` of the checkpoint in `dir` relative to the state groups
/// of the same name: rewrites its `embodiment.toml` and its `statistics.json` (with
/// per-slot `relative_action` statistics, see [`statistics_json`]).
pub fn make_relative(dir: &Path, groups: &[&str]) -> Result<()> {
    let path = dir.join("embodiment.toml");
    let mut cfg = EmbodimentConfig::load(&path)?;
    for g in cfg.action.iter_mut() {
        g.relative = groups.contains(&g.name.as_str());
    }
    cfg.validate()?;
    let write = |name: &str, text: String| {
        let p = dir.join(name);
        std::fs::write(&p, text).map_err(io("writing", &p))
    };
    write("embodiment.toml", cfg.to_toml()?)?;
    write("statistics.json", statistics_json(&cfg, None))
}

fn io<'a>(what: &'a str, path: &'a Path) -> impl FnOnce(std::io::Error) -> Error + 'a {
    move |e| Error::Fixture(format!("{what} `{}`: {e}", path.display()))
}

/// Write a tiny synthetic checkpoint into `dir` (created if missing): `onnx/*.onnx` made by
/// [`MAKE_GRAPHS_PY`] with `python` (`variant` = `""`, or one of `wrong_name`, `wrong_rank`,
/// `wrong_dim`, `wrong_type` to break one graph), `embodiment.toml` ([`tiny_embodiment`]),
/// `statistics.json`, `embodiment_id.json` (slot 3), `pir2_gr00t.safetensors` (zero delay
/// table, a small position embedding, identity `vlln`) and `vocab.txt`.
pub fn write_tiny_checkpoint(dir: &Path, variant: &str, python: &Path) -> Result<()> {
    write_tiny_checkpoint_with_width(dir, variant, D_VL, python)
}

/// [`write_tiny_checkpoint`] with backbone width `d_vl` in place of [`D_VL`] (every graph
/// and the `vlln` side weights), e.g. to match the `D_vl` of a training fixture's head.
pub fn write_tiny_checkpoint_with_width(
    dir: &Path,
    variant: &str,
    d_vl: usize,
    python: &Path,
) -> Result<()> {
    let onnx = dir.join("onnx");
    std::fs::create_dir_all(&onnx).map_err(io("creating", &onnx))?;
    let script = dir.join("make_graphs.py");
    std::fs::write(&script, MAKE_GRAPHS_PY).map_err(io("writing", &script))?;
    let out = std::process::Command::new(python)
        .arg(&script)
        .arg(&onnx)
        .arg(variant)
        .arg(d_vl.to_string())
        .output()
        .map_err(|e| Error::Fixture(format!("cannot run `{}`: {e}", python.display())))?;
    let _ = std::fs::remove_file(&script);
    if !out.status.success() {
        return Err(Error::Fixture(format!(
            "make_graphs.py failed ({}): {}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        )));
    }
    let cfg = tiny_embodiment();
    let write = |name: &str, text: String| {
        let p = dir.join(name);
        std::fs::write(&p, text).map_err(io("writing", &p))
    };
    write("embodiment.toml", cfg.to_toml()?)?;
    write("statistics.json", statistics_json(&cfg, None))?;
    write("embodiment_id.json", r#"{"new_embodiment": 3}"#.into())?;
    write("vocab.txt", VOCAB.into())?;
    let pos: Vec<f32> = (0..64 * D_IN)
        .map(|i| ((i % 7) as f32 - 3.0) * 0.01)
        .collect();
    write_f32(
        &dir.join("pir2_gr00t.safetensors"),
        &[
            (
                DELAY_EMBEDDING,
                vec![cfg.d_vis_max + 1, D_IN],
                vec![0.0; (cfg.d_vis_max + 1) * D_IN],
            ),
            (POSITION_EMBEDDING, vec![64, D_IN], pos),
            ("vlln.weight", vec![d_vl], vec![1.0; d_vl]),
            ("vlln.bias", vec![d_vl], vec![0.0; d_vl]),
        ],
    )
}

/// The split-backbone generator (`make_split_backbone.py SPEC.json OUTDIR [VARIANT]`).
pub const MAKE_SPLIT_BACKBONE_PY: &str = include_str!("make_split_backbone.py");

/// Rows of the synthetic token-embedding table (covers the BPE fixture's ids).
pub const SPLIT_VOCAB: usize = 512;

/// Give the tiny checkpoint in `dir` stand-ins of GR00T's split backbone export for the
/// prompt `prompt` (its embodiment, tokenizer and `vision` section as they are in `dir`):
/// `onnx/vit_fp32.onnx`, `onnx/llm_fp32.onnx` and `model.safetensors` (the token table under
/// `vision.embed_tokens_key`), made by [`MAKE_SPLIT_BACKBONE_PY`] with `python`; removes
/// `onnx/backbone.onnx` and writes the fused composition of the stand-ins, for that prompt's
/// sequence, as `fused_backbone.onnx` in `dir` (move it to `onnx/backbone.onnx` for a fused
/// checkpoint). `variant` (comma-separated; see the script) changes the stand-ins:
/// `wrong_name` / `wrong_width` break the LLM, `llm_bf16` / `vit_bf16` write GR00T's bfloat16
/// files (`llm_bf16.onnx`, `vit_bf16.onnx`: bfloat16 float tensors at the boundary, the same
/// float32 maps inside), `llm_f16` a float16 LLM still named `llm_fp32.onnx`, `llm_f64` a
/// float64 `inputs_embeds`, `llm_bf16_matmul` a bfloat16 MatMul inside. Returns the
/// multimodal positions of the sequence by the generator's Python transcription of the
/// public rule, `[3][T]`.
pub fn write_split_backbone(
    dir: &Path,
    prompt: &str,
    variant: &str,
    python: &Path,
) -> Result<Vec<Vec<i64>>> {
    let files = CheckpointFiles::in_dir(dir);
    let cfg = files.embodiment_config()?;
    let tok = super::tokenizer::load_tokenizer(&files, &cfg.prompt)?;
    let seq = build_sequence(tok.as_ref(), cfg.prompt_for(prompt), &cfg.prompt)?;
    let vision_start = match tok.chat_template() {
        Some(chat) => match tok.encode(&chat.image_begin)?[..] {
            [id] => Some(id),
            _ => None,
        },
        None => None,
    };
    let spec = serde_json::json!({
        "ids": seq.ids,
        "attention": seq.attention,
        "image_token": tok.image_token_id(),
        "vision_start": vision_start,
        "views": cfg.prompt.chat.images,
        "side": cfg.image.pixel_side(),
        "patch": cfg.vision.patch_size,
        "temporal": cfg.vision.temporal_patch_size,
        "merge": cfg.vision.merge_size,
        "d": D_VL,
        "image_tokens": cfg.prompt.image_tokens,
        "vocab": SPLIT_VOCAB,
        "key": cfg.vision.embed_tokens_key,
    });
    let spec_path = dir.join("split_spec.json");
    std::fs::write(&spec_path, spec.to_string()).map_err(io("writing", &spec_path))?;
    let script = dir.join("make_split_backbone.py");
    std::fs::write(&script, MAKE_SPLIT_BACKBONE_PY).map_err(io("writing", &script))?;
    let out = std::process::Command::new(python)
        .arg(&script)
        .arg(&spec_path)
        .arg(dir)
        .arg(variant)
        .output()
        .map_err(|e| Error::Fixture(format!("cannot run `{}`: {e}", python.display())))?;
    let _ = std::fs::remove_file(&script);
    let _ = std::fs::remove_file(&spec_path);
    if !out.status.success() {
        return Err(Error::Fixture(format!(
            "make_split_backbone.py failed ({}): {}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        )));
    }
    let _ = std::fs::remove_file(&files.backbone);
    let pos_path = dir.join("position_ids.json");
    let text = std::fs::read_to_string(&pos_path).map_err(io("reading", &pos_path))?;
    serde_json::from_str(&text).map_err(|e| Error::Fixture(format!("position_ids.json: {e}")))
}

/// A synthetic 640×480 RGB camera: a horizontal gradient whose brightness changes every
/// frame, one frame per `period`, stamped on `clock`, with one image per view (each view's
/// gradient offset differently). Stands in for the cameras in tests and in
/// `pir2 gr00t run … --emulate`.
pub struct SyntheticCamera {
    clock: Arc<dyn Clock>,
    period: Duration,
    views: usize,
    frames: Arc<AtomicU64>,
}

impl std::fmt::Debug for SyntheticCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SyntheticCamera")
            .field("period", &self.period)
            .field("frames", &self.frames.load(Ordering::Relaxed))
            .finish()
    }
}

impl SyntheticCamera {
    /// A camera producing one frame (one view) per `period`.
    pub fn new(clock: Arc<dyn Clock>, period: Duration) -> Self {
        Self::with_views(clock, period, 1)
    }

    /// A camera producing one frame of `views` images per `period`.
    pub fn with_views(clock: Arc<dyn Clock>, period: Duration, views: usize) -> Self {
        Self {
            clock,
            period,
            views,
            frames: Arc::new(AtomicU64::new(0)),
        }
    }

    /// The frame counter (shared; keep it before handing the camera to a run).
    pub fn frames(&self) -> Arc<AtomicU64> {
        self.frames.clone()
    }
}

#[async_trait::async_trait]
impl SlowSource for SyntheticCamera {
    async fn capture(&mut self) -> pir2_runtime::Result<SlowFrame> {
        std::thread::sleep(self.period);
        let k = self.frames.fetch_add(1, Ordering::Relaxed);
        let (h, w) = (480, 640);
        let views = (0..self.views as u64)
            .map(|v| {
                let mut image = vec![0u8; h * w * 3];
                for (i, px) in image.iter_mut().enumerate() {
                    *px = ((i / 3 % w) as u64 * 255 / w as u64 + k * 40 + v * 97) as u8;
                }
                View { image, hw: (h, w) }
            })
            .collect();
        Ok(SlowFrame {
            t_capture: self.clock.now(),
            views,
            ..Default::default()
        })
    }
}
