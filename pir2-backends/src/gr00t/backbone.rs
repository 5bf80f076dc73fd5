//! The slow channel: camera images + prompt → backbone tokens `[T, D_vl]`.
//!
//! [`Gr00tBackbone`] implements the runtime's [`SlowEncoder`], so the real-time driver runs it
//! on its own thread (`SlowChannel::Async`) and caches its output with the frame's capture
//! time. Its pipeline:
//!
//! 1. [`preprocess_image`], for each of the frame's `V` camera views (`prompt.chat.images`,
//!    in the embodiment's view order): HWC `u8` RGB → GR00T N1.7's transform
//!    ([`super::image`]: letterbox, `INTER_AREA` resize to `image.shortest_edge`, centre crop
//!    0.95, resize back) → `(x/255 − mean)/std`, stacked → `pixel_values [V, 3, s, s]`;
//! 2. [`build_sequence`]: with the VLM's `tokenizer.json`, the prompt rendered through GR00T
//!    N1.7's chat template around the image placeholders and padded to `T` (see
//!    [`super::tokenizer`]); with a `vocab.txt`, `image_tokens` image placeholders, then the
//!    prompt's tokens padded / truncated to `text_tokens` → `input_ids [1, T]`,
//!    `attention_mask [1, T]` and the [`VlLayout`] the DiT's masks need;
//! 3. either `backbone.onnx` (ViT + LLM, fused by the user: see `docs/gr00t-contract.md`), or
//!    GR00T's own `vit_*.onnx` + `llm_*.onnx` with the glue done in Rust ([`super::split`]),
//!    picked by the files present ([`CheckpointFiles::backbone_form`]) →
//!    `embeddings [1, T, D_vl]`;
//! 4. GR00T's `vlln` LayerNorm (if the side weights carry it) and `vl_self_attention.onnx`
//!    (if present; GR00T's exporter writes it unchanged).
//!
//! The prompt is tokenised by a [`PromptTokenizer`]: [`super::tokenizer::HfTokenizer`] loads
//! the VLM's `tokenizer.json` (GR00T's own BPE tokenizer, with its chat template);
//! [`super::tokenizer::VocabTokenizer`] reads the simpler vocabulary file of older pir2
//! checkpoints.
//!
//! A remote backbone is any other [`SlowEncoder`] returning `[T, D_vl]` tokens (see
//! [`super::run::BackboneChoice::Custom`]).

use std::path::{Path, PathBuf};

use pir2_runtime::{SlowEncoder, SlowFeatures, SlowFrame, View};

use super::config::{
    BackboneForm, CheckpointFiles, ImageConfig, ImagePipeline, PromptConfig, VisionConfig,
};
use super::contract::{feed, Bindings, Graph, BACKBONE, VL_SELF_ATTENTION};
use super::image::{gr00t_n17_transform, Rgb};
use super::prompt::{PromptTokenizer, Sequence, VlLayout};
use super::split::SplitBackbone;
use super::tokenizer::build_sequence;
use super::weights::SideWeights;
use crate::error::{Error, Result};
use crate::ort::OrtOptions;

/// Preprocess an HWC `u8` RGB camera image with `cfg` (GR00T N1.7's transform by default,
/// [`super::image`]) and normalise it into `out` as CHW `f32` `[3, s, s]`,
/// `s = cfg.pixel_side()`.
pub fn preprocess_image(
    rgb: &[u8],
    (h, w): (usize, usize),
    cfg: &ImageConfig,
    out: &mut Vec<f32>,
) -> Result<()> {
    if h == 0 || w == 0 || rgb.len() != h * w * 3 {
        return Err(Error::input(
            "camera image (HWC u8 RGB)",
            format!("{h}×{w}×3 = {} bytes, non-empty", h * w * 3),
            format!("{} bytes", rgb.len()),
        ));
    }
    match cfg.pipeline {
        ImagePipeline::Gr00tN17 => {
            let img = Rgb::new(h, w, rgb.to_vec())?;
            let t = gr00t_n17_transform(&img, cfg.letterbox, cfg.shortest_edge, cfg.crop_fraction)?;
            if (t.h, t.w) != (cfg.shortest_edge, cfg.shortest_edge) {
                return Err(Error::Gr00tConfig(format!(
                    "image.letterbox = false with a non-square {w}×{h} camera frame gives a \
                     {}×{} image; GR00T N1.7 letterboxes every frame (its \
                     `letter_box_transform` setting is not read), so set image.letterbox = \
                     true (the default) whatever the checkpoint's processor_config.json says; \
                     a non-square image would need the VLM processor's own resize and another \
                     image-token count, which pir2 does not implement",
                    t.w, t.h
                )));
            }
            let (s, n) = (t.h, t.h * t.w);
            out.clear();
            out.resize(3 * n, 0.0);
            for (i, px) in t.data.chunks_exact(3).enumerate() {
                for ch in 0..3 {
                    out[ch * n + i] = (f32::from(px[ch]) / 255.0 - cfg.mean[ch]) / cfg.std[ch];
                }
            }
            let _ = s;
            Ok(())
        }
        ImagePipeline::ResizeCrop => resize_crop(rgb, (h, w), cfg, out),
    }
}

/// The `resize_crop` pipeline: bilinear resize of the shorter side to `cfg.resize`
/// (half-pixel centres), centre crop `cfg.crop`, normalise.
fn resize_crop(
    rgb: &[u8],
    (h, w): (usize, usize),
    cfg: &ImageConfig,
    out: &mut Vec<f32>,
) -> Result<()> {
    let s = cfg.resize as f32 / h.min(w) as f32;
    let (rh, rw) = (
        ((h as f32 * s).round() as usize).max(cfg.crop),
        ((w as f32 * s).round() as usize).max(cfg.crop),
    );
    let (oy, ox) = ((rh - cfg.crop) / 2, (rw - cfg.crop) / 2);
    let (sy, sx) = (h as f32 / rh as f32, w as f32 / rw as f32);
    let c = cfg.crop;
    out.clear();
    out.resize(3 * c * c, 0.0);
    for y in 0..c {
        let fy = ((y + oy) as f32 + 0.5) * sy - 0.5;
        let y0 = fy.floor().clamp(0.0, (h - 1) as f32) as usize;
        let y1 = (y0 + 1).min(h - 1);
        let wy = (fy - y0 as f32).clamp(0.0, 1.0);
        for x in 0..c {
            let fx = ((x + ox) as f32 + 0.5) * sx - 0.5;
            let x0 = fx.floor().clamp(0.0, (w - 1) as f32) as usize;
            let x1 = (x0 + 1).min(w - 1);
            let wx = (fx - x0 as f32).clamp(0.0, 1.0);
            for ch in 0..3 {
                let p = |yy: usize, xx: usize| rgb[(yy * w + xx) * 3 + ch] as f32;
                let top = p(y0, x0) * (1.0 - wx) + p(y0, x1) * wx;
                let bot = p(y1, x0) * (1.0 - wx) + p(y1, x1) * wx;
                let v = (top * (1.0 - wy) + bot * wy) / 255.0;
                out[(ch * c + y) * c + x] = (v - cfg.mean[ch]) / cfg.std[ch];
            }
        }
    }
    Ok(())
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| p.display().to_string())
}

fn layer_norm(x: &mut [f32], d: usize, w: &[f32], b: &[f32]) {
    for row in x.chunks_exact_mut(d) {
        let mean = row.iter().sum::<f32>() / d as f32;
        let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d as f32;
        let inv = 1.0 / (var + 1e-5).sqrt();
        for (j, v) in row.iter_mut().enumerate() {
            *v = (*v - mean) * inv * w[j] + b[j];
        }
    }
}

/// The ONNX graphs of the backbone: fused, or GR00T's split export.
#[derive(Debug)]
enum Core {
    Fused(Graph),
    Split(Box<SplitBackbone>),
}

/// The ONNX backbone (see the module docs).
pub struct Gr00tBackbone {
    core: Core,
    vl_self_attention: Option<Graph>,
    vlln: Option<(Vec<f32>, Vec<f32>)>,
    image: ImageConfig,
    seq: Sequence,
    d_vl: usize,
    views: usize,
    pixels: Vec<f32>,
    view_pixels: Vec<f32>,
    feats: Vec<f32>,
    encoded: u64,
}

impl std::fmt::Debug for Gr00tBackbone {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gr00tBackbone")
            .field("core", &self.core)
            .field("vl_self_attention", &self.vl_self_attention)
            .field("tokens", &self.seq.ids.len())
            .field("d_vl", &self.d_vl)
            .finish()
    }
}

impl Gr00tBackbone {
    /// The backbone of the checkpoint in `dir` for `task` (a key of the embodiment's
    /// `[tasks]`, or a prompt used verbatim): its embodiment, its tokenizer and its
    /// `backbone.onnx`, without a `D_vl` check against an action head (for a backbone served
    /// or measured on its own). Returns the backbone and the prompt it encodes.
    pub fn for_checkpoint(dir: &Path, task: &str, opts: &OrtOptions) -> Result<(Self, String)> {
        let files = CheckpointFiles::in_dir(dir);
        let cfg = files.embodiment_config()?;
        let prompt = cfg.prompt_for(task).to_string();
        let tok = super::tokenizer::load_tokenizer(&files, &cfg.prompt)?;
        let bb = Self::load(
            &files,
            &cfg.image,
            &cfg.prompt,
            &cfg.vision,
            tok.as_ref(),
            &prompt,
            None,
            opts,
        )?;
        Ok((bb, prompt))
    }

    /// Load the backbone graphs — `backbone.onnx`, or GR00T's split `vit_*.onnx` +
    /// `llm_*.onnx` with the checkpoint's token-embedding table (`vision` says how; see
    /// [`CheckpointFiles::backbone_form`]) — (+ `vl_self_attention.onnx` if it exists, +
    /// `vlln` from the side weights if present) and tokenise `prompt`. `d_vl`, when given
    /// (the DiT's `D_vl`), must match the files.
    #[allow(clippy::too_many_arguments)]
    pub fn load(
        files: &CheckpointFiles,
        image: &ImageConfig,
        prompt_cfg: &PromptConfig,
        vision: &VisionConfig,
        tokenizer: &dyn PromptTokenizer,
        prompt: &str,
        d_vl: Option<(usize, PathBuf)>,
        opts: &OrtOptions,
    ) -> Result<Self> {
        let seq = build_sequence(tokenizer, prompt, prompt_cfg)?;
        let mut b = Bindings::default();
        b.bind(
            "crop",
            image.pixel_side(),
            "<embodiment config: image side (shortest_edge, or crop with resize_crop)>",
        );
        b.bind(
            "T",
            seq.ids.len(),
            "<embodiment config: prompt.image_tokens + text_tokens>",
        );
        b.bind(
            "images",
            prompt_cfg.chat.images,
            "<embodiment config: prompt.chat.images (camera views)>",
        );
        if let Some((d, src)) = d_vl {
            b.bind("D_vl", d, src);
        }
        let core = match files.backbone_form()? {
            BackboneForm::Fused => {
                Core::Fused(Graph::load(&files.backbone, BACKBONE, opts, &mut b)?)
            }
            BackboneForm::Split => Core::Split(Box::new(SplitBackbone::load(
                files, image, prompt_cfg, vision, tokenizer, &seq, &mut b, opts,
            )?)),
        };
        let vl_self_attention = if files.vl_self_attention.exists() {
            Some(Graph::load(
                &files.vl_self_attention,
                VL_SELF_ATTENTION,
                opts,
                &mut b,
            )?)
        } else {
            None
        };
        let d_vl = b.get("D_vl").expect("bound by the contract check");
        let vlln = if files.weights.exists() {
            SideWeights::load(&files.weights)?.vlln(d_vl)?
        } else {
            None
        };
        Ok(Gr00tBackbone {
            core,
            vl_self_attention,
            vlln,
            image: image.clone(),
            seq,
            d_vl,
            views: prompt_cfg.chat.images,
            pixels: Vec::new(),
            view_pixels: Vec::new(),
            feats: Vec::new(),
            encoded: 0,
        })
    }

    /// Encode `prompt` from now on (another task): the sequence is rebuilt with `tokenizer`
    /// and `prompt_cfg` (the ones it was loaded with), and a split backbone reads the new
    /// prompt's rows of the token table from `files`. The graphs stay loaded; `T` cannot
    /// change (it is `image_tokens + text_tokens`).
    pub fn set_prompt(
        &mut self,
        files: &CheckpointFiles,
        prompt_cfg: &PromptConfig,
        tokenizer: &dyn PromptTokenizer,
        prompt: &str,
    ) -> Result<()> {
        let seq = build_sequence(tokenizer, prompt, prompt_cfg)?;
        if seq.ids.len() != self.seq.ids.len() {
            return Err(Error::input(
                format!("the token count T of prompt {prompt:?}"),
                self.seq.ids.len(),
                seq.ids.len(),
            ));
        }
        if let Core::Split(s) = &mut self.core {
            s.set_sequence(files, tokenizer, &seq)?;
        }
        self.seq = seq;
        Ok(())
    }

    /// The token layout of this backbone's output.
    pub fn layout(&self) -> &VlLayout {
        &self.seq.layout
    }

    /// The tokenised prompt.
    pub fn sequence(&self) -> &Sequence {
        &self.seq
    }

    /// Tokens `T` and width `D_vl` of the output.
    pub fn output_shape(&self) -> (usize, usize) {
        (self.seq.ids.len(), self.d_vl)
    }

    /// Frames encoded so far.
    pub fn encoded(&self) -> u64 {
        self.encoded
    }

    /// Camera views each frame must carry (`prompt.chat.images`).
    pub fn views(&self) -> usize {
        self.views
    }

    /// Encode one image (HWC `u8` RGB) into `[T, D_vl]` tokens (a one-view backbone).
    pub fn encode_image(&mut self, rgb: &[u8], hw: (usize, usize)) -> Result<&[f32]> {
        self.encode(std::iter::once((rgb, hw)))
    }

    /// Encode the camera views of one frame (HWC `u8` RGB each, in the embodiment's view
    /// order) into `[T, D_vl]` tokens: each view is preprocessed on its own and the backbone
    /// gets them stacked as `pixel_values` `[V, 3, s, s]`. A frame with another number of
    /// views than the prompt's image blocks is one error naming both.
    pub fn encode_views(&mut self, views: &[View]) -> Result<&[f32]> {
        self.encode(views.iter().map(|v| (v.image.as_slice(), v.hw)))
    }

    /// The backbone's own output for the camera views of one frame (HWC `u8` RGB each, in
    /// the embodiment's view order): `[T, D_vl]`, the ViT + LLM features **before** `vlln`
    /// and the VL self-attention. The same preprocessing, prompt and graphs as
    /// [`Self::encode_views`], which applies those two frozen pieces of the action head on
    /// top; this is what `pir2 gr00t train --features` takes (the trainer applies them
    /// itself).
    pub fn backbone_embeddings(&mut self, views: &[(&[u8], (usize, usize))]) -> Result<&[f32]> {
        self.run_backbone(views.iter().copied())?;
        Ok(&self.feats)
    }

    /// Encode the views `(HWC u8 RGB, (h, w))` of one frame (no per-frame allocation beyond
    /// the reused pixel buffers).
    fn encode<'a>(
        &mut self,
        views: impl ExactSizeIterator<Item = (&'a [u8], (usize, usize))>,
    ) -> Result<&[f32]> {
        self.run_backbone(views)?;
        let (t, d) = (self.seq.ids.len(), self.d_vl);
        if let Some((w, b)) = &self.vlln {
            layer_norm(&mut self.feats, d, w, b);
        }
        if let Some(g) = self.vl_self_attention.as_mut() {
            let input = std::mem::take(&mut self.feats);
            let mut out = Vec::with_capacity(input.len());
            g.run_into(
                vec![feed("hidden_states", &[1, t, d], &input)?],
                "output",
                &mut out,
            )?;
            if out.len() != t * d {
                return Err(Error::input(
                    format!("`{}` output [1,T,D_vl]", g.path().display()),
                    t * d,
                    out.len(),
                ));
            }
            self.feats = out;
        }
        self.encoded += 1;
        Ok(&self.feats)
    }

    /// Preprocess the views and run the backbone graphs: `[T, D_vl]` into `self.feats`.
    fn run_backbone<'a>(
        &mut self,
        views: impl ExactSizeIterator<Item = (&'a [u8], (usize, usize))>,
    ) -> Result<()> {
        let n = views.len();
        if n != self.views {
            return Err(Error::input(
                "camera views of a slow frame",
                format!(
                    "{} (prompt.chat.images of the embodiment config)",
                    self.views
                ),
                n,
            ));
        }
        self.pixels.clear();
        for (rgb, hw) in views {
            preprocess_image(rgb, hw, &self.image, &mut self.view_pixels)?;
            self.pixels.extend_from_slice(&self.view_pixels);
        }
        let (t, d, c) = (self.seq.ids.len(), self.d_vl, self.image.pixel_side());
        let mut feats = std::mem::take(&mut self.feats);
        let r = match &mut self.core {
            Core::Fused(g) => Self::run_fused(g, &self.pixels, &self.seq, (n, c, t, d), &mut feats),
            Core::Split(s) => s.run(&self.pixels, &self.seq.attention, &mut feats),
        };
        self.feats = feats;
        r
    }
}

impl Gr00tBackbone {
    /// The graphs run, for run summaries: `` `backbone.onnx` `` or GR00T's split export.
    pub fn describe(&self) -> String {
        match &self.core {
            Core::Fused(g) => format!("`{}`", file_name(g.path())),
            Core::Split(s) => {
                let half = s.half_tensors();
                format!(
                    "GR00T's split export `{}` + `{}` (glued in Rust{})",
                    file_name(s.vit_path()),
                    file_name(s.llm_path()),
                    if half.is_empty() {
                        String::new()
                    } else {
                        format!("; converted from/to f32: {}", half.join(", "))
                    }
                )
            }
        }
    }

    /// Whether this backbone runs GR00T's split export (else the fused `backbone.onnx`).
    pub fn is_split(&self) -> bool {
        matches!(self.core, Core::Split(_))
    }

    /// The multimodal positions the split backbone feeds its LLM (`[3, T]` row-major), or
    /// `None` for a fused backbone.
    pub fn position_ids(&self) -> Option<&[i64]> {
        match &self.core {
            Core::Split(s) => Some(s.position_ids()),
            Core::Fused(_) => None,
        }
    }

    fn run_fused(
        g: &mut Graph,
        pixels: &[f32],
        seq: &Sequence,
        (n, c, t, d): (usize, usize, usize, usize),
        out: &mut Vec<f32>,
    ) -> Result<()> {
        let mut feeds = vec![
            feed("pixel_values", &[n, 3, c, c], pixels)?,
            feed("input_ids", &[1, t], &seq.ids)?,
        ];
        if g.declared.has("attention_mask") {
            feeds.push(feed("attention_mask", &[1, t], &seq.attention)?);
        }
        g.run_into(feeds, "embeddings", out)?;
        if out.len() != t * d {
            return Err(Error::input(
                format!("`{}` output embeddings [1,T,D_vl]", g.path().display()),
                t * d,
                out.len(),
            ));
        }
        Ok(())
    }
}

#[async_trait::async_trait]
impl SlowEncoder for Gr00tBackbone {
    async fn encode(&mut self, frame: SlowFrame) -> pir2_runtime::Result<SlowFeatures> {
        let (t, d) = self.output_shape();
        let data = self.encode_views(&frame.views)?.to_vec();
        Ok(SlowFeatures {
            t_capture: frame.t_capture,
            data,
            tokens: t,
            dim: d,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gr00t::tokenizer::VocabTokenizer;

    fn vocab() -> VocabTokenizer {
        let lines = [
            "<pad>", "<unk>", "<image>", "catch", "the", "book", "put", "in", "bask", "##et", ".",
        ];
        VocabTokenizer::from_lines(lines.into_iter(), Path::new("vocab.txt")).unwrap()
    }

    #[test]
    fn vocab_tokenizer_splits_words_pieces_and_punctuation() {
        let v = vocab();
        assert_eq!(v.encode("Catch the book.").unwrap(), vec![3, 4, 5, 10]);
        assert_eq!(
            v.encode("put the book in the basket").unwrap(),
            vec![6, 4, 5, 7, 4, 8, 9]
        );
        assert_eq!(v.encode("catch the ball").unwrap(), vec![3, 4, 1]);
        let e = VocabTokenizer::from_lines(["<pad>", "<unk>"].into_iter(), Path::new("v.txt"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("v.txt") && e.contains("<image>"), "{e}");
    }

    #[test]
    fn sequence_layout_marks_image_and_padding() {
        let cfg = PromptConfig {
            image_tokens: 3,
            text_tokens: 5,
            ..Default::default()
        };
        let s = build_sequence(&vocab(), "catch the book", &cfg).unwrap();
        assert_eq!(s.ids, vec![2, 2, 2, 3, 4, 5, 0, 0]);
        assert_eq!(s.attention, vec![1, 1, 1, 1, 1, 1, 0, 0]);
        assert_eq!(
            s.layout.image_mask,
            vec![true, true, true, false, false, false, false, false]
        );
        let cfg = PromptConfig {
            image_tokens: 1,
            text_tokens: 2,
            ..Default::default()
        };
        let s = build_sequence(&vocab(), "catch the book", &cfg).unwrap();
        assert_eq!((s.ids.len(), s.truncated), (3, 1));
    }

    #[test]
    fn preprocessing_crops_the_center_and_normalises() {
        // 4×8 image: left half black, right half white; resize 4 → crop 4 keeps the middle.
        let (h, w) = (4, 8);
        let mut img = vec![0u8; h * w * 3];
        for y in 0..h {
            for x in 4..w {
                for c in 0..3 {
                    img[(y * w + x) * 3 + c] = 255;
                }
            }
        }
        let cfg = ImageConfig {
            pipeline: ImagePipeline::ResizeCrop,
            resize: 4,
            crop: 4,
            ..ImageConfig::default()
        };
        let mut out = Vec::new();
        preprocess_image(&img, (h, w), &cfg, &mut out).unwrap();
        assert_eq!(out.len(), 3 * 16);
        // Center crop = columns 2..6: black, black, white, white (no resampling at scale 1).
        let row0: Vec<f32> = out[0..4].to_vec();
        assert_eq!(row0, vec![-1.0, -1.0, 1.0, 1.0]);
        assert!(preprocess_image(&img[1..], (h, w), &cfg, &mut out).is_err());
        // GR00T N1.7's pipeline: letterboxed to 8×8 (2 black rows above and below), 8 px
        // side, crop ⌊8·0.5⌋ = 4 at offset 2, back to 8: the crop's left half is black, its
        // right half white, and it holds no padding.
        let n17 = ImageConfig {
            shortest_edge: 8,
            crop_fraction: 0.5,
            ..ImageConfig::default()
        };
        preprocess_image(&img, (h, w), &n17, &mut out).unwrap();
        assert_eq!(out.len(), 3 * 64);
        assert_eq!(&out[..8], &[-1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0]);
    }
}
