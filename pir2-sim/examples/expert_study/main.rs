//! Success rate of the ball-on-plate LQR expert, and its sensitivity to latency.
//!
//! `cargo run --release -p pir2-sim --example expert_study -- [episodes] [seed0]`

use pir2_sim::expert::{evaluate_expert, LqrConfig, LqrExpert};
use pir2_sim::{BallPlate, BallPlateConfig};

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> pir2_sim::Result<()> {
    let mut args = std::env::args().skip(1);
    let episodes: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(200);
    let seed0: u64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(0);
    let task = BallPlateConfig::default();
    let mut env = BallPlate::new(task.clone())?;
    let mut expert = LqrExpert::new(&task, LqrConfig::default())?;
    let k = expert.gain();
    println!(
        "LQR gain K = [{:.4}, {:.4}, {:.4}, {:.5}]  (θ_ref = −K·(p, v, θ, ω))",
        k[0], k[1], k[2], k[3]
    );
    println!(
        "{episodes} episodes per cell, seeds {seed0}..{}",
        seed0 + episodes as u64
    );
    println!("delay (ticks) | success");
    for delay in [0usize, 2, 4, 6, 8] {
        expert.set_delay(delay);
        let r = evaluate_expert(&mut env, &mut expert, episodes, seed0);
        println!(
            "{delay:>13} | {:.3} ({}/{})",
            r.rate(),
            r.successes,
            r.episodes
        );
    }
    Ok(())
}
