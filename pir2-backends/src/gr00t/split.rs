//! The backbone as GR00T's exporter writes it: `vit_*.onnx` and `llm_*.onnx`, glued in Rust.
//!
//! GR00T N1.7's exporter (`scripts/deployment/export_onnx_n1d7.py`, mode `full_pipeline`)
//! writes the Qwen3-VL vision tower and the text model cut at `select_layer` as two graphs
//! and leaves the glue between them in PyTorch. [`SplitBackbone`] does that glue, once per
//! frame, so the two files are used unchanged:
//!
//! 1. [`patchify`]: `pixel_values [V, 3, s, s]` → the ViT's patch rows `[V·(s/p)², 3·t·p²]`,
//!    each image repeated `t = temporal_patch_size` times along time, rows ordered by merge
//!    block (`merge_size²` neighbouring patches are consecutive rows), columns by
//!    (channel, time, patch row, patch column) — the VLM image processor's layout;
//! 2. the ViT → `image_embeds [N, D]` (the merged image tokens of all views, in view order)
//!    and `deepstack_features [L, N, D]`;
//! 3. the token embeddings of the prompt (rows of the checkpoint's `embed_tokens` table,
//!    read once at load), with the `k`-th image placeholder position (`input_ids ==
//!    image_token_id`, in sequence order) replaced by the `k`-th image token (a masked
//!    scatter);
//! 4. [`mrope_position_ids`]: Qwen3-VL's multimodal rotary positions `[3, 1, T]`;
//! 5. the LLM with `inputs_embeds`, `attention_mask`, `position_ids`, and, when it declares
//!    them, `visual_pos_masks` (the placeholder mask) and `deepstack_l = deepstack_features[l]`
//!    → `embeddings [1, T, D]`, the backbone features (the last kept layer, pre-norm).
//!
//! Either file may be GR00T's `float32` or `bfloat16` export (`vit_fp32.onnx` /
//! `vit_bf16.onnx`, `llm_fp32.onnx` / `llm_bf16.onnx`, the LLM's default being bfloat16) or
//! `float16`: the glue computes in `f32`, and each float tensor is converted at the graph's
//! boundary by the element type the file declares ([`super::contract::Graph::input`]). What
//! runs *inside* a bfloat16 graph is the execution provider's business: ONNX Runtime's CPU
//! provider has no bfloat16 kernels for the math ops (MatMul, Add, Mul, Softmax…), so such a
//! graph needs the CUDA or TensorRT provider, and on the CPU loading it is one
//! [`Error::NoKernel`] naming the file, the op and the way out.

use std::path::Path;

use super::config::{CheckpointFiles, ImageConfig, PromptConfig, VisionConfig};
use super::contract::{feed, Bindings, Graph, DEEPSTACK_INPUTS, LLM, VIT};
use super::prompt::{PromptTokenizer, Sequence};
use super::weights::read_table_rows;
use crate::error::{Error, Result};
use crate::ort::OrtOptions;

/// Patch grid of one image before merging: `(t, h, w)` patches (Qwen's `image_grid_thw`).
pub type Grid = (usize, usize, usize);

/// The patch grid of one `side × side` image (`t = 1`: one image fills one temporal patch).
pub fn image_grid(side: usize, vision: &VisionConfig) -> Result<Grid> {
    let (p, m) = (vision.patch_size, vision.merge_size);
    if p == 0 || m == 0 || vision.temporal_patch_size == 0 || side % (p * m) != 0 {
        return Err(Error::Gr00tConfig(format!(
            "the image side {side} must be a multiple of vision.patch_size × vision.merge_size \
             = {p} × {m} (all three positive, temporal_patch_size = {} too)",
            vision.temporal_patch_size
        )));
    }
    Ok((1, side / p, side / p))
}

/// `pixel_values [views, 3, side, side]` (CHW per view) → the ViT's patch rows
/// `[views·(side/p)², 3·t·p²]` in `out` (see the module docs for the layout).
pub fn patchify(
    pixels: &[f32],
    views: usize,
    side: usize,
    vision: &VisionConfig,
    out: &mut Vec<f32>,
) -> Result<()> {
    let (_, g, _) = image_grid(side, vision)?;
    let (p, m, tp) = (
        vision.patch_size,
        vision.merge_size,
        vision.temporal_patch_size,
    );
    let n = side * side;
    if pixels.len() != views * 3 * n {
        return Err(Error::input(
            "pixel_values [V, 3, s, s]",
            views * 3 * n,
            pixels.len(),
        ));
    }
    let cols = 3 * tp * p * p;
    let blocks = g / m;
    out.clear();
    out.resize(views * g * g * cols, 0.0);
    let mut r = 0;
    for v in 0..views {
        let img = &pixels[v * 3 * n..(v + 1) * 3 * n];
        for bh in 0..blocks {
            for bw in 0..blocks {
                for mh in 0..m {
                    for mw in 0..m {
                        let (y0, x0) = ((bh * m + mh) * p, (bw * m + mw) * p);
                        let row = &mut out[r * cols..(r + 1) * cols];
                        for c in 0..3 {
                            for k in 0..tp {
                                for py in 0..p {
                                    let src = c * n + (y0 + py) * side + x0;
                                    let dst = ((c * tp + k) * p + py) * p;
                                    row[dst..dst + p].copy_from_slice(&img[src..src + p]);
                                }
                            }
                        }
                        r += 1;
                    }
                }
            }
        }
    }
    Ok(())
}

/// Qwen3-VL's multimodal rotary positions of one sequence, `[3, T]` row-major (temporal,
/// height, width), by the public rule (`get_rope_index` of `transformers`' Qwen3-VL):
///
/// - only the valid tokens (`attention == 1`) are numbered; padding keeps position 1;
/// - an image is counted where `vision_start` is directly followed by `image_token`; the
///   `k`-th counted image takes `grids[k]`;
/// - text runs count up from one past the largest position so far (all three rows equal);
/// - an image's `t·(h/m)·(w/m)` tokens, starting at the next `image_token` after the previous
///   block, get `(t_i, h_i, w_i) + start` in raster order, `start` = the position the first
///   of them would have as text.
///
/// Without a `vision_start` id (no chat template) no image is counted and the positions are
/// those of plain text. An image block that is not `t·(h/m)·(w/m)` consecutive image tokens,
/// or more counted images than `grids`, is an error.
pub fn mrope_position_ids(
    ids: &[i64],
    attention: &[i64],
    image_token: i64,
    vision_start: Option<i64>,
    grids: &[Grid],
    merge: usize,
) -> Result<Vec<i64>> {
    let t_len = ids.len();
    if attention.len() != t_len {
        return Err(Error::input(
            "attention_mask",
            format!("{t_len} values (as input_ids)"),
            attention.len(),
        ));
    }
    let valid: Vec<usize> = (0..t_len).filter(|&i| attention[i] == 1).collect();
    let tokens: Vec<i64> = valid.iter().map(|&i| ids[i]).collect();
    let images = match vision_start {
        Some(vs) => tokens
            .windows(2)
            .filter(|w| w[0] == vs && w[1] == image_token)
            .count(),
        None => 0,
    };
    if images > grids.len() {
        return Err(Error::input(
            "images in the prompt (vision_start + image token)",
            format!("at most {} (camera views)", grids.len()),
            images,
        ));
    }
    // Positions of the valid tokens, three rows.
    let mut pos: [Vec<i64>; 3] = Default::default();
    let mut next = 0i64; // one past the largest position so far
    let mut st = 0usize;
    let text = |pos: &mut [Vec<i64>; 3], len: usize, next: &mut i64| {
        for j in 0..len as i64 {
            for row in pos.iter_mut() {
                row.push(*next + j);
            }
        }
        *next += len as i64;
    };
    for (k, &(gt, gh, gw)) in grids.iter().enumerate().take(images) {
        let Some(ed) = (st..tokens.len()).find(|&i| tokens[i] == image_token) else {
            return Err(Error::input(
                format!("image {k} of the prompt"),
                "image placeholder tokens",
                "none left",
            ));
        };
        let (lh, lw) = (gh / merge, gw / merge);
        let n = gt * lh * lw;
        if ed + n > tokens.len() || tokens[ed..ed + n].iter().any(|&t| t != image_token) {
            return Err(Error::input(
                format!("image {k} of the prompt (valid token {ed})"),
                format!("{n} consecutive image placeholder tokens ({gt}×{lh}×{lw})"),
                "a shorter run",
            ));
        }
        text(&mut pos, ed - st, &mut next);
        let start = next;
        let mut top = start;
        for ti in 0..gt {
            for hi in 0..lh {
                for wi in 0..lw {
                    let p = [ti, hi, wi].map(|x| start + x as i64);
                    for (row, v) in pos.iter_mut().zip(p) {
                        row.push(v);
                        top = top.max(v);
                    }
                }
            }
        }
        next = top + 1;
        st = ed + n;
    }
    text(&mut pos, tokens.len() - st, &mut next);
    let mut out = vec![1i64; 3 * t_len];
    for (r, row) in pos.iter().enumerate() {
        for (j, &i) in valid.iter().enumerate() {
            out[r * t_len + i] = row[j];
        }
    }
    Ok(out)
}

/// The id of the chat template's image-block opener (`<|vision_start|>`), when the
/// tokenizer has a chat template and encodes it as one token.
fn vision_start_id(tok: &dyn PromptTokenizer) -> Result<Option<i64>> {
    let Some(chat) = tok.chat_template() else {
        return Ok(None);
    };
    if chat.image_begin.is_empty() {
        return Ok(None);
    }
    let ids = tok.encode(&chat.image_begin)?;
    Ok((ids.len() == 1).then(|| ids[0]))
}

/// GR00T's split backbone (see the module docs).
pub struct SplitBackbone {
    vit: Graph,
    llm: Graph,
    vision: VisionConfig,
    side: usize,
    views: usize,
    patches: usize,
    patch_dim: usize,
    image_tokens: usize,
    d: usize,
    deepstack: usize,
    /// Token embeddings of the prompt `[T, D]` (placeholders included).
    base: Vec<f32>,
    /// Sequence positions of the image placeholders, in order.
    image_pos: Vec<usize>,
    visual: Vec<bool>,
    positions: Vec<i64>,
    rows: Vec<f32>,
    image_embeds: Vec<f32>,
    ds: Vec<f32>,
    inputs: Vec<f32>,
}

impl std::fmt::Debug for SplitBackbone {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SplitBackbone")
            .field("vit", &self.vit)
            .field("llm", &self.llm)
            .field("deepstack", &self.deepstack)
            .finish()
    }
}

impl SplitBackbone {
    /// Load the ViT and the LLM of `files` (checked against [`VIT`] / [`LLM`] with the sizes
    /// the configuration implies), read the prompt's rows of the token-embedding table and
    /// compute the positions of `seq`.
    #[allow(clippy::too_many_arguments)]
    pub fn load(
        files: &CheckpointFiles,
        image: &ImageConfig,
        prompt_cfg: &PromptConfig,
        vision: &VisionConfig,
        tokenizer: &dyn PromptTokenizer,
        seq: &Sequence,
        b: &mut Bindings,
        opts: &OrtOptions,
    ) -> Result<Self> {
        let side = image.pixel_side();
        let grid = image_grid(side, vision)?;
        let views = prompt_cfg.chat.images;
        let per_image = grid.0 * (grid.1 / vision.merge_size) * (grid.2 / vision.merge_size);
        if views * per_image != prompt_cfg.image_tokens {
            return Err(Error::Gr00tConfig(format!(
                "prompt.image_tokens = {} but {views} view(s) of {side}×{side} px with \
                 vision.patch_size = {} and merge_size = {} give {} image tokens",
                prompt_cfg.image_tokens,
                vision.patch_size,
                vision.merge_size,
                views * per_image
            )));
        }
        let patches = views * grid.0 * grid.1 * grid.2;
        let patch_dim = 3 * vision.temporal_patch_size * vision.patch_size * vision.patch_size;
        let src = "<embodiment config: image side, prompt.chat.images, vision.patch_size / temporal_patch_size>";
        b.bind("patches", patches, src);
        b.bind("patch_dim", patch_dim, src);
        b.bind(
            "image_tokens",
            prompt_cfg.image_tokens,
            "<embodiment config: prompt.image_tokens>",
        );
        let vit = Graph::load(&files.vit, VIT, opts, b)?;
        let llm = Graph::load(&files.llm, LLM, opts, b)?;
        let d = b.get("D_vl").expect("bound by the contract check");
        let llm_err = |tensor: &str, problem: String| Error::Gr00tContract {
            path: files.llm.clone(),
            tensor: tensor.to_string(),
            problem,
        };
        let deepstack = DEEPSTACK_INPUTS
            .iter()
            .take_while(|n| llm.declared.has(n))
            .count();
        if let Some(extra) = DEEPSTACK_INPUTS[deepstack..]
            .iter()
            .find(|n| llm.declared.has(n))
        {
            return Err(llm_err(
                extra,
                format!("declared without the deepstack inputs before it (0..{deepstack})"),
            ));
        }
        if deepstack > 0 && !llm.declared.has("visual_pos_masks") {
            return Err(llm_err(
                "visual_pos_masks",
                format!("missing: the LLM declares {deepstack} deepstack input(s)"),
            ));
        }
        if let Some(l) = b.get("deepstack") {
            if l != deepstack {
                return Err(llm_err(
                    "deepstack_0",
                    format!(
                        "the LLM takes {deepstack} deepstack input(s) but `{}` writes {l} \
                         deepstack feature(s)",
                        files.vit.display()
                    ),
                ));
            }
        }
        let mut sb = SplitBackbone {
            vit,
            llm,
            vision: vision.clone(),
            side,
            views,
            patches,
            patch_dim,
            image_tokens: prompt_cfg.image_tokens,
            d,
            deepstack,
            base: Vec::new(),
            image_pos: Vec::new(),
            visual: Vec::new(),
            positions: Vec::new(),
            rows: Vec::new(),
            image_embeds: Vec::new(),
            ds: Vec::new(),
            inputs: Vec::new(),
        };
        sb.set_sequence(files, tokenizer, seq)?;
        Ok(sb)
    }

    /// Take `seq` as the prompt from now on (a new task): its image placeholder positions,
    /// its multimodal positions and its rows of the token-embedding table (read from the
    /// checkpoint's weights). The graphs stay loaded.
    pub fn set_sequence(
        &mut self,
        files: &CheckpointFiles,
        tokenizer: &dyn PromptTokenizer,
        seq: &Sequence,
    ) -> Result<()> {
        let vision = &self.vision;
        let grid = image_grid(self.side, vision)?;
        let views = self.views;
        let d = self.d;
        let image_token = tokenizer.image_token_id();
        let image_pos: Vec<usize> = (0..seq.ids.len())
            .filter(|&i| seq.ids[i] == image_token)
            .collect();
        if image_pos.len() != self.image_tokens {
            return Err(Error::input(
                "image placeholder tokens in the prompt",
                self.image_tokens,
                image_pos.len(),
            ));
        }
        let mut visual = vec![false; seq.ids.len()];
        for &i in &image_pos {
            visual[i] = true;
        }
        let positions = mrope_position_ids(
            &seq.ids,
            &seq.attention,
            image_token,
            vision_start_id(tokenizer)?,
            &vec![grid; views],
            vision.merge_size,
        )?;
        let (d_table, base) = read_table_rows(
            &files.model_index,
            &files.model_weights,
            &vision.embed_tokens_key,
            &seq.ids,
        )?;
        if d_table != d {
            let file = if files.model_index.exists() {
                &files.model_index
            } else {
                &files.model_weights
            };
            return Err(Error::Weights {
                path: file.clone(),
                tensor: vision.embed_tokens_key.clone(),
                problem: format!(
                    "has width {d_table}, but `{}` takes inputs_embeds of width {d}",
                    files.llm.display()
                ),
            });
        }
        self.base = base;
        self.image_pos = image_pos;
        self.visual = visual;
        self.positions = positions;
        Ok(())
    }

    /// The multimodal positions fed to the LLM, `[3, T]` row-major.
    pub fn position_ids(&self) -> &[i64] {
        &self.positions
    }

    /// The ViT file.
    pub fn vit_path(&self) -> &Path {
        self.vit.path()
    }

    /// The LLM file.
    pub fn llm_path(&self) -> &Path {
        self.llm.path()
    }

    /// The half-precision boundary tensors of the two files (`bfloat16`/`float16`, converted
    /// from and to `f32` per call), e.g. `LLM inputs_embeds bfloat16`.
    pub fn half_tensors(&self) -> Vec<String> {
        let named = |role: &str, g: &Graph| {
            g.declared
                .half_tensors()
                .into_iter()
                .map(|t| format!("{role} {t}"))
                .collect::<Vec<_>>()
        };
        let mut v = named("ViT", &self.vit);
        v.extend(named("LLM", &self.llm));
        v
    }

    /// Run the glue for one frame: `pixels` `[V, 3, s, s]`, the sequence's `attention`
    /// mask; the backbone features `[T, D]` go to `out`.
    pub fn run(&mut self, pixels: &[f32], attention: &[i64], out: &mut Vec<f32>) -> Result<()> {
        let (n, d, t) = (self.image_tokens, self.d, self.visual.len());
        patchify(pixels, self.views, self.side, &self.vision, &mut self.rows)?;
        let mut image_embeds = std::mem::take(&mut self.image_embeds);
        let mut ds = std::mem::take(&mut self.ds);
        let pixel_values =
            self.vit
                .input("pixel_values", &[self.patches, self.patch_dim], &self.rows)?;
        let r = self.vit.run_many(
            vec![pixel_values],
            &mut [
                ("image_embeds", &mut image_embeds),
                ("deepstack_features", &mut ds),
            ],
        );
        self.image_embeds = image_embeds;
        self.ds = ds;
        r?;
        let vit = self.vit.path().display().to_string();
        if self.image_embeds.len() != n * d {
            return Err(Error::input(
                format!("`{vit}` output image_embeds [N, D]"),
                format!("{n}×{d} = {}", n * d),
                self.image_embeds.len(),
            ));
        }
        if self.ds.len() < self.deepstack * n * d {
            return Err(Error::input(
                format!("`{vit}` output deepstack_features [L, N, D]"),
                format!("≥ {}×{n}×{d}", self.deepstack),
                self.ds.len(),
            ));
        }
        self.inputs.clear();
        self.inputs.extend_from_slice(&self.base);
        for (k, &i) in self.image_pos.iter().enumerate() {
            self.inputs[i * d..(i + 1) * d].copy_from_slice(&self.image_embeds[k * d..(k + 1) * d]);
        }
        let mut feeds = vec![
            self.llm.input("inputs_embeds", &[1, t, d], &self.inputs)?,
            feed("attention_mask", &[1, t], attention)?,
            feed("position_ids", &[3, 1, t], &self.positions)?,
        ];
        if self.llm.declared.has("visual_pos_masks") {
            feeds.push(feed("visual_pos_masks", &[1, t], &self.visual)?);
        }
        for (l, name) in DEEPSTACK_INPUTS.iter().take(self.deepstack).enumerate() {
            feeds.push(
                self.llm
                    .input(name, &[n, d], &self.ds[l * n * d..(l + 1) * n * d])?,
            );
        }
        self.llm.run_into(feeds, "embeddings", out)?;
        if out.len() != t * d {
            return Err(Error::input(
                format!(
                    "`{}` output embeddings [1, T, D]",
                    self.llm.path().display()
                ),
                t * d,
                out.len(),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Golden numbers: a Python transcription of `get_rope_index` (transformers' Qwen3-VL)
    /// run on this sequence (left padding 2; text 3; two 2×2-merged images of a 4×4 patch
    /// grid, each inside vision_start/vision_end; text 2; image token 9, vision_start 7).
    #[test]
    fn position_ids_match_the_public_rule() {
        let ids = [0, 0, 1, 2, 3, 7, 9, 9, 9, 9, 8, 7, 9, 9, 9, 9, 8, 4, 5];
        let att = [0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1];
        let got = mrope_position_ids(&ids, &att, 9, Some(7), &[(1, 4, 4), (1, 4, 4)], 2).unwrap();
        let golden: [[i64; 19]; 3] = GOLDEN;
        assert_eq!(got, golden.concat());
        // No vision_start id: plain text positions.
        let plain = mrope_position_ids(&ids, &att, 9, None, &[(1, 4, 4)], 2).unwrap();
        let row: Vec<i64> = [1, 1].into_iter().chain(0..17).collect();
        assert_eq!(plain, [row.clone(), row.clone(), row].concat());
        // A short image block is refused.
        let short = [1, 7, 9, 9, 9, 8];
        assert!(mrope_position_ids(&short, &[1; 6], 9, Some(7), &[(1, 4, 4)], 2).is_err());
    }

    const GOLDEN: [[i64; 19]; 3] = [
        [1, 1, 0, 1, 2, 3, 4, 4, 4, 4, 6, 7, 8, 8, 8, 8, 10, 11, 12],
        [1, 1, 0, 1, 2, 3, 4, 4, 5, 5, 6, 7, 8, 8, 9, 9, 10, 11, 12],
        [1, 1, 0, 1, 2, 3, 4, 5, 4, 5, 6, 7, 8, 9, 8, 9, 10, 11, 12],
    ];

    #[test]
    fn patchify_orders_rows_by_merge_block_and_columns_by_channel_time_pixel() {
        // One 4×4 image, patch 1, merge 2, temporal 2: value = 100·c + 10·y + x.
        let v = VisionConfig {
            patch_size: 1,
            temporal_patch_size: 2,
            merge_size: 2,
            ..VisionConfig::default()
        };
        let px: Vec<f32> = (0..3)
            .flat_map(|c| {
                (0..4).flat_map(move |y| (0..4).map(move |x| (100 * c + 10 * y + x) as f32))
            })
            .collect();
        let mut out = Vec::new();
        patchify(&px, 1, 4, &v, &mut out).unwrap();
        assert_eq!(out.len(), 16 * 6);
        // Rows: block (0,0) = (0,0) (0,1) (1,0) (1,1), then block (0,1) = (0,2) (0,3) …
        let yx: Vec<f32> = out.chunks(6).map(|r| r[0]).collect();
        assert_eq!(
            yx,
            [0., 1., 10., 11., 2., 3., 12., 13., 20., 21., 30., 31., 22., 23., 32., 33.]
        );
        // Columns: (c0,t0) (c0,t1) (c1,t0) (c1,t1) (c2,t0) (c2,t1).
        assert_eq!(&out[6 * 3..6 * 4], &[11., 11., 111., 111., 211., 211.]);
        assert!(patchify(&px, 1, 6, &v, &mut out).is_err());
    }
}
