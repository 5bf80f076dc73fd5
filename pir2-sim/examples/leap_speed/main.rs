//! Physics speed of the Leap-cube environment without a policy: control steps per second
//! for the paper's variant (50 Hz, 2 substeps) and the playground's (20 Hz, 5 substeps),
//! with zero and with random actions, on one thread.
//!
//! ```text
//! source .native/env.sh
//! cargo run --release -p pir2-sim --features mujoco --example leap_speed -- 20000
//! ```

use std::time::Instant;

use pir2_runtime::Environment;
use pir2_schedule::Rng;
use pir2_sim::leap::{LeapConfig, LeapCubeEnv, LeapModel, NU};

fn main() -> anyhow::Result<()> {
    let steps: usize = std::env::args()
        .nth(1)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(20_000);
    let model = LeapModel::load(None)?;
    for (name, cfg) in [
        ("paper 50 Hz", LeapConfig::paper()),
        ("playground 20 Hz", LeapConfig::playground()),
    ] {
        for random in [false, true] {
            let mut env = LeapCubeEnv::new(&model, cfg)?;
            let (fd, sd) = cfg.obs_dims();
            let (mut fast, mut slow) = (vec![0.0; fd], vec![0.0; sd]);
            let mut rng = Rng::new(1);
            let mut action = [0.0f32; NU];
            let mut episodes = 0u64;
            env.reset(0);
            let t0 = Instant::now();
            let cpu0 = process_cpu_seconds().unwrap_or(0.0);
            for _ in 0..steps {
                env.observe(&mut fast, &mut slow);
                if random {
                    action
                        .iter_mut()
                        .for_each(|a| *a = rng.uniform_range(-1.0, 1.0));
                }
                if env.step(&action).done {
                    episodes += 1;
                    env.reset(episodes);
                }
            }
            let dt = t0.elapsed().as_secs_f64();
            let cpu = process_cpu_seconds().map_or(f64::NAN, |c| c - cpu0);
            println!(
                "{name:17} {:6} actions: {steps} control steps, {dt:.2} s wall = {:6.0} steps/s; {cpu:.2} CPU-s = {:6.0} control steps per CPU-s ({:6.0} mj_step per CPU-s); {episodes} episodes ended",
                if random { "random" } else { "zero" },
                steps as f64 / dt,
                steps as f64 / cpu,
                (steps * env.substeps()) as f64 / cpu,
            );
        }
    }
    Ok(())
}

/// CPU seconds used by this process so far (user + system, all threads), from
/// `/proc/self/stat` (Linux; assumes the usual 100 clock ticks per second). On a shared
/// machine this measures the work done, not the share of the CPU we happened to get.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = &stat[stat.rfind(')')? + 1..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}
