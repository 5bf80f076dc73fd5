//! The action-head side of the state machine: one call = snapshot in, chunk out.
//!
//! The same [`ActionHead`] runs inside the real-time worker thread and inside the
//! lock-step driver. It owns the model, the latency window and the mode's inference state
//! (the πR² streaming buffer, or the baselines' from-scratch flow).

use serde::{Deserialize, Serialize};

use pir2_schedule::baselines::{StandardFlow, VelocityStrengthRtc};
use pir2_schedule::{Alignment, FrontMode, Rng, StreamBuffer, StreamConfig};

use crate::chunk::Chunk;
use crate::clock::Nanos;
use crate::control::OutputMap;
use crate::error::{Error, Result};
use crate::metrics::CallRecord;
use crate::model::{ModelInput, SlowInput, VelocityModel};
use crate::window::LatencyWindow;

/// Sizes and limits shared by the head and the drivers.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HeadSpec {
    /// Chunk length `H`.
    pub horizon: usize,
    /// Action dimension `A`.
    pub action_dim: usize,
    /// Fast observation history length.
    pub n_obs: usize,
    /// Fast observation width.
    pub fast_dim: usize,
    /// Slow feature width (0 = no slow channel).
    pub slow_dim: usize,
    /// Control period, ns.
    pub period: Nanos,
    /// Largest delay the model was trained for. `0` declares a zero-delay policy (trained
    /// with `d_max = 0`): every call uses the `d = 0` streaming ramp, its single step sees
    /// the newest observation and slot 0 is executed in the same tick. Such a policy runs
    /// only where a call takes zero ticks (the lock-step driver with zero injected latency,
    /// the paper's horizon study); the real-time driver refuses it, since a real call always
    /// takes time.
    pub d_max: usize,
    /// Largest slow-feature age the model was trained for.
    pub d_vis_max: usize,
}

/// How the head infers a chunk.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum HeadMode {
    /// πR²: one denoising step per call on the streaming staircase buffer.
    PiR2 {
        /// NFEs per action (`None` = full ramp).
        nfe: Option<usize>,
        /// Staircase alignment.
        alignment: Alignment,
        /// Front visibility.
        front: FrontMode,
        /// Euler steps of the warm start.
        warm_start_steps: usize,
    },
    /// Standard flow from scratch every call (`K` Euler steps, shared `τ`).
    Flow {
        /// Euler steps `K`.
        steps: usize,
    },
    /// Train-time RTC: the committed front is given clean (`τ = 1`), the back is
    /// integrated from noise with one shared `τ` in `K` steps.
    TrainTimeRtc {
        /// Euler steps `K`.
        steps: usize,
    },
    /// GR00T N1.7's inference-time RTC on a standard-flow model: `K` Euler steps from noise,
    /// the first `overlap` slots started from the chunk in flight (the previous call's,
    /// from the snapshot's tick on) and the first `d` of them kept exactly
    /// ([`VelocityStrengthRtc`]).
    InferenceRtc {
        /// Euler steps `K`.
        steps: usize,
        /// Slots started from the chunk in flight (`None`: every slot it still covers;
        /// always capped at what it covers).
        overlap: Option<usize>,
        /// Rate `ρ > 0` of the velocity-strength ramp.
        ramp_rate: f32,
    },
}

/// Everything a call reads, copied at the snapshot.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// Tick of the snapshot.
    pub tick: u64,
    /// Time the newest fast observation was measured.
    pub t_state: Nanos,
    /// Fast history `[n_obs, F]`, oldest first.
    pub fast: Vec<f32>,
    /// Slow features `[S]`.
    pub slow: Vec<f32>,
    /// Capture time of the slow features.
    pub t_slow: Nanos,
}

impl Snapshot {
    /// An empty snapshot with preallocated storage.
    pub fn new(spec: &HeadSpec) -> Self {
        Self {
            tick: 0,
            t_state: 0,
            fast: vec![0.0; spec.n_obs * spec.fast_dim],
            slow: vec![0.0; spec.slow_dim],
            t_slow: 0,
        }
    }
}

#[derive(Debug)]
enum State {
    PiR2 {
        buf: StreamBuffer,
        offset: u64,
        warm_k: usize,
        /// The reference the buffer's actions are relative to (per-slot output maps).
        carried: Vec<f32>,
    },
    Flow {
        flow: StandardFlow,
    },
    Rtc {
        steps: usize,
        prev: Chunk,
        has_prev: bool,
    },
    InferenceRtc {
        steps: usize,
        overlap: Option<usize>,
        ramp_rate: f32,
        prev: Chunk,
        has_prev: bool,
    },
}

/// The action head (see the module docs).
#[derive(Debug)]
pub struct ActionHead<M> {
    model: M,
    spec: HeadSpec,
    state: State,
    window: LatencyWindow,
    rng: Rng,
    x: Vec<f32>,
    tau: Vec<f32>,
    v: Vec<f32>,
    eps: Vec<f32>,
    forced_delay: Option<usize>,
    slow_grace: Option<Nanos>,
    output: OutputMap,
    rebase: bool,
    reference: Vec<f32>,
}

impl<M: VelocityModel> ActionHead<M> {
    /// Build a head. `window` measures `d`; `seed` drives all noise.
    pub fn new(
        model: M,
        spec: HeadSpec,
        mode: HeadMode,
        window: LatencyWindow,
        seed: u64,
    ) -> Result<Self> {
        let (h, a) = (spec.horizon, spec.action_dim);
        if h == 0 || a == 0 || spec.n_obs == 0 || spec.period == 0 {
            return Err(Error::Config(format!(
                "head spec needs positive horizon, action_dim, n_obs and period: {spec:?}"
            )));
        }
        let state = match mode {
            HeadMode::PiR2 {
                nfe,
                alignment,
                front,
                warm_start_steps,
            } => {
                let cfg = StreamConfig {
                    horizon: h,
                    action_dim: a,
                    nfe,
                    alignment,
                    front,
                    max_delay: spec.d_max,
                };
                State::PiR2 {
                    buf: StreamBuffer::new(cfg, seed)?,
                    offset: 0,
                    warm_k: warm_start_steps.max(1),
                    carried: vec![0.0; a],
                }
            }
            HeadMode::Flow { steps } => State::Flow {
                flow: StandardFlow {
                    steps: steps.max(1),
                },
            },
            HeadMode::TrainTimeRtc { steps } => {
                if spec.d_max >= h {
                    return Err(Error::Config(format!(
                        "train-time RTC needs d_max < H, got {} >= {h}",
                        spec.d_max
                    )));
                }
                State::Rtc {
                    steps: steps.max(1),
                    prev: Chunk::new(h, a),
                    has_prev: false,
                }
            }
            HeadMode::InferenceRtc {
                steps,
                overlap,
                ramp_rate,
            } => {
                VelocityStrengthRtc {
                    steps,
                    frozen: 0,
                    overlap: overlap.unwrap_or(h),
                    ramp_rate,
                }
                .validate(h)
                .map_err(|e| Error::Config(format!("inference-time RTC: {e}")))?;
                State::InferenceRtc {
                    steps,
                    overlap,
                    ramp_rate,
                    prev: Chunk::new(h, a),
                    has_prev: false,
                }
            }
        };
        Ok(Self {
            model,
            spec,
            state,
            window,
            rng: Rng::derive(seed, 0x4EAD),
            x: vec![0.0; h * a],
            tau: vec![0.0; h],
            v: vec![0.0; h * a],
            eps: vec![0.0; h * a],
            forced_delay: None,
            slow_grace: None,
            output: OutputMap::default(),
            rebase: false,
            reference: vec![0.0; a],
        })
    }

    /// Tell the head how actions are decoded (the drivers pass their control
    /// configuration's map before the warm start). With a per-slot map
    /// ([`OutputMap::per_slot`]: relative dimensions or per-slot statistics) every chunk
    /// records its reference (the relative dimensions' values in the snapshot's newest fast
    /// observation), and the actions carried from call to call (πR²'s buffer, train-time
    /// RTC's committed front) are rebased onto each call's reference and slot
    /// ([`OutputMap::rebase`]; through `x̂` for a partly denoised πR² slot, its noise kept).
    /// An absolute per-dimension map changes nothing. Errors name a size or a reference
    /// index outside the fast observation.
    pub fn set_output(&mut self, output: &OutputMap) -> Result<()> {
        let (h, a, f) = (self.spec.horizon, self.spec.action_dim, self.spec.fast_dim);
        output.validate(h, a)?;
        if let Some((j, k)) = output
            .reference
            .iter()
            .enumerate()
            .find_map(|(j, r)| r.filter(|&k| k >= f).map(|k| (j, k)))
        {
            return Err(Error::Config(format!(
                "output.reference[{j}] = {k} is outside the fast observation (fast_dim = {f})"
            )));
        }
        self.output = output.clone();
        self.rebase = self.output.per_slot(a);
        Ok(())
    }

    /// The newest fast observation of `snap`.
    fn newest<'s>(spec: &HeadSpec, snap: &'s Snapshot) -> &'s [f32] {
        &snap.fast[(spec.n_obs - 1) * spec.fast_dim..]
    }

    /// The spec.
    pub fn spec(&self) -> &HeadSpec {
        &self.spec
    }

    /// The model.
    pub fn model(&self) -> &M {
        &self.model
    }

    /// Hand the run's [`StopSignal`](crate::StopSignal) to the model
    /// ([`VelocityModel::watch_stop`]).
    pub fn watch_stop(&mut self, stop: crate::StopSignal) {
        self.model.watch_stop(stop);
    }

    /// Give the model back (e.g. to read its counters after a run).
    pub fn into_model(self) -> M {
        self.model
    }

    /// Record a call latency into the rolling window.
    pub fn record_latency(&mut self, latency: Nanos) {
        self.window.push(latency);
    }

    /// Use a fixed `d` instead of the measured one (lock-step studies pin `d` to the
    /// paper's effective delay); `None` returns to the window.
    pub fn force_delay(&mut self, d: Option<usize>) {
        self.forced_delay = d;
    }

    /// The delay the next call uses.
    pub fn delay(&self) -> usize {
        self.clamp_delay(self.forced_delay.unwrap_or_else(|| self.window.delay()))
    }

    /// `d` clamped to what the model was trained for: `[1, d_max]`, or exactly `0` for a
    /// zero-delay policy (`d_max = 0`).
    pub fn clamp_delay(&self, d: usize) -> usize {
        if self.spec.d_max == 0 {
            0
        } else {
            d.clamp(1, self.spec.d_max)
        }
    }

    /// Stale-slow safety check: a call fails with [`Error::SafetyStop`] when its slow
    /// features are older than `d_vis_max` ticks (rounded, i.e. `(d_vis_max + ½)·T_ctrl`)
    /// for longer than `grace`. `None` (the default) never stops: `d_vis` is clamped to
    /// `d_vis_max`. Set it whenever the slow channel can stall (a remote backbone).
    pub fn set_slow_grace(&mut self, grace: Option<Nanos>) {
        self.slow_grace = grace;
    }

    fn check_slow_age(&self, snap: &Snapshot) -> Result<()> {
        let Some(grace) = self.slow_grace else {
            return Ok(());
        };
        if self.spec.slow_dim == 0 {
            return Ok(());
        }
        let age = snap.t_state.saturating_sub(snap.t_slow);
        let limit = (2 * self.spec.d_vis_max as u64 + 1) * self.spec.period / 2 + grace;
        if age > limit {
            return Err(Error::SafetyStop(format!(
                "slow features are {:.1} ms old: d_vis > d_vis_max = {} for longer than the {:.1} ms grace",
                age as f64 / 1e6,
                self.spec.d_vis_max,
                grace as f64 / 1e6
            )));
        }
        Ok(())
    }

    fn d_vis(&self, snap: &Snapshot) -> usize {
        if self.spec.slow_dim == 0 {
            return 0;
        }
        let age = snap.t_state.saturating_sub(snap.t_slow) as f64 / self.spec.period as f64;
        (age.round() as usize).min(self.spec.d_vis_max)
    }

    fn eval(
        model: &mut M,
        spec: &HeadSpec,
        snap: &Snapshot,
        d_vis: u32,
        x: &[f32],
        tau: &[f32],
        v: &mut [f32],
    ) -> Result<()> {
        let dv = [d_vis];
        let input = ModelInput {
            batch: 1,
            horizon: spec.horizon,
            action_dim: spec.action_dim,
            x,
            tau,
            obs_fast: &snap.fast,
            n_obs: spec.n_obs,
            fast_dim: spec.fast_dim,
            slow: if spec.slow_dim == 0 {
                SlowInput::None
            } else {
                SlowInput::Vector {
                    data: &snap.slow,
                    dim: spec.slow_dim,
                }
            },
            d_vis: &dv,
        };
        model.velocity(&input, v)?;
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(Error::NonFinite { index: i });
        }
        Ok(())
    }

    /// Warm start before the robot moves: a full from-noise inference on `snap`, giving the
    /// first chunk (slot 0 = `snap.tick`, every slot clean).
    pub fn warm_start(&mut self, snap: &Snapshot, d0: usize, out: &mut Chunk) -> Result<()> {
        let d_vis = self.d_vis(snap) as u32;
        let d0 = self.clamp_delay(d0);
        let spec = self.spec;
        self.output
            .fill_reference(Self::newest(&spec, snap), &mut self.reference);
        let (model, x, tau, v) = (&mut self.model, &mut self.x, &mut self.tau, &mut self.v);
        match &mut self.state {
            State::PiR2 {
                buf,
                offset,
                warm_k,
                carried,
            } => {
                carried.copy_from_slice(&self.reference);
                buf.warm_start_with(d0, *warm_k, |xs: &[f32], ts: &[f32], vs: &mut [f32]| {
                    Self::eval(model, &spec, snap, d_vis, xs, ts, vs)
                })?;
                *offset = snap.tick - buf.index();
                out.x.copy_from_slice(buf.xhat());
                out.xhat.copy_from_slice(buf.xhat());
                out.clean.fill(true);
            }
            State::Flow { .. } | State::Rtc { .. } | State::InferenceRtc { .. } => {
                self.rng.fill_normal(x);
                StandardFlow { steps: 10 }.sample(x, tau, v, |xs, ts, vs| {
                    Self::eval(model, &spec, snap, d_vis, xs, ts, vs)
                })?;
                out.x.copy_from_slice(x);
                out.xhat.copy_from_slice(x);
                out.clean.fill(true);
                out.reference.copy_from_slice(&self.reference);
                if let State::Rtc { prev, has_prev, .. }
                | State::InferenceRtc { prev, has_prev, .. } = &mut self.state
                {
                    prev.copy_from(out);
                    prev.base = snap.tick;
                    *has_prev = true;
                }
            }
        }
        out.base = snap.tick;
        out.snapshot_tick = snap.tick;
        out.reference.copy_from_slice(&self.reference);
        out.call = CallRecord {
            tick: snap.tick,
            latency: 0,
            d: d0,
            d_vis: d_vis as usize,
            elapsed: 0,
        };
        Ok(())
    }

    /// One call on `snap`: writes the new chunk into `out`. The latency is recorded by the
    /// driver (it owns the clock) through [`record_latency`](Self::record_latency).
    pub fn call(&mut self, snap: &Snapshot, out: &mut Chunk) -> Result<()> {
        self.check_slow_age(snap)?;
        let d = self.delay();
        let d_vis = self.d_vis(snap);
        let spec = self.spec;
        let (h, a) = (spec.horizon, spec.action_dim);
        self.output
            .fill_reference(Self::newest(&spec, snap), &mut self.reference);
        out.reference.copy_from_slice(&self.reference);
        let (model, x, tau, v, eps) = (
            &mut self.model,
            &mut self.x,
            &mut self.tau,
            &mut self.v,
            &mut self.eps,
        );
        let carry = Carry {
            output: &self.output,
            reference: &self.reference,
            rebase: self.rebase,
        };
        let (output, reference, rebase) = (carry.output, carry.reference, carry.rebase);
        match &mut self.state {
            State::PiR2 {
                buf,
                offset,
                carried,
                ..
            } => {
                // Slide to the snapshot: everything before `snap.tick` has been executed.
                let slot0 = *offset + buf.index();
                let k = (snap.tick.saturating_sub(slot0) as usize).min(h);
                buf.slide(k)?;
                *offset = snap.tick - buf.index();
                if rebase {
                    // Slot p was slot p + k of the previous call (an appended slot holds
                    // the estimate of the previous last slot), relative to `carried`.
                    buf.remap(|p, z, out| {
                        output.rebase(z, (p + k).min(h - 1), carried, p, reference, out)
                    });
                    carried.copy_from_slice(reference);
                }
                buf.plan(d)?;
                Self::eval(
                    model,
                    &spec,
                    snap,
                    d_vis as u32,
                    buf.model_x(),
                    buf.model_tau(),
                    v,
                )?;
                buf.step(v)?;
                out.x.copy_from_slice(buf.x());
                out.xhat.copy_from_slice(buf.xhat());
                for (c, t) in out.clean.iter_mut().zip(buf.tau()) {
                    *c = *t >= 1.0;
                }
            }
            State::Flow { flow } => {
                self.rng.fill_normal(x);
                flow.sample(x, tau, v, |xs, ts, vs| {
                    Self::eval(model, &spec, snap, d_vis as u32, xs, ts, vs)
                })?;
                out.x.copy_from_slice(x);
                out.xhat.copy_from_slice(x);
                out.clean.fill(true);
            }
            State::Rtc {
                steps,
                prev,
                has_prev,
            } => {
                self.rng.fill_normal(eps);
                x.copy_from_slice(eps);
                // The committed front: what the robot executes during this call.
                let front = d.min(h - 1);
                carry.fill(prev, *has_prev, snap.tick, &mut x[..front * a]);
                let dt = 1.0 / *steps as f32;
                for i in 0..*steps {
                    let ti = i as f32 * dt;
                    for (p, t) in tau.iter_mut().enumerate() {
                        *t = if p < front { 1.0 } else { ti };
                    }
                    Self::eval(model, &spec, snap, d_vis as u32, x, tau, v)?;
                    for j in front * a..h * a {
                        x[j] += dt * v[j];
                    }
                }
            }
            State::InferenceRtc {
                steps,
                overlap,
                ramp_rate,
                prev,
                has_prev,
            } => {
                self.rng.fill_normal(x);
                // The chunk in flight from the snapshot's tick on: what it still covers.
                let left = if *has_prev {
                    prev.index_of(snap.tick).map_or(0, |i| h - i)
                } else {
                    0
                };
                let overlap = overlap.unwrap_or(h).min(left);
                let rtc = VelocityStrengthRtc {
                    steps: *steps,
                    frozen: d.min(overlap),
                    overlap,
                    ramp_rate: *ramp_rate,
                };
                carry.fill(prev, *has_prev, snap.tick, &mut eps[..overlap * a]);
                rtc.sample(x, &eps[..overlap * a], a, tau, v, |xs, ts, vs| {
                    Self::eval(model, &spec, snap, d_vis as u32, xs, ts, vs)
                })?;
            }
        }
        out.base = snap.tick;
        out.snapshot_tick = snap.tick;
        out.call = CallRecord {
            tick: snap.tick,
            latency: 0,
            d,
            d_vis,
            elapsed: 0,
        };
        if let State::Rtc { prev, has_prev, .. } | State::InferenceRtc { prev, has_prev, .. } =
            &mut self.state
        {
            // Both RTCs integrate every slot clean in `x`, and carry the chunk into the next
            // call.
            out.x.copy_from_slice(&self.x);
            out.xhat.copy_from_slice(&self.x);
            out.clean.fill(true);
            prev.copy_from(out);
            *has_prev = true;
        }
        Ok(())
    }
}

/// The actions of the chunk in flight carried into a call (train-time RTC's committed front,
/// inference-time RTC's overlap), moved onto the call's reference and slot when actions are
/// relative.
struct Carry<'a> {
    output: &'a OutputMap,
    reference: &'a [f32],
    rebase: bool,
}

impl Carry<'_> {
    /// Fill `dst` (`[m, A]`) with the actions the chunk in flight `prev` gives ticks
    /// `tick .. tick + m` (`has_prev`: there is one); past its end, its last slot is held.
    fn fill(&self, prev: &Chunk, has_prev: bool, tick: u64, dst: &mut [f32]) {
        let (h, a) = (prev.horizon, prev.action_dim);
        for (p, dst) in dst.chunks_exact_mut(a).enumerate() {
            let t = tick + p as u64;
            let src = if has_prev {
                prev.index_of(t).zip(prev.action_at(t))
            } else {
                None
            };
            let (q, vals) = match src {
                Some((q, (vals, _))) => (q, vals),
                None => (h - 1, &prev.x[(h - 1) * a..]),
            };
            if self.rebase {
                // Committed in the previous chunk's coordinates: move it onto this call's
                // reference and slot (the command stays the same).
                self.output
                    .rebase(vals, q, &prev.reference, p, self.reference, dst);
            } else {
                dst.copy_from_slice(vals);
            }
        }
    }
}
