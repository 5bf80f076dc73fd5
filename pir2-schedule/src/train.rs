//! Training draws: per-position `τ`, loss mask and delay for one training sample.
//!
//! Every schedule the deployment can use has a training counterpart here, so a model is
//! trained on exactly the family (and `n`) it will meet at inference (docs/method.md §1).
//!
//! ```
//! use pir2_schedule::{train::{TrainSchedule, PiR2Draws, DelayDist, Draw}, Alignment, Rng};
//! let sched = TrainSchedule::PiR2(PiR2Draws { n: Some(2), ..PiR2Draws::default() });
//! let (h, a) = (16, 2);
//! let mut rng = Rng::new(0);
//! let mut draw = Draw::new(h);
//! sched.draw(&mut rng, &mut draw).unwrap();
//! // Build the model input from ground-truth actions and noise:
//! let actions = vec![0.5f32; h * a];
//! let eps = vec![0.0f32; h * a];
//! let (mut x, mut tau_in, mut target) = (vec![0.0; h * a], vec![0.0; h], vec![0.0; h * a]);
//! draw.build(&actions, &eps, a, &mut x, &mut tau_in, &mut target).unwrap();
//! // Masked front positions carry ground truth and no loss.
//! for p in 0..draw.delay { assert_eq!(draw.mask[p], 0.0); assert_eq!(x[p * a], 0.5); }
//! ```

use serde::{Deserialize, Serialize};

use crate::error::{check_len, Error, Result};
use crate::rng::Rng;
use crate::staircase::{Alignment, Staircase};
use crate::HIDDEN_FRONT_TAU;

/// Distribution of the training delay `d`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum DelayDist {
    /// Uniform over `{1, …, max}`.
    Uniform {
        /// Largest delay `d_max`.
        max: usize,
    },
    /// `p(k) ∝ exp(−rate·k)` over `{0, …, max}`.
    Exponential {
        /// Largest delay `d_max`.
        max: usize,
        /// Decay rate `α_d`.
        rate: f64,
    },
}

impl DelayDist {
    /// The largest delay this distribution can produce.
    pub fn max(&self) -> usize {
        match *self {
            DelayDist::Uniform { max } | DelayDist::Exponential { max, .. } => max,
        }
    }

    /// Probability of delay `k`.
    pub fn pmf(&self, k: usize) -> f64 {
        match *self {
            DelayDist::Uniform { max } => {
                if (1..=max).contains(&k) {
                    1.0 / max as f64
                } else {
                    0.0
                }
            }
            DelayDist::Exponential { max, rate } => {
                if k > max {
                    return 0.0;
                }
                let z: f64 = (0..=max).map(|j| (-rate * j as f64).exp()).sum();
                (-rate * k as f64).exp() / z
            }
        }
    }

    /// Validate the parameters.
    pub fn validate(&self) -> Result<()> {
        match *self {
            DelayDist::Uniform { max: 0 } => Err(Error::Invalid {
                field: "delay.max",
                message: "uniform delays need max >= 1".into(),
            }),
            DelayDist::Exponential { rate, .. } if !rate.is_finite() || rate < 0.0 => {
                Err(Error::Invalid {
                    field: "delay.rate",
                    message: format!("must be finite and >= 0, got {rate}"),
                })
            }
            _ => Ok(()),
        }
    }

    /// Sample a delay.
    pub fn sample(&self, rng: &mut Rng) -> usize {
        match *self {
            DelayDist::Uniform { max } => 1 + rng.below(max as u64) as usize,
            DelayDist::Exponential { max, rate } => {
                // Inverse CDF over the finite support (max is small; no allocation).
                let z: f64 = (0..=max).map(|j| (-rate * j as f64).exp()).sum();
                let mut u = rng.uniform_f64() * z;
                for k in 0..=max {
                    u -= (-rate * k as f64).exp();
                    if u < 0.0 {
                        return k;
                    }
                }
                max
            }
        }
    }
}

/// How the model sees the front (the committed, in-flight actions). docs/method.md §1.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum FrontVisibility {
    /// The model sees the front's clean actions (the paper).
    #[default]
    Visible,
    /// The front is zeroed and its `τ` set to [`HIDDEN_FRONT_TAU`] (the indicator).
    Hidden,
    /// Training only: hidden with probability `p`, visible otherwise.
    Dropped {
        /// Probability of hiding the front in a draw.
        p: f32,
    },
}

/// πR² training draws (docs/method.md §1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PiR2Draws {
    /// Probability of the warm-up branch (one shared `τ ~ U[0,1]`, no mask).
    pub alpha: f32,
    /// Delay distribution of the staircase branch.
    pub delay: DelayDist,
    /// NFEs per action (`None` = full ramp); capped at `n_max(H, d)` per draw.
    pub n: Option<usize>,
    /// Staircase alignment.
    pub alignment: Alignment,
    /// Half-width of the symmetric `τ` jitter on non-front positions (clipped to `[0,1]`).
    pub jitter: f32,
    /// Front visibility.
    pub front: FrontVisibility,
}

impl Default for PiR2Draws {
    fn default() -> Self {
        Self {
            alpha: 0.2,
            delay: DelayDist::Uniform { max: 5 },
            n: None,
            alignment: Alignment::Fresh,
            jitter: 0.0,
            front: FrontVisibility::Visible,
        }
    }
}

/// `α` of GR00T N1.7's flow-time law ([`gr00t_n17_tau`]; Isaac-GR00T's `noise_beta_alpha`).
pub const GR00T_N17_TAU_ALPHA: f32 = 1.5;
/// `β` of GR00T N1.7's flow-time law (`noise_beta_beta`).
pub const GR00T_N17_TAU_BETA: f32 = 1.0;
/// Scale `s` of GR00T N1.7's flow-time law (`noise_s`): `τ < s`, never fully clean.
pub const GR00T_N17_TAU_SCALE: f32 = 0.999;

/// One flow time `τ` (0 = noise, 1 = clean, this crate's convention: `x = (1−τ)ε + τa`) from
/// GR00T N1.7's training law: `τ = s·(1 − B)` with `B ~ Beta(α, β)`, `(α, β, s)` =
/// ([`GR00T_N17_TAU_ALPHA`], [`GR00T_N17_TAU_BETA`], [`GR00T_N17_TAU_SCALE`]) =
/// (1.5, 1, 0.999).
///
/// GR00T's convention is the same as this crate's (its noisy input is `(1 − t)·noise +
/// t·actions`, target `actions − noise`), and it draws `t = (1 − B)·s`; so `τ/s ~ Beta(1,
/// 1.5)`: density `1.5·(1 − τ/s)^½ / s` on `[0, s)`, mean `0.4·s`, CDF `1 − (1 − τ/s)^1.5`,
/// most of its mass near the noise end. (NVIDIA/Isaac-GR00T at commit
/// c5437fa66982969177d20d432eca5b4d966dfbbe: `gr00t/model/gr00t_n1d7/gr00t_n1d7.py` lines
/// 101 (`Beta(noise_beta_alpha, noise_beta_beta)`), 156–159 (`sample_time`), 220–224 (the
/// noisy input, the target and the discretised timestep); `gr00t/configs/model/gr00t_n1d7.py`
/// lines 106–108 (`noise_beta_alpha = 1.5`, `noise_beta_beta = 1.0`, `noise_s = 0.999`).)
///
/// Drawn exactly by inversion with one uniform `U` from `rng`: `Beta(α, 1)` has CDF `x^α`, so
/// `B = U^(1/α)` and `τ = s·(1 − U^(1/α))`. A binding in another language reproduces a
/// stream by drawing `U` = [`Rng::uniform`] and applying the same map.
pub fn gr00t_n17_tau(rng: &mut Rng) -> f32 {
    let u = rng.uniform();
    // β = 1: inversion of Beta(α, 1).
    let b = u.powf(1.0 / GR00T_N17_TAU_ALPHA);
    GR00T_N17_TAU_SCALE * (1.0 - b)
}

/// The CDF of [`gr00t_n17_tau`]'s law at `t`: `1 − (1 − t/s)^α` on `[0, s]`.
pub fn gr00t_n17_tau_cdf(t: f64) -> f64 {
    let s = f64::from(GR00T_N17_TAU_SCALE);
    let x = (t / s).clamp(0.0, 1.0);
    1.0 - (1.0 - x).powf(f64::from(GR00T_N17_TAU_ALPHA))
}

/// A training schedule: one per deployment family.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum TrainSchedule {
    /// πR²: warm-up branch or staircase branch.
    PiR2(PiR2Draws),
    /// Train-time RTC: clean front of `d`, one shared `τ ~ U[0,1]` on the back.
    TrainTimeRtc {
        /// Delay distribution (the paper uses `d_max = 10`).
        delay: DelayDist,
    },
    /// Standard flow matching: one shared `τ ~ U[0,1]`, no mask.
    StandardFlow,
    /// Standard flow matching with GR00T N1.7's law of the shared `τ` ([`gr00t_n17_tau`]:
    /// `τ = 0.999·(1 − B)`, `B ~ Beta(1.5, 1)`, weighted towards noise), no mask: the flow
    /// baseline of `pir2 gr00t train`, trained as GR00T N1.7 trains its head.
    Gr00tFlow,
    /// Streaming diffusion: ramp `τ_p = 1 − (p + u)/H`, `u ~ U[0,1)`, no mask.
    StreamingDiffusion,
}

/// One draw: `τ` per position (the true noise level), the loss mask, the delay, and
/// whether the front is hidden from the model.
#[derive(Debug, Clone, PartialEq)]
pub struct Draw {
    /// True noise level per position, `[H]`.
    pub tau: Vec<f32>,
    /// Loss mask per position, `[H]` (0 on the front).
    pub mask: Vec<f32>,
    /// The drawn delay (front length); 0 for unmasked draws.
    pub delay: usize,
    /// Front hidden from the model in this draw.
    pub hidden: bool,
}

impl Draw {
    /// A reusable draw buffer for chunk length `h`.
    pub fn new(h: usize) -> Self {
        Self {
            tau: vec![0.0; h],
            mask: vec![1.0; h],
            delay: 0,
            hidden: false,
        }
    }

    /// Build the model input and the regression target from ground truth `actions` and
    /// noise `eps` (both `[H, A]`): `x = (1−τ)ε + τa` (front zeroed if hidden),
    /// `tau_in = τ` (or [`HIDDEN_FRONT_TAU`] on a hidden front), `target = a − ε`.
    pub fn build(
        &self,
        actions: &[f32],
        eps: &[f32],
        a: usize,
        x: &mut [f32],
        tau_in: &mut [f32],
        target: &mut [f32],
    ) -> Result<()> {
        let h = self.tau.len();
        check_len("actions", actions.len(), h * a)?;
        check_len("eps", eps.len(), h * a)?;
        check_len("x", x.len(), h * a)?;
        check_len("tau_in", tau_in.len(), h)?;
        check_len("target", target.len(), h * a)?;
        for p in 0..h {
            let t = self.tau[p];
            let hide = self.hidden && p < self.delay;
            tau_in[p] = if hide { HIDDEN_FRONT_TAU } else { t };
            for j in p * a..(p + 1) * a {
                x[j] = if hide {
                    0.0
                } else {
                    (1.0 - t) * eps[j] + t * actions[j]
                };
                target[j] = actions[j] - eps[j];
            }
        }
        Ok(())
    }
}

impl TrainSchedule {
    /// Validate parameters for chunk length `h` (every delay the distribution can draw
    /// must give a valid staircase).
    pub fn validate(&self, h: usize) -> Result<()> {
        match self {
            TrainSchedule::PiR2(c) => {
                c.delay.validate()?;
                if !(0.0..=1.0).contains(&c.alpha) {
                    return Err(Error::Invalid {
                        field: "alpha",
                        message: format!("must be in [0,1], got {}", c.alpha),
                    });
                }
                if !(0.0..=1.0).contains(&c.jitter) {
                    return Err(Error::Invalid {
                        field: "jitter",
                        message: format!("must be in [0,1], got {}", c.jitter),
                    });
                }
                if let FrontVisibility::Dropped { p } = c.front {
                    if !(0.0..=1.0).contains(&p) {
                        return Err(Error::Invalid {
                            field: "front.p",
                            message: format!("must be in [0,1], got {p}"),
                        });
                    }
                }
                let lo = if matches!(c.delay, DelayDist::Uniform { .. }) {
                    1
                } else {
                    0
                };
                for d in lo..=c.delay.max() {
                    let n = c.n.map(|n| n.min(Staircase::n_max(h, d)).max(1));
                    Staircase::new(
                        h,
                        d,
                        if c.alignment == Alignment::Paper {
                            None
                        } else {
                            n
                        },
                        c.alignment,
                    )?;
                }
                Ok(())
            }
            TrainSchedule::TrainTimeRtc { delay } => {
                delay.validate()?;
                if delay.max() >= h {
                    return Err(Error::Invalid {
                        field: "delay.max",
                        message: format!(
                            "train-time RTC needs d_max < H = {h}, got {}",
                            delay.max()
                        ),
                    });
                }
                Ok(())
            }
            TrainSchedule::StandardFlow
            | TrainSchedule::Gr00tFlow
            | TrainSchedule::StreamingDiffusion => Ok(()),
        }
    }

    /// Draw one sample's `τ`, mask and delay into `out` (no allocation).
    pub fn draw(&self, rng: &mut Rng, out: &mut Draw) -> Result<()> {
        let h = out.tau.len();
        check_len("mask", out.mask.len(), h)?;
        out.hidden = false;
        out.delay = 0;
        match self {
            TrainSchedule::PiR2(c) => {
                if rng.uniform() < c.alpha {
                    let t = rng.uniform();
                    out.tau.fill(t);
                    out.mask.fill(1.0);
                    return Ok(());
                }
                let d = c.delay.sample(rng);
                let n = match c.alignment {
                    Alignment::Paper => None,
                    Alignment::Fresh => c.n.map(|n| n.min(Staircase::n_max(h, d)).max(1)),
                };
                let s = Staircase::new(h, d, n, c.alignment)?;
                s.fill(&mut out.tau);
                for p in 0..h {
                    out.mask[p] = if p < d { 0.0 } else { 1.0 };
                }
                if c.jitter > 0.0 {
                    for t in &mut out.tau[d..] {
                        *t = (*t + rng.uniform_range(-c.jitter, c.jitter)).clamp(0.0, 1.0);
                    }
                }
                out.delay = d;
                out.hidden = match c.front {
                    FrontVisibility::Visible => false,
                    FrontVisibility::Hidden => d > 0,
                    FrontVisibility::Dropped { p } => d > 0 && rng.uniform() < p,
                };
            }
            TrainSchedule::TrainTimeRtc { delay } => {
                let d = delay.sample(rng).min(h.saturating_sub(1));
                let t = rng.uniform();
                for p in 0..h {
                    let front = p < d;
                    out.tau[p] = if front { 1.0 } else { t };
                    out.mask[p] = if front { 0.0 } else { 1.0 };
                }
                out.delay = d;
            }
            TrainSchedule::StandardFlow => {
                let t = rng.uniform();
                out.tau.fill(t);
                out.mask.fill(1.0);
            }
            TrainSchedule::Gr00tFlow => {
                let t = gr00t_n17_tau(rng);
                out.tau.fill(t);
                out.mask.fill(1.0);
            }
            TrainSchedule::StreamingDiffusion => {
                let u = rng.uniform();
                for (p, t) in out.tau.iter_mut().enumerate() {
                    *t = (1.0 - (p as f32 + u) / h as f32).clamp(0.0, 1.0);
                }
                out.mask.fill(1.0);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// GR00T N1.7's `τ` law against its Beta moments and CDF, with a fixed seed: mean
    /// `0.4·s` and variance `(α/((α+1)²(α+2)))·s²` of `s·Beta(1, α)`, and a
    /// Kolmogorov–Smirnov distance under its 0.1 % critical value. `U[0, 1]` (mean 0.5,
    /// variance 1/12, KS distance ≈ 0.15 from this law) fails every one of these.
    #[test]
    fn gr00t_n17_tau_has_its_beta_law() {
        let n = 200_000;
        let mut rng = Rng::new(20_260_526);
        let mut v: Vec<f64> = (0..n).map(|_| f64::from(gr00t_n17_tau(&mut rng))).collect();
        let s = f64::from(GR00T_N17_TAU_SCALE);
        let a = f64::from(GR00T_N17_TAU_ALPHA);
        assert!(v.iter().all(|&t| (0.0..s + 1e-7).contains(&t)));
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = v.iter().map(|t| (t - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let (m0, v0) = (s / (1.0 + a), s * s * a / ((1.0 + a).powi(2) * (2.0 + a)));
        // Standard errors: sd/√n ≈ 5.8e-4 for the mean, ≈ 2.2e-4 for the variance.
        assert!((mean - m0).abs() < 3e-3, "mean {mean} vs {m0}");
        assert!((var - v0).abs() < 1.5e-3, "variance {var} vs {v0}");
        assert!((mean - 0.5).abs() > 0.05 && (var - 1.0 / 12.0).abs() > 0.01);
        v.sort_by(f64::total_cmp);
        let ks = v
            .iter()
            .enumerate()
            .map(|(i, &t)| {
                let f = gr00t_n17_tau_cdf(t);
                (f - i as f64 / n as f64).max((i + 1) as f64 / n as f64 - f)
            })
            .fold(0.0, f64::max);
        // 0.1 % critical value of the KS distance: 1.95/√n ≈ 4.4e-3.
        assert!(ks < 1.95 / (n as f64).sqrt(), "KS distance {ks}");
        // The same test rejects U[0, 1] (its KS distance from this law).
        let ks_uniform = (0..=1000)
            .map(|i| {
                let t = i as f64 / 1000.0;
                (gr00t_n17_tau_cdf(t) - t).abs()
            })
            .fold(0.0, f64::max);
        assert!(ks_uniform > 0.1, "{ks_uniform}");
        // The schedule draws it: one shared τ, no mask.
        let mut d = Draw::new(8);
        let mut rng = Rng::new(3);
        TrainSchedule::Gr00tFlow.draw(&mut rng, &mut d).unwrap();
        let mut rng = Rng::new(3);
        let t = gr00t_n17_tau(&mut rng);
        assert!(d.tau.iter().all(|&x| x == t) && d.mask.iter().all(|&m| m == 1.0));
        assert_eq!(d.delay, 0);
    }

    #[test]
    fn exponential_pmf_sums_to_one() {
        let d = DelayDist::Exponential { max: 5, rate: 0.7 };
        let s: f64 = (0..=5).map(|k| d.pmf(k)).sum();
        assert!((s - 1.0).abs() < 1e-12);
        assert_eq!(DelayDist::Uniform { max: 5 }.pmf(0), 0.0);
    }

    #[test]
    fn invalid_configs_name_the_field() {
        let bad = TrainSchedule::PiR2(PiR2Draws {
            alpha: 1.5,
            ..Default::default()
        });
        assert!(matches!(
            bad.validate(16),
            Err(Error::Invalid { field: "alpha", .. })
        ));
        let bad = TrainSchedule::PiR2(PiR2Draws {
            delay: DelayDist::Uniform { max: 6 },
            ..Default::default()
        });
        assert!(matches!(
            bad.validate(16),
            Err(Error::HorizonTooShort { .. })
        ));
        let rtc = TrainSchedule::TrainTimeRtc {
            delay: DelayDist::Uniform { max: 16 },
        };
        assert!(rtc.validate(16).is_err());
    }
}
