//! Small MLP velocity head: `[x, τ features, encoded obs, slow, e(d_vis)] → v`.

use candle_core::{Module, Tensor};

use super::layers::{tau_and_flag, tensor2, CResult, ParamStore};
use super::Inputs;
use crate::config::{MlpConfig, Spec};

/// Per-position `τ` features: `[τ, hidden, sin(πkτ), cos(πkτ) for k = 1..=freqs]`.
pub(crate) fn mlp_tau_features(tau: &[f32], freqs: usize, out: &mut Vec<f32>) {
    out.clear();
    for &t in tau {
        let (tc, flag) = tau_and_flag(t);
        out.push(tc);
        out.push(flag);
        for k in 1..=freqs {
            let (s, c) = (std::f32::consts::PI * k as f32 * tc).sin_cos();
            out.push(s);
            out.push(c);
        }
    }
}

#[derive(Debug)]
pub(crate) struct Mlp {
    pub(crate) hidden: Vec<candle_nn::Linear>,
    pub(crate) out: candle_nn::Linear,
    pub(crate) dvis: candle_nn::Embedding,
    pub(crate) freqs: usize,
    h: usize,
    a: usize,
}

impl Mlp {
    pub(crate) fn tau_width(freqs: usize) -> usize {
        2 + 2 * freqs
    }

    pub(crate) fn input_width(spec: &Spec, c: &MlpConfig) -> usize {
        spec.horizon * spec.action_dim
            + spec.horizon * Self::tau_width(c.tau_freqs)
            + spec.fast_encoded_dim()
            + spec.slow.len()
            + c.dvis_dim
    }

    pub(crate) fn new(ps: &mut ParamStore, spec: &Spec, c: &MlpConfig) -> CResult<Self> {
        let mut din = Self::input_width(spec, c);
        let dvis = ps.embedding_zero("dvis_embed", spec.d_vis_max + 1, c.dvis_dim)?;
        let mut hidden = Vec::with_capacity(c.depth);
        for i in 0..c.depth {
            hidden.push(ps.linear(&format!("mlp.{i}"), din, c.width)?);
            din = c.width;
        }
        let out = ps.linear("mlp.out", din, spec.horizon * spec.action_dim)?;
        Ok(Self {
            hidden,
            out,
            dvis,
            freqs: c.tau_freqs,
            h: spec.horizon,
            a: spec.action_dim,
        })
    }

    pub(crate) fn forward(&self, inp: &Inputs) -> CResult<Tensor> {
        let b = inp.b;
        let mut tf = Vec::new();
        mlp_tau_features(&inp.tau, self.freqs, &mut tf);
        let tw = self.h * Self::tau_width(self.freqs);
        let mut parts = vec![
            inp.x.reshape((b, self.h * self.a))?,
            tensor2(&tf, b, tw)?,
            inp.fast.clone(),
        ];
        if let Some(s) = &inp.slow {
            parts.push(s.flatten_from(1)?);
        }
        parts.push(self.dvis.forward(&inp.dvis)?);
        let mut z = Tensor::cat(&parts, 1)?;
        for l in &self.hidden {
            z = l.forward(&z)?.silu()?;
        }
        self.out.forward(&z)?.reshape((b, self.h, self.a))
    }
}

/// Host copy of the MLP weights for the batch-1 inference path (no tensor allocation per
/// layer; candle's per-op overhead dominates at this size).
#[derive(Debug, Clone)]
pub(crate) struct MlpFast {
    /// `(weight [out, in] row-major, bias [out])` per layer, the output layer last.
    layers: Vec<(Vec<f32>, Vec<f32>)>,
    dvis: Vec<f32>,
    dvis_dim: usize,
    z: Vec<f32>,
    y: Vec<f32>,
    tf: Vec<f32>,
}

fn host(t: &Tensor) -> CResult<Vec<f32>> {
    t.flatten_all()?.to_vec1::<f32>()
}

#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    // Eight independent accumulators so the compiler vectorises the reduction.
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut s = (acc[0] + acc[4]) + (acc[1] + acc[5]) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

impl MlpFast {
    pub(crate) fn from(m: &Mlp) -> CResult<Self> {
        let mut layers = Vec::with_capacity(m.hidden.len() + 1);
        for l in m.hidden.iter().chain(std::iter::once(&m.out)) {
            let b = l.bias().map(host).transpose()?.unwrap_or_default();
            layers.push((host(l.weight())?, b));
        }
        let emb = m.dvis.embeddings();
        Ok(Self {
            layers,
            dvis: host(emb)?,
            dvis_dim: emb.dim(1)?,
            z: Vec::new(),
            y: Vec::new(),
            tf: Vec::new(),
        })
    }

    /// One sample: `x` `[H·A]`, raw `τ` `[H]`, `obs` = (encoded fast obs, normalised slow, clamped `d_vis`).
    pub(crate) fn forward(
        &mut self,
        freqs: usize,
        x: &[f32],
        tau: &[f32],
        obs: (&[f32], &[f32], usize),
        out: &mut [f32],
    ) {
        let (fast, slow, dvis) = obs;
        mlp_tau_features(tau, freqs, &mut self.tf);
        self.z.clear();
        self.z.extend_from_slice(x);
        self.z.extend_from_slice(&self.tf);
        self.z.extend_from_slice(fast);
        self.z.extend_from_slice(slow);
        self.z
            .extend_from_slice(&self.dvis[dvis * self.dvis_dim..(dvis + 1) * self.dvis_dim]);
        let n = self.layers.len();
        for (i, (w, b)) in self.layers.iter().enumerate() {
            let din = self.z.len();
            self.y.clear();
            for (o, &bo) in b.iter().enumerate() {
                let v = dot(&w[o * din..(o + 1) * din], &self.z) + bo;
                // SiLU on hidden layers, identity on the output layer.
                self.y
                    .push(if i + 1 < n { v / (1.0 + (-v).exp()) } else { v });
            }
            std::mem::swap(&mut self.z, &mut self.y);
        }
        out.copy_from_slice(&self.z);
    }
}
