//! Export of a (πR²-fine-tuned) GR00T N1.7 action head to the ONNX layout of the GR00T stack
//! (`docs/gr00t-contract.md`, checked by `pir2_backends::gr00t::contract` on load).
//!
//! One file on purpose: each exported graph is the ONNX twin of one piece of the candle head,
//! emitted by one small emitter over the same weights.
//!
//! The head is read with [`Gr00tN17Head::load`] (a `pir2 gr00t train` step directory or any
//! N1.7 checkpoint with a delay table) and written, without Python, as:
//!
//! | file | graph |
//! |------|-------|
//! | `onnx/state_encoder.onnx` | `state [B,1,S_in]`, `embodiment_id [B]` → `output [B,1,D_in]` (per-slot MLP) |
//! | `onnx/action_encoder.onnx` | `actions [B,H,A_max]`, `timesteps [B,H]` (per position), `embodiment_id` → `output [B,H,D_in]` (no position embedding) |
//! | `onnx/dit.onnx` | `sa_embs [B,1+H,D_in]`, `vl_embs [B,T,D_vl]`, `timestep [B,1+H]` (per token), masks → `output [B,1+H,D_hid]` |
//! | `onnx/action_decoder.onnx` | `model_output [B,1+H,D_hid]`, `embodiment_id` → `output [B,1+H,A_max]` |
//! | `onnx/vl_self_attention.onnx` | only when the head has a VL self-attention stack |
//! | `pir2_gr00t.safetensors` | `delay_embedding.weight`, `position_embedding.weight` (if `add_pos_embed`), `vlln.{weight,bias}` (if `use_vlln`) |
//!
//! Every graph computes exactly what [`Gr00tN17Head`] computes, op for op: the same
//! sinusoid frequency tables, the same AdaLN order (`scale` first in the blocks, `shift`
//! first in the output modulation), the same text/image alternation of the cross-attending
//! blocks (with `image_mask` and `backbone_attention_mask` declared only when the head
//! alternates; a head that does not alternate attends to every token, as the candle head
//! does). The masks turn into an additive `0 / −∞` bias. Float tensors are `float32`.
//!
//! Weights are stored inside the protobuf, except for a graph whose weights exceed
//! [`AUTO_EXTERNAL_BYTES`] (the full-size N1.7 DiT: about 0.55 B parameters, 2.2 GB as `f32`,
//! over protobuf's 2 GiB): its large tensors go to `onnx/<graph>.onnx.data` in ONNX's
//! external-data layout ([`WeightStorage`]).

use std::collections::HashMap;
use std::path::Path;

use crate::error::Error as ExportError;
use crate::export::graph::{attr, GraphBuilder};
use crate::export::proto::{AttrValue, DataType, Dim, ExternalData, ModelProto};
use crate::gr00t::n17::{
    action_time_frequencies, dit_time_frequencies, sinusoidal_table_values, Gr00tN17Config,
    Gr00tN17Head, DELAY_EMBEDDING, PREFIX,
};

const MODEL: &str = "GR00T N1.7 action head";

/// The largest graph (weights included) the exporter writes: protobuf's 2 GiB limit.
pub const MAX_GRAPH_BYTES: usize = (1 << 31) - 1;

/// The graph files under `onnx/`, in the contract's names.
pub const STATE_ENCODER_FILE: &str = "state_encoder.onnx";
/// See [`STATE_ENCODER_FILE`].
pub const ACTION_ENCODER_FILE: &str = "action_encoder.onnx";
/// See [`STATE_ENCODER_FILE`].
pub const DIT_FILE: &str = "dit.onnx";
/// See [`STATE_ENCODER_FILE`].
pub const ACTION_DECODER_FILE: &str = "action_decoder.onnx";
/// See [`STATE_ENCODER_FILE`].
pub const VL_SELF_ATTENTION_FILE: &str = "vl_self_attention.onnx";
/// The side weights file in the checkpoint root.
pub const SIDE_WEIGHTS_FILE: &str = "pir2_gr00t.safetensors";

/// The exported head before it is written: the head's weights (copied, so the head can be
/// dropped), the side weights, and the graphs to build. Each graph is built only while it is
/// written ([`Gr00tExport::write`]), so at most one graph is in memory at a time.
pub struct Gr00tExport {
    cfg: Gr00tN17Config,
    weights: Weights,
    horizon: usize,
    /// `(name, shape, values)` of `pir2_gr00t.safetensors`.
    pub side: Vec<(String, Vec<usize>, Vec<f32>)>,
    /// Rows of the delay table minus one.
    pub d_vis_max: usize,
}

impl std::fmt::Debug for Gr00tExport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gr00tExport")
            .field("graphs", &self.graph_files())
            .field("horizon", &self.horizon)
            .field("d_vis_max", &self.d_vis_max)
            .field("weights", &self.weights.map.len())
            .finish()
    }
}

/// The head's parameters by name (without [`PREFIX`]), as `f32`.
struct Weights {
    map: HashMap<String, (Vec<usize>, Vec<f32>)>,
}

impl Weights {
    fn from_head(head: &Gr00tN17Head) -> Result<Self, ExportError> {
        let mut map = HashMap::new();
        for (name, t) in head.parameters() {
            let short = name.strip_prefix(PREFIX).unwrap_or(name).to_string();
            let data = t
                .flatten_all()
                .and_then(|t| t.to_dtype(candle_core::DType::F32))
                .and_then(|t| t.to_vec1::<f32>())
                .map_err(|e| ExportError::Unsupported {
                    model: MODEL,
                    message: format!("cannot read tensor `{name}`: {e}"),
                })?;
            map.insert(short, (t.dims().to_vec(), data));
        }
        Ok(Weights { map })
    }

    fn get(&self, name: &str, shape: &[usize]) -> Result<&[f32], ExportError> {
        let (s, d) = self
            .map
            .get(name)
            .ok_or_else(|| ExportError::MissingWeight {
                model: MODEL,
                name: format!("{PREFIX}{name}"),
            })?;
        if s.as_slice() != shape {
            return Err(ExportError::WeightShape {
                model: MODEL,
                name: format!("{PREFIX}{name}"),
                expected: shape.to_vec(),
                got: s.clone(),
            });
        }
        Ok(d)
    }
}

fn batch() -> Dim {
    Dim::Symbolic("B".into())
}

fn fixed(n: usize) -> Dim {
    Dim::Fixed(n)
}

/// Emits one graph, reading the weights by name.
struct Emitter<'a> {
    g: GraphBuilder,
    w: &'a Weights,
}

impl Emitter<'_> {
    fn linear(&mut self, x: &str, name: &str, i: usize, o: usize) -> Result<String, ExportError> {
        let w = self.w.get(&format!("{name}.weight"), &[o, i])?;
        let b = self.w.get(&format!("{name}.bias"), &[o])?;
        Ok(self.g.linear(x, name, w, Some(b), i, o))
    }

    /// An AdaLN modulation of `x [B, N, in]`: GR00T's shared layer, or πR²'s per-position
    /// heads (`name_heads.weight [N, out, in]`) when the head has them — token `i` through
    /// head `i`, one batched `MatMul` over the tokens.
    fn ada(
        &mut self,
        x: &str,
        name: &str,
        tokens: usize,
        i: usize,
        o: usize,
    ) -> Result<String, ExportError> {
        let heads = format!("{name}_heads.weight");
        if !self.w.map.contains_key(&heads) {
            return self.linear(x, name, i, o);
        }
        let w = self.w.get(&heads, &[tokens, o, i])?;
        let b = self.w.get(&format!("{name}_heads.bias"), &[tokens, o])?;
        // [N, out, in] → [N, in, out]
        let mut wt = vec![0f32; w.len()];
        for n in 0..tokens {
            for r in 0..o {
                for c in 0..i {
                    wt[(n * i + c) * o + r] = w[(n * o + r) * i + c];
                }
            }
        }
        let wn = self
            .g
            .weight(&format!("{name}_heads.weight"), &[tokens, i, o], &wt);
        let bn = self
            .g
            .weight(&format!("{name}_heads.bias"), &[tokens, o], b);
        let xu = self.g.unsqueeze(x, &[-2]); // [B, N, 1, in]
        let m = self.g.op("MatMul", &[&xu, &wn], vec![]); // [B, N, 1, out]
        let m = self.g.reshape(&m, &[0, tokens as i64, o as i64]);
        Ok(self.g.add(&m, &bn))
    }

    /// GR00T's `CategorySpecificLinear`: `x [B,S,in] · W[ids] [B,in,out] + b[ids]`.
    fn category_linear(
        &mut self,
        x: &str,
        ids: &str,
        name: &str,
        slots: usize,
        i: usize,
        o: usize,
    ) -> Result<String, ExportError> {
        let w = self.w.get(&format!("{name}.W"), &[slots, i, o])?;
        let b = self.w.get(&format!("{name}.b"), &[slots, o])?;
        let wn = self.g.weight(&format!("{name}.W"), &[slots, i, o], w);
        let bn = self.g.weight(&format!("{name}.b"), &[slots, o], b);
        let axis0 = vec![attr("axis", AttrValue::Int(0))];
        let wi = self.g.op("Gather", &[&wn, ids], axis0.clone());
        let bi = self.g.op("Gather", &[&bn, ids], axis0);
        let bu = self.g.unsqueeze(&bi, &[1]);
        let m = self.g.op("MatMul", &[x, &wi], vec![]);
        Ok(self.g.add(&m, &bu))
    }

    fn category_mlp(
        &mut self,
        x: &str,
        ids: &str,
        name: &str,
        slots: usize,
        dims: (usize, usize, usize),
    ) -> Result<String, ExportError> {
        let (i, h, o) = dims;
        let a = self.category_linear(x, ids, &format!("{name}.layer1"), slots, i, h)?;
        let a = self.g.unary("Relu", &a);
        self.category_linear(&a, ids, &format!("{name}.layer2"), slots, h, o)
    }

    /// LayerNorm over the last axis without affine parameters.
    fn plain_norm(&mut self, x: &str, dim: usize, eps: f64) -> String {
        let ones = self.g.const_f32(&[dim], &vec![1.0; dim]);
        self.g.op(
            "LayerNormalization",
            &[x, &ones],
            vec![
                attr("axis", AttrValue::Int(-1)),
                attr("epsilon", AttrValue::Float(eps as f32)),
            ],
        )
    }

    fn affine_norm(
        &mut self,
        x: &str,
        name: &str,
        dim: usize,
        eps: f64,
    ) -> Result<String, ExportError> {
        let w = self.w.get(&format!("{name}.weight"), &[dim])?.to_vec();
        let b = self.w.get(&format!("{name}.bias"), &[dim])?.to_vec();
        Ok(self.g.layer_norm(x, name, &w, Some(&b), eps as f32))
    }

    /// The first `len(x, axis 1)` rows of a constant table `[rows, dim]`.
    fn rows_like(&mut self, table: &str, x: &str) -> String {
        let shape = self.g.op("Shape", &[x], vec![]);
        let n = self.g.slice(&shape, 0, 1, 2);
        let zero = self.g.const_i64(&[0]);
        let axis = self.g.const_i64(&[0]);
        self.g.op("Slice", &[table, &zero, &n, &axis], vec![])
    }

    /// `(x [B,N,dim]` attends to `source [B,M,source_dim]`; `bias [B,1,1,M]` additive).
    #[allow(clippy::too_many_arguments)]
    fn attention(
        &mut self,
        x: &str,
        source: &str,
        bias: Option<&str>,
        name: &str,
        dim: usize,
        source_dim: usize,
        heads: usize,
        head_dim: usize,
    ) -> Result<String, ExportError> {
        let inner = heads * head_dim;
        let q = self.linear(x, &format!("{name}.to_q"), dim, inner)?;
        let k = self.linear(source, &format!("{name}.to_k"), source_dim, inner)?;
        let v = self.linear(source, &format!("{name}.to_v"), source_dim, inner)?;
        let split = |g: &mut GraphBuilder, t: &str| {
            let r = g.reshape(t, &[0, -1, heads as i64, head_dim as i64]);
            g.transpose(&r, &[0, 2, 1, 3])
        };
        let q = split(&mut self.g, &q);
        let k = split(&mut self.g, &k);
        let v = split(&mut self.g, &v);
        let kt = self.g.transpose(&k, &[0, 1, 3, 2]);
        let s = self.g.op("MatMul", &[&q, &kt], vec![]);
        let mut s = self.g.scale(&s, (1.0 / (head_dim as f64).sqrt()) as f32);
        if let Some(b) = bias {
            s = self.g.add(&s, b);
        }
        let p = self
            .g
            .op("Softmax", &[&s], vec![attr("axis", AttrValue::Int(-1))]);
        let o = self.g.op("MatMul", &[&p, &v], vec![]);
        let o = self.g.transpose(&o, &[0, 2, 1, 3]);
        let o = self.g.reshape(&o, &[0, -1, inner as i64]);
        self.linear(&o, &format!("{name}.to_out.0"), inner, dim)
    }

    /// A diffusers-style block as GR00T configures it (see the candle head's `Block`).
    #[allow(clippy::too_many_arguments)]
    fn block(
        &mut self,
        x: &str,
        name: &str,
        temb: Option<(&str, usize)>,
        source: Option<(&str, usize)>,
        bias: Option<&str>,
        dim: usize,
        heads: usize,
        head_dim: usize,
        positions: Option<&str>,
        eps: f64,
    ) -> Result<String, ExportError> {
        let mut h = match temb {
            Some((temb, tokens)) => {
                let st = self.g.silu(temb);
                let m = self.ada(&st, &format!("{name}.norm1.linear"), tokens, dim, 2 * dim)?;
                let scale = self.g.slice(&m, -1, 0, dim as i64);
                let scale = self.g.offset(&scale, 1.0);
                let shift = self.g.slice(&m, -1, dim as i64, 2 * dim as i64);
                let n = self.plain_norm(x, dim, eps);
                let n = self.g.mul(&n, &scale);
                self.g.add(&n, &shift)
            }
            None => self.affine_norm(x, &format!("{name}.norm1"), dim, eps)?,
        };
        if let Some(table) = positions {
            let pe = self.rows_like(table, x);
            h = self.g.add(&h, &pe);
        }
        let (src, src_dim) = source.unwrap_or((h.as_str(), dim));
        let src = src.to_string();
        let a = self.attention(
            &h,
            &src,
            bias,
            &format!("{name}.attn1"),
            dim,
            src_dim,
            heads,
            head_dim,
        )?;
        let x = self.g.add(x, &a);
        let n3 = match temb {
            Some(_) => self.plain_norm(&x, dim, eps),
            None => self.affine_norm(&x, &format!("{name}.norm3"), dim, eps)?,
        };
        let f = self.linear(&n3, &format!("{name}.ff.net.0.proj"), dim, 4 * dim)?;
        let f = self.g.gelu_tanh(&f);
        let f = self.linear(&f, &format!("{name}.ff.net.2"), 4 * dim, dim)?;
        Ok(self.g.add(&x, &f))
    }

    fn finish(self, role: &str) -> ModelProto {
        self.g.finish(vec![
            ("pir2.model".into(), format!("gr00t_n17.{role}")),
            (
                "pir2.contract".into(),
                "docs/gr00t-contract.md (pir2 GR00T export)".into(),
            ),
        ])
    }
}

fn state_encoder(c: &Gr00tN17Config, w: &Weights) -> Result<ModelProto, ExportError> {
    let mut e = Emitter {
        g: GraphBuilder::new("state_encoder"),
        w,
    };
    let s_in = c.state_input_dim();
    let x = e.g.input(
        "state",
        DataType::Float,
        vec![batch(), fixed(1), fixed(s_in)],
    );
    let ids = e.g.input("embodiment_id", DataType::Int64, vec![batch()]);
    let y = e.category_mlp(
        &x,
        &ids,
        "state_encoder",
        c.max_num_embodiments,
        (s_in, c.hidden_size, c.input_embedding_dim),
    )?;
    e.g.output(
        &y,
        "output",
        DataType::Float,
        vec![batch(), fixed(1), fixed(c.input_embedding_dim)],
    );
    Ok(e.finish("state_encoder"))
}

fn action_encoder(c: &Gr00tN17Config, w: &Weights, h: usize) -> Result<ModelProto, ExportError> {
    let mut e = Emitter {
        g: GraphBuilder::new("action_encoder"),
        w,
    };
    let (d, slots) = (c.input_embedding_dim, c.max_num_embodiments);
    let x = e.g.input(
        "actions",
        DataType::Float,
        vec![batch(), fixed(h), fixed(c.max_action_dim)],
    );
    let t =
        e.g.input("timesteps", DataType::Int64, vec![batch(), fixed(h)]);
    let ids = e.g.input("embodiment_id", DataType::Int64, vec![batch()]);
    let a = e.category_linear(&x, &ids, "action_encoder.W1", slots, c.max_action_dim, d)?;
    // [sin(t·ω), cos(t·ω)], ω as the reference computes it.
    let freqs = action_time_frequencies(d);
    let half = freqs.len();
    let tf = e.g.cast_f32(&t);
    let tu = e.g.unsqueeze(&tf, &[-1]);
    let fr = e.g.const_f32(&[half], &freqs);
    let ang = e.g.mul(&tu, &fr);
    let sin = e.g.unary("Sin", &ang);
    let cos = e.g.unary("Cos", &ang);
    let tau = e.g.concat(&[&sin, &cos], -1);
    let x = e.g.concat(&[&a, &tau], -1);
    let x = e.category_linear(&x, &ids, "action_encoder.W2", slots, d + 2 * half, d)?;
    let x = e.g.silu(&x);
    let y = e.category_linear(&x, &ids, "action_encoder.W3", slots, d, d)?;
    e.g.output(
        &y,
        "output",
        DataType::Float,
        vec![batch(), fixed(h), fixed(d)],
    );
    Ok(e.finish("action_encoder"))
}

fn dit(c: &Gr00tN17Config, w: &Weights, h: usize) -> Result<ModelProto, ExportError> {
    let mut e = Emitter {
        g: GraphBuilder::new("dit"),
        w,
    };
    let (d, d_vl, n) = (c.input_embedding_dim, c.backbone_embedding_dim, 1 + h);
    let dc = &c.dit;
    let t_dim = || Dim::Symbolic("T".into());
    let sa = e.g.input(
        "sa_embs",
        DataType::Float,
        vec![batch(), fixed(n), fixed(d)],
    );
    let vl = e.g.input(
        "vl_embs",
        DataType::Float,
        vec![batch(), t_dim(), fixed(d_vl)],
    );
    let t =
        e.g.input("timestep", DataType::Int64, vec![batch(), fixed(n)]);
    // Text and image biases of the alternating DiT, `[B, 1, 1, T]`.
    let biases = if c.use_alternate_vl_dit {
        let img =
            e.g.input("image_mask", DataType::Bool, vec![batch(), t_dim()]);
        let att = e.g.input(
            "backbone_attention_mask",
            DataType::Bool,
            vec![batch(), t_dim()],
        );
        let not_img = e.g.op("Not", &[&img], vec![]);
        let text = e.g.op("And", &[&not_img, &att], vec![]);
        let image = e.g.op("And", &[&img, &att], vec![]);
        let zero = e.g.const_f32(&[], &[0.0]);
        let ninf = e.g.const_f32(&[], &[f32::NEG_INFINITY]);
        let mut bias = |m: &str| {
            let b = e.g.op("Where", &[m, &zero, &ninf], vec![]);
            e.g.unsqueeze(&b, &[1, 2])
        };
        Some((bias(&text), bias(&image)))
    } else {
        None
    };
    // Per-token timestep embedding [B, N, D].
    let tf = e.g.cast_f32(&t);
    let tu = e.g.unsqueeze(&tf, &[-1]);
    let freqs = dit_time_frequencies();
    let fr = e.g.const_f32(&[freqs.len()], &freqs);
    let ang = e.g.mul(&tu, &fr);
    let cos = e.g.unary("Cos", &ang);
    let sin = e.g.unary("Sin", &ang);
    let f = e.g.concat(&[&cos, &sin], -1);
    let te = e.linear(
        &f,
        "model.timestep_encoder.timestep_embedder.linear_1",
        2 * freqs.len(),
        d,
    )?;
    let te = e.g.silu(&te);
    let temb = e.linear(
        &te,
        "model.timestep_encoder.timestep_embedder.linear_2",
        d,
        d,
    )?;
    let positions = if dc.sinusoidal_positions {
        let rows = dc.max_num_positional_embeddings;
        Some(e.g.const_f32(&[rows, d], &sinusoidal_table_values(rows, d)))
    } else {
        None
    };
    let mut x = sa;
    for i in 0..dc.num_layers {
        let is_cross = !(dc.interleave_self_attention && i % 2 == 1);
        let bias = match (&biases, is_cross) {
            (Some((text, image)), true) => Some(if i % (2 * c.attend_text_every_n_blocks) == 0 {
                text.clone()
            } else {
                image.clone()
            }),
            _ => None,
        };
        x = e.block(
            &x,
            &format!("model.transformer_blocks.{i}"),
            Some((&temb, n)),
            is_cross.then_some((vl.as_str(), d_vl)),
            bias.as_deref(),
            d,
            dc.num_attention_heads,
            dc.attention_head_dim,
            positions.as_deref(),
            dc.norm_eps,
        )?;
    }
    let st = e.g.silu(&temb);
    let m = e.ada(&st, "model.proj_out_1", n, d, 2 * d)?;
    let shift = e.g.slice(&m, -1, 0, d as i64);
    let scale = e.g.slice(&m, -1, d as i64, 2 * d as i64);
    let scale = e.g.offset(&scale, 1.0);
    let xn = e.plain_norm(&x, d, 1e-6);
    let xn = e.g.mul(&xn, &scale);
    let xn = e.g.add(&xn, &shift);
    let y = e.linear(&xn, "model.proj_out_2", d, dc.output_dim)?;
    e.g.output(
        &y,
        "output",
        DataType::Float,
        vec![batch(), fixed(n), fixed(dc.output_dim)],
    );
    Ok(e.finish("dit"))
}

fn action_decoder(c: &Gr00tN17Config, w: &Weights, h: usize) -> Result<ModelProto, ExportError> {
    let mut e = Emitter {
        g: GraphBuilder::new("action_decoder"),
        w,
    };
    let n = 1 + h;
    let x = e.g.input(
        "model_output",
        DataType::Float,
        vec![batch(), fixed(n), fixed(c.hidden_size)],
    );
    let ids = e.g.input("embodiment_id", DataType::Int64, vec![batch()]);
    let y = e.category_mlp(
        &x,
        &ids,
        "action_decoder",
        c.max_num_embodiments,
        (c.hidden_size, c.hidden_size, c.max_action_dim),
    )?;
    e.g.output(
        &y,
        "output",
        DataType::Float,
        vec![batch(), fixed(n), fixed(c.max_action_dim)],
    );
    Ok(e.finish("action_decoder"))
}

fn vl_self_attention(c: &Gr00tN17Config, w: &Weights) -> Result<Option<ModelProto>, ExportError> {
    let Some(sa) = &c.vl_self_attention else {
        return Ok(None);
    };
    if sa.num_layers == 0 {
        return Ok(None);
    }
    let mut e = Emitter {
        g: GraphBuilder::new("vl_self_attention"),
        w,
    };
    let d = c.backbone_embedding_dim;
    let t_dim = || Dim::Symbolic("T".into());
    let mut x = e.g.input(
        "hidden_states",
        DataType::Float,
        vec![batch(), t_dim(), fixed(d)],
    );
    let positions = if sa.sinusoidal_positions {
        let rows = sa.max_num_positional_embeddings;
        Some(e.g.const_f32(&[rows, d], &sinusoidal_table_values(rows, d)))
    } else {
        None
    };
    for i in 0..sa.num_layers {
        x = e.block(
            &x,
            &format!("vl_self_attention.transformer_blocks.{i}"),
            None,
            None,
            None,
            d,
            sa.num_attention_heads,
            sa.attention_head_dim,
            positions.as_deref(),
            1e-5,
        )?;
    }
    e.g.output(
        &x,
        "output",
        DataType::Float,
        vec![batch(), t_dim(), fixed(d)],
    );
    Ok(Some(e.finish("vl_self_attention")))
}

/// Build the graphs and side weights of `head` for chunk length `horizon`. The head must
/// carry πR²'s delay table (a `pir2 gr00t train` step checkpoint does); `horizon` must fit
/// the position embedding.
pub fn export_gr00t_n17(head: &Gr00tN17Head, horizon: usize) -> Result<Gr00tExport, ExportError> {
    let c = head.config();
    let unsupported = |message: String| ExportError::Unsupported {
        model: MODEL,
        message,
    };
    if horizon == 0 {
        return Err(unsupported("the chunk length H must be at least 1".into()));
    }
    if c.add_pos_embed && horizon > c.max_seq_len {
        return Err(unsupported(format!(
            "the chunk length H = {horizon} exceeds the position embedding's {} rows \
             (max_seq_len)",
            c.max_seq_len
        )));
    }
    let w = Weights::from_head(head)?;
    let delay = head.delay_embedding().ok_or_else(|| {
        unsupported(format!(
            "the checkpoint has no delay table `{PREFIX}{DELAY_EMBEDDING}`: export a πR² \
             fine-tuned head (a `pir2 gr00t train` step directory), not a base GR00T checkpoint"
        ))
    })?;
    let rows = delay.dim(0).map_err(|e| unsupported(e.to_string()))?;
    let d = c.input_embedding_dim;
    let mut side = vec![(
        "delay_embedding.weight".to_string(),
        vec![rows, d],
        w.get(DELAY_EMBEDDING, &[rows, d])?.to_vec(),
    )];
    if c.add_pos_embed {
        side.push((
            "position_embedding.weight".into(),
            vec![c.max_seq_len, d],
            w.get("position_embedding.weight", &[c.max_seq_len, d])?
                .to_vec(),
        ));
    }
    if c.use_vlln {
        let dv = c.backbone_embedding_dim;
        side.push((
            "vlln.weight".into(),
            vec![dv],
            w.get("vlln.weight", &[dv])?.to_vec(),
        ));
        side.push((
            "vlln.bias".into(),
            vec![dv],
            w.get("vlln.bias", &[dv])?.to_vec(),
        ));
    }
    Ok(Gr00tExport {
        cfg: c.clone(),
        weights: w,
        horizon,
        side,
        d_vis_max: rows - 1,
    })
}

impl Gr00tExport {
    /// The graph files under `onnx/` this export writes.
    pub fn graph_files(&self) -> Vec<&'static str> {
        let mut v = vec![
            STATE_ENCODER_FILE,
            ACTION_ENCODER_FILE,
            DIT_FILE,
            ACTION_DECODER_FILE,
        ];
        if self
            .cfg
            .vl_self_attention
            .as_ref()
            .is_some_and(|s| s.num_layers > 0)
        {
            v.push(VL_SELF_ATTENTION_FILE);
        }
        v
    }

    /// Build the graph written as `file` (one of [`Self::graph_files`]).
    pub fn graph(&self, file: &str) -> Result<ModelProto, ExportError> {
        let (c, w, h) = (&self.cfg, &self.weights, self.horizon);
        match file {
            STATE_ENCODER_FILE => state_encoder(c, w),
            ACTION_ENCODER_FILE => action_encoder(c, w, h),
            DIT_FILE => dit(c, w, h),
            ACTION_DECODER_FILE => action_decoder(c, w, h),
            VL_SELF_ATTENTION_FILE => {
                vl_self_attention(c, w)?.ok_or_else(|| ExportError::Unsupported {
                    model: MODEL,
                    message: "the head has no VL self-attention stack".into(),
                })
            }
            other => Err(ExportError::Unsupported {
                model: MODEL,
                message: format!("no graph `{other}`"),
            }),
        }
    }
}

/// How the exporter stores a graph's weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WeightStorage {
    /// Inside the protobuf, unless the graph's weights exceed [`AUTO_EXTERNAL_BYTES`]; then
    /// as [`WeightStorage::External`].
    #[default]
    Auto,
    /// Always inside the protobuf (a graph over [`MAX_GRAPH_BYTES`] is refused).
    Inline,
    /// Every weight of at least [`EXTERNAL_MIN_BYTES`] in `onnx/<graph>.onnx.data`, ONNX's
    /// external-data layout (each tensor at a 4 KiB-aligned offset); ONNX Runtime reads it
    /// next to the model file.
    External,
}

/// [`WeightStorage::Auto`] stores a graph's weights externally above this many bytes (1 GiB).
pub const AUTO_EXTERNAL_BYTES: usize = 1 << 30;
/// Smaller tensors (shapes, scalars, biases) stay inside the protobuf.
pub const EXTERNAL_MIN_BYTES: usize = 1024;
const EXTERNAL_ALIGN: u64 = 4096;

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> ExportError + '_ {
    move |source| ExportError::OnnxWrite {
        path: path.to_path_buf(),
        source,
    }
}

/// Move the large initializers of `model` into `dir/<file>.data`; returns that file's name.
fn externalize(model: &mut ModelProto, dir: &Path, file: &str) -> Result<String, ExportError> {
    use std::io::Write;
    let name = format!("{file}.data");
    let path = dir.join(&name);
    let f = std::fs::File::create(&path).map_err(io_err(&path))?;
    let mut w = std::io::BufWriter::new(f);
    let mut at = 0u64;
    for t in model.graph.initializers.iter_mut() {
        if t.raw_data.len() < EXTERNAL_MIN_BYTES {
            continue;
        }
        let pad = (EXTERNAL_ALIGN - at % EXTERNAL_ALIGN) % EXTERNAL_ALIGN;
        w.write_all(&vec![0u8; pad as usize])
            .map_err(io_err(&path))?;
        at += pad;
        let bytes = std::mem::take(&mut t.raw_data);
        w.write_all(&bytes).map_err(io_err(&path))?;
        t.external = Some(ExternalData {
            location: name.clone(),
            offset: at,
            length: bytes.len() as u64,
        });
        at += bytes.len() as u64;
    }
    w.flush().map_err(io_err(&path))?;
    Ok(name)
}

impl Gr00tExport {
    /// Write `onnx/*.onnx` (with `onnx/*.onnx.data` for externally stored weights, see
    /// [`WeightStorage`]) and [`SIDE_WEIGHTS_FILE`] into `dir` (which must exist); returns
    /// the files written, relative to `dir`. An inline graph over [`MAX_GRAPH_BYTES`] is
    /// refused by name.
    pub fn write(&self, dir: &Path, storage: WeightStorage) -> Result<Vec<String>, ExportError> {
        let onnx = dir.join("onnx");
        std::fs::create_dir_all(&onnx).map_err(io_err(&onnx))?;
        let mut files = Vec::new();
        for file in self.graph_files() {
            let mut m = self.graph(file)?;
            let weight_bytes: usize = m.graph.initializers.iter().map(|t| t.raw_data.len()).sum();
            let external = match storage {
                WeightStorage::Inline => false,
                WeightStorage::External => true,
                WeightStorage::Auto => weight_bytes > AUTO_EXTERNAL_BYTES,
            };
            if external {
                let data = externalize(&mut m, &onnx, file)?;
                files.push(format!("onnx/{data}"));
            }
            let bytes = m.encode();
            drop(m);
            if bytes.len() > MAX_GRAPH_BYTES {
                return Err(ExportError::Unsupported {
                    model: MODEL,
                    message: format!(
                        "{file} would be {} bytes, over protobuf's 2 GiB limit; store its \
                         weights externally (WeightStorage::External)",
                        bytes.len()
                    ),
                });
            }
            let path = onnx.join(file);
            std::fs::write(&path, bytes).map_err(io_err(&path))?;
            files.push(format!("onnx/{file}"));
        }
        let side = dir.join(SIDE_WEIGHTS_FILE);
        crate::checkpoint::write_tensors(
            &side,
            self.side
                .iter()
                .map(|(n, s, d)| (n.clone(), s.clone(), d.as_slice())),
        )
        .map_err(|e| ExportError::OnnxWrite {
            path: side.clone(),
            source: std::io::Error::other(e.to_string()),
        })?;
        files.push(SIDE_WEIGHTS_FILE.to_string());
        Ok(files)
    }
}
