//! Runtime benchmark: per-tick overhead of the control step (excluding the model, which
//! runs on the worker) and tick jitter, with a fake robot and a fake model, on this machine.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use pir2_schedule::{Alignment, FrontMode};

use crate::clock::{Clock, Nanos, SystemClock};
use crate::control::{CallPolicy, ControlConfig};
use crate::error::Result;
use crate::head::{ActionHead, HeadMode, HeadSpec};
use crate::metrics::Percentiles;
use crate::realtime::{run, RealtimeConfig, SlowChannel};
use crate::testing::{FakeRobot, SleepyModel};
use crate::window::LatencyWindow;

/// What one benchmark run measured.
#[derive(Debug, Clone)]
pub struct RuntimeBench {
    /// Control rate.
    pub rate_hz: f64,
    /// Control-step overhead percentiles (ns).
    pub overhead: Percentiles,
    /// Tick jitter percentiles (ns).
    pub jitter: Percentiles,
    /// Overruns counted.
    pub overruns: u64,
    /// Ticks run.
    pub ticks: u64,
    /// Events (e.g. a refused real-time priority).
    pub events: Vec<String>,
}

/// Run the real-time driver at `rate_hz` for `seconds` with a fake 18-DoF robot and a
/// fake model taking `model_latency` per call (H = 16).
pub fn run_bench(
    rate_hz: f64,
    seconds: f64,
    model_latency: Duration,
    rt_priority: Option<i32>,
) -> Result<RuntimeBench> {
    let period = (1e9 / rate_hz) as Nanos;
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let a = 18;
    let spec = HeadSpec {
        horizon: 16,
        action_dim: a,
        n_obs: 2,
        fast_dim: 2 * a,
        slow_dim: 0,
        period,
        d_max: 5,
        d_vis_max: 5,
    };
    let mode = HeadMode::PiR2 {
        nfe: Some(2),
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
        warm_start_steps: 2,
    };
    let head = ActionHead::new(
        SleepyModel {
            latency: model_latency,
        },
        spec,
        mode,
        LatencyWindow::new(20, 2, period, 5),
        0,
    )?;
    let robot = FakeRobot::new(a, clock.clone());
    let control = ControlConfig {
        horizon: 16,
        action_dim: a,
        policy: CallPolicy::Async,
        ensemble: None,
        output: Default::default(),
    };
    let ticks = (seconds * rate_hz) as u64;
    let cfg = RealtimeConfig {
        period,
        max_ticks: Some(ticks),
        rt_priority,
        ..Default::default()
    };
    let (m, _) = run(
        head,
        control,
        robot.clone(),
        robot,
        SlowChannel::None,
        clock,
        cfg,
        Arc::new(AtomicBool::new(false)),
    )?;
    Ok(RuntimeBench {
        rate_hz,
        overhead: m.tick_overhead.summary(),
        jitter: m.tick_jitter.summary(),
        overruns: m.overruns,
        ticks: m.ticks,
        events: m.events,
    })
}
