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
            TrainSchedule::StandardFlow | TrainSchedule::StreamingDiffusion => Ok(()),
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
