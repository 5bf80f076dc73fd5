//! The embodiment's `[policy]` table: how the action head was fine-tuned and the rows of the
//! paper's real-robot table it can be deployed as.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// How a deployment runs the action head: the rows of the paper's real-robot table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum DeployKind {
    /// πR² with the slow channel on its own worker (the cached backbone features carry
    /// their age `d_vis`); one call costs one NFE.
    #[serde(rename = "pir2_async")]
    PiR2Async,
    /// πR² without async: each call runs the backbone first, so its time counts in `d`.
    #[serde(rename = "pir2_sync")]
    PiR2Sync,
    /// Standard flow, synchronous: the robot holds while a call runs, then executes `h`
    /// actions of the new chunk.
    #[serde(rename = "sync_flow")]
    SyncFlow,
    /// Standard flow, asynchronous: the next chunk is computed while the current one runs
    /// and swapped in when ready (optionally with ACT temporal ensembling).
    #[serde(rename = "naive_async")]
    NaiveAsync,
    /// Train-time RTC: the in-flight actions are the clean front of the next chunk.
    #[serde(rename = "rtc")]
    Rtc,
    /// GR00T N1.7's inference-time RTC (its action head's `get_action` given the previous
    /// chunk) on a standard-flow head: asynchronous like naive async, each call's first
    /// `rtc_overlap` slots start from the chunk in flight, the `d` executed during the call
    /// are kept, the rest ramp to a full denoise at rate `rtc_ramp_rate`.
    #[serde(rename = "inference_rtc")]
    InferenceRtc,
}

impl DeployKind {
    /// Every kind, in the paper's table order.
    pub const ALL: [DeployKind; 6] = [
        DeployKind::SyncFlow,
        DeployKind::NaiveAsync,
        DeployKind::InferenceRtc,
        DeployKind::Rtc,
        DeployKind::PiR2Sync,
        DeployKind::PiR2Async,
    ];

    /// The name used in `embodiment.toml` and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            DeployKind::PiR2Async => "pir2_async",
            DeployKind::PiR2Sync => "pir2_sync",
            DeployKind::SyncFlow => "sync_flow",
            DeployKind::NaiveAsync => "naive_async",
            DeployKind::Rtc => "rtc",
            DeployKind::InferenceRtc => "inference_rtc",
        }
    }

    /// Parse [`DeployKind::name`].
    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }

    /// Whether the slow channel runs on its own worker (only πR² async).
    pub fn async_slow(self) -> bool {
        self == DeployKind::PiR2Async
    }
}

/// The `[policy]` table of an embodiment: what the action head was fine-tuned as (the
/// checkpoint's declaration) and the deployment `pir2 gr00t run` uses unless told otherwise. A
/// deployment the head was not trained for is refused ([`PolicySection::mode`]).
///
/// ```toml
/// [policy]
/// trained = "pi_r2"      # pi_r2 | pi_r2_hidden | pi_r2_full | rtc | flow
/// nfe = 2                # πR²: NFEs per action (n)
/// flow_steps = 4         # flow and train-time RTC: Euler steps K per chunk
/// mode = "pir2_async"    # pir2_async | pir2_sync | sync_flow | naive_async | inference_rtc | rtc
/// h = 10                 # sync flow: actions executed per chunk
/// # ensemble = 0.1       # naive async: ACT temporal ensembling decay (absent: plain swap)
/// # rtc_overlap = 8      # inference_rtc: slots started from the chunk in flight (absent: all)
/// rtc_ramp_rate = 5.0    # inference_rtc: rate of the velocity-strength ramp
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PolicySection {
    /// What the action head was fine-tuned as.
    pub trained: pir2_runtime::Policy,
    /// πR² NFEs per action `n` (policies `pi_r2`, `pi_r2_hidden`; `pi_r2_full` uses the
    /// full ramp).
    pub nfe: usize,
    /// Euler steps `K` per chunk of the flow baselines (the paper's robot table: 4).
    pub flow_steps: usize,
    /// The deployment used unless a run overrides it.
    pub mode: DeployKind,
    /// Sync flow: actions executed per chunk (the paper's robot table: 10).
    pub h: usize,
    /// Naive async: ACT temporal ensembling decay `m` (`None`: plain swap).
    pub ensemble: Option<f32>,
    /// N1.7 inference-time RTC: slots of each call started from the chunk in flight
    /// (`None`: every slot it still covers).
    pub rtc_overlap: Option<usize>,
    /// N1.7 inference-time RTC: rate `ρ > 0` of the exponential velocity-strength ramp
    /// (Isaac-GR00T's action-head tests use 5.0; `get_action` itself has no default).
    pub rtc_ramp_rate: f32,
}

impl Default for PolicySection {
    fn default() -> Self {
        PolicySection {
            trained: pir2_runtime::Policy::PiR2,
            nfe: 2,
            flow_steps: 4,
            mode: DeployKind::PiR2Async,
            h: 10,
            ensemble: None,
            rtc_overlap: None,
            rtc_ramp_rate: 5.0,
        }
    }
}

/// Overrides of a [`PolicySection`] for one run (`None`: the section's value).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ModeOverrides {
    /// The deployment.
    pub mode: Option<DeployKind>,
    /// πR² NFEs per action; must equal the trained `n` (a head trained for one `n` is run
    /// with that `n`).
    pub nfe: Option<usize>,
    /// Euler steps `K` of the flow baselines.
    pub flow_steps: Option<usize>,
    /// Sync flow's `h`.
    pub h: Option<usize>,
    /// Naive async: temporal ensembling decay (`Some(None)`: plain swap).
    pub ensemble: Option<Option<f32>>,
    /// N1.7 inference-time RTC: slots started from the chunk in flight.
    pub rtc_overlap: Option<usize>,
    /// N1.7 inference-time RTC: the velocity-strength ramp rate.
    pub rtc_ramp_rate: Option<f32>,
}

impl PolicySection {
    /// The policies a deployment kind can run: πR² kinds need a πR² head, the flow kinds a
    /// standard-flow head, RTC a train-time-RTC head.
    pub fn trained_for(kind: DeployKind) -> &'static [pir2_runtime::Policy] {
        use pir2_runtime::Policy as P;
        match kind {
            DeployKind::PiR2Async | DeployKind::PiR2Sync => &[
                P::PiR2,
                P::PiR2Hidden,
                P::PiR2Full,
                P::PiR2ZeroDelay,
                P::PiR2ZeroDelayFull,
            ],
            DeployKind::SyncFlow | DeployKind::NaiveAsync | DeployKind::InferenceRtc => &[P::Flow],
            DeployKind::Rtc => &[P::Rtc],
        }
    }

    /// The runtime mode of this section with `o` applied. Errors name both sides of a
    /// mismatch: a deployment the head was not trained for, an `n` other than the trained
    /// one, or a zero `K`, `h`, `n` or an ensembling decay outside `(0, 1]`.
    pub fn mode(&self, o: &ModeOverrides) -> Result<pir2_runtime::Mode> {
        use pir2_runtime::{Mode, Policy as P};
        use pir2_schedule::{Alignment, FrontMode};
        let kind = o.mode.unwrap_or(self.mode);
        let allowed = Self::trained_for(kind);
        if !allowed.contains(&self.trained) {
            let names: Vec<String> = allowed.iter().map(|p| policy_name(*p)).collect();
            return Err(Error::Gr00tConfig(format!(
                "mode {} needs an action head trained as {}, but the checkpoint declares \
                 [policy] trained = \"{}\"",
                kind.name(),
                names.join(" or "),
                policy_name(self.trained)
            )));
        }
        let nfe = o.nfe.unwrap_or(self.nfe);
        if o.nfe.is_some_and(|n| n != self.nfe) {
            return Err(Error::Gr00tConfig(format!(
                "--nfe {nfe}: the checkpoint declares [policy] nfe = {} (a πR² head runs with \
                 the n it was trained for)",
                self.nfe
            )));
        }
        let steps = o.flow_steps.unwrap_or(self.flow_steps);
        let h = o.h.unwrap_or(self.h);
        let ensemble = o.ensemble.unwrap_or(self.ensemble);
        let positive = |what: &str, v: usize| {
            if v == 0 {
                Err(Error::Gr00tConfig(format!("[policy] {what} must be >= 1")))
            } else {
                Ok(v)
            }
        };
        let pir2 = |sync: bool| -> Result<Mode> {
            let (nfe, alignment, front) = match self.trained {
                P::PiR2Full => (None, Alignment::Paper, FrontMode::Visible),
                P::PiR2Hidden => (
                    Some(positive("nfe", nfe)?),
                    Alignment::Fresh,
                    FrontMode::Hidden,
                ),
                _ => (
                    Some(positive("nfe", nfe)?),
                    Alignment::Fresh,
                    FrontMode::Visible,
                ),
            };
            Ok(if sync {
                Mode::PiR2Sync {
                    nfe,
                    alignment,
                    front,
                }
            } else {
                Mode::PiR2Async {
                    nfe,
                    alignment,
                    front,
                }
            })
        };
        Ok(match kind {
            DeployKind::PiR2Async => pir2(false)?,
            DeployKind::PiR2Sync => pir2(true)?,
            DeployKind::SyncFlow => Mode::SyncFlow {
                steps: positive("flow_steps", steps)?,
                h: positive("h", h)?,
            },
            DeployKind::NaiveAsync => {
                if let Some(m) = ensemble {
                    if !(m > 0.0 && m <= 1.0) {
                        return Err(Error::Gr00tConfig(format!(
                            "[policy] ensemble = {m}: the decay must be in (0, 1]"
                        )));
                    }
                }
                Mode::NaiveAsync {
                    steps: positive("flow_steps", steps)?,
                    ensemble,
                }
            }
            DeployKind::Rtc => Mode::TrainTimeRtc {
                steps: positive("flow_steps", steps)?,
            },
            DeployKind::InferenceRtc => {
                let r = o.rtc_ramp_rate.unwrap_or(self.rtc_ramp_rate);
                if !(r.is_finite() && r > 0.0) {
                    return Err(Error::Gr00tConfig(format!(
                        "rtc_ramp_rate = {r} (--rtc-ramp-rate or [policy]): the ramp rate must be finite and > 0"
                    )));
                }
                Mode::InferenceRtc {
                    steps: positive("flow_steps", steps)?,
                    overlap: match o.rtc_overlap.or(self.rtc_overlap) {
                        Some(o) => Some(positive("rtc_overlap", o)?),
                        None => None,
                    },
                    ramp_rate: r,
                }
            }
        })
    }
}

/// The `embodiment.toml` spelling of a policy.
pub fn policy_name(p: pir2_runtime::Policy) -> String {
    serde_json::to_value(p)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{p:?}"))
}
