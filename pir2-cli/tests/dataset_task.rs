//! `pir2 train --data DATASET --task task.toml` on a dataset written by LeRobot's own writer
//! (the committed lerobot 0.4.4 fixture) and on one written by our writer under custom keys;
//! `pir2 export` of the result; errors; same seed ⇒ same bits; `--resume`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use pir2_cli::study::dataset::{self, DatasetTaskConfig, ValidationReport};
use pir2_sim::dataset::{DatasetSpec, DatasetWriter, Episode, FeatureKeys, WriteMode};

mod common;
use common::Scratch;

fn lerobot_fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-sim/tests/fixtures/lerobot-reach")
}

fn pir2(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .output()
        .expect("runs pir2")
}

fn ok(out: &Output) -> String {
    let (so, se) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "pir2 failed:\n{so}\n{se}");
    so.into_owned()
}

fn failed(out: &Output) -> String {
    assert!(!out.status.success(), "pir2 succeeded where it must fail");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The LeRobot fixture's task: position + goal as the fast observation, the scalar speed as
/// the slow one, πR² with n = 2, a small MLP.
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
steps = 300
batch_size = 64
lr = 3e-3
warmup = 20

[validation]
held_out_episodes = [5]
checkpoints = 3
windows = 24
"#;

/// `pir2 train --data data --task task --out out` plus `extra` flags.
fn train(data: &Path, task: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "train",
        "--data",
        s(data),
        "--task",
        s(task),
        "--out",
        s(out),
    ];
    args.extend_from_slice(extra);
    pir2(&args)
}

/// `pir2 export checkpoint --onnx onnx`, which must succeed.
fn export(checkpoint: &Path, onnx: &Path) {
    ok(&pir2(&["export", s(checkpoint), "--onnx", s(onnx)]));
}

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn report(out: &Path) -> ValidationReport {
    dataset::read_report(out).unwrap()
}

/// The chosen checkpoint is the one with the lowest normalised open-loop error, and it
/// learned the task: far below 1.0, the error of always sending the mean action.
fn check_learned(r: &ValidationReport, checkpoints: usize, bound: f64) {
    assert_eq!(r.metric, "open_loop.nrmse");
    assert_eq!(r.checkpoints.len(), checkpoints, "{r:?}");
    let best = r
        .checkpoints
        .iter()
        .min_by(|a, b| a.open_loop.nrmse.total_cmp(&b.open_loop.nrmse))
        .unwrap();
    assert_eq!(r.best_step, Some(best.step), "{r:?}");
    assert!(best.open_loop.nrmse < bound, "{r:?}");
    for c in &r.checkpoints {
        assert!(c.flow_loss.is_finite() && c.flow_loss > 0.0, "{c:?}");
        assert!(c.open_loop.windows > 0);
    }
}

#[test]
fn trains_on_the_lerobot_written_fixture_and_exports_to_onnx() {
    let dir = Scratch::new("dataset-lerobot");
    let task = write(dir.path(), "task.toml", REACH);
    let out = dir.path().join("run");
    let data = lerobot_fixture();
    let stdout = ok(&train(&data, &task, &out, &[]));
    assert!(stdout.contains("← best"), "{stdout}");
    let r = report(&out);
    assert_eq!((r.held_out.as_slice(), r.train_episodes), (&[5][..], 5));
    // One held-out episode with a goal no training episode has: 0.7 is well below both the
    // mean-action predictor (1.0) and the untrained model (about 1.5).
    check_learned(&r, 3, 0.7);
    let onnx = dir.path().join("reach.onnx");
    let best = out.join("best");
    export(&best, &onnx);
    assert!(std::fs::metadata(&onnx).unwrap().len() > 1000);
    // A finished run resumed is kept as it is.
    let again = ok(&train(&data, &task, &out, &["--resume"]));
    assert!(again.contains("← best"), "{again}");
    assert_eq!(report(&out), r);
}

/// A dataset written by our writer under custom keys: the action drives the joints toward
/// a per-episode target, `action = 0.5 · (target − q)`.
fn custom_dataset(root: &Path) {
    custom_dataset_with(root, None);
}

/// [`custom_dataset`], with a NaN action in episode `nan_in` if given.
fn custom_dataset_with(root: &Path, nan_in: Option<usize>) {
    let spec = DatasetSpec {
        fps: 20,
        robot_type: Some("two_joint_arm".into()),
        tasks: vec!["track the target".into()],
        fast_names: vec!["q0".into(), "q1".into()],
        slow_names: vec!["t0".into(), "t1".into()],
        action_names: vec!["dq0".into(), "dq1".into()],
        keys: FeatureKeys {
            fast: "observation.joints".into(),
            slow: "observation.target".into(),
            action: "action.joint_delta".into(),
        },
    };
    let mut w = DatasetWriter::open(root, spec, WriteMode::New).unwrap();
    for e in 0..8 {
        let k = e as f32 / 8.0;
        let target = [0.6 - k, 0.3 * k - 0.2];
        let mut q = [-0.4 + 0.1 * k, 0.5 - k];
        let mut ep = Episode::new(2, 2, 2);
        for t in 0..25 {
            let a = [0.5 * (target[0] - q[0]), 0.5 * (target[1] - q[1])];
            let label = if nan_in == Some(e) && t == 3 {
                [f32::NAN, a[1]]
            } else {
                a
            };
            ep.push(&q, &target, &label);
            q = [q[0] + a[0], q[1] + a[1]];
        }
        w.append(&ep).unwrap();
    }
    w.finish().unwrap();
}

const CUSTOM: &str = r#"
fast_keys = ["observation.joints", "observation.target"]
action_key = "action.joint_delta"
horizon = 6
policy = "flow"

[recipe]
flow_steps = 4

[model]
kind = "mlp"
width = 64
depth = 2

[train]
steps = 300
batch_size = 64
lr = 3e-3
warmup = 20

[validation]
held_out = 0.25
checkpoints = 2
windows = 24
"#;

#[test]
fn trains_flow_on_a_custom_key_dataset_written_by_our_writer() {
    let dir = Scratch::new("dataset-custom");
    let data = dir.path().join("data");
    custom_dataset(&data);
    let task = write(dir.path(), "task.toml", CUSTOM);
    let out = dir.path().join("run");
    ok(&train(&data, &task, &out, &[]));
    let r = report(&out);
    assert_eq!((r.held_out.len(), r.train_episodes), (2, 6));
    check_learned(&r, 2, 0.35);
    let onnx = dir.path().join("custom.onnx");
    export(&out.join("best"), &onnx);
    assert!(onnx.exists());
}

#[test]
fn a_missing_key_or_an_unknown_field_is_one_error_naming_it() {
    let dir = Scratch::new("dataset-errors");
    let data = lerobot_fixture();
    let run = |task: &str, out: &str| {
        let t = write(dir.path(), &format!("{out}.toml"), task);
        train(&data, &t, &dir.path().join(out), &[])
    };
    let err = failed(&run(
        &REACH.replace("\"observation.goal\"", "\"observation.gaol\""),
        "missing",
    ));
    assert!(
        err.contains("`observation.gaol`") && err.contains("not in meta/info.json"),
        "{err}"
    );
    assert!(!dir.path().join("missing").exists(), "nothing written");
    let err = failed(&run(&REACH.replace("horizon = 8", "horizon = 4"), "short"));
    assert!(
        err.contains("`horizon` = 4 does not fit policy PiR2"),
        "{err}"
    );
    let err = failed(&run(&REACH.replace("width = 64", "widht = 64"), "unknown"));
    assert!(err.contains("unknown field `model.widht`"), "{err}");
    let err = failed(&run(
        &REACH.replace("[train]", "[train]\nsteps_per_epoch = 3"),
        "unknown-train",
    ));
    assert!(err.contains("steps_per_epoch"), "{err}");
    let err = failed(&run(
        &REACH.replace("action_key = \"action\"", "action_key = \"frame_index\""),
        "int",
    ));
    assert!(
        err.contains("`frame_index`") && err.contains("float32/float64"),
        "{err}"
    );
    // Stock-task flags do not mix with a task file.
    let t = write(dir.path(), "ok.toml", REACH);
    let err = failed(&train(
        &data,
        &t,
        &dir.path().join("mixed"),
        &["--policy", "flow"],
    ));
    assert!(err.contains("--policy"), "{err}");
}

fn small(seed: u64) -> DatasetTaskConfig {
    let mut c = DatasetTaskConfig::from_toml(REACH).unwrap();
    c.train.steps = 60;
    c.validation.checkpoints = 3;
    c.validation.windows = 8;
    c.seed = seed;
    c
}

fn weights(dir: &Path) -> Vec<u8> {
    std::fs::read(dir.join("best/model.safetensors")).unwrap()
}

#[test]
fn same_seed_same_bits_and_resume_continues_bit_identically() {
    let dir = Scratch::new("dataset-determinism");
    let data = lerobot_fixture();
    let (a, b, c) = (
        dir.path().join("a"),
        dir.path().join("b"),
        dir.path().join("c"),
    );
    let ra = dataset::train(&data, &small(1), &a, false).unwrap();
    let rb = dataset::train(&data, &small(1), &b, false).unwrap();
    assert_eq!(ra, rb);
    assert_eq!(weights(&a), weights(&b));
    let rc = dataset::train(&data, &small(2), &c, false).unwrap();
    assert_ne!(weights(&a), weights(&c), "another seed, other weights");
    assert_ne!(ra.checkpoints, rc.checkpoints);
    // Interrupt `b` after its second checkpoint (drop the last one and the chosen model):
    // `--resume` continues from step 40 to the same bits.
    std::fs::remove_dir_all(b.join("best")).unwrap();
    std::fs::remove_dir_all(b.join("step-000060")).unwrap();
    let rb = dataset::train(&data, &small(1), &b, true).unwrap();
    assert_eq!(weights(&b), weights(&a));
    // The scores of steps 20 and 40 come back from validation.json (JSON keeps f64 to within
    // an ulp), step 60 is computed again.
    assert_eq!((rb.best_step, rb.checkpoints.len()), (ra.best_step, 3));
    for (x, y) in rb.checkpoints.iter().zip(&ra.checkpoints) {
        assert_eq!(x.step, y.step);
        assert!((x.flow_loss - y.flow_loss).abs() < 1e-12, "{x:?} {y:?}");
        assert!(
            (x.open_loop.nrmse - y.open_loop.nrmse).abs() < 1e-12,
            "{x:?} {y:?}"
        );
    }
    assert_eq!(rb.checkpoints[2], ra.checkpoints[2]);
    // Resuming with another task is refused.
    let err = dataset::train(&data, &small(3), &b, true).unwrap_err();
    assert!(format!("{err:#}").contains("task differs"), "{err:#}");
}

/// A NaN in a held-out episode is one error naming the episode, the frame and the key,
/// before any training (before: the validation metric came out NaN, was printed as "held-out
/// flow loss NaN", and the run exited 0 with a checkpoint chosen on it).
#[test]
fn a_nan_in_a_held_out_episode_is_an_error() {
    let dir = Scratch::new("dataset-nan");
    let data = dir.path().join("data");
    let last = 7;
    custom_dataset_with(&data, Some(last));
    let task = write(
        dir.path(),
        "task.toml",
        &CUSTOM
            .replace("held_out = 0.25", &format!("held_out_episodes = [{last}]"))
            .replace("steps = 300", "steps = 20")
            .replace("warmup = 20", "warmup = 2"),
    );
    let out = dir.path().join("run");
    let err = failed(&train(&data, &task, &out, &[]));
    assert!(
        err.contains("episode 7 (by position), frame 3: action.joint_delta[0] is NaN"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written before the error");
    assert!(!err.contains("panicked"), "{err}");
}
