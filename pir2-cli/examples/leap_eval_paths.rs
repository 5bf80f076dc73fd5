//! Benchmark: one Leap-cube evaluation cell run the two ways the study can run it, side by
//! side in one process: every episode on its own with batch-1 model calls on `threads`
//! threads, and the episodes in lock-step groups whose calls are answered by one batched
//! call per round. Prints the wall time, the cells per hour it implies and the ratio; the
//! success counts are printed too (equal in distribution, not bit for bit: the batched
//! kernels round differently).
//!
//! `cargo run --release -p pir2-cli --features mujoco --example leap_eval_paths --
//! CONFIG CHECKPOINT MODE D0 EPISODES [GROUP ...]`
//!
//! `CHECKPOINT` is a trained policy's directory (e.g. `RUN/flow-seed0/best`); `MODE` is
//! `naive` (plain-swap naive async at the config's flow steps), `sync` (sync flow, `h = d`),
//! `rtc` or `pir2` (πR² async at the config's `nfe`); `GROUP` defaults to 25 and 50.

use std::time::Instant;

use anyhow::{bail, Context, Result};
use pir2_backends::candle::{kernel_threads, CandleModel};
use pir2_cli::study::leap_cube::{LeapCubeTask, LeapStudyConfig};
use pir2_cli::study::pipeline::{closed_loop, EvalPath, Models};
use pir2_cli::study::{Policy, Task};
use pir2_runtime::{LockstepTiming, Mode};
use pir2_schedule::{Alignment, FrontMode};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 5 {
        bail!("usage: leap_eval_paths CONFIG CHECKPOINT MODE D0 EPISODES [GROUP ...]");
    }
    let text = std::fs::read_to_string(&args[0]).with_context(|| format!("reading {}", args[0]))?;
    let cfg: LeapStudyConfig =
        toml::from_str(&text).with_context(|| format!("parsing {}", args[0]))?;
    let threads = cfg.threads;
    let task = LeapCubeTask::new(cfg)?;
    let recipe = task.settings().recipe;
    let d0: usize = args[3].parse().context("D0")?;
    let episodes: usize = args[4].parse().context("EPISODES")?;
    let groups: Vec<usize> = if args.len() > 5 {
        args[5..]
            .iter()
            .map(|g| g.parse().context("GROUP"))
            .collect::<Result<_>>()?
    } else {
        vec![25, 50]
    };
    let k = recipe.flow_steps;
    let (policy, mode) = match args[2].as_str() {
        "naive" => (
            Policy::Flow,
            Mode::NaiveAsync {
                steps: k,
                ensemble: None,
            },
        ),
        "sync" => (Policy::Flow, Mode::SyncFlow { steps: k, h: 1 }),
        "rtc" => (Policy::Rtc, Mode::TrainTimeRtc { steps: k }),
        "pir2" => (
            Policy::PiR2,
            Mode::PiR2Async {
                nfe: Some(recipe.nfe),
                alignment: Alignment::Fresh,
                front: FrontMode::Visible,
            },
        ),
        m => bail!("unknown MODE {m:?} (naive, sync, rtc, pir2)"),
    };
    let mut timing = LockstepTiming::for_mode(&mode, d0);
    let mode = match mode {
        Mode::SyncFlow { steps, .. } => Mode::SyncFlow {
            steps,
            h: timing.call_ticks.max(1),
        },
        m => m,
    };
    timing.pin_delay = true;
    let model = CandleModel::load_expect(args[1].as_ref(), &task.spec())?;
    let models = Models::local(&model)?;
    println!(
        "# {} d0 = {d0}, {episodes} episodes, {} kernel threads",
        mode.name(),
        kernel_threads()
    );
    println!("path\tseconds\tcells/h (100 ep)\tsuccesses\tspeed-up");
    let run = |path: EvalPath| -> Result<(f64, usize)> {
        let t = Instant::now();
        let (ok, _) = closed_loop(
            &task,
            &models,
            policy,
            &mode,
            timing,
            episodes,
            2_000_000,
            path,
            &|| {},
        )?;
        Ok((t.elapsed().as_secs_f64(), ok))
    };
    let per_hour = |s: f64| 3600.0 / (s * 100.0 / episodes as f64);
    let (base, ok) = run(EvalPath::Threads(threads))?;
    println!(
        "batch-1, {threads} threads\t{base:.1}\t{:.1}\t{ok}/{episodes}\t1.00",
        per_hour(base)
    );
    for g in groups {
        let (s, ok) = run(EvalPath::Batched(g))?;
        println!(
            "batched, groups of {g}\t{s:.1}\t{:.1}\t{ok}/{episodes}\t{:.2}",
            per_hour(s),
            base / s
        );
    }
    Ok(())
}
