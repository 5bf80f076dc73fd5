//! The ball-on-plate demo end to end at a tiny scale: the library pipeline (`ballplate::run`) and
//! the same stages through the `pir2` binary (`collect` → `train` → `eval` → `plot`).

use std::path::Path;
use std::process::Command;

use pir2_cli::study::ballplate::{self as demo, BallPlateTask, DemoConfig, POLICIES};
use pir2_cli::study::pipeline::{self, Models};
use pir2_cli::study::{Policy, Task};

mod common;
use common::Scratch;

fn tiny() -> DemoConfig {
    DemoConfig {
        demos: 12,
        steps: 200,
        batch_size: 32,
        checkpoints: 2,
        val_episodes: 2,
        episodes: 4,
        seeds: vec![0],
        d0s: vec![1, 3],
        width: 32,
        depth: 2,
        ..DemoConfig::default()
    }
}

#[test]
fn demo_writes_every_row_and_refuses_a_used_directory() {
    let dir = Scratch::new("demo");
    let out = dir.path().join("demo");
    let cfg = tiny();
    let r = demo::run(&cfg, &out).unwrap();
    let rows = BallPlateTask::new(cfg.clone()).rows();
    assert_eq!(r.labels.len(), rows.len());
    assert_eq!(r.cells.len(), rows.len() * cfg.d0s.len() * cfg.seeds.len());
    for c in &r.cells {
        assert_eq!(c.episodes, cfg.episodes);
        assert!(c.successes <= c.episodes);
    }
    // Every policy was validated at each checkpoint (closed loop, not loss).
    assert_eq!(r.validation.len(), POLICIES.len());
    for (_, _, scores) in &r.validation {
        assert_eq!(scores.len(), cfg.checkpoints);
    }
    for f in ["result.json", "table.md", "success.png"] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    for row in &rows {
        assert!(table.contains(&row.label), "table lacks {}", row.label);
    }
    let ds = pir2_sim::dataset::read_dataset(&out.join("dataset")).unwrap();
    assert_eq!(ds.episodes.len(), cfg.demos);
    // The output directory is not reused: nothing a user has is overwritten.
    let err = demo::run(&cfg, &out).unwrap_err().to_string();
    assert!(err.contains("not empty"), "{err}");
}

fn pir2(args: &[&str], cwd: &Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .current_dir(cwd)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "pir2 {args:?} failed:\n{text}");
    text
}

#[test]
fn every_stage_runs_as_its_own_subcommand() {
    let dir = Scratch::new("stages");
    let d = dir.path();
    let cfg = tiny();
    std::fs::write(d.join("tiny.toml"), toml::to_string(&cfg).unwrap()).unwrap();
    pir2(&["collect", "--out", "data", "--episodes", "6"], d);
    // A second collect into the same directory is refused; --resume adds the missing ones.
    let again = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["collect", "--out", "data", "--episodes", "6"])
        .current_dir(d)
        .output()
        .unwrap();
    assert!(!again.status.success());
    let msg = String::from_utf8_lossy(&again.stderr);
    assert!(msg.contains("data"), "{msg}");
    pir2(
        &[
            "train",
            "--data",
            "data",
            "--policy",
            "pir2",
            "--out",
            "ckpt",
            "--config",
            "tiny.toml",
        ],
        d,
    );
    assert!(d.join("ckpt/best").is_dir());
    let table = pir2(
        &[
            "eval",
            "--checkpoint",
            "ckpt/best",
            "--policy",
            "pir2",
            "--d0",
            "1,2",
            "--episodes",
            "3",
            "--json",
            "cells.json",
        ],
        d,
    );
    assert!(table.contains("πR² async (n=2)"), "{table}");
    let cells: Vec<pir2_cli::study::Cell> =
        serde_json::from_str(&std::fs::read_to_string(d.join("cells.json")).unwrap()).unwrap();
    assert_eq!(cells.len(), 2 * 2, "two πR² rows × two delays");
    // Plot a demo result.
    pir2(&["demo", "--config", "tiny.toml", "--out", "run"], d);
    pir2(&["plot", "run/result.json", "--out", "again.png"], d);
    assert!(d.join("again.png").is_file());
    // Outputs a user already has are not replaced.
    for args in [
        vec!["plot", "run/result.json", "--out", "again.png"],
        vec![
            "eval",
            "--checkpoint",
            "ckpt/best",
            "--policy",
            "pir2",
            "--episodes",
            "1",
            "--json",
            "cells.json",
        ],
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_pir2"))
            .args(&args)
            .current_dir(d)
            .output()
            .unwrap();
        let msg = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && msg.contains("already exists"),
            "{args:?}: {msg}"
        );
    }
}

/// A short training run learns a policy that balances the ball (guards the whole chain:
/// observation content, encoding, normalisation, training, runtime, denormalisation).
#[test]
fn a_short_training_run_balances_the_ball() {
    let cfg = DemoConfig {
        steps: 600,
        batch_size: 64,
        width: 64,
        depth: 3,
        checkpoints: 1,
        val_episodes: 1,
        ..DemoConfig::default()
    };
    let demos = demo::collect(40, 11, false).unwrap();
    let task = BallPlateTask::new(cfg);
    let (m, _) = pipeline::train_policy(&task, &demos, Policy::PiR2, 0, None, &|_| {}).unwrap();
    let mode = pir2_runtime::Mode::PiR2Async {
        nfe: Some(2),
        alignment: pir2_schedule::Alignment::Fresh,
        front: pir2_schedule::FrontMode::Visible,
    };
    let timing = pir2_runtime::LockstepTiming::for_mode(&mode, 1);
    let models = Models::local(&m).unwrap();
    let cell = |path| {
        pipeline::closed_loop(
            &task,
            &models,
            Policy::PiR2,
            &mode,
            timing,
            12,
            77,
            path,
            &|| {},
        )
        .unwrap()
        .0
    };
    let ok = cell(pipeline::EvalPath::Threads(2));
    eprintln!("πR² async, d0 = 1: {ok}/12");
    assert!(ok >= 6, "πR² async after 600 steps: {ok}/12");
    // The same cell with the episodes in lock-step and their calls batched through the
    // candle model: another measurement of the same policy (the batched kernels round
    // differently), so it must succeed as often, not in the same episodes.
    let ok_batched = cell(pipeline::EvalPath::Batched(12));
    eprintln!("πR² async, d0 = 1, batched: {ok_batched}/12");
    assert!(
        ok_batched >= 6,
        "πR² async after 600 steps, batched: {ok_batched}/12"
    );
    // The batches' composition follows from the episodes, not from thread timing: the
    // batched cell repeats through the real U-Net's batched kernels.
    let again = cell(pipeline::EvalPath::Batched(12));
    assert_eq!(again, ok_batched, "a batched cell run twice");
    assert!(
        ok_batched >= 6,
        "πR² async after 600 steps, batched: {ok_batched}/12"
    );
}
