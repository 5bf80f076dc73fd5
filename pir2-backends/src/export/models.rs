//! Model definitions written once against [`Ops`], so ONNX export and TorchScript tracing
//! compute exactly the same function from the same weights.
//!
//! One file on purpose: the three model definitions (MLP, U-Net, and their shared τ features and
//! normalisation) must stay in step with the candle models, definition by definition.

use super::contract::{ContractDims, SlowSpec};
use super::ops::{Ops, Unary, WeightSource};
use crate::error::{Error, Result};

/// The contract inputs as values of an [`Ops`] sink.
#[derive(Debug, Clone)]
pub struct Inputs<T> {
    /// `x [B,H,A]`.
    pub x: T,
    /// `tau [B,H]`.
    pub tau: T,
    /// `obs_fast [B,n_obs,F]`.
    pub obs_fast: T,
    /// `obs_slow` (`[B,S]` or `[B,T,D]`), if the model has one.
    pub obs_slow: Option<T>,
    /// `d_vis [B]` (int64), if declared.
    pub d_vis: Option<T>,
}

/// Width of the flattened slow input.
pub fn slow_width(s: SlowSpec) -> usize {
    match s {
        SlowSpec::None => 0,
        SlowSpec::Vector { dim } => dim,
        SlowSpec::Tokens { tokens, dim } => tokens * dim,
    }
}

/// Load a linear layer's weights (`{name}.weight [out,in]`, `{name}.bias [out]`) and apply it.
pub fn linear<O: Ops, W: WeightSource>(
    o: &mut O,
    w: &W,
    model: &'static str,
    name: &str,
    x: &O::T,
    i: usize,
    out: usize,
) -> Result<O::T> {
    let wt = w.weight(model, &format!("{name}.weight"), &[out, i])?;
    let b = w.weight(model, &format!("{name}.bias"), &[out])?;
    Ok(o.linear(x, name, &wt, Some(&b), i, out))
}

// ------------------------------------------------------------------------------------------
// Observation normalisation and τ features (as the candle models compute them)
// ------------------------------------------------------------------------------------------

/// Per-dimension `(mean, std)` used to normalise observations inside the graph (the candle
/// models' `Stats`: fast `o_t`, fast differences, slow features).
#[derive(Debug, Clone, PartialEq)]
pub struct ObsNorm {
    /// Mean and std of `o_t` (width `F`).
    pub fast: (Vec<f32>, Vec<f32>),
    /// Mean and std of `o_t − o_{t−1}` (width `F`).
    pub fast_diff: (Vec<f32>, Vec<f32>),
    /// Mean and std of the slow features (width `S` or `D`; empty without a slow input).
    pub slow: (Vec<f32>, Vec<f32>),
}

impl ObsNorm {
    /// The identity normalisation for `dims`.
    pub fn identity(d: &ContractDims) -> Self {
        let sw = match d.slow {
            SlowSpec::None => 0,
            SlowSpec::Vector { dim } | SlowSpec::Tokens { dim, .. } => dim,
        };
        ObsNorm {
            fast: (vec![0.0; d.fast_dim], vec![1.0; d.fast_dim]),
            fast_diff: (vec![0.0; d.fast_dim], vec![1.0; d.fast_dim]),
            slow: (vec![0.0; sw], vec![1.0; sw]),
        }
    }
}

/// The encoded fast history `[norm(o_t), norm_d(o_t − o_{t−1}), norm_d(o_{t−1} − o_{t−2}), …]`
/// → `[B, n_obs·F]` (oldest-first input `[B, n_obs, F]`).
pub fn encode_fast<O: Ops>(o: &mut O, d: &ContractDims, norm: &ObsNorm, obs: &O::T) -> O::T {
    let (n, f) = (d.n_obs as i64, d.fast_dim as i64);
    let row = |o: &mut O, i: i64| {
        let r = o.slice(obs, 1, i, i + 1);
        o.reshape(&r, &[-1, f])
    };
    let fm = o.constant("stats.fast.mean", &[d.fast_dim], &norm.fast.0);
    let fs = o.constant("stats.fast.std", &[d.fast_dim], &norm.fast.1);
    let last = row(o, n - 1);
    let c = o.sub(&last, &fm);
    let mut parts = vec![o.div(&c, &fs)];
    if n > 1 {
        let dm = o.constant("stats.fast_diff.mean", &[d.fast_dim], &norm.fast_diff.0);
        let ds = o.constant("stats.fast_diff.std", &[d.fast_dim], &norm.fast_diff.1);
        for k in 1..n {
            let newer = row(o, n - k);
            let older = row(o, n - k - 1);
            let diff = o.sub(&newer, &older);
            let c = o.sub(&diff, &dm);
            parts.push(o.div(&c, &ds));
        }
    }
    if parts.len() == 1 {
        parts.pop().expect("one part")
    } else {
        o.concat(&parts, 1)
    }
}

/// The normalised, flattened slow features `[B, S]` or `[B, T·D]`.
pub fn encode_slow<O: Ops>(o: &mut O, d: &ContractDims, norm: &ObsNorm, slow: &O::T) -> O::T {
    let w = norm.slow.0.len();
    let m = o.constant("stats.slow.mean", &[w], &norm.slow.0);
    let s = o.constant("stats.slow.std", &[w], &norm.slow.1);
    let c = o.sub(slow, &m);
    let n = o.div(&c, &s);
    o.reshape(&n, &[-1, slow_width(d.slow) as i64])
}

/// The clean-clamped `τ` and the hidden flag per position: `flag = [τ < 0]`,
/// `τ_c = flag + (1 − flag)·min(τ, 1)` (a hidden front slot reads as clean).
pub fn tau_and_flag<O: Ops>(o: &mut O, tau: &O::T) -> (O::T, O::T) {
    let flag = o.is_negative(tau);
    let m = o.min_scalar(tau, 1.0);
    let nf = o.scale(&flag, -1.0);
    let keep = o.offset(&nf, 1.0);
    let km = o.mul(&keep, &m);
    (o.add(&flag, &km), flag)
}

// ------------------------------------------------------------------------------------------
// MLP
// ------------------------------------------------------------------------------------------

/// The MLP velocity head, as the candle `Mlp` computes it.
///
/// `z = concat(flat(x), flat(τ features), encoded fast history, normalised slow, e(d_vis))`
/// with per-position `τ` features `[τ_c, flag, sin(πkτ_c), cos(πkτ_c) for k = 1..=tau_freqs]`
/// and `e` the `dvis_embed` table `[d_vis_max + 1, dvis_dim]` (ages clamped); `depth` hidden
/// layers `mlp.{i}` (Linear → SiLU) of width `width`, then `mlp.out` (Linear to `H·A`).
#[derive(Debug, Clone, PartialEq)]
pub struct MlpSpec {
    /// Sizes of the contract tensors.
    pub dims: ContractDims,
    /// Hidden width.
    pub width: usize,
    /// Number of hidden layers (≥ 1).
    pub depth: usize,
    /// Fourier frequencies per position for `τ`.
    pub tau_freqs: usize,
    /// Width of the `d_vis` embedding.
    pub dvis_dim: usize,
    /// Largest slow age the embedding knows.
    pub d_vis_max: usize,
    /// Observation normalisation.
    pub norm: ObsNorm,
}

impl MlpSpec {
    /// Per-position τ feature width.
    pub fn tau_width(&self) -> usize {
        2 + 2 * self.tau_freqs
    }

    /// Input width of the first layer.
    pub fn z_dim(&self) -> usize {
        let d = &self.dims;
        d.horizon * d.action_dim
            + d.horizon * self.tau_width()
            + d.n_obs * d.fast_dim
            + slow_width(d.slow)
            + self.dvis_dim
    }

    /// `(name, shape)` of every weight.
    pub fn weight_shapes(&self) -> Vec<(String, Vec<usize>)> {
        let mut v = vec![(
            "dvis_embed".to_string(),
            vec![self.d_vis_max + 1, self.dvis_dim],
        )];
        let mut i = self.z_dim();
        for l in 0..self.depth {
            v.push((format!("mlp.{l}.weight"), vec![self.width, i]));
            v.push((format!("mlp.{l}.bias"), vec![self.width]));
            i = self.width;
        }
        let o = self.dims.horizon * self.dims.action_dim;
        v.push(("mlp.out.weight".to_string(), vec![o, i]));
        v.push(("mlp.out.bias".to_string(), vec![o]));
        v
    }

    /// The forward pass.
    pub fn forward<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        inp: &Inputs<O::T>,
    ) -> Result<O::T> {
        const M: &str = "MLP";
        if self.depth == 0 {
            return Err(Error::Unsupported {
                model: M,
                message: "depth must be >= 1".to_string(),
            });
        }
        let d = &self.dims;
        let (h, a) = (d.horizon as i64, d.action_dim as i64);
        let xf = o.reshape(&inp.x, &[-1, h * a]);
        // τ features.
        let (tc, flag) = tau_and_flag(o, &inp.tau);
        let tcu = o.unsqueeze(&tc, -1);
        let flu = o.unsqueeze(&flag, -1);
        let mut tparts = vec![tcu.clone(), flu];
        if self.tau_freqs > 0 {
            let k = self.tau_freqs;
            let freqs: Vec<f32> = (1..=k).map(|k| std::f32::consts::PI * k as f32).collect();
            let fr = o.constant("mlp.tau_freqs", &[k], &freqs);
            let arg = o.mul(&tcu, &fr); // [B, H, K]
            let s = o.unary(Unary::Sin, &arg);
            let c = o.unary(Unary::Cos, &arg);
            let s = o.unsqueeze(&s, -1);
            let c = o.unsqueeze(&c, -1);
            let sc = o.concat(&[s, c], -1); // [B, H, K, 2]: s1 c1 s2 c2 …
            tparts.push(o.reshape(&sc, &[-1, h, 2 * k as i64]));
        }
        let tf = o.concat(&tparts, -1);
        let tf = o.reshape(&tf, &[-1, h * self.tau_width() as i64]);
        let mut parts = vec![xf, tf, encode_fast(o, d, &self.norm, &inp.obs_fast)];
        if let Some(s) = &inp.obs_slow {
            parts.push(encode_slow(o, d, &self.norm, s));
        }
        if self.dvis_dim > 0 {
            let ids = inp.d_vis.as_ref().ok_or_else(|| Error::Unsupported {
                model: M,
                message: "the graph needs a `d_vis` input".to_string(),
            })?;
            let table = w.weight(M, "dvis_embed", &[self.d_vis_max + 1, self.dvis_dim])?;
            parts.push(o.embedding(ids, "dvis_embed", &table, self.d_vis_max + 1, self.dvis_dim));
        }
        let mut z = o.concat(&parts, 1);
        let mut i = self.z_dim();
        for l in 0..self.depth {
            let y = linear(o, w, M, &format!("mlp.{l}"), &z, i, self.width)?;
            z = o.silu(&y);
            i = self.width;
        }
        let y = linear(o, w, M, "mlp.out", &z, i, d.horizon * d.action_dim)?;
        Ok(o.reshape(&y, &[-1, h, a]))
    }
}

// ------------------------------------------------------------------------------------------
// Conditional U-Net 1D with per-position FiLM
// ------------------------------------------------------------------------------------------

/// How `τ` conditions the U-Net's FiLM layers (mirrors the candle `FilmMode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Film {
    /// One `(γ, β)` per sample from the shared condition.
    Shared,
    /// The paper's: one head per slot, `(γ_l, β_l) = film_heads_l([mish(ē_l), global])`.
    PerPositionHeads,
    /// Ablation: the shared pair plus a per-position term `film_pos(mish(pool_L(e))_l)`.
    PerPositionTau,
}

/// The conditional U-Net 1D, as the candle `UNet` computes it.
///
/// * `τ` embedding per position: `e_p = tau_mlp.1(mish(tau_mlp.0([sin(1000τ_c·ω_k)], [cos(…)], flag)))`,
///   `ω_k = exp(−k·ln(10⁴)/(E/2 − 1))`.
/// * shared condition `[mish(mean_p e_p), encoded fast, mean over tokens of normalised slow, e(d_vis)]`.
/// * residual block `N`: `N.block0` (conv k → GroupNorm `gn` → Mish), FiLM
///   `(γ, β) = N.film(shared) [+ N.film_pos(mish(pool_L(e)))]` or, with per-position heads,
///   `(γ_l, β_l) = N.film_heads[l]([mish(ē_l), global])` (`ē_l`: the mean of `e` over the chunk
///   positions slot `l` covers), `h·(1 + γ) + β`, `N.block1`, `+ N.res(x)`
///   (1×1 conv) or `+ x`.
/// * `down.{i}.res0/res1`, `down.{i}.down` (conv 3, stride 2) except at the last level; `mid.0/1`;
///   `up.{j}.res0/res1` on `concat(h, skip)`, then nearest ×2 and `up.{j}.up` (conv 3);
///   `final.block` (conv block) and `final.conv` (1×1 to `A`).
#[derive(Debug, Clone, PartialEq)]
pub struct UnetSpec {
    /// Sizes of the contract tensors.
    pub dims: ContractDims,
    /// Channel widths per level.
    pub widths: Vec<usize>,
    /// Convolution kernel size (odd).
    pub kernel: usize,
    /// GroupNorm groups.
    pub groups: usize,
    /// `τ` embedding width `E` (even).
    pub tau_dim: usize,
    /// Width of the `d_vis` embedding.
    pub dvis_dim: usize,
    /// Largest slow age the embedding knows.
    pub d_vis_max: usize,
    /// FiLM variant.
    pub film: Film,
    /// Observation normalisation.
    pub norm: ObsNorm,
}

const GN_EPS: f32 = 1e-5;
const UNET: &str = "U-Net";

/// The per-sample width of the slow part of the shared condition (`S`, or `D` after the token mean).
fn slow_cond_width(s: SlowSpec) -> usize {
    match s {
        SlowSpec::None => 0,
        SlowSpec::Vector { dim } | SlowSpec::Tokens { dim, .. } => dim,
    }
}

impl UnetSpec {
    /// Width of the shared condition `E + G`.
    pub fn shared_dim(&self) -> usize {
        let d = &self.dims;
        self.tau_dim + d.n_obs * d.fast_dim + slow_cond_width(d.slow) + self.dvis_dim
    }

    fn all_dims(&self) -> Vec<usize> {
        let mut v = vec![self.dims.action_dim];
        v.extend(&self.widths);
        v
    }

    /// `(name, shape)` of every weight.
    pub fn weight_shapes(&self) -> Vec<(String, Vec<usize>)> {
        let mut v: Vec<(String, Vec<usize>)> = Vec::new();
        let e = self.tau_dim;
        let k = self.kernel;
        let cs = self.shared_dim();
        fn lin(v: &mut Vec<(String, Vec<usize>)>, n: &str, i: usize, o: usize) {
            v.push((format!("{n}.weight"), vec![o, i]));
            v.push((format!("{n}.bias"), vec![o]));
        }
        fn conv(v: &mut Vec<(String, Vec<usize>)>, n: &str, i: usize, o: usize, k: usize) {
            v.push((format!("{n}.weight"), vec![o, i, k]));
            v.push((format!("{n}.bias"), vec![o]));
        }
        let block = |v: &mut Vec<(String, Vec<usize>)>, n: &str, i: usize, o: usize| {
            conv(v, &format!("{n}.conv"), i, o, k);
            v.push((format!("{n}.gn.weight"), vec![o]));
            v.push((format!("{n}.gn.bias"), vec![o]));
        };
        let res = |v: &mut Vec<(String, Vec<usize>)>, n: &str, i: usize, o: usize, l: usize| {
            block(v, &format!("{n}.block0"), i, o);
            block(v, &format!("{n}.block1"), o, o);
            if self.film == Film::PerPositionHeads {
                v.push((format!("{n}.film_heads.weight"), vec![l, 2 * o, cs]));
                v.push((format!("{n}.film_heads.bias"), vec![l, 2 * o]));
            } else {
                lin(v, &format!("{n}.film"), cs, 2 * o);
            }
            if self.film == Film::PerPositionTau {
                lin(v, &format!("{n}.film_pos"), e, 2 * o);
            }
            if i != o {
                conv(v, &format!("{n}.res"), i, o, 1);
            }
        };
        lin(&mut v, "tau_mlp.0", e + 1, 4 * e);
        lin(&mut v, "tau_mlp.1", 4 * e, e);
        v.push((
            "dvis_embed".to_string(),
            vec![self.dims_dvis_rows(), self.dvis_dim],
        ));
        let dims = self.all_dims();
        let n = self.widths.len();
        let hz = self.dims.horizon;
        for i in 0..n {
            res(
                &mut v,
                &format!("down.{i}.res0"),
                dims[i],
                dims[i + 1],
                hz >> i,
            );
            res(
                &mut v,
                &format!("down.{i}.res1"),
                dims[i + 1],
                dims[i + 1],
                hz >> i,
            );
            if i + 1 < n {
                conv(
                    &mut v,
                    &format!("down.{i}.down"),
                    dims[i + 1],
                    dims[i + 1],
                    3,
                );
            }
        }
        let w = self.widths[n - 1];
        res(&mut v, "mid.0", w, w, hz >> (n - 1));
        res(&mut v, "mid.1", w, w, hz >> (n - 1));
        for (j, i) in (1..n).rev().enumerate() {
            res(
                &mut v,
                &format!("up.{j}.res0"),
                2 * dims[i + 1],
                dims[i],
                hz >> i,
            );
            res(&mut v, &format!("up.{j}.res1"), dims[i], dims[i], hz >> i);
            conv(&mut v, &format!("up.{j}.up"), dims[i], dims[i], 3);
        }
        let w0 = self.widths[0];
        block(&mut v, "final.block", w0, w0);
        conv(&mut v, "final.conv", w0, self.dims.action_dim, 1);
        v
    }

    fn dims_dvis_rows(&self) -> usize {
        self.d_vis_max + 1
    }

    #[allow(clippy::too_many_arguments)]
    fn conv<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        n: &str,
        x: &O::T,
        i: usize,
        out: usize,
        k: usize,
        stride: usize,
    ) -> Result<O::T> {
        let cw = w.weight(UNET, &format!("{n}.weight"), &[out, i, k])?;
        let cb = w.weight(UNET, &format!("{n}.bias"), &[out])?;
        Ok(o.conv1d(x, n, &cw, Some(&cb), i, out, k, stride, k / 2))
    }

    fn conv_block<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        n: &str,
        x: &O::T,
        i: usize,
        out: usize,
    ) -> Result<O::T> {
        let y = self.conv(o, w, &format!("{n}.conv"), x, i, out, self.kernel, 1)?;
        let g = w.weight(UNET, &format!("{n}.gn.weight"), &[out])?;
        let b = w.weight(UNET, &format!("{n}.gn.bias"), &[out])?;
        let y = o.group_norm(&y, &format!("{n}.gn"), &g, &b, out, self.groups, GN_EPS);
        Ok(o.mish(&y))
    }

    /// `shared`: `[B, E+G]`; `pos`: `mish(pool_L(e))` (ablation) or `mish(ē)` (heads), `[B, L, E]`.
    #[allow(clippy::too_many_arguments)]
    fn res_block<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        n: &str,
        x: &O::T,
        shared: &O::T,
        pos: Option<&O::T>,
        i: usize,
        out: usize,
        len: usize,
    ) -> Result<O::T> {
        let h = self.conv_block(o, w, &format!("{n}.block0"), x, i, out)?;
        let c = out as i64;
        if let (Film::PerPositionHeads, Some(p)) = (self.film, pos) {
            let f = self.film_heads(o, w, n, shared, p, out, len)?; // [B, L, 2C]
            let f = o.transpose(&f, &[0, 2, 1]);
            let f = o.reshape(&f, &[-1, 2, c, len as i64]);
            return self.film_rest(o, w, n, x, &h, &f, i, out, len as i64);
        }
        let f = linear(
            o,
            w,
            UNET,
            &format!("{n}.film"),
            shared,
            self.shared_dim(),
            2 * out,
        )?;
        let mut f = o.reshape(&f, &[-1, 2, c, 1]);
        let mut l = 1;
        if let (Film::PerPositionTau, Some(p)) = (self.film, pos) {
            let fp = linear(
                o,
                w,
                UNET,
                &format!("{n}.film_pos"),
                p,
                self.tau_dim,
                2 * out,
            )?; // [B, L, 2C]
            let fp = o.transpose(&fp, &[0, 2, 1]);
            let fp = o.reshape(&fp, &[-1, 2, c, len as i64]);
            f = o.add(&fp, &f);
            l = len as i64;
        }
        self.film_rest(o, w, n, x, &h, &f, i, out, l)
    }

    /// The per-slot heads `[B, L, 2C]`: the global part of every head in one product, the `τ`
    /// part slot by slot (ONNX has no batched product with a per-slot weight here).
    #[allow(clippy::too_many_arguments)]
    fn film_heads<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        n: &str,
        shared: &O::T,
        pos: &O::T,
        out: usize,
        len: usize,
    ) -> Result<O::T> {
        let (e, cs, c2) = (self.tau_dim, self.shared_dim(), 2 * out);
        let wt = w.weight(UNET, &format!("{n}.film_heads.weight"), &[len, c2, cs])?;
        let bt = w.weight(UNET, &format!("{n}.film_heads.bias"), &[len, c2])?;
        let g = o.slice(shared, 1, e as i64, cs as i64);
        let wg: Vec<f32> = wt.chunks_exact(cs).flat_map(|r| r[e..].to_vec()).collect();
        let fg = o.linear(
            &g,
            &format!("{n}.film_heads.global"),
            &wg,
            None,
            cs - e,
            len * c2,
        );
        let fg = o.reshape(&fg, &[-1, len as i64, c2 as i64]);
        let mut slots = Vec::with_capacity(len);
        for l in 0..len {
            let wl: Vec<f32> = wt[l * c2 * cs..(l + 1) * c2 * cs]
                .chunks_exact(cs)
                .flat_map(|r| r[..e].to_vec())
                .collect();
            let pl = o.slice(pos, 1, l as i64, l as i64 + 1);
            slots.push(o.linear(
                &pl,
                &format!("{n}.film_heads.{l}"),
                &wl,
                Some(&bt[l * c2..(l + 1) * c2]),
                e,
                c2,
            ));
        }
        let ft = if len == 1 {
            slots.remove(0)
        } else {
            o.concat(&slots, 1)
        };
        Ok(o.add(&ft, &fg))
    }

    /// FiLM `h·(1 + γ) + β` with `f` `[B, 2, C, l]`, then `block1` and the residual.
    #[allow(clippy::too_many_arguments)]
    fn film_rest<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        n: &str,
        x: &O::T,
        h: &O::T,
        f: &O::T,
        i: usize,
        out: usize,
        l: i64,
    ) -> Result<O::T> {
        let c = out as i64;
        let scale = o.slice(f, 1, 0, 1);
        let scale = o.reshape(&scale, &[-1, c, l]);
        let bias = o.slice(f, 1, 1, 2);
        let bias = o.reshape(&bias, &[-1, c, l]);
        let scale1 = o.offset(&scale, 1.0);
        let hs = o.mul(h, &scale1);
        let hb = o.add(&hs, &bias);
        let h = self.conv_block(o, w, &format!("{n}.block1"), &hb, out, out)?;
        let r = if i != out {
            self.conv(o, w, &format!("{n}.res"), x, i, out, 1, 1)?
        } else {
            x.clone()
        };
        Ok(o.add(&h, &r))
    }

    /// The forward pass.
    pub fn forward<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        inp: &Inputs<O::T>,
    ) -> Result<O::T> {
        let d = &self.dims;
        let n = self.widths.len();
        if n == 0
            || self.kernel % 2 == 0
            || self.tau_dim < 2
            || self.tau_dim % 2 != 0
            || d.horizon % (1 << (n - 1)) != 0
        {
            return Err(Error::Unsupported {
                model: UNET,
                message: format!(
                    "need ≥ 1 level, an odd kernel (got {}), an even tau_dim ≥ 2 (got {}) and H = {} divisible by 2^{}",
                    self.kernel,
                    self.tau_dim,
                    d.horizon,
                    n.saturating_sub(1)
                ),
            });
        }
        if self.groups == 0 || self.widths.iter().any(|c| c % self.groups != 0) {
            return Err(Error::Unsupported {
                model: UNET,
                message: format!(
                    "{} groups must divide every width {:?}",
                    self.groups, self.widths
                ),
            });
        }
        let (hz, e) = (d.horizon, self.tau_dim);
        // τ embedding [B, H, E].
        let half = e / 2;
        let step = (10_000f32).ln() / (half.max(2) - 1) as f32;
        let freqs: Vec<f32> = (0..half).map(|k| (-step * k as f32).exp()).collect();
        let (tc, flag) = tau_and_flag(o, &inp.tau);
        let s = o.scale(&tc, 1000.0);
        let su = o.unsqueeze(&s, -1);
        let fr = o.constant("unet.tau_freqs", &[half], &freqs);
        let arg = o.mul(&su, &fr);
        let sn = o.unary(Unary::Sin, &arg);
        let cs = o.unary(Unary::Cos, &arg);
        let fl = o.unsqueeze(&flag, -1);
        let sin = o.concat(&[sn, cs, fl], -1); // [B, H, E+1]
        let t0 = linear(o, w, UNET, "tau_mlp.0", &sin, e + 1, 4 * e)?;
        let t0 = o.mish(&t0);
        let emb = linear(o, w, UNET, "tau_mlp.1", &t0, 4 * e, e)?; // [B, H, E]
                                                                   // Shared condition.
        let mean = o.mean(&emb, 1);
        let mut parts = vec![o.mish(&mean), encode_fast(o, d, &self.norm, &inp.obs_fast)];
        if let Some(sl) = &inp.obs_slow {
            let (t, dd) = match d.slow {
                SlowSpec::Tokens { tokens, dim } => (tokens, dim),
                SlowSpec::Vector { dim } => (1, dim),
                SlowSpec::None => (0, 0),
            };
            let m = o.constant("stats.slow.mean", &[dd], &self.norm.slow.0);
            let sd = o.constant("stats.slow.std", &[dd], &self.norm.slow.1);
            let c = o.sub(sl, &m);
            let nrm = o.div(&c, &sd);
            let nrm = o.reshape(&nrm, &[-1, t as i64, dd as i64]);
            parts.push(o.mean(&nrm, 1));
        }
        if self.dvis_dim > 0 {
            let ids = inp.d_vis.as_ref().ok_or_else(|| Error::Unsupported {
                model: UNET,
                message: "the graph needs a `d_vis` input".to_string(),
            })?;
            let table = w.weight(UNET, "dvis_embed", &[self.dims_dvis_rows(), self.dvis_dim])?;
            parts.push(o.embedding(
                ids,
                "dvis_embed",
                &table,
                self.dims_dvis_rows(),
                self.dvis_dim,
            ));
        }
        // Mish on the τ part only (follows backends 6c7db0e).
        let shared = o.concat(&parts, 1);
        // Per-position term, pooled per level: [B, H >> i, E].
        // Ablation: mish, then the mean over each slot; heads: the mean, then mish.
        let pos = match self.film {
            Film::PerPositionTau => o.mish(&emb),
            _ => emb.clone(),
        };
        let mut pooled = Vec::with_capacity(n);
        for i in 0..n {
            let l = hz >> i;
            let p = if self.film == Film::Shared {
                None
            } else if l == hz {
                Some(pos.clone())
            } else {
                let r = o.reshape(&pos, &[-1, l as i64, (hz / l) as i64, e as i64]);
                Some(o.mean(&r, 2))
            };
            pooled.push(match (self.film, p) {
                (Film::PerPositionHeads, Some(p)) => Some(o.mish(&p)),
                (_, p) => p,
            });
        }

        let dims = self.all_dims();
        let mut x = o.transpose(&inp.x, &[0, 2, 1]); // [B, A, H]
        let mut skips = Vec::with_capacity(n);
        for i in 0..n {
            let l = hz >> i;
            let p = pooled[i].as_ref();
            x = self.res_block(
                o,
                w,
                &format!("down.{i}.res0"),
                &x,
                &shared,
                p,
                dims[i],
                dims[i + 1],
                l,
            )?;
            x = self.res_block(
                o,
                w,
                &format!("down.{i}.res1"),
                &x,
                &shared,
                p,
                dims[i + 1],
                dims[i + 1],
                l,
            )?;
            skips.push(x.clone());
            if i + 1 < n {
                x = self.conv(
                    o,
                    w,
                    &format!("down.{i}.down"),
                    &x,
                    dims[i + 1],
                    dims[i + 1],
                    3,
                    2,
                )?;
            }
        }
        let wm = self.widths[n - 1];
        let lm = hz >> (n - 1);
        x = self.res_block(
            o,
            w,
            "mid.0",
            &x,
            &shared,
            pooled[n - 1].as_ref(),
            wm,
            wm,
            lm,
        )?;
        x = self.res_block(
            o,
            w,
            "mid.1",
            &x,
            &shared,
            pooled[n - 1].as_ref(),
            wm,
            wm,
            lm,
        )?;
        for (j, i) in (1..n).rev().enumerate() {
            let lvl = n - 1 - j;
            let l = hz >> lvl;
            let p = pooled[lvl].as_ref();
            let skip = skips.pop().expect("one skip per level");
            let cat = o.concat(&[x, skip], 1);
            x = self.res_block(
                o,
                w,
                &format!("up.{j}.res0"),
                &cat,
                &shared,
                p,
                2 * dims[i + 1],
                dims[i],
                l,
            )?;
            x = self.res_block(
                o,
                w,
                &format!("up.{j}.res1"),
                &x,
                &shared,
                p,
                dims[i],
                dims[i],
                l,
            )?;
            // Nearest ×2, then conv 3.
            let u = o.unsqueeze(&x, 3);
            let u = o.concat(&[u.clone(), u], 3);
            let u = o.reshape(&u, &[-1, dims[i] as i64, 2 * l as i64]);
            x = self.conv(o, w, &format!("up.{j}.up"), &u, dims[i], dims[i], 3, 1)?;
        }
        let w0 = self.widths[0];
        let y = self.conv_block(o, w, "final.block", &x, w0, w0)?;
        let y = self.conv(o, w, "final.conv", &y, w0, d.action_dim, 1, 1)?;
        Ok(o.transpose(&y, &[0, 2, 1]))
    }
}
