//! `pir2 gr00t run gr00t-xarm-xhand` through the binary on tiny synthetic ONNX graphs
//! (`pir2_backends::gr00t::testing`, `$PIR2_PYTHON` after `source .native/env.sh`): a bounded
//! run against the in-process xArm6 + XHand emulators, and clear errors for a bad checkpoint,
//! an unknown task and an unreachable robot.
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use pir2_backends::gr00t::testing::{
    add_bpe_tokenizer, python_from_env, write_split_backbone, write_tiny_checkpoint,
};

fn checkpoint(name: &str, variant: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("pir2-cli-gr00t-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    write_tiny_checkpoint(&dir, variant, &python_from_env().unwrap()).unwrap();
    dir
}

fn run(ck: &Path, extra: &[&str]) -> (Output, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["gr00t", "run", "gr00t-xarm-xhand", "--checkpoint"])
        .arg(ck)
        .args(extra)
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    (out, text)
}

/// Robot addresses that reach no robot: an unreachable xArm and a missing XHand port.
const UNREACHABLE_ROBOT: [&str; 4] = ["--xarm", "127.0.0.1:1", "--xhand", "/nonexistent/ttyUSB9"];

/// `pir2 gr00t run` of `catch_book` on [`UNREACHABLE_ROBOT`], with `extra` flags.
fn on_unreachable_robot(ck: &Path, extra: &[&str]) -> (Output, String) {
    let mut args = vec!["--task", "catch_book"];
    args.extend_from_slice(extra);
    args.extend(UNREACHABLE_ROBOT);
    run(ck, &args)
}

/// `pir2 gr00t run` of `task` on the in-process emulators for `ticks` ticks, with `extra` flags.
fn emulated(ck: &Path, task: &str, ticks: u32, extra: &[&str]) -> (Output, String) {
    let ticks = ticks.to_string();
    let mut args = vec!["--task", task, "--emulate", "--ticks", &ticks];
    args.extend_from_slice(extra);
    run(ck, &args)
}

/// [`emulated`] with `--json`: the run must succeed; returns its JSON report and output.
fn emulated_json(ck: &Path, task: &str, ticks: u32, extra: &[&str]) -> (serde_json::Value, String) {
    let json = ck.join("run.json");
    let _ = std::fs::remove_file(&json);
    let mut args = extra.to_vec();
    args.extend_from_slice(&["--json", json.to_str().unwrap()]);
    let (out, text) = emulated(ck, task, ticks, &args);
    assert!(out.status.success(), "{extra:?}: {text}");
    let v = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    (v, text)
}

#[test]
fn run_gr00t_on_the_emulators_end_to_end() {
    let ck = checkpoint("e2e", "");
    let (v, text) = emulated_json(&ck, "catch the book", 50, &[]);
    eprintln!("{text}");
    assert_eq!(v["prompt"], "catch the book");
    assert_eq!(v["trace"]["ticks"], 50);
    assert!(v["trace"]["swaps"].as_u64().unwrap() >= 1);
    // Every tick's command reached the emulated hand; the backbone refreshed the cache.
    assert!(v["hand_commands"].as_u64().unwrap() >= 50);
    assert!(v["camera_frames"].as_u64().unwrap() >= 3);
    let calls = v["trace"]["calls"].as_array().unwrap();
    assert!(!calls.is_empty());
    assert!(calls.iter().all(|c| c["d_vis"].as_u64().unwrap() <= 5));
    assert!(text.contains("ticks 50"), "{text}");
    std::fs::remove_dir_all(&ck).ok();
}

#[test]
fn run_gr00t_uses_the_checkpoints_tokenizer_json() {
    use pir2_backends::gr00t::testing::add_bpe_tokenizer;

    let ck = checkpoint("bpe", "");
    add_bpe_tokenizer(&ck).unwrap();
    let (v, _) = emulated_json(&ck, "catch_book", 25, &[]);
    let slow = v["slow"].as_str().unwrap();
    assert!(
        slow.contains("tokenizer.json") && slow.contains("chat template"),
        "{slow}"
    );
    assert_eq!(v["trace"]["ticks"], 25);
    // A broken tokenizer.json stops the run before the robot moves, naming the file.
    std::fs::write(ck.join("tokenizer.json"), "not json").unwrap();
    let (out, text) = emulated(&ck, "catch_book", 5, &[]);
    assert!(!out.status.success());
    assert!(
        text.contains("tokenizer.json") && text.contains("not a Hugging Face tokenizer"),
        "{text}"
    );
    std::fs::remove_dir_all(&ck).ok();
}

#[test]
fn run_gr00t_errors_name_the_problem() {
    let bad = checkpoint("bad", "wrong_name");
    // A graph that breaks the export contract: the file and the tensor are named.
    let (out, text) = emulated(&bad, "catch_book", 5, &[]);
    assert!(!out.status.success());
    assert!(
        text.contains("dit.onnx") && text.contains("sa_emb"),
        "{text}"
    );
    // An unknown task lists the known ones.
    let (out, text) = emulated(&bad, "juggle", 5, &[]);
    assert!(!out.status.success());
    assert!(
        text.contains("unknown task") && text.contains("catch_book"),
        "{text}"
    );
    // A missing checkpoint directory.
    let (out, text) = run(&bad.join("nope"), &["--task", "catch_book", "--emulate"]);
    assert!(!out.status.success());
    assert!(text.contains("does not exist"), "{text}");
    // A bad checkpoint fails before any robot is connected (the xArm address is unreachable,
    // yet the error is the contract's).
    let (out, text) = on_unreachable_robot(&bad, &["--synthetic-camera"]);
    assert!(!out.status.success());
    assert!(
        text.contains("dit.onnx") && !text.contains("connecting to the xArm"),
        "{text}"
    );
    // An unreachable robot (valid checkpoint).
    let good = checkpoint("good-unreachable", "");
    let (out, text) = on_unreachable_robot(&good, &[]);
    assert!(!out.status.success());
    assert!(text.contains("--synthetic-camera"), "{text}");
    let (out, text) = on_unreachable_robot(&good, &["--synthetic-camera"]);
    assert!(!out.status.success());
    assert!(
        text.contains("connecting to the xArm at 127.0.0.1:1"),
        "{text}"
    );
    assert!(!text.contains("panicked"), "{text}");
    std::fs::remove_dir_all(&bad).ok();
    std::fs::remove_dir_all(&good).ok();
}

/// The embodiment's `[safety]` table reaches `pir2 gr00t run`: a bad value is one error naming the
/// field, before any robot is connected; a valid table (tighter arm limits, a shorter grace)
/// runs (before: there was no such table, and `pir2 gr00t run` used fixed 25 Hz limits).
#[test]
fn run_gr00t_takes_the_embodiments_safety_table() {
    let ck = checkpoint("safety-table", "");
    let toml_path = ck.join("embodiment.toml");
    let original = std::fs::read_to_string(&toml_path).unwrap();
    assert!(original.contains("slow_grace_ms = 200.0"), "{original}");

    std::fs::write(
        &toml_path,
        original.replace("slow_grace_ms = 200.0", "slow_grace_ms = 0.0"),
    )
    .unwrap();
    let (out, text) = emulated(&ck, "catch_book", 25, &[]);
    assert!(!out.status.success());
    assert!(text.contains("safety.slow_grace_ms"), "{text}");

    std::fs::write(
        &toml_path,
        format!("{original}\n[safety.limits.hand_joints]\nmax_velocity = -1.0\n"),
    )
    .unwrap();
    let (out, text) = emulated(&ck, "catch_book", 25, &[]);
    assert!(!out.status.success());
    assert!(
        text.contains("safety.limits.hand_joints.max_velocity"),
        "{text}"
    );

    std::fs::write(
        &toml_path,
        format!("{original}\n[safety.limits.wrist]\nmax_velocity = 1.0\n"),
    )
    .unwrap();
    let (out, text) = emulated(&ck, "catch_book", 25, &[]);
    assert!(!out.status.success());
    assert!(text.contains("safety.limits.wrist"), "{text}");

    std::fs::write(
        &toml_path,
        format!(
            "{}\n[safety.limits.arm_joints]\nmax_velocity = 0.5\ntracking_error = 0.3\n",
            original.replace("slow_grace_ms = 200.0", "slow_grace_ms = 150.0")
        ),
    )
    .unwrap();
    let (out, text) = emulated(&ck, "catch_book", 25, &[]);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("ticks 25"), "{text}");
    std::fs::remove_dir_all(&ck).ok();
}

/// Every row of the paper's robot table runs from one `pir2 gr00t run` command on the emulators
/// and is named in the summary and `--json`; a mode the head was not trained for is refused
/// by name before any robot is connected (before: πR² async with n = 2 was hard-coded).
#[test]
fn run_gr00t_runs_every_mode_of_the_robot_table() {
    let ck = checkpoint("modes", "");
    let toml_path = ck.join("embodiment.toml");
    let original = std::fs::read_to_string(&toml_path).unwrap();
    assert!(original.contains("trained = \"pi_r2\""), "{original}");
    let trained_as = |p: &str| {
        std::fs::write(
            &toml_path,
            original.replace("trained = \"pi_r2\"", &format!("trained = \"{p}\"")),
        )
        .unwrap()
    };
    for (trained, mode, extra, kind, says) in [
        (
            "flow",
            "sync_flow",
            &["--h", "10"][..],
            "sync_flow",
            "sync flow (K = 4, h = 10)",
        ),
        (
            "flow",
            "naive_async",
            &["--ensemble", "0.1"][..],
            "naive_async",
            "naive async (K = 4, temporal ensembling m = 0.1)",
        ),
        (
            "flow",
            "inference_rtc",
            &["--rtc-overlap", "8"][..],
            "inference_rtc",
            "N1.7 inference-time RTC (K = 4, overlap = 8, ramp rate = 5)",
        ),
        (
            "rtc",
            "rtc",
            &[][..],
            "train_time_rtc",
            "train-time RTC (K = 4)",
        ),
        (
            "pi_r2",
            "pir2_sync",
            &[][..],
            "pi_r2_sync",
            "πR² w/o async (n = 2",
        ),
        (
            "pi_r2",
            "pir2_async",
            &[][..],
            "pi_r2_async",
            "πR² async (n = 2",
        ),
    ] {
        trained_as(trained);
        let mut args = vec!["--mode", mode];
        args.extend_from_slice(extra);
        let (v, text) = emulated_json(&ck, "catch_book", 40, &args);
        assert!(text.contains(&format!("mode: {says}")), "{mode}: {text}");
        assert_eq!(v["mode"]["kind"], kind, "{mode}");
        assert_eq!(v["trace"]["ticks"], 40, "{mode}");
        assert!(v["trace"]["swaps"].as_u64().unwrap() >= 1, "{mode}");
        if mode == "sync_flow" {
            // The robot holds while each synchronous call runs.
            assert!(v["trace"]["holds"].as_u64().unwrap() >= 1, "{text}");
        }
    }
    // N1.7's RTC with a ramp rate that is not a rate: one error naming it, nothing started.
    trained_as("flow");
    let (out, text) = emulated(
        &ck,
        "catch_book",
        5,
        &["--mode", "inference_rtc", "--rtc-ramp-rate", "0"],
    );
    assert!(!out.status.success());
    assert!(text.contains("rtc_ramp_rate = 0"), "{text}");
    assert!(!text.contains("ticks 5"), "{text}");
    // A mode the head was not trained for: one error naming both, nothing started.
    trained_as("pi_r2");
    let (out, text) = emulated(&ck, "catch_book", 5, &["--mode", "rtc"]);
    assert!(!out.status.success());
    assert!(
        text.contains("mode rtc") && text.contains("trained = \"pi_r2\""),
        "{text}"
    );
    assert!(!text.contains("ticks 5"), "{text}");
    std::fs::remove_dir_all(&ck).ok();
}

/// `--ep cuda|tensorrt` on the CPU build of ONNX Runtime (what CI installs): one error naming
/// the library and the provider, before any robot is connected (the emulators are never
/// started: no "warm-up done" line). `pir2 gr00t bench` prints the one-NFE latency and the
/// `d` it implies at 25 Hz, on the CPU.
#[test]
fn gpu_providers_are_refused_by_name_and_bench_gr00t_reports_the_implied_delay() {
    let ck = checkpoint("ep", "");
    for ep in ["cuda", "tensorrt"] {
        let (out, text) = emulated(&ck, "catch the book", 5, &["--ep", ep]);
        assert!(!out.status.success(), "{ep}: {text}");
        let provider = if ep == "cuda" {
            "CUDAExecutionProvider"
        } else {
            "TensorrtExecutionProvider"
        };
        assert!(
            text.contains(provider) && text.contains("onnxruntime-gpu"),
            "{ep}: {text}"
        );
        assert!(!text.contains("warm-up done"), "{ep}: {text}");
        eprintln!("{text}");
    }
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args([
            "gr00t",
            "bench",
            "--seconds",
            "0.2",
            "--task",
            "catch the book",
        ])
        .arg("--checkpoint")
        .arg(&ck)
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{text}");
    eprintln!("{text}");
    for part in [
        "on CPU",
        "one NFE (batch 1): median",
        "at 25 Hz: πR² (one NFE per call) d = ",
        "backbone (`backbone.onnx`), one frame of 1 640×480 view(s)",
    ] {
        assert!(text.contains(part), "`{part}` missing: {text}");
    }
    std::fs::remove_dir_all(&ck).ok();
}

/// `--frames DIR` replays recorded frames as the camera through GR00T's preprocessing: a run
/// on the emulators driven by the committed test frames, and an empty folder refused by name
/// before any robot is connected.
#[test]
fn a_replayed_frame_folder_drives_a_run_end_to_end() {
    let ck = checkpoint("frames", "");
    let frames =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-backends/tests/data/gr00t_image");
    let (v, _) = emulated_json(
        &ck,
        "catch the book",
        40,
        &["--frames", frames.to_str().unwrap(), "--frame-ms", "20"],
    );
    assert!(
        v["slow"].as_str().unwrap().contains("4 recorded frames"),
        "{v}"
    );
    assert!(v["camera_frames"].as_u64().unwrap() >= 2, "{v}");
    assert_eq!(v["trace"]["ticks"], 40);
    let empty = ck.join("no-frames");
    std::fs::create_dir_all(&empty).unwrap();
    let (out, text) = emulated(
        &ck,
        "catch the book",
        5,
        &["--frames", empty.to_str().unwrap()],
    );
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains("no .png") && text.contains("no-frames"),
        "{text}"
    );
    assert!(!text.contains("warm-up done"), "{text}");
    std::fs::remove_dir_all(&ck).ok();
}

/// One `--frames` folder per camera view: a two-view checkpoint runs on two replayed cameras
/// joined into one slow frame, and a count that is not the embodiment's views is one error
/// naming both, before any robot.
#[test]
fn one_replayed_camera_per_view_drives_a_multi_view_run() {
    use pir2_backends::gr00t::EmbodimentConfig;
    let ck = checkpoint("views", "");
    let frames =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-backends/tests/data/gr00t_image");
    let f = frames.to_str().unwrap();
    // The one-view checkpoint refuses two cameras.
    let (out, text) = emulated(&ck, "catch the book", 5, &["--frames", f, "--frames", f]);
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains("2 --frames given")
            && text.contains("1 camera view")
            && text.contains("prompt.chat.images"),
        "{text}"
    );
    assert!(!text.contains("warm-up done"), "{text}");
    // A two-view embodiment: two folders run; one is refused.
    let path = ck.join("embodiment.toml");
    let mut cfg = EmbodimentConfig::load(&path).unwrap();
    cfg.prompt.chat.images = 2;
    std::fs::write(&path, cfg.to_toml().unwrap()).unwrap();
    let (v, _) = emulated_json(
        &ck,
        "catch the book",
        40,
        &["--frames", f, "--frames", f, "--frame-ms", "20"],
    );
    let slow = v["slow"].as_str().unwrap();
    assert!(slow.contains("view 0: 4 recorded frames"), "{v}");
    assert!(slow.contains("view 1: 4 recorded frames"), "{v}");
    assert!(v["camera_frames"].as_u64().unwrap() >= 2, "{v}");
    assert_eq!(v["trace"]["ticks"], 40);
    let (out, text) = emulated(&ck, "catch the book", 5, &["--frames", f]);
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains("1 --frames given") && text.contains("2 camera view"),
        "{text}"
    );
    // The synthetic camera of --emulate gives every view.
    let (v, _) = emulated_json(&ck, "catch the book", 20, &[]);
    assert!(v["slow"].as_str().unwrap().contains("2 view(s)"), "{v}");
    std::fs::remove_dir_all(&ck).ok();
}

/// `--camera /dev/videoN`: a path that is no camera is one error naming it, before any robot
/// is connected (the xArm address is unreachable, yet the error is the camera's); the camera
/// options are checked by the argument parser (no camera is needed: CI has none).
#[test]
fn a_bad_camera_device_is_one_error_naming_it_before_any_robot() {
    let ck = checkpoint("camera", "");
    for (dev, why) in [
        ("/dev/video-pir2-missing", "No such file"),
        ("/dev/null", "not a V4L2 device"),
    ] {
        let (out, text) = on_unreachable_robot(&ck, &["--camera", dev]);
        eprintln!("{text}");
        assert!(!out.status.success(), "{text}");
        assert!(
            text.contains(&format!("camera {dev}")) && text.contains(why),
            "{text}"
        );
        assert!(!text.contains("connecting to the xArm"), "{text}");
        assert!(!text.contains("panicked"), "{text}");
    }
    let refused = [
        vec!["--camera", "/dev/video0", "--frames", "/tmp"],
        vec!["--camera", "/dev/video0", "--synthetic-camera"],
        vec!["--camera-size", "640x480"],
        vec!["--camera", "/dev/video0", "--camera-format", "h264"],
    ];
    for extra in refused {
        let (out, text) = on_unreachable_robot(&ck, &extra);
        assert!(!out.status.success(), "{extra:?}: {text}");
        assert!(
            text.contains("error:") && !text.contains("connecting to the xArm"),
            "{extra:?}: {text}"
        );
    }
    let (out, text) = on_unreachable_robot(&ck, &["--camera", "/dev/null", "--camera-size", "640"]);
    assert!(!out.status.success());
    assert!(text.contains("camera size \"640\""), "{text}");
    std::fs::remove_dir_all(&ck).ok();
}

/// Relative actions (GR00T N1.7's `use_relative_action`) on the emulators: the arm group
/// made relative to the arm state with per-slot `relative_action` statistics runs in πR²
/// async, train-time RTC, naive async with temporal ensembling and N1.7's inference-time
/// RTC, and the summary and
/// `--json` name the relative group; a statistic of the wrong shape is one error naming the
/// key and both shapes, before any robot is connected.
#[test]
fn relative_arm_actions_run_on_the_emulators() {
    use pir2_backends::gr00t::testing::make_relative;
    let ck = checkpoint("relative", "");
    make_relative(&ck, &["arm_joints"]).unwrap();
    let toml_path = ck.join("embodiment.toml");
    let original = std::fs::read_to_string(&toml_path).unwrap();
    assert!(original.contains("relative = true"), "{original}");
    for (trained, mode, extra) in [
        ("pi_r2", "pir2_async", &[][..]),
        ("rtc", "rtc", &[][..]),
        ("flow", "naive_async", &["--ensemble", "0.1"][..]),
        ("flow", "inference_rtc", &[][..]),
    ] {
        std::fs::write(
            &toml_path,
            original.replace("trained = \"pi_r2\"", &format!("trained = \"{trained}\"")),
        )
        .unwrap();
        let mut args = vec!["--mode", mode];
        args.extend_from_slice(extra);
        let (v, text) = emulated_json(&ck, "catch_book", 40, &args);
        assert!(
            text.contains("relative actions: arm_joints → arm_joints"),
            "{mode}: {text}"
        );
        assert_eq!(
            v["relative_actions"][0], "arm_joints → arm_joints",
            "{mode}"
        );
        assert_eq!(v["trace"]["ticks"], 40, "{mode}");
        assert!(v["trace"]["swaps"].as_u64().unwrap() >= 1, "{mode}");
        assert!(v["hand_commands"].as_u64().unwrap() >= 40, "{mode}");
    }

    let stats_path = ck.join("statistics.json");
    let mut stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats_path).unwrap()).unwrap();
    let min = &mut stats["new_embodiment"]["relative_action"]["arm_joints"]["min"];
    min.as_array_mut().unwrap().truncate(16);
    std::fs::write(&stats_path, stats.to_string()).unwrap();
    std::fs::write(&toml_path, &original).unwrap();
    let (out, text) = emulated(&ck, "catch_book", 5, &[]);
    assert!(!out.status.success());
    assert!(
        text.contains("new_embodiment.relative_action.arm_joints.min")
            && text.contains("has shape [16, 6], expected [50, 6]"),
        "{text}"
    );
    assert!(!text.contains("warm-up done"), "{text}");
    std::fs::remove_dir_all(&ck).ok();
}

/// A checkpoint with GR00T's split backbone export (`vit_fp32.onnx` + `llm_fp32.onnx` + the
/// token table in `model.safetensors`, tiny stand-ins) instead of a fused `backbone.onnx`:
/// `pir2 gr00t run` and `pir2 gr00t bench` pick it by its files and say so; a half split set is one
/// error naming the missing file, before any robot; GR00T's bfloat16 LLM runs with its
/// boundary converted, and one whose bfloat16 ops the CPU provider cannot run is one error.
#[test]
fn run_gr00t_takes_gr00ts_split_backbone_export() {
    use pir2_backends::gr00t::EmbodimentConfig;
    let ck = checkpoint("split", "");
    add_bpe_tokenizer(&ck).unwrap();
    let path = ck.join("embodiment.toml");
    let mut cfg = EmbodimentConfig::load(&path).unwrap();
    cfg.vision.patch_size = 4;
    std::fs::write(&path, cfg.to_toml().unwrap()).unwrap();
    write_split_backbone(&ck, "catch the book", "", &python_from_env().unwrap()).unwrap();
    let (v, text) = emulated_json(&ck, "catch the book", 30, &[]);
    let slow = v["slow"].as_str().unwrap();
    assert!(
        slow.contains("split export `vit_fp32.onnx` + `llm_fp32.onnx`"),
        "{slow}\n{text}"
    );
    assert!(v["camera_frames"].as_u64().unwrap() >= 1, "{v}");
    assert_eq!(v["trace"]["ticks"], 30);
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args([
            "gr00t",
            "bench",
            "--seconds",
            "0.1",
            "--task",
            "catch the book",
        ])
        .arg("--checkpoint")
        .arg(&ck)
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("backbone (GR00T's split export"), "{text}");
    std::fs::remove_file(ck.join("onnx/vit_fp32.onnx")).unwrap();
    let (out, text) = emulated(&ck, "catch the book", 5, &[]);
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains("vit_fp32.onnx")
            && text.contains("missing")
            && !text.contains("warm-up done"),
        "{text}"
    );
    // GR00T's default bfloat16 LLM (`llm_bf16.onnx`, boundary Casts around an f32 stand-in):
    // run with the conversion at its boundary, named in the slow-channel line.
    let python = python_from_env().unwrap();
    std::fs::remove_file(ck.join("onnx/llm_fp32.onnx")).unwrap();
    write_split_backbone(&ck, "catch the book", "llm_bf16", &python).unwrap();
    let (v, text) = emulated_json(&ck, "catch the book", 10, &[]);
    let slow = v["slow"].as_str().unwrap();
    assert!(
        slow.contains("`llm_bf16.onnx`") && slow.contains("LLM inputs_embeds bfloat16"),
        "{slow}\n{text}"
    );
    // A bfloat16 op inside, on the CPU provider: one error naming the file, the op and the
    // way out, before any robot.
    for f in ["onnx/vit_fp32.onnx", "onnx/llm_bf16.onnx"] {
        std::fs::remove_file(ck.join(f)).unwrap();
    }
    write_split_backbone(&ck, "catch the book", "llm_bf16_matmul", &python).unwrap();
    let (out, text) = emulated(&ck, "catch the book", 5, &[]);
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains("llm_bf16.onnx")
            && text.contains("MatMul")
            && text.contains("CPUExecutionProvider")
            && text.contains("--ep cuda")
            && !text.contains("warm-up done"),
        "{text}"
    );
    std::fs::remove_dir_all(&ck).ok();
}
