//! The lock-step driver: the same state machine as the real-time driver, stepped with a
//! simulated environment. A call "takes" an injected number of ticks (`d` for the action
//! head) and the slow channel arrives `d_vis` ticks late, so deployment studies are
//! deterministic and fast.
//!
//! Tick order (identical to the real-time control thread): observe → publish → swap in a
//! chunk if one is due → start a call if the policy wants one → send one action → step.

use serde::{Deserialize, Serialize};

use crate::chunk::Chunk;
use crate::control::{ControlConfig, ControlState, OutputMap};
use crate::error::{Error, Result};
use crate::head::{ActionHead, HeadSpec, Snapshot};
use crate::io::Environment;
use crate::metrics::RunMetrics;
use crate::mode::Mode;
use crate::model::VelocityModel;
use crate::window::LatencyWindow;
use pir2_schedule::Rng;

/// Timing injected into a lock-step episode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct LockstepTiming {
    /// Ticks one action-head call takes.
    pub call_ticks: usize,
    /// Age of the slow features (pipelined camera latency) in ticks.
    pub slow_delay: usize,
    /// Extra ticks added to every `overrun_every`-th call (0 = never), to exercise overruns.
    pub overrun_ticks: usize,
    /// Which calls overrun (every n-th; 0 = none).
    pub overrun_every: usize,
    /// Pin the head's `d` to `call_ticks` (studies) instead of measuring it with the window.
    pub pin_delay: bool,
}

impl LockstepTiming {
    /// Zero injected latency: a call takes no tick and the slow features are fresh (the
    /// horizon study's timing; `d` is pinned).
    pub fn zero_latency() -> Self {
        Self {
            call_ticks: 0,
            slow_delay: 0,
            overrun_ticks: 0,
            overrun_every: 0,
            pin_delay: true,
        }
    }

    /// The paper's timing for `mode` at unit delay `d0`.
    pub fn for_mode(mode: &Mode, d0: usize) -> Self {
        let e = mode.effective_delays(d0);
        Self {
            call_ticks: e.d,
            slow_delay: e.d_vis,
            overrun_ticks: 0,
            overrun_every: 0,
            pin_delay: true,
        }
    }
}

/// Result of one episode.
#[derive(Debug, Clone)]
pub struct EpisodeResult {
    /// The task succeeded.
    pub success: bool,
    /// Control steps run.
    pub steps: usize,
    /// Sum of rewards.
    pub reward: f64,
    /// The run's metrics.
    pub metrics: RunMetrics,
}

/// Reusable buffers of the lock-step driver.
#[derive(Debug)]
pub struct LockstepDriver {
    fast_hist: Vec<f32>,
    slow_hist: Vec<f32>,
    obs_fast: Vec<f32>,
    obs_slow: Vec<f32>,
    snap: Snapshot,
    pending: Chunk,
    spare: Chunk,
    output: OutputMap,
}

impl LockstepDriver {
    /// Buffers for a head of this spec.
    pub fn new<M: VelocityModel>(head: &ActionHead<M>) -> Self {
        let s = head.spec();
        Self {
            fast_hist: Vec::new(),
            slow_hist: Vec::new(),
            obs_fast: vec![0.0; s.fast_dim],
            obs_slow: vec![0.0; s.slow_dim],
            snap: Snapshot::new(s),
            pending: Chunk::new(s.horizon, s.action_dim),
            spare: Chunk::new(s.horizon, s.action_dim),
            output: OutputMap::default(),
        }
    }

    /// Map model actions to environment commands (e.g. denormalise: `u = x·scale + offset`;
    /// relative actions and per-slot statistics too, see [`OutputMap`]). The head is given
    /// the same map at the start of each episode ([`ActionHead::set_output`]).
    pub fn with_output(mut self, output: OutputMap) -> Self {
        self.output = output;
        self
    }

    /// Run one episode of `env` (reset with `seed`) under `mode`'s control policy with the
    /// injected `timing`. With `timing.pin_delay` the head's `d` is pinned to
    /// `timing.call_ticks` (the measured window gives the same value at steady state;
    /// pinning makes a study independent of warm-up); otherwise the window measures it.
    pub fn run_episode<M: VelocityModel, E: Environment + ?Sized>(
        &mut self,
        env: &mut E,
        head: &mut ActionHead<M>,
        mode: &Mode,
        timing: LockstepTiming,
        seed: u64,
        mut on_tick: impl FnMut(u64, &[f32]),
    ) -> Result<EpisodeResult> {
        let spec = *head.spec();
        let es = env.spec();
        if es.fast_dim != spec.fast_dim
            || es.slow_dim != spec.slow_dim
            || es.action_dim != spec.action_dim
        {
            return Err(Error::shape(
                "environment (fast, slow, action) dims vs model",
                (spec.fast_dim, spec.slow_dim, spec.action_dim),
                (es.fast_dim, es.slow_dim, es.action_dim),
            ));
        }
        if es.control_period != spec.period {
            return Err(Error::Config(format!(
                "environment control period {} ns differs from the head's {} ns",
                es.control_period, spec.period
            )));
        }
        let period = spec.period;
        // `call_ticks = 0` simulates zero inference latency: the chunk is swapped in within
        // the tick of its snapshot (the horizon study). `d` stays at least 1 unless the
        // policy is a zero-delay one (`d_max = 0`), which needs exactly that timing.
        let call_ticks = timing.call_ticks;
        if spec.d_max == 0
            && (call_ticks > 0 || (timing.overrun_every > 0 && timing.overrun_ticks > 0))
        {
            return Err(Error::Config(format!(
                "a zero-delay policy (d_max = 0) needs calls that take zero ticks, got call_ticks = {call_ticks}, \
                 overrun_ticks = {} every {} calls",
                timing.overrun_ticks, timing.overrun_every
            )));
        }
        if timing.pin_delay {
            head.force_delay(Some(head.clamp_delay(call_ticks)));
        }
        let mut control = ControlState::new(ControlConfig {
            horizon: spec.horizon,
            action_dim: spec.action_dim,
            policy: mode.call_policy(),
            ensemble: mode.ensemble(),
            output: self.output.clone(),
        })?;
        head.set_output(&self.output)?;
        env.reset(seed);
        let (f, s, n_obs) = (spec.fast_dim, spec.slow_dim, spec.n_obs);
        // Histories: fast keeps n_obs frames; slow keeps slow_delay + 1 frames.
        let slow_keep = timing.slow_delay + 1;
        self.fast_hist.clear();
        self.fast_hist.resize(n_obs * f, 0.0);
        self.slow_hist.clear();
        self.slow_hist.resize(slow_keep * s, 0.0);
        let mut due: Option<u64> = None;
        let mut calls = 0usize;
        let mut reward = 0.0f64;
        let mut result = EpisodeResult {
            success: false,
            steps: 0,
            reward: 0.0,
            metrics: RunMetrics::default(),
        };
        for t in 0..es.max_steps as u64 {
            env.observe(&mut self.obs_fast, &mut self.obs_slow);
            if t == 0 {
                for k in 0..n_obs {
                    self.fast_hist[k * f..(k + 1) * f].copy_from_slice(&self.obs_fast);
                }
                for k in 0..slow_keep {
                    self.slow_hist[k * s..(k + 1) * s].copy_from_slice(&self.obs_slow);
                }
            } else {
                self.fast_hist.copy_within(f.., 0);
                self.fast_hist[(n_obs - 1) * f..].copy_from_slice(&self.obs_fast);
                self.slow_hist.copy_within(s.., 0);
                self.slow_hist[(slow_keep - 1) * s..].copy_from_slice(&self.obs_slow);
            }
            // Snapshot content for a call at this tick.
            let fill_snapshot = |snap: &mut Snapshot, fast_hist: &[f32], slow_hist: &[f32]| {
                snap.tick = t;
                snap.t_state = t * period;
                snap.fast.copy_from_slice(fast_hist);
                // Oldest kept frame = captured slow_delay ticks ago (clamped at episode start).
                snap.slow.copy_from_slice(&slow_hist[..s]);
                snap.t_slow = t.saturating_sub(timing.slow_delay as u64) * period;
            };
            if t == 0 {
                fill_snapshot(&mut self.snap, &self.fast_hist, &self.slow_hist);
                head.warm_start(&self.snap, head.clamp_delay(call_ticks), &mut self.spare)?;
                control.deliver(&mut self.spare);
            }
            if due == Some(t) {
                control.deliver(&mut self.pending);
                due = None;
            }
            if due.is_none() && control.wants_call() {
                fill_snapshot(&mut self.snap, &self.fast_hist, &self.slow_hist);
                control.call_started();
                head.call(&self.snap, &mut self.pending)?;
                calls += 1;
                let extra = if timing.overrun_every > 0 && calls % timing.overrun_every == 0 {
                    timing.overrun_ticks
                } else {
                    0
                };
                let ticks = call_ticks + extra;
                self.pending.call.latency = ticks as u64 * period;
                head.record_latency(ticks as u64 * period);
                due = Some(t + ticks as u64);
                if ticks == 0 {
                    control.deliver(&mut self.pending);
                    due = None;
                }
            }
            let action = control.action();
            on_tick(t, action);
            let st = env.step(action);
            reward += st.reward as f64;
            result.steps = t as usize + 1;
            if st.done {
                result.success = st.success;
                break;
            }
        }
        head.force_delay(None);
        result.reward = reward;
        result.metrics = std::mem::take(&mut control.metrics);
        Ok(result)
    }
}

/// One study cell as each of its episodes runs: the action head's spec, the mode and the
/// timing it runs under, the map from its actions to the environment's, and how many
/// episodes are run with seeds derived from which seed ([`eval_cell`],
/// [`crate::eval_cell_batched`]).
#[derive(Debug, Clone, Copy)]
pub struct StudyCell<'a> {
    /// The action head every episode builds.
    pub head: HeadSpec,
    /// How the head is run.
    pub mode: Mode,
    /// The timing injected into every episode.
    pub timing: LockstepTiming,
    /// From the head's actions to the environment's.
    pub output: &'a OutputMap,
    /// Episodes in the cell.
    pub episodes: usize,
    /// Episode `ep`'s seeds derive from `(seed, ep)`.
    pub seed: u64,
}

/// Episode `ep` of `cell`: a fresh head around `model` (its seeds derived from
/// `(cell.seed, ep)`, `d` from a fresh latency window) driven through `env`. Shared by
/// [`eval_cell`] and [`crate::eval_cell_batched`], so both run an episode the same way.
pub(crate) fn cell_episode<E: Environment, M: VelocityModel>(
    model: M,
    env: &mut E,
    cell: &StudyCell<'_>,
    ep: usize,
) -> Result<EpisodeResult> {
    let spec = cell.head;
    let ep_seed = Rng::derive(cell.seed, ep as u64).next_u64();
    let window = LatencyWindow::new(20, 0, spec.period, spec.d_max);
    let mut head = ActionHead::new(
        model,
        spec,
        cell.mode.head_mode(10),
        window,
        ep_seed ^ 0xA5A5,
    )?;
    let mut drv = LockstepDriver::new(&head).with_output(cell.output.clone());
    drv.run_episode(env, &mut head, &cell.mode, cell.timing, ep_seed, |_, _| {})
}

/// Run the episodes of `cell` in parallel on `threads` threads; returns the successes and
/// the overrun ticks over all episodes. Every episode gets its own environment, head and
/// seeds derived from `(cell.seed, episode)`, so the result does not depend on the thread
/// count.
pub fn eval_cell<E, M, FE, FM>(
    make_env: &FE,
    make_model: &FM,
    cell: &StudyCell<'_>,
    threads: usize,
    progress: &(dyn Fn() + Sync),
) -> Result<(usize, u64)>
where
    E: Environment,
    M: VelocityModel,
    FE: Fn() -> E + Sync,
    FM: Fn() -> M + Sync,
{
    let episodes = cell.episodes;
    let threads = threads.clamp(1, episodes.max(1));
    let results: Vec<Result<(usize, u64)>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|w| {
                s.spawn(move || -> Result<(usize, u64)> {
                    let mut env = make_env();
                    let (mut ok, mut overruns) = (0, 0);
                    let mut ep = w;
                    while ep < episodes {
                        let r = cell_episode(make_model(), &mut env, cell, ep)?;
                        ok += r.success as usize;
                        overruns += r.metrics.overruns;
                        progress();
                        ep += threads;
                    }
                    Ok((ok, overruns))
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|p| Err(Error::panicked("evaluation thread", &*p)))
            })
            .collect()
    });
    let mut total = (0, 0);
    for r in results {
        let (a, b) = r?;
        total.0 += a;
        total.1 += b;
    }
    Ok(total)
}
