//! Checkpoint identity through the `pir2` binary: `pir2 train` records the policy a
//! checkpoint was trained as (and the SHA-256 of its weights) in `identity.json`; `pir2 eval`
//! refuses to run it as another policy, by name; a checkpoint written before checkpoints
//! recorded their identity still runs (its policy reported as unrecorded); weights replaced
//! after the checkpoint was written are refused.

use std::path::Path;
use std::process::{Command, Output};

use pir2_cli::study::ballplate::DemoConfig;

mod common;
use common::Scratch;

fn tiny() -> DemoConfig {
    DemoConfig {
        demos: 6,
        steps: 30,
        batch_size: 16,
        checkpoints: 1,
        val_episodes: 1,
        episodes: 1,
        seeds: vec![0],
        d0s: vec![1],
        width: 32,
        depth: 2,
        ..DemoConfig::default()
    }
}

fn pir2(args: &[&str], cwd: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .current_dir(cwd)
        .output()
        .unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn ok(args: &[&str], cwd: &Path) -> String {
    let o = pir2(args, cwd);
    assert!(o.status.success(), "pir2 {args:?} failed:\n{}", text(&o));
    text(&o)
}

fn refused(args: &[&str], cwd: &Path) -> String {
    let o = pir2(args, cwd);
    assert!(
        !o.status.success(),
        "pir2 {args:?} must fail:\n{}",
        text(&o)
    );
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn eval_as(checkpoint: &str, policy: &str) -> Vec<String> {
    [
        "eval",
        "--checkpoint",
        checkpoint,
        "--policy",
        policy,
        "--d0",
        "1",
        "--episodes",
        "1",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect()
}

fn args(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn train(policy: &str, out: &str, cwd: &Path) {
    ok(
        &[
            "train",
            "--data",
            "data",
            "--policy",
            policy,
            "--out",
            out,
            "--config",
            "tiny.toml",
        ],
        cwd,
    );
}

fn copy_dir(from: &Path, to: &Path, skip: &str) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_name() != skip {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// A checkpoint trained as rtc and evaluated as pir2 (or flow), or trained as pir2 and
/// evaluated as rtc, is refused with one error naming the checkpoint and both policies;
/// evaluated as what it was trained as, it runs. Before: every pairing ran silently.
#[test]
fn a_checkpoint_evaluated_as_another_policy_is_refused_and_an_old_one_still_runs() {
    let dir = Scratch::new("identity");
    let d = dir.path();
    std::fs::write(d.join("tiny.toml"), toml::to_string(&tiny()).unwrap()).unwrap();
    ok(&["collect", "--out", "data", "--episodes", "6"], d);
    train("rtc", "ck-rtc", d);
    train("pir2", "ck-pir2", d);

    // The identity is recorded in the chosen checkpoint and in every step checkpoint.
    let id: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.join("ck-rtc/best/identity.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(id["policy"], "rtc", "{id}");
    assert_eq!(id["weights_sha256"].as_str().unwrap().len(), 64, "{id}");
    let steps: Vec<_> = std::fs::read_dir(d.join("ck-pir2/steps"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with("step-")
        })
        .collect();
    assert!(!steps.is_empty());
    for s in &steps {
        let t = std::fs::read_to_string(s.join("identity.json")).unwrap();
        assert!(t.contains("\"pi_r2\""), "{}: {t}", s.display());
    }

    for (ck, trained, asked) in [
        ("ck-rtc/best", "rtc", "pir2"),
        ("ck-rtc/best", "rtc", "flow"),
        ("ck-pir2/best", "pir2", "rtc"),
    ] {
        let err = refused(&args(&eval_as(ck, asked)), d);
        assert!(
            err.contains(&format!(
                "checkpoint {ck} was trained as {trained}; --policy {asked} would run it under \
                 another schedule"
            )),
            "{ck} as {asked}: {err}"
        );
        assert_eq!(err.matches("would run it").count(), 1, "one error: {err}");
    }
    let table = ok(&args(&eval_as("ck-rtc/best", "rtc")), d);
    assert!(table.contains("RTC"), "{table}");
    // The options of a leap-cube study are refused by name, not ignored.
    for (extra, named) in [
        (["--policies", "rtc"], "--policies"),
        (["--best-of-last", "0"], "--best-of-last"),
    ] {
        let mut a = eval_as("ck-rtc/best", "rtc");
        a.extend(extra.map(String::from));
        let err = refused(&args(&a), d);
        assert!(err.contains(named) && err.contains("ballplate"), "{err}");
    }

    // A checkpoint written before identity.json existed runs as the policy asked for, and
    // says its policy is unrecorded.
    copy_dir(&d.join("ck-rtc/best"), &d.join("old"), "identity.json");
    let out = ok(&args(&eval_as("old", "pir2")), d);
    assert!(out.contains("unrecorded"), "{out}");

    // Weights replaced after the checkpoint was written: refused, naming identity.json.
    copy_dir(
        &d.join("ck-rtc/best"),
        &d.join("swapped"),
        "model.safetensors",
    );
    std::fs::copy(
        d.join("ck-pir2/best/model.safetensors"),
        d.join("swapped/model.safetensors"),
    )
    .unwrap();
    let err = refused(&args(&eval_as("swapped", "rtc")), d);
    assert!(
        err.contains("identity.json") && err.contains("the weights were replaced"),
        "{err}"
    );
}
