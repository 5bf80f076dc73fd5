//! Collect ball-on-plate demonstrations with the LQR expert into a LeRobotDataset v3.0.
//!
//! `cargo run --release -p pir2-sim --example collect_demos -- OUT_DIR [episodes] [new|resume|overwrite]`

use std::io::Write;
use std::path::PathBuf;

use pir2_sim::dataset::{collect_to_dataset, read_dataset, CollectConfig, DatasetSpec, WriteMode};
use pir2_sim::{BallPlate, BallPlateConfig, LqrConfig, LqrExpert};

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> pir2_sim::Result<()> {
    let mut args = std::env::args().skip(1);
    let Some(root) = args.next().map(PathBuf::from) else {
        eprintln!("usage: collect_demos OUT_DIR [episodes] [new|resume|overwrite]");
        std::process::exit(2);
    };
    let episodes: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(200);
    let mode = match args.next().as_deref() {
        None | Some("new") => WriteMode::New,
        Some("resume") => WriteMode::Resume,
        Some("overwrite") => WriteMode::Overwrite,
        Some(other) => {
            eprintln!("unknown mode {other:?} (new|resume|overwrite)");
            std::process::exit(2);
        }
    };
    let task = BallPlateConfig::default();
    let mut env = BallPlate::new(task.clone())?;
    let mut expert = LqrExpert::new(&task, LqrConfig::default())?;
    let cfg = CollectConfig {
        episodes,
        ..Default::default()
    };
    let spec = DatasetSpec::ballplate(task.control_hz as u32);
    let (stats, summary) =
        collect_to_dataset(&mut env, &mut expert, &cfg, &root, &spec, mode, &mut |p| {
            eprint!(
                "\r{}/{} episodes kept, {} attempts, {} failed",
                p.kept, p.total, p.attempts, p.failures
            );
            let _ = std::io::stderr().flush();
        })?;
    eprintln!();
    println!(
        "kept {} of {} attempts in this session; dataset: {} episodes, {} frames at {}",
        stats.kept,
        stats.attempts,
        summary.total_episodes,
        summary.total_frames,
        root.display()
    );
    let ds = read_dataset(&root)?;
    println!(
        "read back: {} episodes, {} frames, tasks {:?}",
        ds.episodes.len(),
        ds.total_frames(),
        ds.tasks
    );
    Ok(())
}
