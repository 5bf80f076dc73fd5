//! `Gr00tActionHead::record_nfe` through the library on the checkpoint `write_example`
//! writes (pure Rust; ONNX Runtime from `source .native/env.sh`): only the first `calls`
//! calls are written, no temporary file is left, a write that fails is the call's typed
//! error, and a directory that is not empty or cannot be created is refused naming it.
#![cfg(all(feature = "gr00t", feature = "candle"))]

use std::path::Path;

use pir2_backends::gr00t::{load_action_head, write_example, Gr00tActionHead, NfeRecorder};
use pir2_backends::ort::OrtOptions;
use pir2_backends::Error;
use pir2_runtime::{ModelInput, SlowInput};

/// One call on fixed inputs (`B = 1`, the example's sizes), its result.
fn call(head: &mut Gr00tActionHead) -> pir2_backends::Result<Vec<f32>> {
    let d = *head.dims();
    let (h, a) = (d.horizon, d.action_dim);
    let t = head.vl_layout().map(|l| l.image_mask.len()).unwrap_or(8);
    let x: Vec<f32> = (0..h * a)
        .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
        .collect();
    let tau: Vec<f32> = (0..h).map(|p| 1.0 - p as f32 / h as f32).collect();
    let obs: Vec<f32> = (0..d.n_obs * d.state_dim)
        .map(|i| (i as f32 * 0.1).sin())
        .collect();
    let vl: Vec<f32> = (0..t * d.d_vl).map(|i| (i as f32 * 0.37).cos()).collect();
    let d_vis = [2u32];
    let input = ModelInput {
        batch: 1,
        horizon: h,
        action_dim: a,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: d.n_obs,
        fast_dim: d.state_dim,
        slow: SlowInput::Tokens {
            data: &vl,
            tokens: t,
            dim: d.d_vl,
        },
        d_vis: &d_vis,
    };
    let mut v = vec![0.0; h * a];
    head.forward(&input, &mut v)?;
    Ok(v)
}

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn record_nfe_writes_the_first_calls_and_a_failed_write_is_the_calls_error() {
    let root = std::env::temp_dir().join(format!("pir2-gr00t-record-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let ck = root.join("ex");
    write_example(&ck, 5).unwrap();
    let (mut head, _) = load_action_head(&ck, "catch_book", &OrtOptions::default()).unwrap();
    let plain = call(&mut head).unwrap();

    // The first two calls of three are recorded; recording changes nothing computed.
    let rec = root.join("rec");
    head.record_nfe(&rec, 2).unwrap();
    for _ in 0..3 {
        assert_eq!(call(&mut head).unwrap(), plain);
    }
    assert_eq!(
        names(&rec),
        ["nfe-0000.safetensors", "nfe-0001.safetensors"]
    );
    assert_eq!(head.recorder().unwrap().written(), 2);
    assert_eq!(NfeRecorder::file(&rec, 1), rec.join("nfe-0001.safetensors"));

    // A non-empty directory, or one that cannot be created, is refused naming it.
    let again = head.record_nfe(&rec, 1).unwrap_err();
    assert!(
        matches!(&again, Error::NfeRecord { path, .. } if path == &rec),
        "{again}"
    );
    assert!(again.to_string().contains("not empty"), "{again}");
    let file = root.join("a-file");
    std::fs::write(&file, "x").unwrap();
    let under_file = file.join("rec");
    let bad = head.record_nfe(&under_file, 1).unwrap_err();
    assert!(
        matches!(&bad, Error::NfeRecord { path, .. } if path == &under_file),
        "{bad}"
    );

    // The directory gone mid-run: the call fails with the typed error naming the file.
    let gone = root.join("gone");
    head.record_nfe(&gone, 1).unwrap();
    std::fs::remove_dir(&gone).unwrap();
    let e = call(&mut head).unwrap_err();
    assert!(
        matches!(&e, Error::NfeRecord { path, .. } if path == &NfeRecorder::file(&gone, 0)),
        "{e}"
    );
    // As a runtime error it keeps the message (the run stops as on any head error).
    let r: pir2_runtime::Error = e.into();
    assert!(r.to_string().contains("nfe-0000.safetensors"), "{r}");
    std::fs::remove_dir_all(&root).ok();
}
