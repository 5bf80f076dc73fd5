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
}

impl ParamStore {
    pub(crate) fn new(seed: u64) -> Self {
        Self {
            vars: Vec::new(),
            rng: Rng::new(seed),
            dev: Device::Cpu,
        }
    }

    pub(crate) fn param(&mut self, name: &str, shape: &[usize], init: Init) -> CResult<Tensor> {
        let n: usize = shape.iter().product();
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

/// 1-D convolution as im2col + matmul from differentiable primitives (pad, narrow, cat,
/// matmul). candle 0.11's CPU `conv1d` backward gave wrong gradients in our finite-difference
/// check (tests/gradcheck.rs), so the U-Net does not use it.
#[derive(Debug, Clone)]
pub(crate) struct Conv1d {
    weight: Tensor,
    bias: Tensor,
    k: usize,
    stride: usize,
}

impl Module for Conv1d {
    fn forward(&self, x: &Tensor) -> CResult<Tensor> {
        let (b, c, l) = x.dims3()?;
        let o = self.weight.dim(0)?;
        let cols = if self.k == 1 {
            x.clone()
        } else {
            let xp = x.pad_with_zeros(2, self.k / 2, self.k / 2)?;
            let taps = (0..self.k)
                .map(|j| xp.narrow(2, j, l))
                .collect::<CResult<Vec<_>>>()?;
            Tensor::cat(&taps, 1)? // [B, K·C, L], index j·C + c
        };
        let w = self.weight.transpose(1, 2)?.reshape((o, self.k * c))?; // [O, K·C]
        let y = w
            .broadcast_left(b)?
            .matmul(&cols)?
            .broadcast_add(&self.bias.reshape((1, o, 1))?)?;
        if self.stride == 1 {
            Ok(y)
        } else {
            // Stride s on a same-padded conv = every s-th output position.
            y.reshape((b, o, l / self.stride, self.stride))?
                .narrow(3, 0, 1)?
                .squeeze(3)
        }
    }
}

/// GroupNorm over `[B, C, L]` built from differentiable primitives.
#[derive(Debug, Clone)]
pub(crate) struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    groups: usize,
    eps: f64,
}

impl Module for GroupNorm {
    fn forward(&self, x: &Tensor) -> CResult<Tensor> {
        let (b, c, l) = x.dims3()?;
        let xg = x.reshape((b, self.groups, (c / self.groups) * l))?;
        let mean = xg.mean_keepdim(D::Minus1)?;
        let xc = xg.broadcast_sub(&mean)?;
        let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
        let xn = xc
            .broadcast_div(&(var + self.eps)?.sqrt()?)?
            .reshape((b, c, l))?;
        xn.broadcast_mul(&self.weight.reshape((1, c, 1))?)?
            .broadcast_add(&self.bias.reshape((1, c, 1))?)
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
