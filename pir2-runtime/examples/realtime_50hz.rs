//! Wire a model, a fake robot and a camera stub into the real-time driver at 50 Hz.
//! Run: `cargo run --release -p pir2-runtime --example realtime_50hz`
use std::sync::{atomic::AtomicBool, Arc};
use std::time::Duration;

use pir2_runtime::realtime::{run, RealtimeConfig, SlowChannel};
use pir2_runtime::testing::{CameraStub, FakeRobot, PassThroughEncoder, SleepyModel};
use pir2_runtime::*;
use pir2_schedule::{Alignment, FrontMode};

fn main() -> Result<()> {
    let period = 20_000_000; // 50 Hz
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let spec = HeadSpec {
        horizon: 16,
        action_dim: 6,
        n_obs: 2,
        fast_dim: 12,
        slow_dim: 8,
        period,
        d_max: 5,
        d_vis_max: 5,
    };
    let mode = HeadMode::PiR2 {
        nfe: Some(2),
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
        warm_start_steps: 4,
    };
    let model = SleepyModel {
        latency: Duration::from_millis(3),
    }; // your VelocityModel here
    let head = ActionHead::new(
        model,
        spec,
        mode,
        LatencyWindow::new(20, 2, period, spec.d_max),
        0,
    )?;
    let robot = FakeRobot::new(6, clock.clone()); // your FastSource + Actuator here
    let slow = SlowChannel::Async {
        source: Box::new(CameraStub::new(clock.clone(), Duration::from_millis(33), 8)),
        encoder: Box::new(PassThroughEncoder {
            latency: Duration::from_millis(40),
        }),
    };
    let control = ControlConfig {
        horizon: 16,
        action_dim: 6,
        policy: CallPolicy::Async,
        ensemble: None,
        output: Default::default(),
    };
    let cfg = RealtimeConfig {
        period,
        max_ticks: Some(250),
        ..Default::default()
    };
    let (m, _) = run(
        head,
        control,
        robot.clone(),
        robot,
        slow,
        clock,
        cfg,
        Arc::new(AtomicBool::new(false)),
    )?;
    let ds: Vec<usize> = m.calls.iter().map(|c| c.d).collect();
    let dv: Vec<usize> = m.calls.iter().map(|c| c.d_vis).collect();
    println!(
        "ticks {} swaps {} overruns {}",
        m.ticks, m.swaps, m.overruns
    );
    println!("d: median {}   d_vis: median {}", median(ds), median(dv));
    let (j, c) = (m.tick_jitter.summary(), m.call_latency.summary());
    println!(
        "tick jitter p50 {} µs p99 {} µs; call latency p50 {} µs",
        j.p50 / 1000,
        j.p99 / 1000,
        c.p50 / 1000
    );
    Ok(())
}

fn median(mut v: Vec<usize>) -> usize {
    v.sort();
    v[v.len() / 2]
}
