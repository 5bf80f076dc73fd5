//! Inference schedules of the baselines: `K`-step standard flow, inference-time RTC
//! inpainting with a frozen prefix, GR00T N1.7's inference-time RTC (velocity strength), and
//! ACT temporal-ensembling weights.
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

/// GR00T N1.7's inference-time RTC, the form its action head's `get_action` takes when it is
/// given the previous chunk: `K` Euler steps in which
///
/// - the first `overlap` slots start from the previous chunk's actions (the `prefix`) instead
///   of noise, the other slots from the noise `ε`;
/// - every Euler update of slot `p` is scaled by a *velocity strength* `w_p`:
///   `x_p ← x_p + Δt·w_p·v_p`, with `w_p = 0` on the first `frozen` slots (kept exactly),
///   `w_p = r_i` on the `m = overlap − frozen` slots after them, and `w_p = 1` beyond
///   `overlap`. The ramp is exponential and normalised:
///   `r_i = (1 − e^{−ρ·t_i}) / (1 − e^{−ρ})`, `t_i = i/(m + 1)`, `i = 1..m`, `ρ` the ramp rate.
///
/// This is the model's velocity used as is (no vector–Jacobian guidance); with `frozen = d`,
/// the delay, the actions the robot executes while the call runs are the previous chunk's.
///
/// ```
/// use pir2_schedule::baselines::VelocityStrengthRtc;
/// let r = VelocityStrengthRtc { steps: 4, frozen: 2, overlap: 5, ramp_rate: 5.0 };
/// let w: Vec<f32> = (0..8).map(|p| r.strength(p)).collect();
/// assert_eq!(&w[..2], &[0.0, 0.0]);
/// assert!(w[2] > 0.0 && w[2] < w[3] && w[3] < w[4] && w[4] < 1.0);
/// assert_eq!(&w[5..], &[1.0, 1.0, 1.0]);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VelocityStrengthRtc {
    /// Euler steps `K`.
    pub steps: usize,
    /// Slots kept exactly as the previous chunk's (the delay `d`).
    pub frozen: usize,
    /// Slots that start from the previous chunk (`frozen ≤ overlap ≤ H`).
    pub overlap: usize,
    /// Rate `ρ > 0` of the exponential ramp between `frozen` and `overlap`.
    pub ramp_rate: f32,
}

impl VelocityStrengthRtc {
    /// Check the parameters against a chunk of `h` slots: `K ≥ 1`,
    /// `frozen ≤ overlap ≤ H`, and a finite `ρ > 0`.
    pub fn validate(&self, h: usize) -> crate::Result<()> {
        let bad = |field, message: String| Err(crate::Error::Invalid { field, message });
        if self.steps == 0 {
            return bad("steps", "need at least one Euler step".into());
        }
        if self.overlap > h {
            return bad("overlap", format!("{} is more than H = {h}", self.overlap));
        }
        if self.frozen > self.overlap {
            return bad(
                "frozen",
                format!("{} is more than overlap = {}", self.frozen, self.overlap),
            );
        }
        if !(self.ramp_rate.is_finite() && self.ramp_rate > 0.0) {
            return bad(
                "ramp_rate",
                format!("{} is not a finite rate > 0", self.ramp_rate),
            );
        }
        Ok(())
    }

    /// The velocity strength `w_p` of slot `p`.
    pub fn strength(&self, p: usize) -> f32 {
        if p < self.frozen {
            return 0.0;
        }
        if p >= self.overlap {
            return 1.0;
        }
        let m = self.overlap - self.frozen;
        let i = p - self.frozen + 1;
        let t = i as f32 / (m + 1) as f32;
        let r = |t: f32| 1.0 - (-self.ramp_rate * t).exp();
        r(t) / r(1.0).max(1e-8)
    }

    /// Integrate `x` (`[H, A]`, initially the noise `ε`) to a clean chunk; `prefix` holds the
    /// previous chunk's actions for the first `overlap` slots (`[overlap, A]`) and replaces
    /// the noise there before the first step. `tau` (`[H]`) and `v` (`[H, A]`) are
    /// caller-owned scratch; `model(x, tau, v_out)` fills the velocity. Errors of
    /// [`validate`](Self::validate) and a prefix of the wrong length are returned as
    /// [`crate::Error`] through `E: From<crate::Error>`.
    #[allow(clippy::too_many_arguments)]
    pub fn sample<E, F>(
        &self,
        x: &mut [f32],
        prefix: &[f32],
        a: usize,
        tau: &mut [f32],
        v: &mut [f32],
        mut model: F,
    ) -> Result<(), E>
    where
        E: From<crate::Error>,
        F: FnMut(&[f32], &[f32], &mut [f32]) -> Result<(), E>,
    {
        let h = tau.len();
        self.validate(h)?;
        for (what, got, expected) in [
            ("x", x.len(), h * a),
            ("v", v.len(), h * a),
            ("prefix", prefix.len(), self.overlap * a),
        ] {
            if got != expected {
                return Err(crate::Error::Length {
                    what,
                    got,
                    expected,
                }
                .into());
            }
        }
        x[..prefix.len()].copy_from_slice(prefix);
        let dt = 1.0 / self.steps as f32;
        for i in 0..self.steps {
            tau.fill(i as f32 * dt);
            model(x, tau, v)?;
            for p in self.frozen..h {
                let w = dt * self.strength(p);
                for j in p * a..(p + 1) * a {
                    x[j] += w * v[j];
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
    fn velocity_strength_rtc_is_n17s_ramp() {
        // N1.7: linspace(0, 1, m + 2), r = 1 − exp(−ρ t), r /= r[-1], keep r[1..=m].
        let r = VelocityStrengthRtc {
            steps: 4,
            frozen: 1,
            overlap: 4,
            ramp_rate: 5.0,
        };
        let norm = 1.0 - (-5.0f32).exp();
        for (p, t) in [(1, 0.25f32), (2, 0.5), (3, 0.75)] {
            let want = (1.0 - (-5.0 * t).exp()) / norm;
            assert!((r.strength(p) - want).abs() < 1e-6, "slot {p}");
        }
        assert_eq!(r.strength(0), 0.0);
        assert_eq!(r.strength(4), 1.0);
        // No middle slots: frozen, then fully denoised.
        let r = VelocityStrengthRtc { overlap: 1, ..r };
        assert_eq!((r.strength(0), r.strength(1)), (0.0, 1.0));
    }

    #[test]
    fn velocity_strength_rtc_keeps_the_frozen_slots_and_scales_the_rest() {
        let (h, a) = (6, 2);
        let r = VelocityStrengthRtc {
            steps: 5,
            frozen: 2,
            overlap: 4,
            ramp_rate: 5.0,
        };
        let eps: Vec<f32> = (0..h * a).map(|i| i as f32 * 0.1).collect();
        let prefix: Vec<f32> = (0..r.overlap * a).map(|i| -(i as f32)).collect();
        let mut x = eps.clone();
        let (mut tau, mut v) = (vec![0.0; h], vec![0.0; h * a]);
        r.sample(
            &mut x,
            &prefix,
            a,
            &mut tau,
            &mut v,
            |_x, _t, v: &mut [f32]| {
                v.fill(0.5);
                Ok::<(), crate::Error>(())
            },
        )
        .unwrap();
        assert_eq!(
            &x[..2 * a],
            &prefix[..2 * a],
            "frozen slots are the prefix, exactly"
        );
        for p in 2..4 {
            for j in p * a..(p + 1) * a {
                let want = prefix[j] + 0.5 * r.strength(p);
                assert!((x[j] - want).abs() < 1e-5, "ramp slot {p}");
            }
        }
        for j in 4 * a..h * a {
            assert!(
                (x[j] - (eps[j] + 0.5)).abs() < 1e-5,
                "free slots start from noise"
            );
        }
    }

    #[test]
    fn velocity_strength_rtc_refuses_bad_parameters_by_name() {
        let r = VelocityStrengthRtc {
            steps: 4,
            frozen: 3,
            overlap: 2,
            ramp_rate: 5.0,
        };
        let e = r.validate(8).unwrap_err().to_string();
        assert!(e.contains("frozen"), "{e}");
        let e = VelocityStrengthRtc { overlap: 9, ..r }
            .validate(8)
            .unwrap_err()
            .to_string();
        assert!(e.contains("overlap"), "{e}");
        let e = VelocityStrengthRtc {
            frozen: 0,
            ramp_rate: f32::NAN,
            ..r
        }
        .validate(8)
        .unwrap_err()
        .to_string();
        assert!(e.contains("ramp_rate"), "{e}");
        let (mut x, mut tau, mut v) = (vec![0.0; 8], vec![0.0; 8], vec![0.0; 8]);
        let ok = VelocityStrengthRtc { frozen: 1, ..r };
        let e = ok
            .sample(&mut x, &[0.0; 3], 1, &mut tau, &mut v, |_, _, _| {
                Ok::<(), crate::Error>(())
            })
            .unwrap_err()
            .to_string();
        assert!(e.contains("prefix"), "{e}");
    }

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
