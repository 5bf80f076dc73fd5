//! A 50 Hz πR² loop: a model, a robot and an asynchronous camera channel.
//! Run: `cargo run --release -p pir2-runtime --example realtime_50hz` (README beside it).
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::testing::{CameraStub, FakeRobot, PassThroughEncoder, SleepyModel};
use pir2_runtime::{Mode, Realtime, Result, SystemClock};

fn main() -> Result<()> {
    let clock = Arc::new(SystemClock::new());
    let robot = FakeRobot::new(6, clock.clone()); // your FastSource + Actuator here
    let model = SleepyModel {
        latency: Duration::from_millis(3),
    }; // your VelocityModel here
    let camera = CameraStub::new(clock.clone(), Duration::from_millis(33), 8);
    let backbone = PassThroughEncoder {
        latency: Duration::from_millis(40),
    };
    let m = Realtime::builder(model)
        .chunk(16, 6) // H = 16 actions of 6 values
        .fast(12, 2) // 12 proprioceptive values, 2 frames
        .hz(50.0)
        .mode(Mode::pir2_async(2)) // one NFE per call, n = 2 per action
        .trained_for(5, 5) // d_max, d_vis_max
        .slow_async(8, Box::new(camera), Box::new(backbone))
        .max_ticks(250)
        .clock(clock)
        .run(robot.clone(), robot)?;
    let (j, c) = (m.tick_jitter.summary(), m.call_latency.summary());
    println!(
        "ticks {} swaps {} overruns {}",
        m.ticks, m.swaps, m.overruns
    );
    println!(
        "tick jitter p99 {} µs; call latency p50 {} µs",
        j.p99 / 1000,
        c.p50 / 1000
    );
    Ok(())
}
