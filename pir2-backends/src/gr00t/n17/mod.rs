//! GR00T N1.7's action head in candle, loaded from a GR00T checkpoint's safetensors, with
//! πR²'s per-position timesteps.
//!
//! One file on purpose: the head's loading, its forward (state/action encoders, DiT, decoder) and
//! its per-position heads share one set of tensors and shape checks; the layers, weights, dropout
//! and config are in the files beside it.
//!
//! The architecture and the tensor names are those of NVIDIA's Isaac-GR00T N1.7
//! (`Gr00tN1d7ActionHead`); every tensor lives under `action_head.` in the checkpoint:
//!
//! | piece | tensors | computes |
//! |-------|---------|----------|
//! | `vlln` | `vlln.{weight,bias}` `[D_vl]` | LayerNorm (ε = 10⁻⁵) of the backbone tokens |
//! | `vl_self_attention` (optional) | `vl_self_attention.transformer_blocks.i.*` | self-attention blocks over the VL tokens |
//! | `state_encoder` | `state_encoder.layer{1,2}.{W,b}` | per-embodiment MLP `S_in → hidden → D_in`, ReLU |
//! | `action_encoder` | `action_encoder.W{1,2,3}.{W,b}` | `W3·silu(W2·[W1·a ; sin/cos(t)])`, per embodiment |
//! | `position_embedding` | `position_embedding.weight` `[max_seq_len, D_in]` | added to action token `p` |
//! | `model` (DiT) | `model.timestep_encoder…`, `model.transformer_blocks.i.*`, `model.proj_out_{1,2}` | see below |
//! | `action_decoder` | `action_decoder.layer{1,2}.{W,b}` | per-embodiment MLP `hidden → hidden → A_max`, ReLU |
//! | `delay_embedding` (πR², optional) | `delay_embedding.weight` `[d_vis_max + 1, D_in]` | row `min(d_vis, d_vis_max)` added to every action token |
//!
//! Per-embodiment layers hold one matrix per slot (`W [slots, in, out]`, `b [slots, out]`).
//!
//! **DiT.** Tokens `[state; action₁ … action_H]` of width `D_in = heads · head_dim`. A
//! timestep `t` (an integer in `[0, buckets)`, `t = ⌊τ · 1000⌋` for the flow time `τ`,
//! 0 = noise) is embedded by `linear_2(silu(linear_1(f(t))))` with `f` diffusers' 256-wide
//! sinusoid. Block `i` is `AdaLN → attention → residual → LayerNorm → GELU(tanh) MLP →
//! residual`; AdaLN is `LN(x)·(1 + scale) + shift`, `[scale, shift] = norm1.linear(silu(temb))`.
//! With `interleave_self_attention` the odd blocks self-attend; the others cross-attend to the
//! VL tokens. In N1.7's `AlternateVLDiT` the cross-attending blocks alternate between the
//! text tokens (`i mod 2n = 0`, `n = attend_text_every_n_blocks`) and the image tokens, both
//! restricted to the backbone's attention mask. The output is
//! `proj_out_2(LN(x)·(1 + scale) + shift)`, `[shift, scale] = proj_out_1(silu(temb))`.
//!
//! **πR².** GR00T gives every token of a sample the same timestep. Here the timestep can be
//! per position ([`Timesteps::PerPosition`]): the action encoder takes one per action token
//! `[B, H]`, and the DiT one per token `[B, 1 + H]` (state token first), so every AdaLN and
//! the output modulation use that token's own embedding. [`Timesteps::Shared`] is GR00T's
//! behaviour and equals the per-position form with all entries equal.
//!
//! **Fine-tuning.** [`Gr00tN17Head::load_trainable`] loads the same network with its trained
//! tensors ([`is_trained`]) as candle [`Var`]s and a zero-initialised delay table, so the
//! untrained head reproduces the checkpoint's. The training forward is
//! [`Gr00tN17Head::velocity_train`]: the same network with GR00T's dropout in the DiT blocks
//! ([`DitDropout`]: rate `diffusion_model_cfg.dropout`, 0.2 in N1.7, after the attention
//! output and inside and after the feed-forward), its masks a pure function of
//! `(seed, step, site)`. [`Gr00tN17Head::velocity`] (inference, export, `pir2 gr00t run`) never
//! drops. The frozen `vlln` / VL self-attention never drop either: GR00T puts frozen modules
//! in `eval` mode, which is what lets their output be cached. Per-position AdaLN here means
//! every token's AdaLN and output modulation read that token's own timestep embedding;
//! [`Gr00tN17Head::with_position_heads`] makes those modulations one head per token (the
//! paper's architecture, initialised from the shared pair), and a checkpoint holding
//! `<layer>_heads.*` tensors loads with them.
//!
//! Loading ([`Gr00tN17Head::load`]) reads `config.json` ([`Gr00tN17Config`]) and the
//! `action_head.*` tensors of `model.safetensors` or of a sharded checkpoint
//! (`model.safetensors.index.json`); the backbone's tensors are never read. A missing tensor
//! is [`Error::MissingTensor`], a mis-shaped one [`Error::TensorShape`], an
//! `action_head.*` tensor the configuration does not use [`Error::UnexpectedTensor`]; each
//! names the tensor and the file. BF16/F16 weights are widened to `f32`.
//!
//! ```no_run
//! use candle_core::{Device, Tensor};
//! use pir2_backends::gr00t::n17::{Gr00tN17Head, Timesteps, VlTokens};
//! # fn main() -> pir2_backends::Result<()> {
//! let dev = Device::Cpu;
//! let head = Gr00tN17Head::load("GR00T_N17_CHECKPOINT".as_ref(), &dev)?;
//! let c = head.config();
//! let vl = head.process_backbone(&Tensor::zeros((1, 64, c.backbone_embedding_dim), candle_core::DType::F32, &dev)?)?;
//! let image = Tensor::ones((1, 64), candle_core::DType::U8, &dev)?;
//! let vl = VlTokens { embeddings: &vl, attention_mask: None, image_mask: Some(&image), d_vis: None };
//! let emb = Tensor::new(&[0u32], &dev)?;
//! let state = Tensor::zeros((1, c.state_history_length, c.max_state_dim), candle_core::DType::F32, &dev)?;
//! let s = head.encode_state(&state, &emb)?;
//! let x = Tensor::randn(0f32, 1.0, (1, c.action_horizon, c.max_action_dim), &dev)?;
//! let t = Tensor::new(&[0u32], &dev)?;
//! let v = head.velocity(&s, &x, Timesteps::Shared(&t), &vl, &emb)?;
//! # let _ = v; Ok(()) }
//! ```

mod config;
mod dropout;
pub mod export;
mod layers;
pub mod train;
mod weights;

use std::path::Path;

use candle_core::{DType, Device, Tensor, Var, D};

pub use config::{DitConfig, Gr00tN17Config, VlSelfAttentionConfig};
pub use dropout::{DitDropout, DropoutSite, MaskSource, DEVICE_MODULUS};
pub(crate) use layers::{action_time_frequencies, dit_time_frequencies, sinusoidal_table_values};
pub use weights::{TensorIndex, INDEX_FILE, SINGLE_FILE};

use crate::error::{Error, Result};
use layers::{
    action_time_features, attention_bias, dit_time_features, sinusoidal_table, Ada, AffineNorm,
    Block, CategoryLinear, CategoryMlp, Linear, Loader, Norm1,
};

/// Prefix of the action head's tensors in a GR00T checkpoint.
pub const PREFIX: &str = "action_head.";

/// πR²'s delay table `[d_vis_max + 1, D_in]` under [`PREFIX`] (absent in GR00T's own
/// checkpoints; written by πR² fine-tuning). Row `d` is added to every action token when the
/// slow features are `d` control ticks old (older ones use the last row).
pub const DELAY_EMBEDDING: &str = "delay_embedding.weight";

/// Whether πR² fine-tuning trains the tensor `name` (relative to [`PREFIX`]): everything but
/// the backbone post-processing (`vlln`, `vl_self_attention`), which stays frozen with the
/// backbone, as in the paper's recipe (state/action projectors, position embedding, DiT,
/// decoder, plus the delay table).
pub fn is_trained(name: &str) -> bool {
    !(name.starts_with("vlln.") || name.starts_with("vl_self_attention."))
}

/// The name and shape of every tensor the head of configuration `cfg` reads (relative to
/// [`PREFIX`], without the optional delay table), in load order. With random values of these
/// shapes, `model.safetensors` (names prefixed with [`PREFIX`]) and `cfg`'s `config.json` make
/// a loadable synthetic checkpoint.
pub fn head_tensor_shapes(cfg: &Gr00tN17Config) -> Vec<(String, Vec<usize>)> {
    type Shapes = Vec<(String, Vec<usize>)>;
    fn lin(v: &mut Shapes, n: &str, i: usize, o: usize) {
        v.push((format!("{n}.weight"), vec![o, i]));
        v.push((format!("{n}.bias"), vec![o]));
    }
    fn norm(v: &mut Shapes, n: &str, dim: usize) {
        v.push((format!("{n}.weight"), vec![dim]));
        v.push((format!("{n}.bias"), vec![dim]));
    }
    /// `(dim, inner, source)` widths; `ada`: AdaLN (DiT) or affine norms (VL stack).
    fn block(v: &mut Shapes, n: &str, (dim, inner, source): (usize, usize, usize), ada: bool) {
        if ada {
            lin(v, &format!("{n}.norm1.linear"), dim, 2 * dim);
        } else {
            norm(v, &format!("{n}.norm1"), dim);
        }
        lin(v, &format!("{n}.attn1.to_q"), dim, inner);
        lin(v, &format!("{n}.attn1.to_k"), source, inner);
        lin(v, &format!("{n}.attn1.to_v"), source, inner);
        lin(v, &format!("{n}.attn1.to_out.0"), inner, dim);
        if !ada {
            norm(v, &format!("{n}.norm3"), dim);
        }
        lin(v, &format!("{n}.ff.net.0.proj"), dim, 4 * dim);
        lin(v, &format!("{n}.ff.net.2"), 4 * dim, dim);
    }
    let c = cfg;
    let (n_emb, d_in, hid, d_vl) = (
        c.max_num_embodiments,
        c.input_embedding_dim,
        c.hidden_size,
        c.backbone_embedding_dim,
    );
    let cat = |v: &mut Shapes, n: &str, i: usize, o: usize| {
        v.push((format!("{n}.W"), vec![n_emb, i, o]));
        v.push((format!("{n}.b"), vec![n_emb, o]));
    };
    let mut v: Shapes = Vec::new();
    if c.use_vlln {
        norm(&mut v, "vlln", d_vl);
    }
    if let Some(sa) = &c.vl_self_attention {
        for i in 0..sa.num_layers {
            let inner = sa.num_attention_heads * sa.attention_head_dim;
            let n = format!("vl_self_attention.transformer_blocks.{i}");
            block(&mut v, &n, (d_vl, inner, d_vl), false);
        }
    }
    cat(&mut v, "state_encoder.layer1", c.state_input_dim(), hid);
    cat(&mut v, "state_encoder.layer2", hid, d_in);
    cat(&mut v, "action_encoder.W1", c.max_action_dim, d_in);
    cat(&mut v, "action_encoder.W2", 2 * d_in, d_in);
    cat(&mut v, "action_encoder.W3", d_in, d_in);
    if c.add_pos_embed {
        v.push((
            "position_embedding.weight".into(),
            vec![c.max_seq_len, d_in],
        ));
    }
    let dc = &c.dit;
    for i in 0..dc.num_layers {
        let is_cross = !(dc.interleave_self_attention && i % 2 == 1);
        let n = format!("model.transformer_blocks.{i}");
        let inner = dc.num_attention_heads * dc.attention_head_dim;
        let source = if is_cross { d_vl } else { d_in };
        block(&mut v, &n, (d_in, inner, source), true);
    }
    lin(
        &mut v,
        "model.timestep_encoder.timestep_embedder.linear_1",
        256,
        d_in,
    );
    lin(
        &mut v,
        "model.timestep_encoder.timestep_embedder.linear_2",
        d_in,
        d_in,
    );
    lin(&mut v, "model.proj_out_1", d_in, 2 * d_in);
    lin(&mut v, "model.proj_out_2", d_in, dc.output_dim);
    cat(&mut v, "action_decoder.layer1", hid, hid);
    cat(&mut v, "action_decoder.layer2", hid, c.max_action_dim);
    v
}

/// GR00T's discrete timestep of the flow time `τ` (0 = noise, 1 = clean):
/// `min(⌊clamp(τ, 0, 1) · buckets⌋, buckets − 1)`; a non-finite `τ` and a hidden front slot
/// (`τ < 0`) map to 0. The same map as the ONNX stack's (`docs/gr00t-contract.md`).
pub fn timestep_bucket(tau: f32, buckets: usize) -> u32 {
    let t = if tau.is_finite() {
        tau.clamp(0.0, 1.0)
    } else {
        0.0
    };
    ((t * buckets as f32).floor() as u32).min(buckets.saturating_sub(1) as u32)
}

/// Timesteps of one velocity evaluation (integers in `[0, num_timestep_buckets)`, any
/// integer or float dtype).
#[derive(Debug, Clone, Copy)]
pub enum Timesteps<'a> {
    /// GR00T's base model: one timestep per sample, `[B]`, shared by all its tokens.
    Shared(&'a Tensor),
    /// πR²: one timestep per action position `[B, H]` (action encoder) and one per DiT
    /// token `[B, 1 + H]`, the state token first (per-token AdaLN).
    PerPosition {
        /// `[B, H]`.
        actions: &'a Tensor,
        /// `[B, 1 + H]`.
        tokens: &'a Tensor,
    },
}

/// The backbone tokens the DiT cross-attends to.
#[derive(Debug, Clone, Copy)]
pub struct VlTokens<'a> {
    /// `[B, T, D_vl]`, after [`Gr00tN17Head::process_backbone`].
    pub embeddings: &'a Tensor,
    /// `[B, T]`, nonzero = a real token (GR00T's `backbone_attention_mask`); `None` = all.
    pub attention_mask: Option<&'a Tensor>,
    /// `[B, T]`, nonzero = an image token (GR00T's `image_mask`); required by the
    /// alternating DiT (`use_alternate_vl_dit`), ignored otherwise.
    pub image_mask: Option<&'a Tensor>,
    /// `[B]`, the age of these tokens in control ticks (πR²'s `d_vis`, non-negative
    /// integers); required by a head with a delay table ([`Gr00tN17Head::delay_embedding`]),
    /// ignored by one without.
    pub d_vis: Option<&'a Tensor>,
}

#[derive(Debug, Clone)]
struct ActionEncoder {
    w1: CategoryLinear,
    w2: CategoryLinear,
    w3: CategoryLinear,
}

#[derive(Debug, Clone)]
struct Dit {
    time_1: Linear,
    time_2: Linear,
    blocks: Vec<Block>,
    /// Whether block `i` cross-attends.
    cross: Vec<bool>,
    proj_out_1: Ada,
    proj_out_2: Linear,
}

/// GR00T N1.7's action head (see the [module docs](self)).
#[derive(Debug, Clone)]
pub struct Gr00tN17Head {
    cfg: Gr00tN17Config,
    device: Device,
    vlln: Option<AffineNorm>,
    vl_self_attention: Vec<Block>,
    state_encoder: CategoryMlp,
    action_encoder: ActionEncoder,
    position_embedding: Option<Tensor>,
    dit: Dit,
    action_decoder: CategoryMlp,
    /// πR²'s delay table `[rows, D_in]`, if the head has one.
    delay_embedding: Option<Tensor>,
    /// Every parameter by checkpoint name (computed tables excluded), in load order.
    params: Vec<(String, Tensor)>,
    /// The trainable parameters (empty for an inference head), sorted by name.
    vars: Vec<(String, Var)>,
}

fn shape_err(what: &str, expected: impl std::fmt::Debug, got: &Tensor) -> Error {
    Error::shape(what, expected, got.dims())
}

/// Values of a small integer-valued tensor as `f32`, checked against `shape`.
fn values(what: &str, t: &Tensor, shape: &[usize]) -> Result<Vec<f32>> {
    if t.dims() != shape {
        return Err(shape_err(what, shape, t));
    }
    Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?)
}

impl Gr00tN17Head {
    /// Load a GR00T N1.7 checkpoint directory: `config.json` and `model.safetensors` or
    /// `model.safetensors.index.json` with its shards.
    pub fn load(checkpoint: &Path, device: &Device) -> Result<Self> {
        let cfg = Gr00tN17Config::from_json_file(&config::config_path(checkpoint))?;
        Self::load_weights(checkpoint, cfg, device)
    }

    /// Load the `action_head.*` tensors of `weights` (a directory as in [`Self::load`], an
    /// index file or one `.safetensors` file) for the configuration `cfg`.
    pub fn load_weights(weights: &Path, cfg: Gr00tN17Config, device: &Device) -> Result<Self> {
        let index = TensorIndex::open(weights, PREFIX)?;
        Self::from_index(&index, cfg, device)
    }

    /// Build the head from an opened [`TensorIndex`]. A delay table
    /// (`action_head.delay_embedding.weight`, written by πR² fine-tuning) is loaded when
    /// present.
    pub fn from_index(index: &TensorIndex, cfg: Gr00tN17Config, device: &Device) -> Result<Self> {
        Self::build(index, cfg, device, None)
    }

    /// Load a checkpoint directory (as [`Self::load`]) for πR² fine-tuning: the tensors
    /// [`is_trained`] accepts become [`Var`]s ([`Self::trainable_vars`]), and the delay table
    /// has `d_vis_max + 1` rows: the checkpoint's own if it has one (of another size it is
    /// [`Error::TensorShape`]), else zeros, so that the untrained head computes exactly what
    /// the checkpoint's head computes.
    pub fn load_trainable(checkpoint: &Path, d_vis_max: usize, device: &Device) -> Result<Self> {
        let cfg = Gr00tN17Config::from_json_file(&config::config_path(checkpoint))?;
        let index = TensorIndex::open(checkpoint, PREFIX)?;
        Self::build(&index, cfg, device, Some(d_vis_max))
    }

    /// [`Self::load_trainable`] from an opened [`TensorIndex`].
    pub fn trainable_from_index(
        index: &TensorIndex,
        cfg: Gr00tN17Config,
        d_vis_max: usize,
        device: &Device,
    ) -> Result<Self> {
        Self::build(index, cfg, device, Some(d_vis_max))
    }

    /// `train`: `Some(d_vis_max)` makes the trained tensors variables and ensures a delay
    /// table of `d_vis_max + 1` rows.
    fn build(
        index: &TensorIndex,
        cfg: Gr00tN17Config,
        device: &Device,
        train: Option<usize>,
    ) -> Result<Self> {
        cfg.validate(index.source())?;
        let mut l = Loader {
            index,
            prefix: PREFIX,
            device,
            used: Vec::new(),
            loaded: Vec::new(),
            trainable: train.is_some(),
            vars: Vec::new(),
        };
        let c = &cfg;
        let (n_emb, d_in, hid) = (c.max_num_embodiments, c.input_embedding_dim, c.hidden_size);
        let vlln = if c.use_vlln {
            Some(l.layer_norm("vlln", c.backbone_embedding_dim, 1e-5)?)
        } else {
            None
        };
        let mut vl_self_attention = Vec::new();
        if let Some(v) = &c.vl_self_attention {
            let pe = v
                .sinusoidal_positions
                .then(|| {
                    sinusoidal_table(
                        v.max_num_positional_embeddings,
                        c.backbone_embedding_dim,
                        device,
                    )
                })
                .transpose()?;
            for i in 0..v.num_layers {
                vl_self_attention.push(Block::load(
                    &mut l,
                    &format!("vl_self_attention.transformer_blocks.{i}"),
                    c.backbone_embedding_dim,
                    v.num_attention_heads,
                    v.attention_head_dim,
                    None,
                    false,
                    pe.as_ref(),
                    1e-5,
                )?);
            }
        }
        let state_encoder = CategoryMlp::load(
            &mut l,
            "state_encoder",
            n_emb,
            c.state_input_dim(),
            hid,
            d_in,
        )?;
        let action_encoder = ActionEncoder {
            w1: l.category_linear("action_encoder.W1", n_emb, c.max_action_dim, d_in)?,
            w2: l.category_linear("action_encoder.W2", n_emb, 2 * d_in, d_in)?,
            w3: l.category_linear("action_encoder.W3", n_emb, d_in, d_in)?,
        };
        let position_embedding = if c.add_pos_embed {
            Some(l.tensor("position_embedding.weight", &[c.max_seq_len, d_in])?)
        } else {
            None
        };
        let dc = &c.dit;
        let pe = dc
            .sinusoidal_positions
            .then(|| sinusoidal_table(dc.max_num_positional_embeddings, d_in, device))
            .transpose()?;
        let mut blocks = Vec::new();
        let mut cross = Vec::new();
        for i in 0..dc.num_layers {
            let is_cross = !(dc.interleave_self_attention && i % 2 == 1);
            blocks.push(Block::load(
                &mut l,
                &format!("model.transformer_blocks.{i}"),
                d_in,
                dc.num_attention_heads,
                dc.attention_head_dim,
                is_cross.then_some(c.backbone_embedding_dim),
                true,
                pe.as_ref(),
                dc.norm_eps,
            )?);
            cross.push(is_cross);
        }
        let dit = Dit {
            time_1: l.linear(
                "model.timestep_encoder.timestep_embedder.linear_1",
                256,
                d_in,
            )?,
            time_2: l.linear(
                "model.timestep_encoder.timestep_embedder.linear_2",
                d_in,
                d_in,
            )?,
            blocks,
            cross,
            proj_out_1: l.ada("model.proj_out_1", d_in, 2 * d_in)?,
            proj_out_2: l.linear("model.proj_out_2", d_in, dc.output_dim)?,
        };
        let action_decoder =
            CategoryMlp::load(&mut l, "action_decoder", n_emb, hid, hid, c.max_action_dim)?;
        let delay_name = format!("{PREFIX}{DELAY_EMBEDDING}");
        let mut delay_embedding = match index.shape(&delay_name) {
            Some(shape) => {
                let rows = shape.first().copied().unwrap_or(0);
                if rows == 0 {
                    return Err(Error::TensorShape {
                        path: index.source().to_path_buf(),
                        name: delay_name,
                        expected: vec![1, d_in],
                        got: shape.to_vec(),
                    });
                }
                let want = train.map_or(rows, |d| d + 1);
                Some(l.tensor(DELAY_EMBEDDING, &[want, d_in])?)
            }
            None => None,
        };
        if let (None, Some(d_vis_max)) = (&delay_embedding, train) {
            // Zero-initialised: the untrained head is the checkpoint's head exactly.
            let v = Var::zeros((d_vis_max + 1, d_in), DType::F32, device)?;
            delay_embedding = Some(v.as_tensor().clone());
            l.loaded.push((delay_name.clone(), v.as_tensor().clone()));
            l.vars.push((delay_name, v));
        }
        // Everything under the prefix must have been used, except the sinusoidal tables
        // (buffers computed here, as in the reference).
        let used: std::collections::HashSet<&str> = l.used.iter().map(String::as_str).collect();
        if let Some(extra) = index
            .names()
            .find(|n| !used.contains(n) && !n.ends_with(".pos_embed.pe"))
        {
            return Err(Error::UnexpectedTensor {
                path: index.source().to_path_buf(),
                name: extra.to_string(),
            });
        }
        let mut vars = std::mem::take(&mut l.vars);
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(Self {
            cfg,
            device: device.clone(),
            vlln,
            vl_self_attention,
            state_encoder,
            action_encoder,
            position_embedding,
            dit,
            action_decoder,
            delay_embedding,
            params: std::mem::take(&mut l.loaded),
            vars,
        })
    }

    /// πR²'s one architectural change: every AdaLN modulation of the DiT (each block's
    /// `norm1.linear` and the output's `proj_out_1`) becomes one head per DiT token — the
    /// state token and `horizon` action tokens — each a copy of the shared layer
    /// (`<layer>_heads.weight [1 + horizon, out, in]`, `<layer>_heads.bias [1 + horizon, out]`,
    /// replacing `<layer>.{weight,bias}`). The head then computes exactly what it computed
    /// before, for any timesteps, and a trainable head's heads are variables that specialise in
    /// training. A head that already has per-position heads is returned unchanged if their
    /// count is `1 + horizon`, else it is an error naming the count.
    ///
    /// Cost: `(1 + horizon)×` the modulation parameters (`2·D_in²` per block and for the
    /// output): for N1.7 at full size (`D_in` 1536, 16 blocks, `horizon` 50) about 4.1·10⁹
    /// parameters; the multiply-adds per call equal the shared layer's applied per token.
    pub fn with_position_heads(mut self, horizon: usize) -> Result<Self> {
        let n = horizon + 1;
        let trainable = !self.vars.is_empty();
        let mut layers: Vec<(String, &mut Ada)> = self
            .dit
            .blocks
            .iter_mut()
            .enumerate()
            .filter_map(|(i, b)| match &mut b.norm1 {
                Norm1::Ada(a) => Some((format!("model.transformer_blocks.{i}.norm1.linear"), a)),
                Norm1::Affine(_) => None,
            })
            .collect();
        layers.push(("model.proj_out_1".to_string(), &mut self.dit.proj_out_1));
        let mut renamed = Vec::new();
        for (name, ada) in layers {
            let Some((w, b)) = ada.shared() else {
                if let Ada::Heads { w, .. } = ada {
                    if w.dim(0)? != n {
                        return Err(Error::shape(
                            "per-position AdaLN heads (1 + horizon)",
                            n,
                            w.dim(0)?,
                        ));
                    }
                }
                continue;
            };
            let (out, inp) = w.dims2()?;
            let mut wt = w.unsqueeze(0)?.broadcast_as((n, out, inp))?.contiguous()?;
            let mut bt = b.unsqueeze(0)?.broadcast_as((n, out))?.contiguous()?;
            let mut vars = Vec::new();
            if trainable {
                for (t, k) in [(&mut wt, "weight"), (&mut bt, "bias")] {
                    let v = Var::from_tensor(t)?;
                    *t = v.as_tensor().clone();
                    vars.push((format!("{PREFIX}{name}_heads.{k}"), v));
                }
            }
            renamed.push((name, wt.clone(), bt.clone(), vars));
            *ada = Ada::Heads { w: wt, b: bt };
        }
        for (name, wt, bt, vars) in renamed {
            for (k, t) in [("weight", wt), ("bias", bt)] {
                let old = format!("{PREFIX}{name}.{k}");
                if let Some(p) = self.params.iter_mut().find(|(n, _)| *n == old) {
                    *p = (format!("{PREFIX}{name}_heads.{k}"), t);
                }
                self.vars.retain(|(n, _)| *n != old);
            }
            self.vars.extend(vars);
        }
        self.vars.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(self)
    }

    /// Whether the DiT's AdaLN modulations are per-position heads, and how many tokens they
    /// serve (`1 + horizon`).
    pub fn position_heads(&self) -> Option<usize> {
        match &self.dit.proj_out_1 {
            Ada::Heads { w, .. } => w.dim(0).ok(),
            Ada::Shared(_) => None,
        }
    }

    /// The trainable parameters by checkpoint name (`action_head.…`), sorted by name; empty
    /// for a head loaded for inference. They are the tensors the forward reads: `Var::set`
    /// changes the network, and a loss's gradients reach them.
    pub fn trainable_vars(&self) -> &[(String, Var)] {
        &self.vars
    }

    /// Every parameter by checkpoint name (`action_head.…`; the sinusoidal tables, which
    /// are computed, are not included), in load order.
    pub fn parameters(&self) -> &[(String, Tensor)] {
        &self.params
    }

    /// πR²'s delay table `[d_vis_max + 1, D_in]`, if the head has one.
    pub fn delay_embedding(&self) -> Option<&Tensor> {
        self.delay_embedding.as_ref()
    }

    /// Write every parameter under its checkpoint name as one `f32` safetensors file (the
    /// head part of a GR00T checkpoint's `model.safetensors`; with the delay table if the
    /// head has one). [`Self::load`] reads it back with the checkpoint's `config.json`.
    pub fn save_weights(&self, path: &Path) -> Result<()> {
        let mut data = Vec::with_capacity(self.params.len());
        for (name, t) in &self.params {
            data.push((
                name.clone(),
                t.dims().to_vec(),
                t.flatten_all()?.to_vec1::<f32>()?,
            ));
        }
        crate::checkpoint::write_tensors(
            path,
            data.iter()
                .map(|(n, s, d)| (n.clone(), s.clone(), d.as_slice())),
        )
    }

    /// Add the delay table's row `min(d_vis, rows − 1)` to every action token:
    /// `action_tokens [B, H, D_in]`, `d_vis [B]`. A head without a table returns the tokens
    /// unchanged; a head with one needs `d_vis`.
    pub fn add_delay_embedding(
        &self,
        action_tokens: &Tensor,
        d_vis: Option<&Tensor>,
    ) -> Result<Tensor> {
        let Some(table) = &self.delay_embedding else {
            return Ok(action_tokens.clone());
        };
        let b = action_tokens.dim(0)?;
        let d = d_vis.ok_or_else(|| {
            Error::config(
                "d_vis",
                "this head has a delay table (πR²); give the age of the VL tokens",
            )
        })?;
        let rows = table.dim(0)?;
        let v = values("d_vis", d, &[b])?;
        if let Some(bad) = v.iter().find(|&&x| x < 0.0 || x.fract() != 0.0) {
            return Err(Error::shape("d_vis", "non-negative integers", bad));
        }
        let idx: Vec<u32> = v
            .iter()
            .map(|&x| (x as usize).min(rows - 1) as u32)
            .collect();
        let e = table
            .index_select(&Tensor::from_vec(idx, b, &self.device)?, 0)?
            .unsqueeze(1)?;
        Ok(action_tokens.broadcast_add(&e)?)
    }

    /// The configuration.
    pub fn config(&self) -> &Gr00tN17Config {
        &self.cfg
    }

    /// The device the parameters live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Embodiment slots `[B]` as `u32`, checked against the configuration.
    fn embodiment(&self, ids: &Tensor, b: usize) -> Result<Tensor> {
        let v = values("embodiment_id", ids, &[b])?;
        if let Some(bad) = v
            .iter()
            .find(|&&x| x < 0.0 || x.fract() != 0.0 || x as usize >= self.cfg.max_num_embodiments)
        {
            return Err(Error::shape(
                "embodiment_id",
                format!("slots in 0..{}", self.cfg.max_num_embodiments),
                bad,
            ));
        }
        let v: Vec<u32> = v.iter().map(|&x| x as u32).collect();
        Ok(Tensor::from_vec(v, b, &self.device)?)
    }

    /// GR00T's backbone post-processing: `vlln`, then `vl_self_attention`.
    /// `features [B, T, D_vl]` → `[B, T, D_vl]`.
    pub fn process_backbone(&self, features: &Tensor) -> Result<Tensor> {
        let d = self.cfg.backbone_embedding_dim;
        match features.dims() {
            [_, _, w] if *w == d => {}
            _ => return Err(shape_err("backbone features", ("B", "T", d), features)),
        }
        let mut x = match &self.vlln {
            Some(n) => n.forward(features)?,
            None => features.clone(),
        };
        for b in &self.vl_self_attention {
            x = b.forward(&x, None, None, None, None)?;
        }
        Ok(x)
    }

    /// The state token: `state [B, state_history_length, max_state_dim]` (normalised and
    /// padded as GR00T's processor does), `embodiment_id [B]` → `[B, 1, D_in]`.
    pub fn encode_state(&self, state: &Tensor, embodiment_id: &Tensor) -> Result<Tensor> {
        let c = &self.cfg;
        let b = match state.dims() {
            [b, h, s] if *h == c.state_history_length && *s == c.max_state_dim => *b,
            _ => {
                return Err(shape_err(
                    "state",
                    ("B", c.state_history_length, c.max_state_dim),
                    state,
                ))
            }
        };
        let ids = self.embodiment(embodiment_id, b)?;
        let x = state.reshape((b, 1, c.state_input_dim()))?;
        self.state_encoder.forward(&x, &ids)
    }

    /// The action tokens: `actions [B, H, A_max]` at `timesteps [B, H]` → `[B, H, D_in]`
    /// (the action encoder plus the position embedding).
    pub fn encode_actions(
        &self,
        actions: &Tensor,
        timesteps: &Tensor,
        embodiment_id: &Tensor,
    ) -> Result<Tensor> {
        let c = &self.cfg;
        let (b, h) = match actions.dims() {
            [b, h, a] if *a == c.max_action_dim => (*b, *h),
            _ => return Err(shape_err("actions", ("B", "H", c.max_action_dim), actions)),
        };
        if c.add_pos_embed && h > c.max_seq_len {
            return Err(shape_err(
                "actions",
                ("B", c.max_seq_len, c.max_action_dim),
                actions,
            ));
        }
        let t = values("action timesteps", timesteps, &[b, h])?;
        let ids = self.embodiment(embodiment_id, b)?;
        let e = &self.action_encoder;
        let a = e.w1.forward(actions, &ids)?;
        let tau = action_time_features(&t, c.input_embedding_dim, &self.device)?.reshape((
            b,
            h,
            c.input_embedding_dim,
        ))?;
        let x = Tensor::cat(&[&a, &tau], D::Minus1)?;
        let x = e.w2.forward(&x, &ids)?.silu()?;
        let mut x = e.w3.forward(&x, &ids)?;
        if let Some(pe) = &self.position_embedding {
            x = x.broadcast_add(&pe.narrow(0, 0, h)?)?;
        }
        Ok(x)
    }

    /// Timestep embedding `[B, 1, D_in]` (shared) or `[B, N, D_in]` (per token).
    fn time_embedding(&self, t: &[f32], b: usize, n: usize) -> Result<Tensor> {
        let f = dit_time_features(t, &self.device)?;
        let e = self
            .dit
            .time_2
            .forward(&self.dit.time_1.forward(&f)?.silu()?)?;
        Ok(e.reshape((b, n, self.cfg.input_embedding_dim))?)
    }

    /// The DiT: `sa_embs [B, N, D_in]` (state token, then action tokens), the VL tokens and
    /// a timestep per sample `[B]` or per token `[B, N]` → `[B, N, output_dim]`.
    pub fn dit(&self, sa_embs: &Tensor, vl: &VlTokens<'_>, timestep: &Tensor) -> Result<Tensor> {
        self.dit_with(sa_embs, vl, timestep, None)
    }

    /// [`Self::dit`] with the training forward's dropout in every block (`None`: inference).
    fn dit_with(
        &self,
        sa_embs: &Tensor,
        vl: &VlTokens<'_>,
        timestep: &Tensor,
        dropout: Option<&DitDropout>,
    ) -> Result<Tensor> {
        let c = &self.cfg;
        let (b, n) = match sa_embs.dims() {
            [b, n, d] if *d == c.input_embedding_dim => (*b, *n),
            _ => {
                return Err(shape_err(
                    "sa_embs",
                    ("B", "N", c.input_embedding_dim),
                    sa_embs,
                ))
            }
        };
        let temb = match timestep.dims() {
            [tb] if *tb == b => self.time_embedding(&values("timestep", timestep, &[b])?, b, 1)?,
            _ => self.time_embedding(&values("timestep", timestep, &[b, n])?, b, n)?,
        };
        let s = match vl.embeddings.dims() {
            [vb, s, d] if *vb == b && *d == c.backbone_embedding_dim => *s,
            _ => {
                return Err(shape_err(
                    "VL embeddings",
                    (b, "T", c.backbone_embedding_dim),
                    vl.embeddings,
                ))
            }
        };
        let mask = |what: &str, m: Option<&Tensor>, default: bool| -> Result<Vec<Vec<bool>>> {
            Ok(match m {
                None => vec![vec![default; s]; b],
                Some(m) => values(what, m, &[b, s])?
                    .chunks(s)
                    .map(|r| r.iter().map(|&x| x != 0.0).collect())
                    .collect(),
            })
        };
        // (text bias, image bias) of the alternating DiT
        let biases = if c.use_alternate_vl_dit {
            let image = vl.image_mask.ok_or_else(|| {
                Error::config(
                    "image_mask",
                    "the alternating DiT (use_alternate_vl_dit) needs the image mask",
                )
            })?;
            let image = mask("image_mask", Some(image), false)?;
            let attn = mask("backbone_attention_mask", vl.attention_mask, true)?;
            let pick = |want_image: bool| -> Vec<Vec<bool>> {
                image
                    .iter()
                    .zip(&attn)
                    .map(|(im, at)| {
                        im.iter()
                            .zip(at)
                            .map(|(&i, &a)| a && i == want_image)
                            .collect()
                    })
                    .collect()
            };
            let (text, img) = (pick(false), pick(true));
            let n_alt = c.attend_text_every_n_blocks;
            let uses = |want_image: bool| {
                self.dit
                    .cross
                    .iter()
                    .enumerate()
                    .any(|(i, &x)| x && (i % (2 * n_alt) != 0) == want_image)
            };
            for (what, m, want) in [("text", &text, false), ("image", &img, true)] {
                if uses(want) {
                    if let Some(row) = m.iter().position(|r| !r.iter().any(|&x| x)) {
                        return Err(Error::config(
                            "image_mask",
                            format!(
                                "sample {row} has no attended {what} token; its {what} \
                                 cross-attention would be undefined"
                            ),
                        ));
                    }
                }
            }
            Some((
                attention_bias(&text, &self.device)?,
                attention_bias(&img, &self.device)?,
            ))
        } else {
            None
        };
        let mut x = sa_embs.clone();
        for (i, (block, &is_cross)) in self.dit.blocks.iter().zip(&self.dit.cross).enumerate() {
            let drop = dropout.map(|d| (d, i));
            x = if !is_cross {
                block.forward(&x, Some(&temb), None, None, drop)?
            } else {
                let bias = biases.as_ref().map(|(text, image)| {
                    if i % (2 * c.attend_text_every_n_blocks) == 0 {
                        text
                    } else {
                        image
                    }
                });
                block.forward(&x, Some(&temb), Some(vl.embeddings), bias, drop)?
            };
        }
        let d = c.input_embedding_dim;
        let m = self.dit.proj_out_1.forward(&temb.silu()?)?;
        let shift = m.narrow(D::Minus1, 0, d)?;
        let scale = (m.narrow(D::Minus1, d, d)? + 1.0)?;
        let x = crate::candle::layers::layer_norm(&x, 1e-6)?
            .broadcast_mul(&scale)?
            .broadcast_add(&shift)?;
        self.dit.proj_out_2.forward(&x)
    }

    /// The action decoder: `model_output [B, N, hidden_size]` → `[B, N, A_max]`.
    pub fn decode(&self, model_output: &Tensor, embodiment_id: &Tensor) -> Result<Tensor> {
        let b = match model_output.dims() {
            [b, _, d] if *d == self.cfg.hidden_size => *b,
            _ => {
                return Err(shape_err(
                    "model_output",
                    ("B", "N", self.cfg.hidden_size),
                    model_output,
                ))
            }
        };
        let ids = self.embodiment(embodiment_id, b)?;
        self.action_decoder.forward(model_output, &ids)
    }

    /// One velocity evaluation (one NFE): `state_features [B, 1, D_in]` from
    /// [`Self::encode_state`], `actions [B, H, A_max]` → velocity `[B, H, A_max]`.
    /// Deterministic: no dropout (GR00T in `eval` mode).
    pub fn velocity(
        &self,
        state_features: &Tensor,
        actions: &Tensor,
        timesteps: Timesteps<'_>,
        vl: &VlTokens<'_>,
        embodiment_id: &Tensor,
    ) -> Result<Tensor> {
        self.velocity_with(state_features, actions, timesteps, vl, embodiment_id, None)
    }

    /// The training forward: [`Self::velocity`] with GR00T's dropout in the DiT blocks
    /// ([`DitDropout`]; its masks depend on its seed and step only). With a zero rate it is
    /// [`Self::velocity`] bit for bit.
    pub fn velocity_train(
        &self,
        state_features: &Tensor,
        actions: &Tensor,
        timesteps: Timesteps<'_>,
        vl: &VlTokens<'_>,
        embodiment_id: &Tensor,
        dropout: &DitDropout,
    ) -> Result<Tensor> {
        self.velocity_with(
            state_features,
            actions,
            timesteps,
            vl,
            embodiment_id,
            Some(dropout),
        )
    }

    fn velocity_with(
        &self,
        state_features: &Tensor,
        actions: &Tensor,
        timesteps: Timesteps<'_>,
        vl: &VlTokens<'_>,
        embodiment_id: &Tensor,
        dropout: Option<&DitDropout>,
    ) -> Result<Tensor> {
        let (b, h) = match actions.dims() {
            [b, h, _] => (*b, *h),
            _ => return Err(shape_err("actions", ("B", "H", "A_max"), actions)),
        };
        if state_features.dims() != [b, 1, self.cfg.input_embedding_dim] {
            return Err(shape_err(
                "state_features",
                (b, 1, self.cfg.input_embedding_dim),
                state_features,
            ));
        }
        let (t_actions, t_tokens) = match timesteps {
            Timesteps::Shared(t) => {
                values("timesteps", t, &[b])?;
                (t.reshape((b, 1))?.broadcast_as((b, h))?, t.clone())
            }
            Timesteps::PerPosition { actions, tokens } => {
                values("token timesteps", tokens, &[b, 1 + h])?;
                (actions.clone(), tokens.clone())
            }
        };
        let a = self.encode_actions(actions, &t_actions, embodiment_id)?;
        let a = self.add_delay_embedding(&a, vl.d_vis)?;
        let sa = Tensor::cat(&[state_features, &a], 1)?;
        let out = self.dit_with(&sa, vl, &t_tokens, dropout)?;
        let pred = self.decode(&out, embodiment_id)?;
        Ok(pred.narrow(1, 1, h)?)
    }

    /// GR00T's own sampler (the base model's `get_action` without RTC):
    /// `num_inference_timesteps` Euler steps from `noise [B, H, A_max]` with the shared
    /// timestep `⌊k/K · buckets⌋` at step `k` → actions `[B, H, A_max]`.
    pub fn sample(
        &self,
        state_features: &Tensor,
        noise: &Tensor,
        vl: &VlTokens<'_>,
        embodiment_id: &Tensor,
    ) -> Result<Tensor> {
        let b = noise.dim(0)?;
        let k_total = self.cfg.num_inference_timesteps;
        let dt = (1.0 / k_total as f64) as f32;
        let mut x = noise.clone();
        for k in 0..k_total {
            let t = ((k as f64 / k_total as f64) * self.cfg.num_timestep_buckets as f64) as u32;
            let t = Tensor::from_vec(vec![t; b], b, &self.device)?;
            let v = self.velocity(state_features, &x, Timesteps::Shared(&t), vl, embodiment_id)?;
            x = (x + (v * dt as f64)?)?;
        }
        Ok(x)
    }
}
