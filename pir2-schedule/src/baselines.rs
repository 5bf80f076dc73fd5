//! Inference schedules of the baselines: `K`-step standard flow, inference-time RTC
//! inpainting with a frozen prefix, and ACT temporal-ensembling weights.
//!
//! ```
//! use pir2_schedule::baselines::{ensemble_weights, StandardFlow};
//! // K-step Euler flow from noise with an exact velocity lands on the target.
//! let target = [0.25f32, -0.5];
//! let mut x = [1.0f32, 2.0]; // the initial noise ε
//! let eps = x;
//! let (mut tau, mut v) = ([0.0f32; 1], [0.0f32; 2]);
//! StandardFlow { steps: 4 }
//!     .sample(&mut x, &mut tau, &mut v, |_x, _t, v: &mut [f32]| {
//!         for j in 0..2 { v[j] = target[j] - eps[j]; }
//!         Ok::<(), ()>(())
//!     })
//!     .unwrap();
//! assert!((x[0] - 0.25).abs() < 1e-6 && (x[1] + 0.5).abs() < 1e-6);
//! // ACT weights, oldest prediction first, normalised.
//! let mut w = [0.0; 3];
//! ensemble_weights(0.1, &mut w);
//! assert!(w[0] > w[1] && w[1] > w[2] && (w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
//! ```

use serde::{Deserialize, Serialize};

/// Standard chunked flow: `K` Euler steps with one shared `τ_k = k/K`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StandardFlow {
    /// Number of Euler steps `K`.
    pub steps: usize,
}

impl StandardFlow {
    /// Integrate `x` (initially noise, `[H, A]`) to a clean chunk. `tau` (`[H]`) and `v`
    /// (`[H, A]`) are caller-owned scratch; `model(x, tau, v_out)` fills the velocity.
    pub fn sample<E, F>(
        &self,
        x: &mut [f32],
        tau: &mut [f32],
        v: &mut [f32],
        mut model: F,
    ) -> Result<(), E>
    where
        F: FnMut(&[f32], &[f32], &mut [f32]) -> Result<(), E>,
    {
        let k = self.steps.max(1);
        let dt = 1.0 / k as f32;
        for i in 0..k {
            tau.fill(i as f32 * dt);
            model(x, tau, v)?;
            for (x, v) in x.iter_mut().zip(v.iter()) {
                *x += dt * v;
            }
        }
        Ok(())
    }
}

/// Inference-time RTC inpainting: `K` Euler steps from noise while the prefix is pulled
/// towards the frozen (already committed) actions with RTC's soft mask: weight 1 on the
/// first `d` slots, an exponential decay over the middle, 0 on the last `s` slots.
///
/// RTC proper adds a guidance term that needs the model's vector–Jacobian product; the
/// [`VelocityModel`](https://docs.rs/pir2-runtime) contract does not expose one, so this is
/// the replacement form of the same soft-masked inpainting (listed among the
/// baselines in `docs/method.md` §1 as inference-time RTC inpainting).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RtcInpainting {
    /// Euler steps `K`.
    pub steps: usize,
    /// Frozen prefix length (the delay `d`).
    pub frozen: usize,
    /// Execution horizon `s`: the last `s` slots get weight 0.
    pub exec_horizon: usize,
}

impl RtcInpainting {
    /// Soft-mask weight of position `p` in a chunk of `h`.
    pub fn weight(&self, p: usize, h: usize) -> f32 {
        let d = self.frozen;
        let end = h.saturating_sub(self.exec_horizon);
        if p < d {
            1.0
        } else if p < end {
            let c = (end - p) as f32 / (end - d + 1) as f32;
            c * (c.exp() - 1.0) / (std::f32::consts::E - 1.0)
        } else {
            0.0
        }
    }

    /// Integrate `x` (`[H, A]`, initially the noise `ε`; `eps` keeps a copy) while
    /// inpainting `prefix` (`[H, A]`, only the first positions are used by the mask).
    #[allow(clippy::too_many_arguments)]
    pub fn sample<E, F>(
        &self,
        x: &mut [f32],
        eps: &[f32],
        prefix: &[f32],
        a: usize,
        tau: &mut [f32],
        v: &mut [f32],
        mut model: F,
    ) -> Result<(), E>
    where
        F: FnMut(&[f32], &[f32], &mut [f32]) -> Result<(), E>,
    {
        let h = tau.len();
        let k = self.steps.max(1);
        let dt = 1.0 / k as f32;
        for i in 0..k {
            tau.fill(i as f32 * dt);
            model(x, tau, v)?;
            let t_next = (i + 1) as f32 * dt;
            for p in 0..h {
                let w = self.weight(p, h);
                for j in p * a..(p + 1) * a {
                    x[j] += dt * v[j];
                    if w > 0.0 {
                        let want = (1.0 - t_next) * eps[j] + t_next * prefix[j];
                        x[j] += w * (want - x[j]);
                    }
                }
            }
        }
        Ok(())
    }
}

/// ACT temporal-ensembling weights `w_i = exp(−m·i)`, `i = 0` the oldest prediction,
/// normalised to sum to one.
pub fn ensemble_weights(m: f32, out: &mut [f32]) {
    let mut s = 0.0;
    for (i, w) in out.iter_mut().enumerate() {
        *w = (-m * i as f32).exp();
        s += *w;
    }
    if s > 0.0 {
        for w in out.iter_mut() {
            *w /= s;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rtc_mask_shape() {
        let r = RtcInpainting {
            steps: 5,
            frozen: 3,
            exec_horizon: 4,
        };
        let w: Vec<f32> = (0..16).map(|p| r.weight(p, 16)).collect();
        assert_eq!(&w[..3], &[1.0, 1.0, 1.0]);
        assert!(w[3] < 1.0 && w[3] > w[8]);
        assert_eq!(&w[12..], &[0.0; 4]);
    }

    #[test]
    fn rtc_reproduces_the_frozen_prefix() {
        let (h, a) = (8, 1);
        let r = RtcInpainting {
            steps: 10,
            frozen: 2,
            exec_horizon: 2,
        };
        let eps: Vec<f32> = (0..h).map(|i| i as f32 * 0.1).collect();
        let prefix = vec![0.7f32; h];
        let mut x = eps.clone();
        let (mut tau, mut v) = (vec![0.0; h], vec![0.0; h]);
        r.sample(
            &mut x,
            &eps,
            &prefix,
            a,
            &mut tau,
            &mut v,
            |_x, _t, v: &mut [f32]| {
                v.fill(-0.3);
                Ok::<(), ()>(())
            },
        )
        .unwrap();
        assert!((x[0] - 0.7).abs() < 1e-5 && (x[1] - 0.7).abs() < 1e-5);
        assert!(
            (x[7] - (0.7 - 0.3)).abs() < 1e-5,
            "unmasked slot follows the model"
        );
    }
}
