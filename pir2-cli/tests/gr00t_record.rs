//! `pir2 gr00t run … --record-nfe DIR --record-calls N` through the binary, on the checkpoint
//! `pir2 gr00t example` writes: the files, their tensors (names, dtypes, shapes, metadata),
//! the recorded timesteps against pir2's τ, and the recorded velocity recomputed by the candle
//! head the example's ONNX graphs were exported from (`DIR/head`), fed the recorded graph
//! inputs. And the refusals: a non-empty DIR, `--candle-head`, before anything is started.
//! Needs ONNX Runtime (`source .native/env.sh`); no Python.
#![cfg(feature = "gr00t")]

use std::collections::HashMap;
use std::ffi::OsStr;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use pir2_backends::gr00t::n17::Gr00tN17Head;
use pir2_backends::gr00t::EmbodimentConfig;

mod common;
use common::gr00t::pir2_text as pir2;
use common::gr00t::{candle_on_recorded_call, run_emulated_seconds};
use common::Scratch;

fn example(dir: &Path) {
    let (out, text) = pir2(&[
        OsStr::new("gr00t"),
        OsStr::new("example"),
        dir.as_os_str(),
        OsStr::new("--seed"),
        OsStr::new("3"),
    ]);
    assert!(out.status.success(), "example: {text}");
}

fn run(ck: &Path, extra: &[&OsStr]) -> (std::process::Output, String) {
    run_emulated_seconds(ck, "1", extra)
}

/// The safetensors metadata (`__metadata__` of the JSON header).
fn metadata(path: &Path) -> HashMap<String, String> {
    let bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    serde_json::from_value(header["__metadata__"].clone()).unwrap()
}

fn f32s(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn i64s(t: &Tensor) -> Vec<i64> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

/// `|a − b| ≤ tol·(1 + |b|)` everywhere, else the worst index.
fn close(what: &str, a: &[f32], b: &[f32], tol: f32) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    let worst = a
        .iter()
        .zip(b)
        .enumerate()
        .map(|(i, (x, y))| (i, (x - y).abs() / (1.0 + y.abs())))
        .fold((0, 0f32), |m, v| if v.1 > m.1 { v } else { m });
    assert!(
        worst.1 <= tol,
        "{what}: index {} differs by {} (relative), {} vs {}",
        worst.0,
        worst.1,
        a[worst.0],
        b[worst.0]
    );
}

#[test]
fn record_nfe_writes_what_the_graphs_were_fed_and_the_candle_head_recomputes_it() {
    let scratch = Scratch::new("gr00t-record");
    let ck = scratch.path().join("ex");
    example(&ck);
    let rec = scratch.path().join("rec");
    let (out, text) = run(
        &ck,
        &[
            OsStr::new("--record-nfe"),
            rec.as_os_str(),
            OsStr::new("--record-calls"),
            OsStr::new("2"),
        ],
    );
    eprintln!("{text}");
    assert!(out.status.success(), "run: {text}");
    let mut files: Vec<String> = std::fs::read_dir(&rec)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(files, ["nfe-0000.safetensors", "nfe-0001.safetensors"]);

    let emb = EmbodimentConfig::load(&ck.join("embodiment.toml")).unwrap();
    let dev = Device::Cpu;
    let head = Gr00tN17Head::load(&ck.join("head"), &dev).unwrap();
    let c = head.config().clone();
    let (h, a) = (emb.horizon, emb.action_dim());
    let d_in = c.input_embedding_dim;
    for f in &files {
        let path = rec.join(f);
        let t = candle_core::safetensors::load(&path, &dev).unwrap();
        let b = t["embodiment_id"].dim(0).unwrap();
        assert_eq!(b, 1, "{f}: one sample per call");
        let tokens = t["vl_embs"].dim(1).unwrap();
        let d_vl = t["vl_embs"].dim(2).unwrap();
        let want: &[(&str, DType, Vec<usize>)] = &[
            ("state", DType::F32, vec![b, 1, emb.n_obs * c.max_state_dim]),
            ("embodiment_id", DType::I64, vec![b]),
            ("actions", DType::F32, vec![b, h, c.max_action_dim]),
            ("timesteps", DType::I64, vec![b, h]),
            ("sa_embs", DType::F32, vec![b, 1 + h, d_in]),
            ("timestep", DType::I64, vec![b, 1 + h]),
            ("vl_embs", DType::F32, vec![b, tokens, d_vl]),
            ("image_mask", DType::U8, vec![b, tokens]),
            ("backbone_attention_mask", DType::U8, vec![b, tokens]),
            ("d_vis", DType::I64, vec![b]),
            ("tau", DType::F32, vec![b, h]),
            ("x", DType::F32, vec![b, h, a]),
            ("velocity", DType::F32, vec![b, h, a]),
        ];
        let mut names: Vec<&str> = t.keys().map(String::as_str).collect();
        names.sort();
        let mut expected: Vec<&str> = want.iter().map(|w| w.0).collect();
        expected.sort();
        assert_eq!(names, expected, "{f}");
        for (name, dtype, shape) in want {
            assert_eq!(t[*name].dtype(), *dtype, "{f}: {name}");
            assert_eq!(t[*name].dims(), shape.as_slice(), "{f}: {name}");
        }
        assert_eq!(d_vl, c.backbone_embedding_dim, "{f}");
        let meta = metadata(&path);
        assert_eq!(meta["pir2_version"], env!("CARGO_PKG_VERSION"));
        assert_eq!(meta["embodiment_id"], emb.embodiment_id.to_string());
        assert_eq!(meta["buckets"], emb.num_timestep_buckets.to_string());
        let state_t: i64 = meta["state_timestep"].parse().unwrap();
        assert_eq!(state_t, emb.state_timestep());
        assert_eq!(i64s(&t["embodiment_id"]), [emb.embodiment_id]);

        // The timesteps are pir2's τ bucketed; the DiT's are the state token's then those.
        let buckets = emb.num_timestep_buckets;
        let tau = f32s(&t["tau"]);
        let ts = i64s(&t["timesteps"]);
        for (p, (&tau, &tb)) in tau.iter().zip(&ts).enumerate() {
            let tau = if tau.is_finite() {
                tau.clamp(0.0, 1.0)
            } else {
                0.0
            };
            let want = ((tau * buckets as f32).floor() as i64).min(buckets - 1);
            assert_eq!(tb, want, "{f}: position {p}, τ {tau}");
        }
        let all = i64s(&t["timestep"]);
        assert_eq!(all[0], state_t, "{f}");
        assert_eq!(&all[1..], ts.as_slice(), "{f}");
        // The padded actions are x, then zeros.
        let x = f32s(&t["x"]);
        let padded = f32s(&t["actions"]);
        for p in 0..h {
            let row = &padded[p * c.max_action_dim..(p + 1) * c.max_action_dim];
            assert_eq!(&row[..a], &x[p * a..(p + 1) * a], "{f}: position {p}");
            assert!(row[a..].iter().all(|&v| v == 0.0), "{f}: padding {p}");
        }
        let v = f32s(&t["velocity"]);
        assert!(v.iter().all(|v| v.is_finite()), "{f}");

        // The candle head the ONNX graphs were exported from, on the recorded inputs: the
        // DiT's tokens from the state and action encoders with the delay row added, and the
        // DiT and decoder on the recorded DiT inputs give the recorded velocity.
        let (sa, out) = candle_on_recorded_call(&head, &t, emb.n_obs, a);
        close("sa_embs", &f32s(&t["sa_embs"]), &f32s(&sa), 1e-4);
        close("velocity", &v, &f32s(&out), 1e-3);
    }
}

#[test]
fn record_nfe_into_a_non_empty_directory_or_with_the_candle_head_is_refused_before_the_run() {
    let scratch = Scratch::new("gr00t-record-refused");
    let ck = scratch.path().join("ex");
    example(&ck);
    let rec = scratch.path().join("rec");
    std::fs::create_dir_all(&rec).unwrap();
    std::fs::write(rec.join("keep.txt"), "mine").unwrap();
    let (out, text) = run(&ck, &[OsStr::new("--record-nfe"), rec.as_os_str()]);
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains(&rec.display().to_string()) && text.contains("not empty"),
        "{text}"
    );
    assert_eq!(text.matches("Error").count(), 1, "{text}");
    // Nothing was started: no emulator, no limits, no robot.
    assert!(!text.contains("limits in force"), "{text}");
    assert!(!text.contains("emulat"), "{text}");
    let files: Vec<_> = std::fs::read_dir(&rec).unwrap().collect();
    assert_eq!(files.len(), 1, "the directory was written to");

    let fresh = scratch.path().join("rec-candle");
    let (out, text) = run(
        &ck,
        &[
            OsStr::new("--record-nfe"),
            fresh.as_os_str(),
            OsStr::new("--candle-head"),
            ck.join("head").as_os_str(),
        ],
    );
    assert!(!out.status.success(), "{text}");
    assert!(text.contains("--candle-head"), "{text}");
    assert!(!text.contains("limits in force"), "{text}");
    assert!(!fresh.exists(), "{text}");
}
