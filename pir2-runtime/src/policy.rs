//! Policies: how a model is trained and how it is deployed, in one place.
//!
//! A [`Mode`] says how a trained model is run; a [`Policy`] says which training schedule
//! (the draw recipe of [`pir2_schedule::train`]) produced the model and in which modes it is
//! deployed. The two must agree: a πR² policy is trained on the same staircase family and
//! the same `n` it is deployed with, a front-hidden policy hides the front in both, and the
//! largest delay a policy must handle at run time is the largest delay it was trained on.
//!
//! The study tasks (ball-on-plate, Leap cube) pick their rows from [`Policy::deployments`]
//! and train every policy with [`Policy::schedule`]; nothing else names a schedule.

use serde::{Deserialize, Serialize};

use pir2_schedule::train::{DelayDist, FrontVisibility, PiR2Draws, TrainSchedule};
use pir2_schedule::{Alignment, FrontMode};

use crate::mode::Mode;

/// A trained policy: schedule at training time, modes at deployment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Policy {
    /// πR², small `n` (fresh alignment), front visible.
    PiR2,
    /// πR², small `n`, front hidden in training and at inference.
    PiR2Hidden,
    /// πR² with the paper's literal full-chunk ramp (paper alignment, `n = n_max`).
    PiR2Full,
    /// Train-time RTC: clean front of `d`, one shared `τ` on the back.
    Rtc,
    /// Standard chunked flow matching (deployed sync, naive async, or with ensembling).
    Flow,
    /// πR², small `n`, trained for zero delay only (`d_max = 0`: every staircase draw has
    /// `d = 0`, a ramp of `n` slots). A labelled extra of the zero-latency horizon study:
    /// deployed with a head whose `d_max` is 0, it acts on the newest observation within the
    /// tick (lock-step with zero-tick calls only).
    PiR2ZeroDelay,
    /// The paper's zero-delay variant: trained for `d = 0` only (`d_max = 0`) on the full
    /// streaming ramp (`n = H`, one action emitted per call, every action's last step in the
    /// call that emits it: `τ*_p = (H−1−p)/H`, which the step advances to `1 − p/H`). The
    /// policy of the paper's horizon study; lock-step with zero-tick calls only.
    PiR2ZeroDelayFull,
}

/// The law of the per-batch delay draws of πR² and train-time RTC.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "law", rename_all = "snake_case")]
pub enum DelayLaw {
    /// `d ~ U{1..d_max}`.
    Uniform,
    /// `p(d = k) ∝ e^{−rate·k}` over `{0..d_max}` (small delays more likely).
    Exponential {
        /// Decay rate `α_d`.
        rate: f64,
    },
}

impl DelayLaw {
    /// The distribution over delays up to `d_max`.
    pub fn dist(self, d_max: usize) -> DelayDist {
        match self {
            DelayLaw::Uniform => DelayDist::Uniform { max: d_max },
            DelayLaw::Exponential { rate } => DelayDist::Exponential { max: d_max, rate },
        }
    }
}

/// The knobs shared by a study's policies: `n` of the πR² policies, the baselines' Euler
/// steps, the sync-flow execution horizon, the ensembling decay, and the training delays
/// (law, `d_max` of πR² and of train-time RTC, `τ` jitter). [`Recipe::default`] is the
/// recipe of the embedded studies (uniform delays, πR² `d_max` 5, RTC 6, no jitter);
/// [`Recipe::paper_sim`] is the paper's simulation protocol.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Recipe {
    /// NFEs per action of the small-`n` πR² policies (training and inference).
    pub nfe: usize,
    /// Euler steps `K` of the flow baselines (standard flow, train-time RTC).
    pub flow_steps: usize,
    /// Execution horizon of the sync-flow row.
    pub sync_h: usize,
    /// Decay `m` of ACT temporal ensembling in the "naive async + TE" row.
    pub ensemble: f32,
    /// Law of the training delay draws (πR² and train-time RTC).
    pub delays: DelayLaw,
    /// Largest training delay of the πR² policies (and their head's latency window).
    pub pir2_d_max: usize,
    /// Largest training delay of train-time RTC (and the latency window of the flow
    /// baselines' heads).
    pub rtc_d_max: usize,
    /// Half-width `j` of the symmetric `τ` jitter of the πR² staircase draws.
    pub jitter: f32,
}

impl Default for Recipe {
    fn default() -> Self {
        Self {
            nfe: 2,
            flow_steps: 10,
            sync_h: 8,
            ensemble: 0.1,
            delays: DelayLaw::Uniform,
            pir2_d_max: 5,
            rtc_d_max: 6,
            jitter: 0.0,
        }
    }
}

impl Recipe {
    /// The paper's simulation protocol (its appendix): delays `p(d) ∝ e^{−d}` over
    /// `{0..d_max}`, πR² `d_max` 5, train-time RTC `d_max` 10, `K = 15` Euler steps for the
    /// flow baselines, no jitter (the paper names a jitter `j` but gives no value for the
    /// simulation). `n` of the small-`n` πR² rows as the default recipe.
    pub fn paper_sim() -> Self {
        Self {
            flow_steps: 15,
            delays: DelayLaw::Exponential { rate: 1.0 },
            pir2_d_max: 5,
            rtc_d_max: 10,
            jitter: 0.0,
            ..Self::default()
        }
    }
}

/// One way to deploy a policy: a table label and the mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Deployment {
    /// Table label.
    pub label: String,
    /// The policy (the trained model) deployed.
    pub policy: Policy,
    /// The deployment mode.
    pub mode: Mode,
}

impl Policy {
    /// Every policy, in table order.
    pub const ALL: [Policy; 7] = [
        Policy::PiR2,
        Policy::PiR2Hidden,
        Policy::PiR2Full,
        Policy::Rtc,
        Policy::Flow,
        Policy::PiR2ZeroDelay,
        Policy::PiR2ZeroDelayFull,
    ];

    /// The policy's name on the command line (`pir2 train|eval --policy`): `pir2`,
    /// `pir2-hidden`, `pir2-full`, `rtc`, `flow`, `pir2-zero-delay`, `pir2-zero-delay-full`.
    pub fn name(self) -> &'static str {
        match self {
            Policy::PiR2 => "pir2",
            Policy::PiR2Hidden => "pir2-hidden",
            Policy::PiR2Full => "pir2-full",
            Policy::Rtc => "rtc",
            Policy::Flow => "flow",
            Policy::PiR2ZeroDelay => "pir2-zero-delay",
            Policy::PiR2ZeroDelayFull => "pir2-zero-delay-full",
        }
    }

    /// Whether the policy's network gives every chunk position its own modulation head (the
    /// paper's architecture for πR²; the baselines keep the shared head).
    pub fn per_position_heads(self) -> bool {
        !matches!(self, Policy::Rtc | Policy::Flow)
    }

    /// The largest delay the policy must handle (the trained `d_max`; the head's latency
    /// window is capped there): the recipe's πR² or RTC `d_max` (the flow baselines share
    /// RTC's window), 0 for the zero-delay policy.
    pub fn d_max(self, r: &Recipe) -> usize {
        match self {
            Policy::Rtc | Policy::Flow => r.rtc_d_max,
            Policy::PiR2ZeroDelay | Policy::PiR2ZeroDelayFull => 0,
            Policy::PiR2 | Policy::PiR2Hidden | Policy::PiR2Full => r.pir2_d_max,
        }
    }

    /// The training schedule: the same staircase family and `n` as deployment, α = 0.2,
    /// delays from the recipe's law up to [`d_max`](Self::d_max), the recipe's jitter on
    /// the πR² staircases.
    pub fn schedule(self, r: &Recipe) -> TrainSchedule {
        let base = PiR2Draws {
            alpha: 0.2,
            delay: r.delays.dist(r.pir2_d_max),
            n: Some(r.nfe),
            jitter: r.jitter,
            ..Default::default()
        };
        match self {
            Policy::PiR2 => TrainSchedule::PiR2(base),
            Policy::PiR2Hidden => TrainSchedule::PiR2(PiR2Draws {
                front: FrontVisibility::Hidden,
                ..base
            }),
            Policy::PiR2Full => TrainSchedule::PiR2(PiR2Draws {
                n: None,
                alignment: Alignment::Paper,
                ..base
            }),
            Policy::Rtc => TrainSchedule::TrainTimeRtc {
                delay: r.delays.dist(r.rtc_d_max),
            },
            Policy::Flow => TrainSchedule::StandardFlow,
            // The exponential law over {0..0} draws d = 0 every time.
            Policy::PiR2ZeroDelay => TrainSchedule::PiR2(PiR2Draws {
                delay: DelayDist::Exponential { max: 0, rate: 1.0 },
                ..base
            }),
            // n = None with the fresh alignment: n_max(H, 0) = H, the full streaming ramp.
            Policy::PiR2ZeroDelayFull => TrainSchedule::PiR2(PiR2Draws {
                delay: DelayDist::Exponential { max: 0, rate: 1.0 },
                n: None,
                alignment: Alignment::Fresh,
                ..base
            }),
        }
    }

    /// The modes this policy is deployed in, with their table labels, in table order.
    pub fn deployments(self, r: &Recipe) -> Vec<Deployment> {
        let k = r.flow_steps;
        let fresh = |front| Mode::PiR2Async {
            nfe: Some(r.nfe),
            alignment: Alignment::Fresh,
            front,
        };
        let rows: Vec<(String, Mode)> = match self {
            Policy::Flow => vec![
                (
                    "sync flow".into(),
                    Mode::SyncFlow {
                        steps: k,
                        h: r.sync_h,
                    },
                ),
                (
                    "naive async".into(),
                    Mode::NaiveAsync {
                        steps: k,
                        ensemble: None,
                    },
                ),
                (
                    "naive async + TE".into(),
                    Mode::NaiveAsync {
                        steps: k,
                        ensemble: Some(r.ensemble),
                    },
                ),
            ],
            Policy::Rtc => vec![("train-time RTC".into(), Mode::TrainTimeRtc { steps: k })],
            Policy::PiR2 => vec![
                (
                    format!("πR² w/o async (n={})", r.nfe),
                    Mode::PiR2Sync {
                        nfe: Some(r.nfe),
                        alignment: Alignment::Fresh,
                        front: FrontMode::Visible,
                    },
                ),
                (
                    format!("πR² async (n={})", r.nfe),
                    fresh(FrontMode::Visible),
                ),
            ],
            Policy::PiR2Hidden => vec![(
                format!("πR² async, front hidden (n={})", r.nfe),
                fresh(FrontMode::Hidden),
            )],
            Policy::PiR2Full => vec![(
                "πR² async, paper full ramp".into(),
                Mode::PiR2Async {
                    nfe: None,
                    alignment: Alignment::Paper,
                    front: FrontMode::Visible,
                },
            )],
            Policy::PiR2ZeroDelay => vec![(
                format!("πR² zero delay (n={})", r.nfe),
                fresh(FrontMode::Visible),
            )],
            Policy::PiR2ZeroDelayFull => vec![(
                "πR² zero delay, paper streaming ramp".into(),
                Mode::PiR2Async {
                    nfe: None,
                    alignment: Alignment::Fresh,
                    front: FrontMode::Visible,
                },
            )],
        };
        rows.into_iter()
            .map(|(label, mode)| Deployment {
                label,
                policy: self,
                mode,
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deployments_match_the_training_schedule() {
        let r = Recipe::default();
        for p in Policy::ALL {
            let s = p.schedule(&r);
            for d in p.deployments(&r) {
                assert_eq!(d.policy, p);
                match (s, d.mode) {
                    (
                        TrainSchedule::PiR2(draws),
                        Mode::PiR2Async {
                            nfe,
                            alignment,
                            front,
                        },
                    )
                    | (
                        TrainSchedule::PiR2(draws),
                        Mode::PiR2Sync {
                            nfe,
                            alignment,
                            front,
                        },
                    ) => {
                        assert_eq!(draws.n, nfe, "{p:?}");
                        assert_eq!(draws.alignment, alignment, "{p:?}");
                        let hidden = draws.front == FrontVisibility::Hidden;
                        assert_eq!(hidden, front == FrontMode::Hidden, "{p:?}");
                        assert!(draws.delay.max() <= p.d_max(&r));
                    }
                    (TrainSchedule::TrainTimeRtc { delay }, Mode::TrainTimeRtc { .. }) => {
                        assert_eq!(delay.max(), p.d_max(&r));
                    }
                    (
                        TrainSchedule::StandardFlow,
                        Mode::SyncFlow { .. } | Mode::NaiveAsync { .. },
                    ) => {}
                    (s, m) => panic!("{p:?}: schedule {s:?} deployed as {m:?}"),
                }
            }
        }
    }

    #[test]
    fn the_zero_delay_policy_draws_only_zero_delays() {
        for r in [Recipe::default(), Recipe::paper_sim()] {
            let TrainSchedule::PiR2(draws) = Policy::PiR2ZeroDelay.schedule(&r) else {
                panic!("a πR² schedule");
            };
            draws.delay.validate().unwrap();
            let mut rng = pir2_schedule::Rng::new(3);
            assert!((0..100).all(|_| draws.delay.sample(&mut rng) == 0));
            assert_eq!(Policy::PiR2ZeroDelay.d_max(&r), 0);
            let d = Policy::PiR2ZeroDelay.deployments(&r);
            assert_eq!(d.len(), 1);
            assert!(matches!(d[0].mode, Mode::PiR2Async { nfe: Some(2), .. }));
        }
    }

    /// The paper's zero-delay variant trains and runs the full streaming ramp at d = 0:
    /// H − 1 ramp slots after the emitted one, every action's last step in the call that emits
    /// it, and the step leaves the streaming ramp `1 − p/H`.
    #[test]
    fn the_paper_zero_delay_policy_is_the_streaming_ramp() {
        let r = Recipe::paper_sim();
        let p = Policy::PiR2ZeroDelayFull;
        let TrainSchedule::PiR2(draws) = p.schedule(&r) else {
            panic!("a πR² schedule");
        };
        let mut rng = pir2_schedule::Rng::new(5);
        assert!((0..100).all(|_| draws.delay.sample(&mut rng) == 0));
        assert_eq!((draws.n, draws.alignment), (None, Alignment::Fresh));
        assert_eq!(p.d_max(&r), 0);
        let h = 16;
        let s = pir2_schedule::Staircase::new(h, 0, draws.n, draws.alignment).unwrap();
        assert_eq!(s.nfe(), h);
        for q in 0..h {
            assert!((s.tau(q) - (h - 1 - q) as f32 / h as f32).abs() < 1e-6);
            assert!((s.tau_after(q) - (1.0 - q as f32 / h as f32)).abs() < 1e-6);
        }
        let d = p.deployments(&r);
        assert!(matches!(
            d[0].mode,
            Mode::PiR2Async {
                nfe: None,
                alignment: Alignment::Fresh,
                ..
            }
        ));
    }

    #[test]
    fn the_paper_recipe_draws_the_appendix_delays() {
        let r = Recipe::paper_sim();
        let TrainSchedule::PiR2(draws) = Policy::PiR2.schedule(&r) else {
            panic!("a πR² schedule");
        };
        assert_eq!(draws.delay, DelayDist::Exponential { max: 5, rate: 1.0 });
        assert_eq!(
            Policy::Rtc.schedule(&r),
            TrainSchedule::TrainTimeRtc {
                delay: DelayDist::Exponential { max: 10, rate: 1.0 }
            }
        );
        assert_eq!(Policy::Flow.d_max(&r), 10);
        assert_eq!(r.flow_steps, 15);
        // The default recipe is what the embedded studies were measured with.
        let d = Recipe::default();
        let TrainSchedule::PiR2(draws) = Policy::PiR2.schedule(&d) else {
            panic!("a πR² schedule");
        };
        assert_eq!(draws.delay, DelayDist::Uniform { max: 5 });
        assert_eq!(
            Policy::Rtc.schedule(&d),
            TrainSchedule::TrainTimeRtc {
                delay: DelayDist::Uniform { max: 6 }
            }
        );
        assert_eq!((Policy::Flow.d_max(&d), d.flow_steps), (6, 10));
    }
}
