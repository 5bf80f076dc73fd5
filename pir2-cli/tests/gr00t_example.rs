//! The README's two-command walkthrough through the binary: `pir2 gr00t example DIR` (pure
//! Rust, seeded) then `pir2 gr00t run gr00t-xarm-xhand --checkpoint DIR --emulate` for a short
//! time; the same seed writes the same bytes; a second `example` into the non-empty DIR is
//! refused and changes nothing. Needs ONNX Runtime for the run (`source .native/env.sh`); no
//! Python.
#![cfg(feature = "gr00t")]

use std::ffi::OsStr;
use std::path::Path;

mod common;
use common::gr00t::{pir2_text as pir2, read_json, run_emulated_seconds};
use common::Scratch;

fn example(dir: &Path, seed: &str) -> (std::process::Output, String) {
    pir2(&[
        OsStr::new("gr00t"),
        OsStr::new("example"),
        dir.as_os_str(),
        OsStr::new("--seed"),
        OsStr::new(seed),
    ])
}

/// Every file under `dir` (relative path, bytes), sorted.
fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<(String, Vec<u8>)>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p.strip_prefix(root).unwrap().display().to_string();
                out.push((rel, std::fs::read(&p).unwrap()));
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

#[test]
fn example_checkpoint_runs_on_the_emulators_and_is_never_overwritten() {
    let scratch = Scratch::new("gr00t-example");
    let ck = scratch.path().join("ex");
    let (out, text) = example(&ck, "7");
    assert!(out.status.success(), "example: {text}");
    for f in [
        "onnx/state_encoder.onnx",
        "onnx/action_encoder.onnx",
        "onnx/dit.onnx",
        "onnx/action_decoder.onnx",
        "onnx/backbone.onnx",
        "pir2_gr00t.safetensors",
        "tokenizer.json",
        "embodiment.toml",
        "statistics.json",
        "embodiment_id.json",
        "head/config.json",
        "head/model.safetensors",
    ] {
        assert!(ck.join(f).is_file(), "{f} missing: {text}");
    }
    let written = snapshot(&ck);

    // Seeded: the same seed writes the same bytes, another seed other weights.
    let again = scratch.path().join("ex-again");
    let (out, text) = example(&again, "7");
    assert!(out.status.success(), "example: {text}");
    assert!(snapshot(&again) == written, "same seed, different files");
    let other = scratch.path().join("ex-other");
    let (out, text) = example(&other, "8");
    assert!(out.status.success(), "example: {text}");
    assert!(snapshot(&other) != written, "another seed, same files");

    // The walkthrough's run, on the emulators for 2 s.
    let json = scratch.path().join("run.json");
    let (out, text) = run_emulated_seconds(&ck, "2", &[OsStr::new("--json"), json.as_os_str()]);
    eprintln!("{text}");
    assert!(out.status.success(), "run: {text}");
    let v = read_json(&json);
    assert_eq!(v["mode"]["kind"], "pi_r2_async", "{v}");
    let ticks = v["trace"]["ticks"].as_u64().unwrap();
    assert_eq!(ticks, 50, "2 s at 25 Hz: {v}");
    assert!(v["trace"]["swaps"].as_u64().unwrap() >= 1, "{v}");
    assert!(v["head"].as_str().unwrap().contains("ONNX"), "{v}");

    // A second `example` into the non-empty directory: refused by name, nothing changed.
    let (out, text) = example(&ck, "9");
    assert!(!out.status.success(), "overwrote: {text}");
    assert!(
        text.contains(&ck.display().to_string()) && text.contains("not empty"),
        "{text}"
    );
    assert!(
        snapshot(&ck) == written,
        "the refused example changed files"
    );
    // No partial directory is left next to it.
    let leftovers: Vec<_> = std::fs::read_dir(scratch.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".partial"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

/// `pir2 gr00t bench --train` on the example's head: a few training steps at a tiny batch,
/// its `--json` with finite positive times; `--device cuda` in a build without feature `cuda`
/// is one error naming the feature (never a CPU run); `--train` with `--task` is refused.
#[test]
fn bench_train_times_training_steps_of_the_example_head() {
    let scratch = Scratch::new("gr00t-bench-train");
    let ck = scratch.path().join("ex");
    let (out, text) = example(&ck, "3");
    assert!(out.status.success(), "example: {text}");
    let head = ck.join("head");
    let json = scratch.path().join("bench.json");
    // `pir2 gr00t bench --train --checkpoint HEAD EXTRA…`.
    let bench = |extra: &[&OsStr]| {
        let mut args = vec![
            OsStr::new("gr00t"),
            OsStr::new("bench"),
            OsStr::new("--train"),
            OsStr::new("--checkpoint"),
            head.as_os_str(),
        ];
        args.extend_from_slice(extra);
        pir2(&args)
    };
    let (out, text) = bench(&[
        OsStr::new("--batch"),
        OsStr::new("4"),
        OsStr::new("--steps"),
        OsStr::new("2"),
        OsStr::new("--warmup"),
        OsStr::new("1"),
        OsStr::new("--json"),
        json.as_os_str(),
    ]);
    assert!(out.status.success(), "bench --train: {text}");
    assert!(text.contains("median"), "{text}");
    let r = read_json(&json);
    assert_eq!(r["batch"], 4);
    assert_eq!(r["steps"], 2);
    assert_eq!(r["warmup"], 1);
    assert_eq!(r["device"], "cpu");
    assert!(r["parameters"].as_u64().unwrap() > 0);
    for k in ["median_ms", "p90_ms", "samples_per_s"] {
        let v = r[k].as_f64().unwrap();
        assert!(v.is_finite() && v > 0.0, "{k} = {v}");
    }
    let steps = r["step_ms"].as_array().unwrap();
    assert_eq!(steps.len(), 2);
    assert!(steps
        .iter()
        .all(|s| s.as_f64().is_some_and(|v| v.is_finite() && v > 0.0)));
    assert!(r["p90_ms"].as_f64().unwrap() >= r["median_ms"].as_f64().unwrap());

    if !cfg!(feature = "cuda") {
        let (out, text) = bench(&[OsStr::new("--device"), OsStr::new("cuda")]);
        assert!(!out.status.success(), "{text}");
        assert!(text.contains("--features cuda"), "{text}");
        assert!(!text.contains("median"), "{text}");
    }
    let (out, text) = bench(&[OsStr::new("--task"), OsStr::new("catch the book")]);
    assert!(!out.status.success(), "{text}");
    assert!(text.contains("cannot be used with"), "{text}");
}
