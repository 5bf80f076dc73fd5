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
            println!(
                "{name:17} {:6} actions: {steps} control steps in {dt:.2} s = {:8.0} control steps/s ({:8.0} mj_step/s), {episodes} episodes ended",
                if random { "random" } else { "zero" },
                steps as f64 / dt,
                (steps * env.substeps()) as f64 / dt,
            );
        }
    }
    Ok(())
}
