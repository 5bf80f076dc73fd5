//! Interrupted training through the `pir2` binary: SIGTERM during `pir2 train --task` (a
//! user's dataset) and during `pir2 train ballplate` ends the run with a non-zero status and
//! one error naming the saved training state and the `--resume` command; `--resume`
//! continues from it and finishes. Before: `train --task` had no signal handling (SIGTERM
//! killed it and every step since the last checkpoint was lost), and `train ballplate` saved
//! its state, said to resume, then refused `--resume`.

use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use pir2_cli::study::ballplate::DemoConfig;

mod common;
use common::Scratch;

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

fn pir2(args: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_pir2"));
    c.args(args);
    c
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn ok(o: Output) -> String {
    assert!(o.status.success(), "pir2 failed:\n{}", text(&o));
    text(&o)
}

/// Whether `dir` holds an entry whose name starts with `prefix`.
fn holds(dir: &Path, prefix: &str) -> bool {
    std::fs::read_dir(dir).is_ok_and(|rd| {
        rd.flatten()
            .any(|e| e.file_name().to_string_lossy().starts_with(prefix))
    })
}

/// Start `cmd`, wait (≤ 300 s) until `ready()` (training has reached a step checkpoint),
/// send SIGTERM, and return the output of the ended process.
fn sigterm_when(mut cmd: Command, ready: impl Fn() -> bool) -> Output {
    let mut child: Child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !ready() {
        if let Some(st) = child.try_wait().unwrap() {
            let out = child.wait_with_output().unwrap();
            panic!("ended ({st}) before the signal:\n{}", text(&out));
        }
        if t0.elapsed() > Duration::from_secs(300) {
            let _ = child.kill();
            panic!("no step checkpoint after 300 s");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    // SAFETY: plain kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    let t1 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t1.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            panic!("still running 120 s after SIGTERM");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// The interrupted run's error: non-zero exit (not killed by the signal), the saved state
/// named (and on disk), the resume command named. Returns the saved state's path.
fn check_interrupted(out: &Output, resume_cmd: &str) -> PathBuf {
    let msg = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "must fail: {}", text(out));
    assert_eq!(out.status.signal(), None, "killed by the signal: {msg}");
    assert!(msg.contains(resume_cmd), "names `{resume_cmd}`: {msg}");
    let saved = msg
        .split("training state saved in ")
        .nth(1)
        .and_then(|r| r.split(')').next())
        .unwrap_or_else(|| panic!("names the saved state: {msg}"));
    let saved = PathBuf::from(saved);
    assert!(
        saved.join("train_state.json").is_file(),
        "{} holds the training state: {msg}",
        saved.display()
    );
    saved
}

const REACH: &str = r#"
fast_keys = ["observation.state", "observation.goal"]
slow_keys = ["observation.speed"]
action_key = "action"
horizon = 8
n_obs = 2
policy = "pi_r2"
seed = 7

[recipe]
pir2_d_max = 2

[model]
kind = "mlp"
width = 64
depth = 2

[train]
steps = 400
batch_size = 64
lr = 3e-3
warmup = 20

[validation]
held_out_episodes = [5]
checkpoints = 4
windows = 8
"#;

/// SIGTERM during `pir2 train --task`: exit non-zero naming the saved state and the resume
/// command; `--resume` finishes the run (a chosen checkpoint, every validation).
#[test]
fn sigterm_during_dataset_training_saves_the_state_and_resume_finishes() {
    let dir = Scratch::new("train-interrupt-task");
    let data =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-sim/tests/fixtures/lerobot-reach");
    let task = dir.path().join("task.toml");
    std::fs::write(&task, REACH).unwrap();
    let out = dir.path().join("out");
    let args = [
        "train",
        "--data",
        s(&data),
        "--task",
        s(&task),
        "--out",
        s(&out),
    ];
    let o = sigterm_when(pir2(&args), || holds(&out, "step-"));
    let resume = format!(
        "pir2 train --task {} --data {} --out {} --resume",
        s(&task),
        s(&data),
        s(&out)
    );
    let saved = check_interrupted(&o, &resume);
    assert!(saved.starts_with(&out), "{}", saved.display());
    assert!(!out.join("best").exists());

    let mut again = args.to_vec();
    again.push("--resume");
    let log = ok(pir2(&again).output().unwrap());
    assert!(out.join("best/model.safetensors").is_file(), "{log}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("validation.json")).unwrap())
            .unwrap();
    assert_eq!(
        report["checkpoints"].as_array().unwrap().len(),
        4,
        "{report}"
    );
    assert!(
        !holds(&out, "interrupted-"),
        "the finished run removes its interrupted state"
    );
}

/// SIGTERM during `pir2 train ballplate`: exit non-zero naming the saved state and the
/// resume command; that command (`--resume`) finishes the run. `--resume` with another
/// policy is refused by name.
#[test]
fn sigterm_during_ballplate_training_saves_the_state_and_resume_finishes() {
    let dir = Scratch::new("train-interrupt-ballplate");
    let d = dir.path();
    let cfg = DemoConfig {
        demos: 6,
        steps: 400,
        batch_size: 16,
        checkpoints: 4,
        val_episodes: 1,
        width: 32,
        depth: 2,
        ..DemoConfig::default()
    };
    let config = d.join("tiny.toml");
    std::fs::write(&config, toml::to_string(&cfg).unwrap()).unwrap();
    let data = d.join("data");
    ok(pir2(&["collect", "--out", s(&data), "--episodes", "6"])
        .output()
        .unwrap());
    let out = d.join("ck");
    let args = [
        "train",
        "--data",
        s(&data),
        "--policy",
        "rtc",
        "--config",
        s(&config),
        "--out",
        s(&out),
    ];
    let steps = out.join("steps");
    let o = sigterm_when(pir2(&args), || holds(&steps, "step-"));
    let resume = format!(
        "pir2 train ballplate --data {} --policy rtc --seed 0 --config {} --out {} --resume",
        s(&data),
        s(&config),
        s(&out)
    );
    let saved = check_interrupted(&o, &resume);
    assert!(saved.starts_with(&steps), "{}", saved.display());

    // Another policy does not continue this run.
    let mut other = args.to_vec();
    other[4] = "pir2";
    other.push("--resume");
    let o = pir2(&other).output().unwrap();
    assert!(!o.status.success());
    let msg = String::from_utf8_lossy(&o.stderr);
    assert!(msg.contains("was trained as --policy rtc"), "{msg}");

    let mut again = args.to_vec();
    again.push("--resume");
    let log = ok(pir2(&again).output().unwrap());
    assert!(out.join("best/model.safetensors").is_file(), "{log}");
    assert!(
        std::fs::read_to_string(out.join("best/identity.json"))
            .unwrap()
            .contains("\"rtc\""),
        "{log}"
    );
    assert!(holds(&steps, "step-000400"), "{log}");
    assert!(!holds(&steps, "interrupted-"), "{log}");
}
