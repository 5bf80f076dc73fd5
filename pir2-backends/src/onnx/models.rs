//! Model definitions written once against [`Ops`], so ONNX export and TorchScript tracing
//! compute exactly the same function from the same weights.

use super::contract::{ContractDims, SlowSpec};
use super::ops::{Ops, Unary, WeightSource};
use super::ExportError;

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

/// Activation functions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `x · tanh(softplus(x))`.
    Mish,
    /// `x · sigmoid(x)`.
    Silu,
    /// `max(x, 0)`.
    Relu,
}

/// Apply an activation.
pub fn act<O: Ops>(o: &mut O, a: Activation, x: &O::T) -> O::T {
    match a {
        Activation::Mish => o.mish(x),
        Activation::Silu => o.silu(x),
        Activation::Relu => o.unary(Unary::Relu, x),
    }
}

/// Sinusoidal features of `t` (any shape `[..]`) → `[.., dim]`:
/// `[sin(scale·t·ω_k), cos(scale·t·ω_k)]`, `ω_k = exp(−ln(10⁴)·k/(dim/2 − 1))`, `k < dim/2`.
pub fn sinusoidal<O: Ops>(o: &mut O, t: &O::T, dim: usize, scale: f32) -> O::T {
    let half = dim / 2;
    let denom = (half.max(2) - 1) as f32;
    let freqs: Vec<f32> = (0..half)
        .map(|k| scale * (-(10_000f32).ln() * k as f32 / denom).exp())
        .collect();
    let f = o.constant("sinusoidal.freqs", &[half], &freqs);
    let tu = o.unsqueeze(t, -1);
    let arg = o.mul(&tu, &f);
    let s = o.unary(Unary::Sin, &arg);
    let c = o.unary(Unary::Cos, &arg);
    o.concat(&[s, c], -1)
}

/// Width of the flattened slow input.
pub fn slow_width(s: SlowSpec) -> usize {
    match s {
        SlowSpec::None => 0,
        SlowSpec::Vector { dim } => dim,
        SlowSpec::Tokens { tokens, dim } => tokens * dim,
    }
}

/// Flattened observation `concat(flat(obs_fast), flat(obs_slow))` → `[B, n_obs·F + S]`.
pub fn obs_vector<O: Ops>(o: &mut O, d: &ContractDims, inp: &Inputs<O::T>) -> O::T {
    let mut parts = vec![o.reshape(&inp.obs_fast, &[-1, (d.n_obs * d.fast_dim) as i64])];
    if let Some(s) = &inp.obs_slow {
        parts.push(o.reshape(s, &[-1, slow_width(d.slow) as i64]));
    }
    if parts.len() == 1 {
        parts.pop().expect("one part")
    } else {
        o.concat(&parts, 1)
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
) -> Result<O::T, ExportError> {
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
    ) -> Result<O::T, ExportError> {
        const M: &str = "MLP";
        if self.depth == 0 {
            return Err(ExportError::Unsupported {
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
            let ids = inp.d_vis.as_ref().ok_or_else(|| ExportError::Unsupported {
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

/// Conditional U-Net 1D (Diffusion-Policy layout) with per-position FiLM.
///
/// * τ encoder: `sinusoidal(τ_p, tau_dim)` → `tau_mlp.0` (Linear `tau_dim → 4·tau_dim`) →
///   Mish → `tau_mlp.2` (Linear `4·tau_dim → tau_dim`): one embedding per position.
/// * condition per position: `c_p = concat(τ-embedding_p, obs)` (`obs` = flattened fast +
///   slow observation, the same for every position) → `[B, C_d, H]`; at level `l` it is
///   average-pooled by `2^l` along the chunk.
/// * residual block `…`: `block0` (Conv k, GroupNorm, Mish) → per-position FiLM
///   (`cond.1`: Mish → Linear `C_d → 2·C_out` at every position; `γ = [:C_out]`, `β = [C_out:]`,
///   `h = γ·h + β`) → `block1` (Conv k, GroupNorm, Mish) → `+ residual` (1×1 conv `res` when the
///   width changes).
/// * `down.{l}.{0,1}` residual blocks, `down.{l}.2` Conv(k 3, stride 2, pad 1) except at the last
///   level; `mid.{0,1}`; `up.{l}.{0,1}` on `concat(h, skip)`, `up.{l}.2` ConvTranspose(k 4,
///   stride 2, pad 1); `final.0` Conv block, `final.1` 1×1 Conv to `A`.
#[derive(Debug, Clone, PartialEq)]
pub struct UnetSpec {
    /// Sizes of the contract tensors.
    pub dims: ContractDims,
    /// Channel widths per level, e.g. `[64, 128, 256]`.
    pub down_dims: Vec<usize>,
    /// Convolution kernel size (odd).
    pub kernel: usize,
    /// GroupNorm groups.
    pub groups: usize,
    /// τ embedding width (even).
    pub tau_dim: usize,
    /// Scale applied to τ inside the sinusoid.
    pub tau_scale: f32,
}

const GN_EPS: f32 = 1e-5;

impl UnetSpec {
    /// Width of the per-position condition.
    pub fn cond_dim(&self) -> usize {
        let d = &self.dims;
        self.tau_dim + d.n_obs * d.fast_dim + slow_width(d.slow)
    }

    fn levels(&self) -> Vec<(usize, usize)> {
        let mut all = vec![self.dims.action_dim];
        all.extend(&self.down_dims);
        all.windows(2).map(|w| (w[0], w[1])).collect()
    }

    /// `(name, shape)` of every weight.
    pub fn weight_shapes(&self) -> Vec<(String, Vec<usize>)> {
        let mut v = Vec::new();
        let e = self.tau_dim;
        let lin = |v: &mut Vec<(String, Vec<usize>)>, n: &str, i: usize, o: usize| {
            v.push((format!("{n}.weight"), vec![o, i]));
            v.push((format!("{n}.bias"), vec![o]));
        };
        lin(&mut v, "tau_mlp.0", e, 4 * e);
        lin(&mut v, "tau_mlp.2", 4 * e, e);
        let cd = self.cond_dim();
        let k = self.kernel;
        let res = |v: &mut Vec<(String, Vec<usize>)>, n: &str, i: usize, o: usize| {
            for (b, ci) in [("block0", i), ("block1", o)] {
                v.push((format!("{n}.{b}.conv.weight"), vec![o, ci, k]));
                v.push((format!("{n}.{b}.conv.bias"), vec![o]));
                v.push((format!("{n}.{b}.norm.weight"), vec![o]));
                v.push((format!("{n}.{b}.norm.bias"), vec![o]));
            }
            v.push((format!("{n}.cond.1.weight"), vec![2 * o, cd]));
            v.push((format!("{n}.cond.1.bias"), vec![2 * o]));
            if i != o {
                v.push((format!("{n}.res.weight"), vec![o, i, 1]));
                v.push((format!("{n}.res.bias"), vec![o]));
            }
        };
        let lv = self.levels();
        for (l, &(i, o)) in lv.iter().enumerate() {
            res(&mut v, &format!("down.{l}.0"), i, o);
            res(&mut v, &format!("down.{l}.1"), o, o);
            if l + 1 < lv.len() {
                v.push((format!("down.{l}.2.weight"), vec![o, o, 3]));
                v.push((format!("down.{l}.2.bias"), vec![o]));
            }
        }
        let m = *self.down_dims.last().unwrap_or(&0);
        res(&mut v, "mid.0", m, m);
        res(&mut v, "mid.1", m, m);
        for (u, &(i, o)) in lv[1..].iter().rev().enumerate() {
            res(&mut v, &format!("up.{u}.0"), 2 * o, i);
            res(&mut v, &format!("up.{u}.1"), i, i);
            v.push((format!("up.{u}.2.weight"), vec![i, i, 4]));
            v.push((format!("up.{u}.2.bias"), vec![i]));
        }
        let s = self.down_dims[0];
        v.push(("final.0.conv.weight".to_string(), vec![s, s, k]));
        v.push(("final.0.conv.bias".to_string(), vec![s]));
        v.push(("final.0.norm.weight".to_string(), vec![s]));
        v.push(("final.0.norm.bias".to_string(), vec![s]));
        v.push((
            "final.1.weight".to_string(),
            vec![self.dims.action_dim, s, 1],
        ));
        v.push(("final.1.bias".to_string(), vec![self.dims.action_dim]));
        v
    }

    #[allow(clippy::too_many_arguments)]
    fn conv_block<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        n: &str,
        x: &O::T,
        i: usize,
        out: usize,
    ) -> Result<O::T, ExportError> {
        const M: &str = "U-Net";
        let k = self.kernel;
        let cw = w.weight(M, &format!("{n}.conv.weight"), &[out, i, k])?;
        let cb = w.weight(M, &format!("{n}.conv.bias"), &[out])?;
        let y = o.conv1d(x, &format!("{n}.conv"), &cw, Some(&cb), i, out, k, 1, k / 2);
        let g = w.weight(M, &format!("{n}.norm.weight"), &[out])?;
        let b = w.weight(M, &format!("{n}.norm.bias"), &[out])?;
        let y = o.group_norm(&y, &format!("{n}.norm"), &g, &b, out, self.groups, GN_EPS);
        Ok(o.mish(&y))
    }

    /// `cond_t`: the condition as `[B, L, C_d]` at this block's resolution.
    #[allow(clippy::too_many_arguments)]
    fn res_block<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        n: &str,
        x: &O::T,
        cond_t: &O::T,
        i: usize,
        out: usize,
    ) -> Result<O::T, ExportError> {
        const M: &str = "U-Net";
        let h = self.conv_block(o, w, &format!("{n}.block0"), x, i, out)?;
        let c = o.mish(cond_t);
        let film = linear(
            o,
            w,
            M,
            &format!("{n}.cond.1"),
            &c,
            self.cond_dim(),
            2 * out,
        )?; // [B, L, 2C]
        let film = o.transpose(&film, &[0, 2, 1]); // [B, 2C, L]
        let gamma = o.slice(&film, 1, 0, out as i64);
        let beta = o.slice(&film, 1, out as i64, 2 * out as i64);
        let h = o.mul(&gamma, &h);
        let h = o.add(&h, &beta);
        let h = self.conv_block(o, w, &format!("{n}.block1"), &h, out, out)?;
        let r = if i != out {
            let rw = w.weight(M, &format!("{n}.res.weight"), &[out, i, 1])?;
            let rb = w.weight(M, &format!("{n}.res.bias"), &[out])?;
            o.conv1d(x, &format!("{n}.res"), &rw, Some(&rb), i, out, 1, 1, 0)
        } else {
            x.clone()
        };
        Ok(o.add(&h, &r))
    }

    /// Average-pool `[B, L, C]` by 2 along `L`.
    fn pool_cond<O: Ops>(&self, o: &mut O, c: &O::T, len: usize) -> O::T {
        let cd = self.cond_dim() as i64;
        let r = o.reshape(c, &[-1, (len / 2) as i64, 2, cd]);
        let a = o.slice(&r, 2, 0, 1);
        let b = o.slice(&r, 2, 1, 2);
        let s = o.add(&a, &b);
        let s = o.scale(&s, 0.5);
        o.reshape(&s, &[-1, (len / 2) as i64, cd])
    }

    /// The forward pass.
    pub fn forward<O: Ops, W: WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        inp: &Inputs<O::T>,
    ) -> Result<O::T, ExportError> {
        const M: &str = "U-Net";
        let d = &self.dims;
        let lv = self.levels();
        let n_down = lv.len() - 1;
        if self.down_dims.is_empty()
            || self.kernel % 2 == 0
            || self.tau_dim % 2 != 0
            || d.horizon % (1 << n_down) != 0
        {
            return Err(ExportError::Unsupported {
                model: M,
                message: format!(
                    "need ≥ 1 level, an odd kernel (got {}), an even tau_dim (got {}) and H = {} divisible by 2^{n_down}",
                    self.kernel, self.tau_dim, d.horizon
                ),
            });
        }
        if self.down_dims.iter().any(|c| c % self.groups != 0) {
            return Err(ExportError::Unsupported {
                model: M,
                message: format!(
                    "channels {:?} not divisible by {} groups",
                    self.down_dims, self.groups
                ),
            });
        }
        let hz = d.horizon;
        // Per-position condition [B, H, C_d].
        let e = self.tau_dim;
        let te = sinusoidal(o, &inp.tau, e, self.tau_scale); // [B, H, E]
        let te = linear(o, w, M, "tau_mlp.0", &te, e, 4 * e)?;
        let te = o.mish(&te);
        let te = linear(o, w, M, "tau_mlp.2", &te, 4 * e, e)?;
        let ob = obs_vector(o, d, inp); // [B, G]
        let ob = o.unsqueeze(&ob, 1); // [B, 1, G]
        let g = d.n_obs * d.fast_dim + slow_width(d.slow);
        let zeros = o.constant("unet.broadcast", &[hz, g], &vec![0.0; hz * g]);
        let ob = o.add(&ob, &zeros); // [B, H, G]
        let mut conds = vec![o.concat(&[te, ob], -1)];
        let mut len = hz;
        for _ in 0..n_down {
            let c = self.pool_cond(o, conds.last().expect("level 0"), len);
            conds.push(c);
            len /= 2;
        }

        let mut h = o.transpose(&inp.x, &[0, 2, 1]); // [B, A, H]
        let mut skips = Vec::new();
        for (l, &(i, out)) in lv.iter().enumerate() {
            h = self.res_block(o, w, &format!("down.{l}.0"), &h, &conds[l], i, out)?;
            h = self.res_block(o, w, &format!("down.{l}.1"), &h, &conds[l], out, out)?;
            skips.push(h.clone());
            if l + 1 < lv.len() {
                let dw = w.weight(M, &format!("down.{l}.2.weight"), &[out, out, 3])?;
                let db = w.weight(M, &format!("down.{l}.2.bias"), &[out])?;
                h = o.conv1d(
                    &h,
                    &format!("down.{l}.2"),
                    &dw,
                    Some(&db),
                    out,
                    out,
                    3,
                    2,
                    1,
                );
            }
        }
        let m = self.down_dims[self.down_dims.len() - 1];
        h = self.res_block(o, w, "mid.0", &h, &conds[n_down], m, m)?;
        h = self.res_block(o, w, "mid.1", &h, &conds[n_down], m, m)?;
        let mut level = n_down;
        for (u, &(i, out)) in lv[1..].iter().rev().enumerate() {
            let skip = skips.pop().expect("one skip per level");
            let cat = o.concat(&[h, skip], 1);
            h = self.res_block(o, w, &format!("up.{u}.0"), &cat, &conds[level], 2 * out, i)?;
            h = self.res_block(o, w, &format!("up.{u}.1"), &h, &conds[level], i, i)?;
            let uw = w.weight(M, &format!("up.{u}.2.weight"), &[i, i, 4])?;
            let ub = w.weight(M, &format!("up.{u}.2.bias"), &[i])?;
            h = o.conv_transpose1d(&h, &format!("up.{u}.2"), &uw, Some(&ub), i, i, 4, 2, 1, 0);
            level -= 1;
        }
        let s = self.down_dims[0];
        h = self.conv_block(o, w, "final.0", &h, s, s)?;
        let fw = w.weight(M, "final.1.weight", &[d.action_dim, s, 1])?;
        let fb = w.weight(M, "final.1.bias", &[d.action_dim])?;
        h = o.conv1d(&h, "final.1", &fw, Some(&fb), s, d.action_dim, 1, 1, 0);
        Ok(o.transpose(&h, &[0, 2, 1]))
    }
}
