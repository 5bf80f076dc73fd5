//! The front door of the real-time driver: one builder in place of the head spec, the latency
//! window, the control config and the driver config, each size given once.
//!
//! ```
//! use std::time::Duration;
//! use pir2_runtime::testing::{FakeRobot, SleepyModel};
//! use pir2_runtime::{Mode, Realtime, SystemClock};
//!
//! # fn main() -> pir2_runtime::Result<()> {
//! let clock = std::sync::Arc::new(SystemClock::new());
//! let robot = FakeRobot::new(6, clock.clone()); // your FastSource + Actuator
//! let model = SleepyModel { latency: Duration::from_millis(2) }; // your VelocityModel
//! let metrics = Realtime::builder(model)
//!     .chunk(16, 6) // H actions of A values
//!     .fast(12, 2) // F values per observation, n_obs of them
//!     .hz(50.0)
//!     .mode(Mode::pir2_async(2)) // πR², n = 2 NFEs per action
//!     .max_ticks(25)
//!     .clock(clock)
//!     .run(robot.clone(), robot)?;
//! assert_eq!(metrics.ticks, 25);
//! # Ok(()) }
//! ```
//!
//! Defaults: the trained `d_max` 5 and `d_vis_max` 0, a latency window of 20 calls that skips
//! the first 2, 4 warm-start steps, no slow channel ([`RealtimeBuilder::slow_async`] adds one),
//! the system clock, a stop flag of its own ([`RealtimeBuilder::stop_flag`] shares one).

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use crate::clock::{Clock, Nanos, SystemClock};
use crate::control::{ControlConfig, OutputMap};
use crate::error::{Error, Result};
use crate::head::{ActionHead, HeadSpec};
use crate::io::{Actuator, FastSource, SlowEncoder, SlowSource};
use crate::metrics::RunMetrics;
use crate::mode::Mode;
use crate::model::VelocityModel;
use crate::realtime::{run, RealtimeConfig, SlowChannel};
use crate::window::LatencyWindow;

/// Entry point: [`Realtime::builder`].
#[derive(Debug)]
pub struct Realtime;

impl Realtime {
    /// A builder for a real-time run of `model`.
    pub fn builder<M: VelocityModel>(model: M) -> RealtimeBuilder<M> {
        RealtimeBuilder {
            model,
            horizon: 0,
            action_dim: 0,
            fast_dim: 0,
            n_obs: 1,
            period: 20_000_000,
            d_max: 5,
            d_vis_max: 0,
            mode: Mode::pir2_async(2),
            warm_start_steps: 4,
            window: (20, 2),
            seed: 0,
            output: OutputMap::default(),
            slow: SlowChannel::None,
            slow_dim: 0,
            cfg: RealtimeConfig::default(),
            clock: None,
            stop: None,
        }
    }
}

/// Builds and runs the real-time driver ([`crate::realtime::run`]); see the module docs.
pub struct RealtimeBuilder<M> {
    model: M,
    horizon: usize,
    action_dim: usize,
    fast_dim: usize,
    n_obs: usize,
    period: Nanos,
    d_max: usize,
    d_vis_max: usize,
    mode: Mode,
    warm_start_steps: usize,
    window: (usize, usize),
    seed: u64,
    output: OutputMap,
    slow: SlowChannel,
    slow_dim: usize,
    cfg: RealtimeConfig,
    clock: Option<Arc<dyn Clock>>,
    stop: Option<Arc<AtomicBool>>,
}

impl<M> std::fmt::Debug for RealtimeBuilder<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RealtimeBuilder")
            .field("horizon", &self.horizon)
            .field("action_dim", &self.action_dim)
            .field("fast_dim", &self.fast_dim)
            .field("n_obs", &self.n_obs)
            .field("period", &self.period)
            .field("mode", &self.mode)
            .field("slow", &self.slow)
            .finish_non_exhaustive()
    }
}

impl<M: VelocityModel> RealtimeBuilder<M> {
    /// The action chunk: `horizon` actions of `action_dim` values.
    pub fn chunk(mut self, horizon: usize, action_dim: usize) -> Self {
        self.horizon = horizon;
        self.action_dim = action_dim;
        self
    }

    /// The fast channel: `dim` values per observation, the last `n_obs` of them per call.
    pub fn fast(mut self, dim: usize, n_obs: usize) -> Self {
        self.fast_dim = dim;
        self.n_obs = n_obs;
        self
    }

    /// The control rate (the period is rounded to whole nanoseconds).
    pub fn hz(mut self, hz: f64) -> Self {
        self.period = if hz.is_finite() && hz > 0.0 {
            (1e9 / hz).round() as Nanos
        } else {
            0
        };
        self
    }

    /// How the head is called ([`Mode`]: πR² async or sync, or a baseline).
    pub fn mode(mut self, mode: Mode) -> Self {
        self.mode = mode;
        self
    }

    /// The largest delay (`d_max`) and slow-feature age (`d_vis_max`) the model was trained
    /// for (defaults 5 and 0).
    pub fn trained_for(mut self, d_max: usize, d_vis_max: usize) -> Self {
        self.d_max = d_max;
        self.d_vis_max = d_vis_max;
        self
    }

    /// Euler steps of the warm start (default 4).
    pub fn warm_start_steps(mut self, steps: usize) -> Self {
        self.warm_start_steps = steps;
        self
    }

    /// The rolling latency window: `calls` calls, skipping the first `warmup` (default 20, 2).
    pub fn latency_window(mut self, calls: usize, warmup: usize) -> Self {
        self.window = (calls, warmup);
        self
    }

    /// The seed of the head's noise (default 0).
    pub fn seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }

    /// Map from model actions to robot commands (default: identity).
    pub fn output(mut self, output: OutputMap) -> Self {
        self.output = output;
        self
    }

    /// A slow channel of `dim` features, captured and encoded by a worker of its own and
    /// cached with their age (the paper's asynchronous vision-language channel).
    pub fn slow_async(
        self,
        dim: usize,
        source: Box<dyn SlowSource>,
        encoder: Box<dyn SlowEncoder>,
    ) -> Self {
        self.slow(dim, SlowChannel::Async { source, encoder })
    }

    /// A slow channel captured and encoded inside each call (its time counts in `d`).
    pub fn slow_inline(
        self,
        dim: usize,
        source: Box<dyn SlowSource>,
        encoder: Box<dyn SlowEncoder>,
    ) -> Self {
        self.slow(dim, SlowChannel::Inline { source, encoder })
    }

    fn slow(mut self, dim: usize, channel: SlowChannel) -> Self {
        self.slow_dim = dim;
        self.slow = channel;
        self
    }

    /// Stop after `ticks` control ticks (default: run until the stop flag is set).
    pub fn max_ticks(mut self, ticks: u64) -> Self {
        self.cfg.max_ticks = Some(ticks);
        self
    }

    /// Everything else of the driver's configuration (its period is the builder's).
    pub fn config(mut self, cfg: RealtimeConfig) -> Self {
        self.cfg = cfg;
        self
    }

    /// The clock (default: the system clock).
    pub fn clock(mut self, clock: Arc<dyn Clock>) -> Self {
        self.clock = Some(clock);
        self
    }

    /// A stop flag shared with the caller (a signal handler sets it to end the run).
    pub fn stop_flag(mut self, stop: Arc<AtomicBool>) -> Self {
        self.stop = Some(stop);
        self
    }

    /// The head's spec as configured.
    pub fn spec(&self) -> HeadSpec {
        HeadSpec {
            horizon: self.horizon,
            action_dim: self.action_dim,
            n_obs: self.n_obs,
            fast_dim: self.fast_dim,
            slow_dim: self.slow_dim,
            period: self.period,
            d_max: self.d_max,
            d_vis_max: self.d_vis_max,
        }
    }

    /// Run until `max_ticks` or the stop flag, with `fast` the fast channel and `actuator` the
    /// robot (often the same driver). The robot is stopped on every exit path.
    pub fn run<F: FastSource, A: Actuator>(self, fast: F, actuator: A) -> Result<RunMetrics> {
        Ok(self.run_keep_head(fast, actuator)?.0)
    }

    /// [`Self::run`], handing the head (model, window) back with the metrics.
    pub fn run_keep_head<F: FastSource, A: Actuator>(
        self,
        fast: F,
        actuator: A,
    ) -> Result<(RunMetrics, ActionHead<M>)> {
        for (what, v) in [
            ("chunk horizon", self.horizon),
            ("action dim", self.action_dim),
            ("fast dim", self.fast_dim),
            ("n_obs", self.n_obs),
            ("period (hz)", self.period as usize),
        ] {
            if v == 0 {
                return Err(Error::Config(format!(
                    "realtime builder: {what} is not set"
                )));
            }
        }
        let spec = self.spec();
        let head = ActionHead::new(
            self.model,
            spec,
            self.mode.head_mode(self.warm_start_steps),
            LatencyWindow::new(self.window.0, self.window.1, self.period, self.d_max),
            self.seed,
        )?;
        let control = ControlConfig {
            horizon: self.horizon,
            action_dim: self.action_dim,
            policy: self.mode.call_policy(),
            ensemble: self.mode.ensemble(),
            output: self.output,
        };
        let cfg = RealtimeConfig {
            period: self.period,
            ..self.cfg
        };
        let clock = self
            .clock
            .unwrap_or_else(|| Arc::new(SystemClock::new()) as Arc<dyn Clock>);
        let stop = self
            .stop
            .unwrap_or_else(|| Arc::new(AtomicBool::new(false)));
        run(head, control, fast, actuator, self.slow, clock, cfg, stop)
    }
}
