//! The building blocks of GR00T N1.7's action head, computed as the reference does them.

use candle_core::{DType, Device, Module, Tensor, Var, D};

use super::dropout::{DitDropout, DropoutSite};
use super::weights::TensorIndex;
use crate::candle::layers::layer_norm;
use crate::error::{Error, Result};

/// Loads tensors under the checkpoint prefix and remembers which ones were used.
#[derive(Debug)]
pub(super) struct Loader<'a> {
    pub(super) index: &'a TensorIndex,
    pub(super) prefix: &'static str,
    pub(super) device: &'a Device,
    pub(super) used: Vec<String>,
    /// Every tensor loaded, by its checkpoint name, in load order.
    pub(super) loaded: Vec<(String, Tensor)>,
    /// Make the tensors [`super::is_trained`] accepts trainable ([`Var`]s).
    pub(super) trainable: bool,
    /// The trainable tensors, by checkpoint name.
    pub(super) vars: Vec<(String, Var)>,
}

impl Loader<'_> {
    pub(super) fn tensor(&mut self, name: &str, shape: &[usize]) -> Result<Tensor> {
        let full = format!("{}{name}", self.prefix);
        let mut t = self.index.load(&full, shape, self.device)?;
        if self.trainable && super::is_trained(name) {
            // The network keeps the variable's own tensor: gradients reach it, and
            // `Var::set` updates what the forward reads.
            let v = Var::from_tensor(&t)?;
            t = v.as_tensor().clone();
            self.vars.push((full.clone(), v));
        }
        self.loaded.push((full.clone(), t.clone()));
        self.used.push(full);
        Ok(t)
    }

    /// An AdaLN modulation `name` (`torch.nn.Linear(input, output)` in GR00T): πR²'s
    /// per-position heads `name_heads.{weight [N, output, input], bias [N, output]}` when the
    /// checkpoint holds them (one head per DiT token, `N` from the file), else GR00T's shared
    /// layer.
    pub(super) fn ada(&mut self, name: &str, input: usize, output: usize) -> Result<Ada> {
        let heads = format!("{}{name}_heads.weight", self.prefix);
        match self.index.shape(&heads).map(<[usize]>::to_vec) {
            Some(shape) => {
                let n = shape.first().copied().unwrap_or(0).max(1);
                Ok(Ada::Heads {
                    w: self.tensor(&format!("{name}_heads.weight"), &[n, output, input])?,
                    b: self.tensor(&format!("{name}_heads.bias"), &[n, output])?,
                })
            }
            None => Ok(Ada::Shared(self.linear(name, input, output)?)),
        }
    }

    /// `torch.nn.Linear(input, output)`: `weight [output, input]`, `bias [output]`.
    pub(super) fn linear(&mut self, name: &str, input: usize, output: usize) -> Result<Linear> {
        let w = self.tensor(&format!("{name}.weight"), &[output, input])?;
        let b = self.tensor(&format!("{name}.bias"), &[output])?;
        Ok(Linear(candle_nn::Linear::new(w, Some(b))))
    }

    /// `torch.nn.LayerNorm(dim)` with its affine parameters.
    pub(super) fn layer_norm(&mut self, name: &str, dim: usize, eps: f64) -> Result<AffineNorm> {
        Ok(AffineNorm {
            weight: self.tensor(&format!("{name}.weight"), &[dim])?,
            bias: self.tensor(&format!("{name}.bias"), &[dim])?,
            eps,
        })
    }

    /// GR00T's `CategorySpecificLinear`: `W [C, input, output]`, `b [C, output]`.
    pub(super) fn category_linear(
        &mut self,
        name: &str,
        categories: usize,
        input: usize,
        output: usize,
    ) -> Result<CategoryLinear> {
        Ok(CategoryLinear {
            w: self.tensor(&format!("{name}.W"), &[categories, input, output])?,
            b: self.tensor(&format!("{name}.b"), &[categories, output])?,
        })
    }
}

/// `y = x·Wᵀ + b` over the last dimension.
#[derive(Debug, Clone)]
pub(super) struct Linear(candle_nn::Linear);

impl Linear {
    pub(super) fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.0.forward(x)?)
    }
}

/// An AdaLN modulation: GR00T's one layer shared by every token, or πR²'s one head per DiT
/// token (state token first), each initialised as a copy of the shared layer.
#[derive(Debug, Clone)]
pub(super) enum Ada {
    /// `temb [B, 1 or N, D]` → `[B, 1 or N, out]`.
    Shared(Linear),
    /// Weight `[N, out, in]`, bias `[N, out]`: token `i` through head `i`.
    Heads { w: Tensor, b: Tensor },
}

impl Ada {
    /// `x`: the activated timestep embedding `[B, 1, D]` (per sample) or `[B, N, D]` (per
    /// token); with heads the result is per token, `[B, N, out]`.
    pub(super) fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match self {
            Ada::Shared(l) => l.forward(x),
            Ada::Heads { w, b } => {
                let n = w.dim(0)?;
                let (bs, t, d) = x.dims3()?;
                if t != n && t != 1 {
                    return Err(Error::shape(
                        "DiT tokens (per-position AdaLN heads)",
                        format!("1 or {n}"),
                        t,
                    ));
                }
                let x = x.broadcast_as((bs, n, d))?.transpose(0, 1)?.contiguous()?;
                Ok(x.matmul(&w.transpose(1, 2)?)?
                    .broadcast_add(&b.unsqueeze(1)?)?
                    .transpose(0, 1)?
                    .contiguous()?)
            }
        }
    }

    /// The shared layer's weight `[out, in]` and bias `[out]` (`None` for heads).
    pub(super) fn shared(&self) -> Option<(&Tensor, &Tensor)> {
        match self {
            Ada::Shared(l) => Some((l.0.weight(), l.0.bias()?)),
            Ada::Heads { .. } => None,
        }
    }
}

/// LayerNorm over the last dimension with a learned scale and shift.
#[derive(Debug, Clone)]
pub(super) struct AffineNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl AffineNorm {
    pub(super) fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(layer_norm(x, self.eps)?
            .broadcast_mul(&self.weight)?
            .broadcast_add(&self.bias)?)
    }
}

/// A linear map with one weight matrix per embodiment slot.
#[derive(Debug, Clone)]
pub(super) struct CategoryLinear {
    w: Tensor,
    b: Tensor,
}

impl CategoryLinear {
    /// `x [B, T, in]`, `ids` (u32) `[B]` → `[B, T, out]`.
    pub(super) fn forward(&self, x: &Tensor, ids: &Tensor) -> Result<Tensor> {
        let w = self.w.index_select(ids, 0)?;
        let b = self.b.index_select(ids, 0)?.unsqueeze(1)?;
        Ok(x.contiguous()?.matmul(&w)?.broadcast_add(&b)?)
    }
}

/// GR00T's `CategorySpecificMLP`: `layer2(relu(layer1(x)))`, per embodiment.
#[derive(Debug, Clone)]
pub(super) struct CategoryMlp {
    pub(super) layer1: CategoryLinear,
    pub(super) layer2: CategoryLinear,
}

impl CategoryMlp {
    pub(super) fn load(
        l: &mut Loader<'_>,
        name: &str,
        categories: usize,
        input: usize,
        hidden: usize,
        output: usize,
    ) -> Result<Self> {
        Ok(Self {
            layer1: l.category_linear(&format!("{name}.layer1"), categories, input, hidden)?,
            layer2: l.category_linear(&format!("{name}.layer2"), categories, hidden, output)?,
        })
    }

    pub(super) fn forward(&self, x: &Tensor, ids: &Tensor) -> Result<Tensor> {
        let h = self.layer1.forward(x, ids)?.relu()?;
        self.layer2.forward(&h, ids)
    }
}

/// `exp` of an `f32`, rounded from `f64` (what a correctly rounded `f32` library returns).
fn exp32(x: f32) -> f32 {
    (x as f64).exp() as f32
}

/// The angular frequencies `ω_k = exp(−k · ln(10⁴)/(w/2))`, `k < w/2`, of
/// [`action_time_features`] (computed in `f32` as the reference does).
pub(crate) fn action_time_frequencies(width: usize) -> Vec<f32> {
    let half = width / 2;
    let step = (10_000f32).ln() / half as f32;
    (0..half).map(|k| exp32(-(k as f32) * step)).collect()
}

/// Half the width of the DiT's timestep features.
pub(crate) const DIT_TIME_HALF: usize = 128;

/// The angular frequencies `ω_k = exp(−ln(10⁴)·k/127)`, `k < 128`, of [`dit_time_features`].
pub(crate) fn dit_time_frequencies() -> Vec<f32> {
    let c = -(10_000f64.ln() as f32);
    (0..DIT_TIME_HALF)
        .map(|k| exp32(c * k as f32 / (DIT_TIME_HALF - 1) as f32))
        .collect()
}

/// The action encoder's timestep features (GR00T's `SinusoidalPositionalEncoding`):
/// `[sin(t·ω_k), cos(t·ω_k)]` with `ω_k = exp(−k · ln(10⁴)/(w/2))`, `k < w/2`, in `f32` as the
/// reference computes them. `t` holds one timestep per row.
pub(super) fn action_time_features(t: &[f32], width: usize, device: &Device) -> Result<Tensor> {
    let freqs = action_time_frequencies(width);
    let half = freqs.len();
    let mut out = Vec::with_capacity(t.len() * 2 * half);
    for &tv in t {
        out.extend(freqs.iter().map(|&w| (tv * w).sin()));
        out.extend(freqs.iter().map(|&w| (tv * w).cos()));
    }
    Ok(Tensor::from_vec(out, (t.len(), 2 * half), device)?)
}

/// The DiT's timestep features (diffusers' `Timesteps(256, flip_sin_to_cos=True,
/// downscale_freq_shift=1)`): `[cos(t·ω_k), sin(t·ω_k)]`, `ω_k = exp(−ln(10⁴)·k/127)`, `k < 128`.
pub(super) fn dit_time_features(t: &[f32], device: &Device) -> Result<Tensor> {
    const HALF: usize = DIT_TIME_HALF;
    let freqs = dit_time_frequencies();
    let mut out = Vec::with_capacity(t.len() * 2 * HALF);
    for &tv in t {
        out.extend(freqs.iter().map(|&w| (tv * w).cos()));
        out.extend(freqs.iter().map(|&w| (tv * w).sin()));
    }
    Ok(Tensor::from_vec(out, (t.len(), 2 * HALF), device)?)
}

/// diffusers' `SinusoidalPositionalEmbedding` table `[rows, dim]`: even columns
/// `sin(p·ω_j)`, odd columns `cos(p·ω_j)`, `ω_j = exp(2j · (−ln(10⁴)/dim))`.
pub(super) fn sinusoidal_table(rows: usize, dim: usize, device: &Device) -> Result<Tensor> {
    Ok(Tensor::from_vec(
        sinusoidal_table_values(rows, dim),
        (rows, dim),
        device,
    )?)
}

/// The values of [`sinusoidal_table`], row-major `[rows, dim]`.
pub(crate) fn sinusoidal_table_values(rows: usize, dim: usize) -> Vec<f32> {
    let c = -(10_000f64.ln() / dim as f64) as f32;
    let div: Vec<f32> = (0..dim.div_ceil(2))
        .map(|j| exp32((2 * j) as f32 * c))
        .collect();
    let mut out = vec![0f32; rows * dim];
    for p in 0..rows {
        for (j, &w) in div.iter().enumerate() {
            let a = p as f32 * w;
            out[p * dim + 2 * j] = a.sin();
            if 2 * j + 1 < dim {
                out[p * dim + 2 * j + 1] = a.cos();
            }
        }
    }
    out
}

/// diffusers' `Attention` (bias on every projection, no q/k norm): multi-head scaled
/// dot-product attention of `x` to `source`.
#[derive(Debug, Clone)]
pub(super) struct Attention {
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
}

impl Attention {
    pub(super) fn load(
        l: &mut Loader<'_>,
        name: &str,
        dim: usize,
        source_dim: usize,
        heads: usize,
        head_dim: usize,
    ) -> Result<Self> {
        let inner = heads * head_dim;
        Ok(Self {
            to_q: l.linear(&format!("{name}.to_q"), dim, inner)?,
            to_k: l.linear(&format!("{name}.to_k"), source_dim, inner)?,
            to_v: l.linear(&format!("{name}.to_v"), source_dim, inner)?,
            to_out: l.linear(&format!("{name}.to_out.0"), inner, dim)?,
            heads,
        })
    }

    /// `x [B, N, dim]` attends to `source [B, M, source_dim]`; `bias` (additive, 0 or −∞)
    /// broadcasts to `[B, heads, N, M]`.
    pub(super) fn forward(
        &self,
        x: &Tensor,
        source: &Tensor,
        bias: Option<&Tensor>,
    ) -> Result<Tensor> {
        let (b, n, _) = x.dims3()?;
        let m = source.dim(1)?;
        let q = self.to_q.forward(x)?;
        let inner = q.dim(D::Minus1)?;
        let hd = inner / self.heads;
        let split = |t: Tensor, len: usize| -> Result<Tensor> {
            Ok(t.reshape((b, len, self.heads, hd))?
                .transpose(1, 2)?
                .contiguous()?)
        };
        let q = split(q, n)?;
        let k = split(self.to_k.forward(source)?, m)?;
        let v = split(self.to_v.forward(source)?, m)?;
        let mut scores = (q.matmul(&k.t()?)? * (1.0 / (hd as f64).sqrt()))?;
        if let Some(bias) = bias {
            scores = scores.broadcast_add(bias)?;
        }
        // The composed softmax (max-shifted, differentiable): the same code trains and infers.
        let p = candle_nn::ops::softmax(&scores, D::Minus1)?;
        let o = p
            .matmul(&v)?
            .transpose(1, 2)?
            .reshape((b, n, inner))?
            .contiguous()?;
        self.to_out.forward(&o)
    }
}

/// How a block normalises its input before attention.
#[derive(Debug, Clone)]
pub(super) enum Norm1 {
    /// GR00T's `AdaLayerNorm`: `LN(x)·(1 + scale) + shift`, `[scale, shift] = W·silu(temb) + b`
    /// with `temb` per sample `[B, 1, D]` or per token `[B, N, D]`.
    Ada(Ada),
    /// A plain LayerNorm with affine parameters.
    Affine(AffineNorm),
}

/// diffusers-style `BasicTransformerBlock` as GR00T configures it: norm → attention
/// (self or cross) → residual, LayerNorm → GELU(tanh) feed-forward (×4) → residual.
#[derive(Debug, Clone)]
pub(super) struct Block {
    pub(super) norm1: Norm1,
    pub(super) attn: Attention,
    /// `None`: LayerNorm without affine parameters.
    pub(super) norm3: Option<AffineNorm>,
    pub(super) ff_in: Linear,
    pub(super) ff_out: Linear,
    /// Sinusoidal table added to the normalised input, `[rows, D]`.
    pub(super) positions: Option<Tensor>,
    pub(super) eps: f64,
}

impl Block {
    /// Load `name` (`…transformer_blocks.i`). `source_dim`: `Some` for cross-attention.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn load(
        l: &mut Loader<'_>,
        name: &str,
        dim: usize,
        heads: usize,
        head_dim: usize,
        source_dim: Option<usize>,
        ada: bool,
        positions: Option<&Tensor>,
        eps: f64,
    ) -> Result<Self> {
        let norm1 = if ada {
            Norm1::Ada(l.ada(&format!("{name}.norm1.linear"), dim, 2 * dim)?)
        } else {
            Norm1::Affine(l.layer_norm(&format!("{name}.norm1"), dim, eps)?)
        };
        let attn = Attention::load(
            l,
            &format!("{name}.attn1"),
            dim,
            source_dim.unwrap_or(dim),
            heads,
            head_dim,
        )?;
        let norm3 = if ada {
            None
        } else {
            Some(l.layer_norm(&format!("{name}.norm3"), dim, eps)?)
        };
        Ok(Self {
            norm1,
            attn,
            norm3,
            ff_in: l.linear(&format!("{name}.ff.net.0.proj"), dim, 4 * dim)?,
            ff_out: l.linear(&format!("{name}.ff.net.2"), 4 * dim, dim)?,
            positions: positions.cloned(),
            eps,
        })
    }

    /// `x [B, N, D]`; `temb` for AdaLN blocks; `source` for cross-attention (else self);
    /// `dropout`: the training forward's dropout and this block's index (`None`: inference).
    pub(super) fn forward(
        &self,
        x: &Tensor,
        temb: Option<&Tensor>,
        source: Option<&Tensor>,
        bias: Option<&Tensor>,
        dropout: Option<(&DitDropout, usize)>,
    ) -> Result<Tensor> {
        let d = x.dim(D::Minus1)?;
        let mut h = match &self.norm1 {
            Norm1::Ada(lin) => {
                let temb = temb.ok_or_else(|| {
                    Error::config("timestep", "an AdaLN block needs a timestep embedding")
                })?;
                let m = lin.forward(&temb.silu()?)?;
                let scale = (m.narrow(D::Minus1, 0, d)? + 1.0)?;
                let shift = m.narrow(D::Minus1, d, d)?;
                layer_norm(x, self.eps)?
                    .broadcast_mul(&scale)?
                    .broadcast_add(&shift)?
            }
            Norm1::Affine(n) => n.forward(x)?,
        };
        if let Some(pe) = &self.positions {
            h = h.broadcast_add(&pe.narrow(0, 0, x.dim(1)?)?)?;
        }
        let mut a = self.attn.forward(&h, source.unwrap_or(&h), bias)?;
        if let Some((d, i)) = dropout {
            a = d.apply(&a, DropoutSite::Attention(i))?;
            if d.final_dropout {
                a = d.apply(&a, DropoutSite::AttentionFinal(i))?;
            }
        }
        let x = (x + a)?;
        let n3 = match &self.norm3 {
            Some(n) => n.forward(&x)?,
            None => layer_norm(&x, self.eps)?,
        };
        let mut f = self.ff_in.forward(&n3)?.gelu()?;
        if let Some((d, i)) = dropout {
            f = d.apply(&f, DropoutSite::FeedForwardInner(i))?;
        }
        let mut f = self.ff_out.forward(&f)?;
        if let Some((d, i)) = dropout.filter(|(d, _)| d.final_dropout) {
            f = d.apply(&f, DropoutSite::FeedForwardOutput(i))?;
        }
        Ok((x + f)?)
    }
}

/// `mask` (nonzero = attend) `[B, S]` → additive bias `[B, 1, 1, S]` (0 or −∞).
pub(super) fn attention_bias(mask: &[Vec<bool>], device: &Device) -> Result<Tensor> {
    let b = mask.len();
    let s = mask.first().map_or(0, Vec::len);
    let v: Vec<f32> = mask
        .iter()
        .flat_map(|row| row.iter().map(|&m| if m { 0.0 } else { f32::NEG_INFINITY }))
        .collect();
    Ok(Tensor::from_vec(v, (b, 1, 1, s), device)?.to_dtype(DType::F32)?)
}
