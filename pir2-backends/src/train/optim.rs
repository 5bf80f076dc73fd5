//! AdamW with the cosine schedule's learning rate and grad-norm clipping.

use super::*;

/// Global grad norm of candle gradients; scales them in place when it exceeds `clip`.
pub(crate) fn clip_grad_store(
    grads: &mut candle_core::backprop::GradStore,
    vars: &[candle_core::Var],
    clip: Option<f64>,
) -> Result<f32> {
    let mut sq = 0.0f64;
    for v in vars {
        if let Some(g) = grads.get(v.as_tensor()) {
            sq += g.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
        }
    }
    let norm = sq.sqrt();
    if let Some(c) = clip {
        if norm > c && norm.is_finite() {
            let s = c / (norm + 1e-6);
            for v in vars {
                if let Some(g) = grads.remove(v.as_tensor()) {
                    grads.insert(v.as_tensor(), (g * s)?);
                }
            }
        }
    }
    Ok(norm as f32)
}

/// Global grad norm (f64 accumulation); scales the gradients in place when it exceeds `clip`.
pub(crate) fn clip_grads(grads: &mut [Vec<f32>], clip: Option<f64>) -> f32 {
    let sq: f64 = grads
        .iter()
        .map(|g| g.iter().map(|&v| (v as f64) * (v as f64)).sum::<f64>())
        .sum();
    let norm = sq.sqrt();
    if let Some(c) = clip {
        if norm > c && norm.is_finite() {
            let s = (c / (norm + 1e-6)) as f32;
            for g in grads.iter_mut() {
                for v in g.iter_mut() {
                    *v *= s;
                }
            }
        }
    }
    norm as f32
}

/// AdamW on host buffers, the same update as `candle_nn::AdamW` (decoupled weight decay,
/// bias-corrected moments), with state that can be saved and restored.
#[derive(Debug, Clone)]
pub(crate) struct AdamW {
    pub(crate) beta1: f64,
    pub(crate) beta2: f64,
    pub(crate) eps: f64,
    pub(crate) weight_decay: f64,
    pub(crate) t: u64,
    pub(crate) m: Vec<Vec<f32>>,
    pub(crate) v: Vec<Vec<f32>>,
}

impl AdamW {
    pub(crate) fn new(cfg: &TrainConfig, params: &[Vec<f32>]) -> Self {
        Self {
            beta1: cfg.betas.0,
            beta2: cfg.betas.1,
            eps: cfg.eps,
            weight_decay: cfg.weight_decay,
            t: 0,
            m: params.iter().map(|p| vec![0.0; p.len()]).collect(),
            v: params.iter().map(|p| vec![0.0; p.len()]).collect(),
        }
    }

    pub(crate) fn step(&mut self, params: &mut [Vec<f32>], grads: &[Vec<f32>], lr: f64) {
        self.t += 1;
        let (b1, b2) = (self.beta1, self.beta2);
        let scale_m = (1.0 / (1.0 - b1.powi(self.t as i32))) as f32;
        let scale_v = (1.0 / (1.0 - b2.powi(self.t as i32))) as f32;
        let decay = (1.0 - lr * self.weight_decay) as f32;
        let (b1f, c1) = (b1 as f32, (1.0 - b1) as f32);
        let (b2f, c2) = (b2 as f32, (1.0 - b2) as f32);
        let (eps, lrf) = (self.eps as f32, lr as f32);
        for (((p, g), m), v) in params
            .iter_mut()
            .zip(grads)
            .zip(self.m.iter_mut())
            .zip(self.v.iter_mut())
        {
            for (((pi, &gi), mi), vi) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                *mi = *mi * b1f + gi * c1;
                *vi = *vi * b2f + gi * gi * c2;
                let mh = *mi * scale_m;
                let vh = *vi * scale_v;
                *pi = *pi * decay - (mh / (vh.sqrt() + eps)) * lrf;
            }
        }
    }
}
