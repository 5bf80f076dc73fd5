//! Minimal layers over a deterministic parameter store.
//!
//! candle's CPU random initialisers cannot be seeded, so parameters are drawn here from
//! [`pir2_schedule::Rng`] in a fixed order: same seed → same initial weights.

use candle_core::{Device, Module, Tensor, Var, D};
use pir2_schedule::Rng;

pub(crate) type CResult<T> = candle_core::Result<T>;

/// Parameter initialisers.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Init {
    Zeros,
    Ones,
    /// Uniform in `[-b, b]`.
    Uniform(f32),
}

/// Creates named parameters deterministically and remembers them in creation order.
#[derive(Debug)]
pub(crate) struct ParamStore {
    pub(crate) vars: Vec<(String, Var)>,
    rng: Rng,
    dev: Device,
    /// Most weight values the store may create (a checkpoint being loaded holds this many):
    /// a configuration claiming more is refused before anything that size is allocated.
    budget: Option<usize>,
    used: usize,
}

impl ParamStore {
    pub(crate) fn new(seed: u64) -> Self {
        Self {
            vars: Vec::new(),
            rng: Rng::new(seed),
            dev: Device::Cpu,
            budget: None,
            used: 0,
        }
    }

    /// A store that refuses to create more than `values` weight values in total.
    pub(crate) fn with_budget(seed: u64, values: usize) -> Self {
        Self {
            budget: Some(values),
            ..Self::new(seed)
        }
    }

    /// Count `shape`'s values against the budget; their number.
    fn reserve(&mut self, name: &str, shape: &[usize]) -> CResult<usize> {
        let n = shape
            .iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .ok_or_else(|| {
                candle_core::Error::Msg(format!("weight `{name}`: shape {shape:?} overflows"))
            })?;
        self.used = self.used.saturating_add(n);
        if let Some(budget) = self.budget.filter(|b| self.used > *b) {
            return Err(candle_core::Error::Msg(format!(
                "the configuration needs more weight values than the checkpoint holds \
                 ({budget}); exceeded at `{name}` {shape:?}"
            )));
        }
        Ok(n)
    }

    pub(crate) fn param(&mut self, name: &str, shape: &[usize], init: Init) -> CResult<Tensor> {
        let n = self.reserve(name, shape)?;
        let data: Vec<f32> = match init {
            Init::Zeros => vec![0.0; n],
            Init::Ones => vec![1.0; n],
            Init::Uniform(b) => (0..n).map(|_| self.rng.uniform_range(-b, b)).collect(),
        };
        let var = Var::from_vec(data, shape, &self.dev)?;
        let t = var.as_tensor().clone();
        self.vars.push((name.to_owned(), var));
        Ok(t)
    }

    /// `nn.Linear`: weight `[out, in]`, PyTorch's default uniform(±1/√in) init.
    pub(crate) fn linear(
        &mut self,
        name: &str,
        din: usize,
        dout: usize,
    ) -> CResult<candle_nn::Linear> {
        let b = 1.0 / (din as f32).sqrt();
        let w = self.param(&format!("{name}.weight"), &[dout, din], Init::Uniform(b))?;
        let bias = self.param(&format!("{name}.bias"), &[dout], Init::Uniform(b))?;
        Ok(candle_nn::Linear::new(w, Some(bias)))
    }

    /// `n` copies of one `nn.Linear` drawn exactly as [`ParamStore::linear`] draws it (same
    /// random numbers in the same order): weight `[n, out, in]`, bias `[n, out]`. Per-position
    /// heads initialised from the shared head, so a model with heads starts as the shared model
    /// with the same seed.
    pub(crate) fn linear_heads(
        &mut self,
        name: &str,
        n: usize,
        din: usize,
        dout: usize,
    ) -> CResult<(Tensor, Tensor)> {
        let b = 1.0 / (din as f32).sqrt();
        let w: Vec<f32> = (0..din * dout)
            .map(|_| self.rng.uniform_range(-b, b))
            .collect();
        let bias: Vec<f32> = (0..dout).map(|_| self.rng.uniform_range(-b, b)).collect();
        let w = self.param_from(&format!("{name}.weight"), &[n, dout, din], &w)?;
        let bias = self.param_from(&format!("{name}.bias"), &[n, dout], &bias)?;
        Ok((w, bias))
    }

    /// A parameter whose value is `tile` repeated to fill `shape`.
    fn param_from(&mut self, name: &str, shape: &[usize], tile: &[f32]) -> CResult<Tensor> {
        let n = self.reserve(name, shape)?;
        let data: Vec<f32> = tile.iter().copied().cycle().take(n).collect();
        let var = Var::from_vec(data, shape, &self.dev)?;
        let t = var.as_tensor().clone();
        self.vars.push((name.to_owned(), var));
        Ok(t)
    }

    /// A zero-initialised linear layer (AdaLN-zero, per-position FiLM deltas, output heads).
    pub(crate) fn linear_zero(
        &mut self,
        name: &str,
        din: usize,
        dout: usize,
    ) -> CResult<candle_nn::Linear> {
        let w = self.param(&format!("{name}.weight"), &[dout, din], Init::Zeros)?;
        let bias = self.param(&format!("{name}.bias"), &[dout], Init::Zeros)?;
        Ok(candle_nn::Linear::new(w, Some(bias)))
    }

    /// `nn.Conv1d` (weight `[out, in, k]`) with same-padding for odd kernels and `stride` 1 or 2.
    pub(crate) fn conv1d(
        &mut self,
        name: &str,
        cin: usize,
        cout: usize,
        k: usize,
        stride: usize,
    ) -> CResult<Conv1d> {
        let b = 1.0 / ((cin * k) as f32).sqrt();
        let weight = self.param(&format!("{name}.weight"), &[cout, cin, k], Init::Uniform(b))?;
        let bias = self.param(&format!("{name}.bias"), &[cout], Init::Uniform(b))?;
        Ok(Conv1d {
            weight,
            bias,
            k,
            stride,
        })
    }

    /// A zero-initialised embedding table `[n, dim]` (the `d_vis` embedding).
    pub(crate) fn embedding_zero(
        &mut self,
        name: &str,
        n: usize,
        dim: usize,
    ) -> CResult<candle_nn::Embedding> {
        let t = self.param(name, &[n, dim], Init::Zeros)?;
        Ok(candle_nn::Embedding::new(t, dim))
    }

    pub(crate) fn group_norm(
        &mut self,
        name: &str,
        groups: usize,
        channels: usize,
    ) -> CResult<GroupNorm> {
        let weight = self.param(&format!("{name}.weight"), &[channels], Init::Ones)?;
        let bias = self.param(&format!("{name}.bias"), &[channels], Init::Zeros)?;
        Ok(GroupNorm {
            weight,
            bias,
            groups,
            eps: 1e-5,
        })
    }
}

/// 1-D convolution on **channels-last** `[B, L, C]` as im2col + one matmul, built from
/// differentiable primitives (pad, narrow, cat, matmul). Weight `[out, in, k]` (PyTorch
/// layout). candle 0.11's CPU `conv1d` backward failed our finite-difference check
/// (tests/gradcheck.rs), and one `[B·L, C·K] × [C·K, O]` matmul is also far faster at
/// batch 256 than candle's batched small convolutions.
#[derive(Debug, Clone)]
pub(crate) struct Conv1d {
    weight: Tensor,
    bias: Tensor,
    k: usize,
    stride: usize,
}

impl Module for Conv1d {
    fn forward(&self, x: &Tensor) -> CResult<Tensor> {
        let (b, l, c) = x.dims3()?;
        let o = self.weight.dim(0)?;
        let cols = if self.k == 1 {
            x.reshape((b * l, c))?
        } else {
            let xp = x.pad_with_zeros(1, self.k / 2, self.k / 2)?;
            let taps = (0..self.k)
                .map(|j| xp.narrow(1, j, l)?.unsqueeze(3))
                .collect::<CResult<Vec<_>>>()?;
            Tensor::cat(&taps, 3)?.reshape((b * l, c * self.k))? // index c·K + j
        };
        let w = self.weight.reshape((o, c * self.k))?;
        let y = cols
            .matmul(&w.t()?)?
            .broadcast_add(&self.bias)?
            .reshape((b, l, o))?;
        if self.stride == 1 {
            Ok(y)
        } else {
            // Stride s on a same-padded conv = every s-th output position.
            y.reshape((b, l / self.stride, self.stride, o))?
                .narrow(2, 0, 1)?
                .squeeze(2)
        }
    }
}

/// GroupNorm over channels-last `[B, L, C]` built from differentiable primitives.
#[derive(Debug, Clone)]
pub(crate) struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    groups: usize,
    eps: f64,
}

impl Module for GroupNorm {
    fn forward(&self, x: &Tensor) -> CResult<Tensor> {
        let (b, l, c) = x.dims3()?;
        let xg = x.reshape((b, l, self.groups, c / self.groups))?;
        let mean = xg.mean_keepdim((1, 3))?;
        let xc = xg.broadcast_sub(&mean)?;
        let var = xc.sqr()?.mean_keepdim((1, 3))?;
        let xn = xc
            .broadcast_div(&(var + self.eps)?.sqrt()?)?
            .reshape((b, l, c))?;
        xn.broadcast_mul(&self.weight)?.broadcast_add(&self.bias)
    }
}

/// LayerNorm over the last dim without affine parameters (AdaLN supplies them).
pub(crate) fn layer_norm(x: &Tensor, eps: f64) -> CResult<Tensor> {
    let mean = x.mean_keepdim(D::Minus1)?;
    let xc = x.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    xc.broadcast_div(&(var + eps)?.sqrt()?)
}

/// Mish: `x · tanh(softplus(x))`, with a softplus that is finite for every `x`.
pub(crate) fn mish(x: &Tensor) -> CResult<Tensor> {
    let sp = (x.relu()? + (x.abs()?.neg()?.exp()? + 1.0)?.log()?)?;
    x.mul(&sp.tanh()?)
}

/// The clean-clamped `τ` and the hidden flag of one position.
#[inline]
pub(crate) fn tau_and_flag(t: f32) -> (f32, f32) {
    if t < 0.0 {
        // HIDDEN_FRONT_TAU: a hidden front slot is a committed (clean) action the model does not see.
        (1.0, 1.0)
    } else {
        (t.min(1.0), 0.0)
    }
}

/// Sinusoidal embedding of `τ·1000` (diffusion-policy style, `dim/2` log-spaced
/// frequencies up to period 10⁴) plus the hidden flag: `dim + 1` features per position.
pub(crate) fn sinusoidal_tau(tau: &[f32], dim: usize, out: &mut Vec<f32>) {
    let half = dim / 2;
    out.clear();
    out.reserve(tau.len() * (dim + 1));
    let step = (10_000f32).ln() / (half.max(2) - 1) as f32;
    for &t in tau {
        let (tc, flag) = tau_and_flag(t);
        let s = tc * 1000.0;
        for k in 0..half {
            out.push((s * (-step * k as f32).exp()).sin());
        }
        for k in 0..half {
            out.push((s * (-step * k as f32).exp()).cos());
        }
        out.push(flag);
    }
}

/// Helper: a `[rows, cols]` f32 tensor from a slice.
pub(crate) fn tensor2(data: &[f32], rows: usize, cols: usize) -> CResult<Tensor> {
    Tensor::from_slice(data, (rows, cols), &Device::Cpu)
}
