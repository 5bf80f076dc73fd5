//! A MuJoCo Playground LeapCubeReorient policy as an expert on the paper's environment:
//! `scripts/playground-expert.py` converts an ONNX graph of the published policy's shape, and
//! `PpoExpert` (tanh head, goal-relative orientation from the paper's observation, previous
//! action) must reproduce onnxruntime's actions on observations built the playground's way
//! with MuJoCo's own quaternion functions. Needs `PIR2_PYTHON` (a Python with `onnx`,
//! `onnxruntime`, `mujoco`, `numpy`: `scripts/setup-native.sh`).
#![cfg(feature = "mujoco")]

use std::path::{Path, PathBuf};
use std::process::Command;

use pir2_schedule::Rng;
use pir2_sim::leap::math::{self, blue_side_up_goals, rot_rows_23};
use pir2_sim::leap::ppo::{nearest_goal_rows, OrientationInput, PpoExpert, Squash};

fn python() -> String {
    std::env::var("PIR2_PYTHON").expect(
        "PIR2_PYTHON must name a Python with onnx, onnxruntime, mujoco and numpy \
         (bash scripts/setup-native.sh; source .native/env.sh)",
    )
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn run(cmd: &mut Command) -> String {
    let out = cmd.output().expect("spawn python");
    assert!(
        out.status.success(),
        "{cmd:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn converted_playground_policy_matches_onnxruntime() {
    let dir = std::env::temp_dir().join(format!("pir2-playground-expert-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let py = python();
    run(Command::new(&py)
        .arg(repo().join("pir2-sim/tests/playground_expert.py"))
        .arg(&dir)
        .arg("3"));
    let weights = dir.join("expert.safetensors");
    run(Command::new(&py)
        .arg(repo().join("scripts/playground-expert.py"))
        .arg(dir.join("policy.onnx"))
        .arg(&weights));
    // The converter never overwrites.
    let again = Command::new(&py)
        .arg(repo().join("scripts/playground-expert.py"))
        .arg(dir.join("policy.onnx"))
        .arg(&weights)
        .output()
        .unwrap();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("refusing to overwrite"));

    let mut ex = PpoExpert::load(&weights).expect("load the converted expert");
    assert_eq!(ex.squash(), Squash::Tanh);
    assert_eq!(ex.orientation_input(), OrientationInput::NearestGoal);
    assert!(ex.uses_prev_action());
    let cases: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("cases.json")).unwrap()).unwrap();
    let f = |v: &serde_json::Value| -> Vec<f32> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap() as f32)
            .collect()
    };
    ex.reset();
    let mut worst = 0.0f32;
    let cases = cases["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 40);
    for c in cases {
        let a = ex.act(&f(&c["fast"]), &f(&c["slow"]));
        for (x, y) in a.iter().zip(f(&c["action"])) {
            worst = worst.max((x - y).abs());
        }
    }
    assert!(
        worst < 1e-4,
        "largest action difference vs onnxruntime: {worst}"
    );

    // Saving keeps the options; a malformed option is one error naming it.
    let back = dir.join("back.safetensors");
    ex.save(&back).unwrap();
    let ex2 = PpoExpert::load(&back).unwrap();
    assert_eq!(ex2.squash(), Squash::Tanh);
    assert_eq!(ex2.orientation_input(), OrientationInput::NearestGoal);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn nearest_goal_rows_are_the_rotation_from_the_nearest_goal() {
    let goals = blue_side_up_goals();
    let mut rng = Rng::new(11);
    for _ in 0..200 {
        let q = math::uniform_quat(&mut rng);
        let rows = rot_rows_23(&q);
        let r32: [f32; 6] = std::array::from_fn(|k| rows[k] as f32);
        let got = nearest_goal_rows(&r32);
        let (g, _) = pir2_sim::leap::ppo::task::nearest_goal(&q, &goals);
        let want = rot_rows_23(&math::mul_inv(&q, &g));
        for k in 0..6 {
            assert!(
                (got[k] as f64 - want[k]).abs() < 1e-5,
                "q {q:?}: row value {k}: {} vs {}",
                got[k],
                want[k]
            );
        }
    }
}
