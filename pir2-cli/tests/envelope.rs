//! The safety envelope through the binary (`pir2 gr00t run gr00t-xarm-xhand` on the in-process
//! emulators, tiny synthetic ONNX graphs from `$PIR2_PYTHON`): the robot's ceiling bounds
//! every checkpoint and flag, statistics that would invert or blow up the actions are refused,
//! the `--json` folder is checked before the robot moves, and the limits in force are printed
//! and written. Each refused case failed open on the code before these checks (it ran).
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};
use std::process::Command;

use pir2_backends::gr00t::testing::{python_from_env, write_tiny_checkpoint};

fn checkpoint(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("pir2-envelope-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    write_tiny_checkpoint(&dir, "", &python_from_env().unwrap()).unwrap();
    dir
}

/// `pir2 gr00t run` on the emulators for 10 ticks with `extra` flags: (success, output).
fn run(ck: &Path, extra: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args([
            "gr00t",
            "run",
            "gr00t-xarm-xhand",
            "--task",
            "catch_book",
            "--emulate",
        ])
        .args(["--ticks", "10", "--checkpoint"])
        .arg(ck)
        .args(extra)
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

/// Run with `embodiment.toml` edited by `edit`; the run must be refused with every `want`
/// in its output and before the robot came under control.
fn refused_with_embodiment(ck: &Path, edit: &dyn Fn(&str) -> String, want: &[&str]) {
    let path = ck.join("embodiment.toml");
    let original = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, edit(&original)).unwrap();
    let (ok, text) = run(ck, &[]);
    std::fs::write(&path, &original).unwrap();
    assert!(!ok, "ran: {text}");
    for w in want {
        assert!(text.contains(w), "missing {w:?} in: {text}");
    }
    assert!(!text.contains("under control"), "the robot moved: {text}");
}

#[test]
fn a_checkpoint_or_a_flag_may_only_tighten_the_envelope() {
    let ck = checkpoint("tighten");
    let limits = |table: &str| {
        let table = table.to_string();
        move |t: &str| format!("{t}\n{table}\n")
    };
    // Joint ranges, speed, acceleration and tracking beyond the xArm6 + XHand ceiling.
    refused_with_embodiment(
        &ck,
        &limits("[safety.limits.hand_joints]\nupper = [100.0, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6]"),
        &["safety.limits.hand_joints.upper[0] = 100", "only tighten"],
    );
    refused_with_embodiment(
        &ck,
        &limits("[safety.limits.arm_joints]\nmax_velocity = 1000.0"),
        &[
            "safety.limits.arm_joints.max_velocity[0] = 1000",
            "ceiling 4",
        ],
    );
    refused_with_embodiment(
        &ck,
        &limits("[safety.limits.arm_joints]\nmax_accel = 1e9"),
        &["safety.limits.arm_joints.max_accel"],
    );
    refused_with_embodiment(
        &ck,
        &limits("[safety.limits.hand_joints]\ntracking_error = 5.0"),
        &["safety.limits.hand_joints.tracking_error"],
    );
    // The grace and the control rate have ceilings too.
    refused_with_embodiment(
        &ck,
        &|t| t.replace("slow_grace_ms = 200.0", "slow_grace_ms = 1000000000.0"),
        &["safety.slow_grace_ms must be in (0, 1000]"],
    );
    let hz = |t: &str| {
        let line = t.lines().find(|l| l.starts_with("control_hz")).unwrap();
        t.replace(line, "control_hz = 1000000000.0")
    };
    refused_with_embodiment(&ck, &hz, &["control_hz must be in (0, 250]"]);
    // A flag may shorten the grace, never lengthen it.
    let (ok, text) = run(&ck, &["--slow-grace-ms", "1e12"]);
    assert!(!ok && text.contains("may only shorten"), "{text}");
    let (ok, text) = run(&ck, &["--slow-grace-ms", "150"]);
    assert!(ok, "{text}");
    assert!(text.contains("stale-slow grace 150 ms"), "{text}");
    // The control watchdog has a ceiling an operator cannot pass.
    let (ok, text) = run(&ck, &["--stall-limit-ms", "60000"]);
    assert!(
        !ok && text.contains("--stall-limit-ms must be in (0, 5000]"),
        "{text}"
    );
    // Tighter limits run, and are what is printed and written.
    let path = ck.join("embodiment.toml");
    let original = std::fs::read_to_string(&path).unwrap();
    std::fs::write(
        &path,
        format!("{original}\n[safety.limits.arm_joints]\nmax_velocity = 0.5\n"),
    )
    .unwrap();
    let json = ck.join("run.json");
    let (ok, text) = run(&ck, &["--json", json.to_str().unwrap()]);
    assert!(ok, "{text}");
    assert!(text.contains("limits in force: control"), "{text}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let l = &v["limits"];
    assert_eq!(l["max_velocity"][0], 0.5, "{l}");
    assert_eq!(l["max_velocity"].as_array().unwrap().len(), 18, "{l}");
    assert_eq!(l["slow_grace_ms"], 200.0, "{l}");
    assert_eq!(l["stall_limit_ms"], 1000.0, "{l}");
    std::fs::remove_dir_all(&ck).ok();
}

#[test]
fn statistics_that_invert_or_blow_up_the_actions_are_refused() {
    let ck = checkpoint("stats");
    let path = ck.join("statistics.json");
    let original = std::fs::read_to_string(&path).unwrap();
    let edit = |f: &dyn Fn(&mut serde_json::Value)| {
        let mut v: serde_json::Value = serde_json::from_str(&original).unwrap();
        let emb = v.as_object_mut().unwrap().values_mut().next().unwrap();
        f(emb);
        std::fs::write(&path, v.to_string()).unwrap();
        let r = run(&ck, &[]);
        std::fs::write(&path, &original).unwrap();
        r
    };
    // The first action group's statistics, whichever the tiny checkpoint names.
    let first_action = |emb: &mut serde_json::Value| -> (String, serde_json::Value) {
        let (name, g) = emb["action"].as_object().unwrap().iter().next().unwrap();
        (name.clone(), g.clone())
    };
    let (ok, text) = edit(&|emb| {
        let (name, mut g) = first_action(emb);
        let max = g["max"][0].as_f64().unwrap();
        g["min"][0] = serde_json::json!(max + 1.0);
        emb["action"][&name] = g;
    });
    assert!(!ok && text.contains("inverted"), "{text}");
    let (ok, text) = edit(&|emb| {
        let (name, mut g) = first_action(emb);
        g["max"][0] = serde_json::json!(1e30);
        emb["action"][&name] = g;
    });
    assert!(!ok && text.contains("1e30"), "{text}");
    assert!(!text.contains("under control"), "{text}");
    std::fs::remove_dir_all(&ck).ok();
}

#[test]
fn the_json_folder_is_checked_before_the_robot_moves() {
    let ck = checkpoint("json");
    let missing = ck.join("no-such-dir").join("run.json");
    let (ok, text) = run(&ck, &["--json", missing.to_str().unwrap()]);
    assert!(!ok, "{text}");
    assert!(
        text.contains("does not exist") && text.contains("no-such-dir"),
        "{text}"
    );
    assert!(
        !text.contains("under control") && !text.contains("ticks 10"),
        "{text}"
    );
    std::fs::remove_dir_all(&ck).ok();
}
