//! AdamW with the cosine schedule's learning rate and grad-norm clipping.

use candle_core::{DType, Var};

use super::*;

/// Global grad norm of candle gradients; scales them in place when it exceeds `clip`.
///
/// The squared norm of each gradient is reduced on its device; only those per-tensor sums
/// (one `f32` per variable, in one transfer) reach the host, where they are added in `f64`
/// in `vars` order. The scaling stays on the device.
pub(crate) fn clip_grad_store(
    grads: &mut candle_core::backprop::GradStore,
    vars: &[candle_core::Var],
    clip: Option<f64>,
) -> Result<f32> {
    let sums = vars
        .iter()
        .filter_map(|v| grads.get(v.as_tensor()))
        .map(|g| Ok(g.sqr()?.sum_all()?.to_dtype(candle_core::DType::F32)?))
        .collect::<Result<Vec<Tensor>>>()?;
    let sq: f64 = if sums.is_empty() {
        0.0
    } else {
        Tensor::stack(&sums, 0)?
            .to_vec1::<f32>()?
            .iter()
            .map(|&s| s as f64)
            .sum()
    };
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

    /// The `f32` constants of update number `t` at learning rate `lr`, shared by the host
    /// and the device update so that both compute the same bits.
    fn coeffs(&self, t: u64, lr: f64) -> Coeffs {
        adam_coeffs(self.beta1, self.beta2, self.eps, self.weight_decay, t, lr)
    }

    pub(crate) fn step(&mut self, params: &mut [Vec<f32>], grads: &[Vec<f32>], lr: f64) {
        self.t += 1;
        let k = self.coeffs(self.t, lr);
        for (((p, g), m), v) in params
            .iter_mut()
            .zip(grads)
            .zip(self.m.iter_mut())
            .zip(self.v.iter_mut())
        {
            for (((pi, &gi), mi), vi) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                *mi = *mi * k.b1 + gi * k.c1;
                *vi = *vi * k.b2 + gi * gi * k.c2;
                let mh = *mi * k.scale_m;
                let vh = *vi * k.scale_v;
                *pi = *pi * k.decay - (mh / (vh.sqrt() + k.eps)) * k.lr;
            }
        }
    }
}

/// The per-step constants of the AdamW update, in `f32`.
#[derive(Debug, Clone, Copy)]
struct Coeffs {
    b1: f32,
    c1: f32,
    b2: f32,
    c2: f32,
    scale_m: f32,
    scale_v: f32,
    decay: f32,
    eps: f32,
    lr: f32,
}

fn adam_coeffs(beta1: f64, beta2: f64, eps: f64, weight_decay: f64, t: u64, lr: f64) -> Coeffs {
    Coeffs {
        b1: beta1 as f32,
        c1: (1.0 - beta1) as f32,
        b2: beta2 as f32,
        c2: (1.0 - beta2) as f32,
        scale_m: (1.0 / (1.0 - beta1.powi(t as i32))) as f32,
        scale_v: (1.0 / (1.0 - beta2.powi(t as i32))) as f32,
        decay: (1.0 - lr * weight_decay) as f32,
        eps: eps as f32,
        lr: lr as f32,
    }
}

/// [`AdamW`] with its moments on the variables' device: the update runs as tensor ops there
/// and writes the variables in place ([`Var::set`]); nothing crosses to the host per step.
///
/// Each element sees exactly the host update's operations, in its order and with its `f32`
/// constants (one elementwise op per candle kernel, every constant multiplied in as an
/// `f32` scalar tensor, never through `affine`): on the CPU the result is the host
/// [`AdamW`]'s, bit for bit. The state converts to and from the host form ([`Self::from_host`],
/// [`Self::to_host`]) only to be saved or restored.
#[derive(Debug)]
pub(crate) struct DeviceAdamW {
    beta1: f64,
    beta2: f64,
    eps: f64,
    weight_decay: f64,
    t: u64,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
}

impl DeviceAdamW {
    /// The device form of `host`, whose moments are those of `vars` (in order, flattened).
    pub(crate) fn from_host(host: &AdamW, vars: &[Var]) -> Result<Self> {
        if host.m.len() != vars.len() || host.v.len() != vars.len() {
            return Err(Error::shape("AdamW moments", vars.len(), host.m.len()));
        }
        let upload = |h: &[Vec<f32>]| -> Result<Vec<Tensor>> {
            vars.iter()
                .zip(h)
                .map(|(var, x)| {
                    if var.dtype() != DType::F32 {
                        return Err(Error::config(
                            "train",
                            format!("AdamW needs f32 variables, got {:?}", var.dtype()),
                        ));
                    }
                    if x.len() != var.elem_count() {
                        return Err(Error::shape("AdamW moment", var.elem_count(), x.len()));
                    }
                    Ok(Tensor::from_slice(x, var.shape(), var.device())?)
                })
                .collect()
        };
        Ok(Self {
            beta1: host.beta1,
            beta2: host.beta2,
            eps: host.eps,
            weight_decay: host.weight_decay,
            t: host.t,
            m: upload(&host.m)?,
            v: upload(&host.v)?,
        })
    }

    /// Copy the step count and the moments into `host` (for a checkpoint).
    pub(crate) fn to_host(&self, host: &mut AdamW) -> Result<()> {
        host.t = self.t;
        host.m = self
            .m
            .iter()
            .map(|m| Ok(m.flatten_all()?.to_vec1::<f32>()?))
            .collect::<Result<_>>()?;
        host.v = self
            .v
            .iter()
            .map(|v| Ok(v.flatten_all()?.to_vec1::<f32>()?))
            .collect::<Result<_>>()?;
        Ok(())
    }

    /// One update of `vars` with the gradients of `grads` (a variable without one gets a
    /// zero gradient, as on the host) at learning rate `lr`.
    pub(crate) fn step(
        &mut self,
        vars: &[Var],
        grads: &candle_core::backprop::GradStore,
        lr: f64,
    ) -> Result<()> {
        if vars.len() != self.m.len() {
            return Err(Error::shape("AdamW variables", self.m.len(), vars.len()));
        }
        self.t += 1;
        let k = adam_coeffs(
            self.beta1,
            self.beta2,
            self.eps,
            self.weight_decay,
            self.t,
            lr,
        );
        // The constants once per device and step (a variable on another device gets its own).
        let mut scalars: Option<(candle_core::Device, [Tensor; 9])> = None;
        for ((var, m), v) in vars.iter().zip(self.m.iter_mut()).zip(self.v.iter_mut()) {
            let dev = var.device();
            if !scalars.as_ref().is_some_and(|(d, _)| d.same_device(dev)) {
                let s = |x: f32| Tensor::new(x, dev);
                scalars = Some((
                    dev.clone(),
                    [
                        s(k.b1)?,
                        s(k.c1)?,
                        s(k.b2)?,
                        s(k.c2)?,
                        s(k.scale_m)?,
                        s(k.scale_v)?,
                        s(k.decay)?,
                        s(k.eps)?,
                        s(k.lr)?,
                    ],
                ));
            }
            let Some((_, [b1, c1, b2, c2, scale_m, scale_v, decay, eps, lrf])) = &scalars else {
                continue;
            };
            let p = var.as_tensor();
            let g = match grads.get(p) {
                Some(g) => g.clone(),
                None => p.zeros_like()?,
            };
            *m = (m.broadcast_mul(b1)? + g.broadcast_mul(c1)?)?;
            *v = (v.broadcast_mul(b2)? + g.mul(&g)?.broadcast_mul(c2)?)?;
            let mh = m.broadcast_mul(scale_m)?;
            let vh = v.broadcast_mul(scale_v)?;
            let upd = mh
                .div(&vh.sqrt()?.broadcast_add(eps)?)?
                .broadcast_mul(lrf)?;
            var.set(&(p.broadcast_mul(decay)? - upd)?)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use candle_core::backprop::GradStore;
    use candle_core::Device;

    use super::*;

    /// 25 updates of random parameters with random gradients (one variable without a
    /// gradient, clipping on some steps, weight decay, the cosine schedule's rates): the
    /// device AdamW on the CPU writes the host AdamW's bits, moments included.
    #[test]
    fn device_adamw_on_the_cpu_is_the_host_adamw_bit_for_bit() {
        let dev = Device::Cpu;
        let cfg = TrainConfig {
            weight_decay: 0.05,
            steps: 25,
            ..TrainConfig::default()
        };
        let mut rng = Rng::new(3);
        let mut normal = |n: usize, s: f32| -> Vec<f32> {
            (0..n)
                .map(|_| (rng.uniform() + rng.uniform() + rng.uniform() - 1.5) * s)
                .collect()
        };
        let shapes: [&[usize]; 4] = [&[7, 5], &[13], &[2, 3, 4], &[6]];
        let mut params: Vec<Vec<f32>> = shapes
            .iter()
            .map(|s| normal(s.iter().product(), 1.0))
            .collect();
        let vars = shapes
            .iter()
            .zip(&params)
            .map(|(s, p)| Ok(Var::from_tensor(&Tensor::from_slice(p, *s, &dev)?)?))
            .collect::<Result<Vec<_>>>()
            .unwrap();
        let initial = params.clone();
        let mut host = AdamW::new(&cfg, &params);
        let mut device = DeviceAdamW::from_host(&host, &vars).unwrap();
        let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        for step in 0..cfg.steps {
            let lr = cfg.lr_at(step);
            // The last variable has no gradient (the host sees zeros).
            let grads: Vec<Vec<f32>> = params
                .iter()
                .map(|p| normal(p.len(), if step % 4 == 3 { 1e-3 } else { 0.3 }))
                .collect();
            let mut store = GradStore::default();
            for (v, (g, s)) in vars.iter().zip(grads.iter().zip(shapes)).take(3) {
                store.insert(v.as_tensor(), Tensor::from_slice(g, s, &dev).unwrap());
            }
            let clip = (step % 3 == 0).then_some(0.5);
            clip_grad_store(&mut store, &vars, clip).unwrap();
            // The host update reads the clipped gradients (as `backward_to_host` copies them).
            let host_grads: Vec<Vec<f32>> = vars
                .iter()
                .zip(&params)
                .map(|(v, p)| match store.get(v.as_tensor()) {
                    Some(g) => g.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                    None => vec![0.0; p.len()],
                })
                .collect();
            host.step(&mut params, &host_grads, lr);
            device.step(&vars, &store, lr).unwrap();
        }
        let mut back = AdamW::new(&cfg, &params);
        device.to_host(&mut back).unwrap();
        assert_eq!(back.t, host.t);
        for (i, v) in vars.iter().enumerate() {
            let p = v
                .as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            assert_eq!(bits(&p), bits(&params[i]), "param {i}");
            assert_eq!(bits(&back.m[i]), bits(&host.m[i]), "m {i}");
            assert_eq!(bits(&back.v[i]), bits(&host.v[i]), "v {i}");
        }
        assert_eq!(host.t, 25);
        assert!(
            params.iter().zip(&initial).all(|(p, q)| p != q),
            "every variable moved"
        );
    }
}
