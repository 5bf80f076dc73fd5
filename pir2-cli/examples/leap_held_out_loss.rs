//! Diagnostic: is a Leap study run fitting the task or memorising its demonstrations?
//!
//! For every step checkpoint of one trained policy (`RUN/<policy>-seed<s>/step-*`), the mean
//! flow-matching loss on the training demonstrations and on held-out ones (demonstrations
//! collected with other expert seeds), drawn exactly as the trainer draws a batch (frames,
//! delays, noise, schedule), with the same draws for every checkpoint. A training loss that
//! keeps falling while the held-out loss rises is over-fitting.
//!
//! `cargo run --release -p pir2-cli --features mujoco --example leap_held_out_loss --
//! CONFIG RUN POLICY SEED TRAIN_DATA HELD_OUT_DATA [BATCHES]`
//!
//! `POLICY` as in the study config (`flow`, `rtc`, `pi_r2`, `pi_r2_hidden`, `pi_r2_full`,
//! `pi_r2_zero_delay`); `BATCHES` batches of 256 samples per data set (default 8).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pir2_backends::candle::CandleModel;
use pir2_backends::train::held_out_loss;
use pir2_cli::study::leap_cube::{LeapCubeTask, LeapStudyConfig};
use pir2_cli::study::pipeline::{policy_dir, Episodes};
use pir2_cli::study::{Policy, Task};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 6 {
        bail!(
            "usage: leap_held_out_loss CONFIG RUN POLICY SEED TRAIN_DATA HELD_OUT_DATA [BATCHES]"
        );
    }
    let text = std::fs::read_to_string(&args[0]).with_context(|| format!("reading {}", args[0]))?;
    let cfg: LeapStudyConfig =
        toml::from_str(&text).with_context(|| format!("parsing {}", args[0]))?;
    let policy: Policy = serde_json::from_str(&format!("\"{}\"", args[2]))
        .with_context(|| format!("unknown policy {:?}", args[2]))?;
    let seed: u64 = args[3].parse().context("SEED")?;
    let batches: usize = args.get(6).map(|b| b.parse()).transpose()?.unwrap_or(8);
    // The study's own demonstration loader (successful episodes, slow frames stacked as
    // configured), pointed at each data set in turn.
    let held_task = LeapCubeTask::new(LeapStudyConfig {
        dataset: args[5].clone(),
        ..cfg.clone()
    })?;
    let task = LeapCubeTask::new(LeapStudyConfig {
        dataset: args[4].clone(),
        ..cfg
    })?;
    let spec = task.spec();
    let schedule = policy.schedule(&task.settings().recipe);
    let train = task.demonstrations(Path::new(&args[1]))?;
    let held = held_task.demonstrations(Path::new(&args[1]))?;
    let frames = |d: &[pir2_sim::dataset::Episode]| d.iter().map(|e| e.len()).sum::<usize>();
    println!(
        "# {policy:?} seed {seed}: train {} episodes / {} frames, held out {} / {}, {batches} × 256 samples each",
        train.len(),
        frames(&train),
        held.len(),
        frames(&held)
    );
    let dir = Path::new(&args[1]).join(policy_dir(policy, seed));
    let mut steps: Vec<PathBuf> = std::fs::read_dir(&dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("step-"))
        })
        .collect();
    steps.sort();
    println!("step\ttrain\theld_out\tgap");
    for s in steps {
        let mut model = CandleModel::load_expect(&s, &spec)?;
        let a = held_out_loss(&mut model, &Episodes(&train), schedule, 256, batches, 7)?;
        let b = held_out_loss(&mut model, &Episodes(&held), schedule, 256, batches, 7)?;
        let name = s.file_name().unwrap().to_string_lossy().into_owned();
        println!(
            "{}\t{a:.4}\t{b:.4}\t{:.4}",
            name.trim_start_matches("step-"),
            b - a
        );
    }
    Ok(())
}
