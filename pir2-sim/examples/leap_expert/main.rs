//! Measure the MPC expert on the paper's Leap-cube variant: success rate and control steps/s.
//!
//! ```text
//! source .native/env.sh
//! cargo run --release -p pir2-sim --features mujoco --example leap_expert -- --episodes 100
//! ```
//! Options: `--episodes N` (100), `--start I` (0, first episode index), `--seed S` (0),
//! `--fast` (the cheaper recipe), `--pin` (`MpcConfig::pin_first_knot`, as `pir2 collect`
//! uses), `--threads T` (2), `--samples K`, `--horizon H`.

use std::time::Instant;

use anyhow::{bail, Context};
use pir2_sim::leap::{collect, CollectConfig, LeapModel, MpcConfig};

fn main() -> anyhow::Result<()> {
    let mut episodes = 100usize;
    let mut start = 0usize;
    let mut cfg = CollectConfig::default();
    let mut mpc = MpcConfig::default();
    let mut threads = None;
    let mut samples = None;
    let mut horizon = None;
    let mut pin = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = |name: &str| args.next().with_context(|| format!("{name} needs a value"));
        match a.as_str() {
            "--episodes" => episodes = val("--episodes")?.parse()?,
            "--start" => start = val("--start")?.parse()?,
            "--seed" => cfg.seed = val("--seed")?.parse()?,
            "--fast" => mpc = MpcConfig::fast(),
            "--pin" => pin = true,
            "--threads" => threads = Some(val("--threads")?.parse()?),
            "--samples" => samples = Some(val("--samples")?.parse()?),
            "--horizon" => horizon = Some(val("--horizon")?.parse()?),
            other => bail!("unknown argument {other}"),
        }
    }
    mpc.threads = threads.unwrap_or(mpc.threads);
    mpc.samples = samples.unwrap_or(mpc.samples);
    mpc.horizon = horizon.unwrap_or(mpc.horizon);
    mpc.pin_first_knot |= pin;
    cfg.mpc = mpc;
    let model = LeapModel::load(None)?;
    println!("config: {:?}", cfg);
    let t0 = Instant::now();
    let cpu0 = process_cpu_seconds().unwrap_or(0.0);
    let (mut done, mut wins, mut steps) = (0usize, 0usize, 0usize);
    let mut win_steps = Vec::new();
    let eps = collect(&model, &cfg, start..start + episodes, |ep| {
        done += 1;
        steps += ep.frames.len();
        if ep.success {
            wins += 1;
            win_steps.push(ep.frames.len());
        }
        let dt = t0.elapsed().as_secs_f64();
        println!(
            "episode {:4}: {} in {:3} steps | {}/{} = {:.3} | {:.1} control steps/s",
            ep.index,
            if ep.success { "success" } else { "FAIL   " },
            ep.frames.len(),
            wins,
            done,
            wins as f64 / done as f64,
            steps as f64 / dt
        );
    })?;
    let dt = t0.elapsed().as_secs_f64();
    let cpu = process_cpu_seconds().map_or(f64::NAN, |c| c - cpu0);
    win_steps.sort_unstable();
    let median = win_steps.get(win_steps.len() / 2).copied().unwrap_or(0);
    println!(
        "RESULT success {}/{} = {:.3}; median steps to success {}; {} control steps in {:.1} s wall = {:.1} steps/s; {:.1} CPU-s = {:.1} steps per CPU-second",
        wins,
        eps.len(),
        wins as f64 / eps.len().max(1) as f64,
        median,
        steps,
        dt,
        steps as f64 / dt,
        cpu,
        steps as f64 / cpu
    );
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
