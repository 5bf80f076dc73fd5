//! End to end on the Leap cube (feature `mujoco`): 2 expert episodes, a few training steps, 1 episode
//! per cell; checks the dataset, the tables and the output files.
#![cfg(feature = "mujoco")]

use pir2_cli::study::leap_cube::ExpertChoice;
use pir2_cli::study::leap_cube::{collect_leap, study_deployment, study_horizon, LeapStudyConfig};
use pir2_sim::dataset::{read_dataset, WriteMode};

#[test]
fn leap_pipeline_runs_end_to_end() {
    let dir = std::env::temp_dir().join(format!("pir2-leap-e2e-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("dataset");
    // Episode 0 of seed 0 fails with the smooth fast expert; episode 1 succeeds.
    let s = collect_leap(
        &data,
        &[0],
        2,
        WriteMode::New,
        &ExpertChoice::Mpc { fast: true },
        &Default::default(),
    )
    .expect("collect");
    assert_eq!(s.total_episodes, 2);
    // Resuming a complete collection adds nothing.
    let s2 = collect_leap(
        &data,
        &[0],
        2,
        WriteMode::Resume,
        &ExpertChoice::Mpc { fast: true },
        &Default::default(),
    )
    .expect("resume");
    assert_eq!(s2.total_episodes, 2);
    let ds = read_dataset(&data).expect("read");
    assert_eq!(ds.episodes.len(), 2);
    assert_eq!(
        (
            ds.episodes[0].fast_dim,
            ds.episodes[0].slow_dim,
            ds.episodes[0].action_dim
        ),
        (32, 9, 16)
    );
    assert!(
        ds.episodes.iter().any(|e| e.success),
        "the test needs one successful expert episode"
    );

    let cfg = LeapStudyConfig {
        dataset: data.to_string_lossy().into_owned(),
        steps: 3,
        batch_size: 8,
        warmup: 1,
        widths: vec![8, 16],
        groups: 4,
        checkpoints: 1,
        val_episodes: 1,
        episodes: 1,
        seeds: vec![0],
        d0s: vec![1, 3],
        hs: vec![1, 8],
        flow_steps: 2,
        max_steps: 10,
        threads: 1,
        ..LeapStudyConfig::default()
    };
    let r = study_deployment(&cfg, &dir.join("deployment"), false).expect("deployment study");
    // Rows: sync flow (h = d), naive async (plain swap), naive async + TE (labelled extra),
    // train-time RTC, πR² w/o async, πR² async, πR² full ramp.
    assert_eq!(r.labels.len(), 7, "{:?}", r.labels);
    assert!(r.labels[0].starts_with("sync flow"), "{:?}", r.labels);
    assert!(
        r.labels.iter().any(|l| l == "naive async"),
        "{:?}",
        r.labels
    );
    assert_eq!(r.cells.len(), 7 * 2);
    assert!(r.cells.iter().all(|c| c.episodes == 1 && c.successes <= 1));
    let t = std::fs::read_to_string(dir.join("deployment/table.md")).expect("table");
    assert!(t.contains("πR² async (n=2)") && t.contains("d0=3"), "{t}");
    assert!(dir.join("deployment/success.png").exists());
    let h = study_horizon(&cfg, &dir.join("horizon"), false).expect("horizon study");
    assert_eq!(h.cells.len(), 3 * 2);
    let t = std::fs::read_to_string(dir.join("horizon/table.md")).expect("table");
    assert!(t.contains("| sync flow |") && t.contains("h=8"), "{t}");
    let _ = std::fs::remove_dir_all(&dir);
}
