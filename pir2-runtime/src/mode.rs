//! Deployment modes: each is a small policy over the same machinery (docs/method.md §2, §4).

use serde::{Deserialize, Serialize};

use pir2_schedule::{Alignment, FrontMode};

use crate::control::CallPolicy;
use crate::head::HeadMode;

/// The five deployment modes of the paper's study, and GR00T N1.7's inference-time RTC (the
/// baseline N1.7's users already have).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Mode {
    /// Synchronous flow: the robot holds while a `K`-step call runs, then executes `h`.
    SyncFlow {
        /// Euler steps.
        steps: usize,
        /// Execution horizon `h`.
        h: usize,
    },
    /// Naive async: `K`-step flow from scratch on every call, swap at the elapsed index,
    /// ACT temporal ensembling with weight decay `m`.
    NaiveAsync {
        /// Euler steps.
        steps: usize,
        /// Ensembling decay `m` (`None` = plain swap).
        ensemble: Option<f32>,
    },
    /// Train-time RTC: committed front given clean, back integrated in `K` steps.
    TrainTimeRtc {
        /// Euler steps.
        steps: usize,
    },
    /// GR00T N1.7's inference-time RTC: a standard-flow model, `K` Euler steps per call, the
    /// first `overlap` slots started from the chunk in flight and the first `d` of them kept
    /// (velocity strength, [`VelocityStrengthRtc`](pir2_schedule::baselines::VelocityStrengthRtc)).
    /// Calls run asynchronously and swap in at the elapsed index, as naive async.
    InferenceRtc {
        /// Euler steps.
        steps: usize,
        /// Slots started from the chunk in flight (`None`: every slot it still covers).
        overlap: Option<usize>,
        /// Rate `ρ` of the exponential velocity-strength ramp.
        ramp_rate: f32,
    },
    /// πR² with the slow channel computed inside each call.
    PiR2Sync {
        /// NFEs per action.
        nfe: Option<usize>,
        /// Alignment.
        alignment: Alignment,
        /// Front visibility.
        front: FrontMode,
    },
    /// πR² with an asynchronous slow worker.
    PiR2Async {
        /// NFEs per action.
        nfe: Option<usize>,
        /// Alignment.
        alignment: Alignment,
        /// Front visibility.
        front: FrontMode,
    },
}

/// How long calls and the slow channel take, in control ticks, for a unit delay `d0`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct EffectiveDelays {
    /// Ticks one action-head call takes (the effective `d`).
    pub d: usize,
    /// Age of the slow features at a snapshot.
    pub d_vis: usize,
}

impl Mode {
    /// πR² with the asynchronous slow channel, `n` NFEs per action, the fresh alignment and
    /// the front visible (the usual deployment).
    pub fn pir2_async(n: usize) -> Self {
        Mode::PiR2Async {
            nfe: Some(n),
            alignment: Alignment::Fresh,
            front: FrontMode::Visible,
        }
    }

    /// πR² with the asynchronous slow channel on the paper's full-chunk ramp.
    pub fn pir2_async_full_ramp() -> Self {
        Mode::PiR2Async {
            nfe: None,
            alignment: Alignment::Paper,
            front: FrontMode::Visible,
        }
    }

    /// Short name for tables.
    pub fn name(&self) -> &'static str {
        match self {
            Mode::SyncFlow { .. } => "sync flow",
            Mode::NaiveAsync { .. } => "naive async",
            Mode::TrainTimeRtc { .. } => "train-time RTC",
            Mode::InferenceRtc { .. } => "N1.7 inference-time RTC",
            Mode::PiR2Sync { .. } => "πR² w/o async",
            Mode::PiR2Async { .. } => "πR² async",
        }
    }

    /// The mode with its schedule, for logs and run summaries, e.g. `πR² async (n = 2, fresh
    /// alignment, front visible)` or `sync flow (K = 4, h = 10)`.
    pub fn describe(&self) -> String {
        let pir2 = |nfe: &Option<usize>, alignment: &Alignment, front: &FrontMode| {
            let n = match nfe {
                Some(n) => format!("n = {n}"),
                None => "full ramp".to_string(),
            };
            let a = match alignment {
                Alignment::Fresh => "fresh alignment",
                Alignment::Paper => "paper alignment",
            };
            let f = match front {
                FrontMode::Visible => "front visible",
                FrontMode::Hidden => "front hidden",
            };
            format!("{} ({n}, {a}, {f})", self.name())
        };
        match self {
            Mode::SyncFlow { steps, h } => format!("sync flow (K = {steps}, h = {h})"),
            Mode::NaiveAsync { steps, ensemble } => match ensemble {
                Some(m) => format!("naive async (K = {steps}, temporal ensembling m = {m})"),
                None => format!("naive async (K = {steps}, plain swap)"),
            },
            Mode::TrainTimeRtc { steps } => format!("train-time RTC (K = {steps})"),
            Mode::InferenceRtc {
                steps,
                overlap,
                ramp_rate,
            } => {
                let o = match overlap {
                    Some(o) => format!("overlap = {o}"),
                    None => "overlap = every slot in flight".to_string(),
                };
                format!(
                    "{} (K = {steps}, {o}, ramp rate = {ramp_rate})",
                    self.name()
                )
            }
            Mode::PiR2Sync {
                nfe,
                alignment,
                front,
            }
            | Mode::PiR2Async {
                nfe,
                alignment,
                front,
            } => pir2(nfe, alignment, front),
        }
    }

    /// The paper's effective delays for unit delay `d0` (docs/method.md §4): `⌈1.75·d0⌉` for the
    /// `K`-step baselines, `d0` for πR² without async (action head + slow encoder in one
    /// call), and `1` for πR² with async plus `d_vis = d0` on the slow subset.
    pub fn effective_delays(&self, d0: usize) -> EffectiveDelays {
        let slow = (7 * d0).div_ceil(4); // ⌈1.75·d0⌉ in integers
        match self {
            Mode::SyncFlow { .. }
            | Mode::NaiveAsync { .. }
            | Mode::TrainTimeRtc { .. }
            | Mode::InferenceRtc { .. } => EffectiveDelays {
                d: slow.max(1),
                d_vis: 0,
            },
            Mode::PiR2Sync { .. } => EffectiveDelays {
                d: d0.max(1),
                d_vis: 0,
            },
            Mode::PiR2Async { .. } => EffectiveDelays { d: 1, d_vis: d0 },
        }
    }

    /// The head mode.
    pub fn head_mode(&self, warm_start_steps: usize) -> HeadMode {
        match *self {
            Mode::SyncFlow { steps, .. } | Mode::NaiveAsync { steps, .. } => {
                HeadMode::Flow { steps }
            }
            Mode::TrainTimeRtc { steps } => HeadMode::TrainTimeRtc { steps },
            Mode::InferenceRtc {
                steps,
                overlap,
                ramp_rate,
            } => HeadMode::InferenceRtc {
                steps,
                overlap,
                ramp_rate,
            },
            Mode::PiR2Sync {
                nfe,
                alignment,
                front,
            }
            | Mode::PiR2Async {
                nfe,
                alignment,
                front,
            } => HeadMode::PiR2 {
                nfe,
                alignment,
                front,
                warm_start_steps,
            },
        }
    }

    /// When calls are made.
    pub fn call_policy(&self) -> CallPolicy {
        match *self {
            Mode::SyncFlow { h, .. } => CallPolicy::Sync { h },
            _ => CallPolicy::Async,
        }
    }

    /// Temporal ensembling decay, if any.
    pub fn ensemble(&self) -> Option<f32> {
        match *self {
            Mode::NaiveAsync { ensemble, .. } => ensemble,
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_effective_delay_table() {
        let na = Mode::NaiveAsync {
            steps: 10,
            ensemble: Some(0.1),
        };
        let rtc = Mode::TrainTimeRtc { steps: 10 };
        let ps = Mode::PiR2Sync {
            nfe: Some(2),
            alignment: Alignment::Fresh,
            front: FrontMode::Visible,
        };
        let pa = Mode::PiR2Async {
            nfe: Some(2),
            alignment: Alignment::Fresh,
            front: FrontMode::Visible,
        };
        for (d0, slow) in [(1, 2), (2, 4), (3, 6)] {
            assert_eq!(
                na.effective_delays(d0),
                EffectiveDelays { d: slow, d_vis: 0 }
            );
            assert_eq!(
                rtc.effective_delays(d0),
                EffectiveDelays { d: slow, d_vis: 0 }
            );
            assert_eq!(ps.effective_delays(d0), EffectiveDelays { d: d0, d_vis: 0 });
            assert_eq!(pa.effective_delays(d0), EffectiveDelays { d: 1, d_vis: d0 });
        }
    }
}
