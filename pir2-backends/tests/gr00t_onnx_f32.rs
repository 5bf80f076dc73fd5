//! `gr00t::onnx_f32`: a bfloat16 ONNX graph (the kind GR00T N1.7's exporter writes for the
//! LLM, `llm_bf16.onnx`) rewritten to float32 in Rust runs under ONNX Runtime's CPU provider
//! and matches a float32 reference computed here.
//!
//! The graph (written by `gr00t_onnx_f32.py` with the `onnx` package, inline and with every
//! initializer in external data) has what an exported bf16 LLM has: a bfloat16 input,
//! bfloat16 initializers (one over the external-data threshold, one under it), a `Constant`
//! node holding a bfloat16 tensor, a `Cast` to bfloat16 and one back to float, and bfloat16
//! `value_info`. Needs `source .native/env.sh` (ONNX Runtime, `$PIR2_PYTHON` with `onnx`);
//! without `$PIR2_PYTHON` the test says so and passes without running.
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};
use std::process::Command;

use pir2_backends::gr00t::onnx_f32::{convert_bf16_to_f32, has_bf16};
use pir2_backends::ort::{runtime, session_builder, OrtOptions};
use pir2_backends::Error;

const IN: usize = 64;
const OUT: usize = 32;

/// A bfloat16-exact value (the upper 16 bits of an f32).
fn bf16_exact(x: f32) -> f32 {
    f32::from_bits(x.to_bits() & 0xffff_0000)
}

fn values(seed: u64, n: usize, scale: f32) -> Vec<f32> {
    let mut rng = pir2_schedule::Rng::new(seed);
    (0..n)
        .map(|_| bf16_exact(rng.uniform_range(-scale, scale)))
        .collect()
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("pir2-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn python() -> Option<PathBuf> {
    std::env::var_os("PIR2_PYTHON").map(PathBuf::from)
}

fn write_graph(py: &Path, dir: &Path, w: &[f32], b: &[f32], mode: &str) -> PathBuf {
    let bin = dir.join("values.bin");
    let bytes: Vec<u8> = w.iter().chain(b).flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&bin, bytes).unwrap();
    let out = dir.join(format!("llm_bf16_{mode}.onnx"));
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/gr00t_onnx_f32.py");
    let o = Command::new(py)
        .arg(&script)
        .arg(&bin)
        .arg(&out)
        .arg(mode)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    out
}

/// Run `path` on the CPU provider with `x [2, IN]`; `y [2, OUT]`.
fn run_cpu(path: &Path, x: &[f32]) -> Result<Vec<f32>, String> {
    let rt = runtime(None).map_err(|e| e.to_string())?;
    let mut session = session_builder(rt, &OrtOptions::default(), path)
        .map_err(|e| e.to_string())?
        .commit_from_file(path)
        .map_err(|e| e.to_string())?;
    let t = ort::value::Tensor::from_array((vec![2usize, IN], x.to_vec()))
        .map_err(|e| e.to_string())?;
    let outputs = session
        .run(ort::inputs!["x" => t])
        .map_err(|e| e.to_string())?;
    let (shape, y) = outputs["y"]
        .try_extract_tensor::<f32>()
        .map_err(|e| e.to_string())?;
    assert_eq!(&**shape, &[2, OUT as i64]);
    Ok(y.to_vec())
}

/// `tanh(bf16(x·W + b) · 0.5)` in f32; the graph's `Cast` to bfloat16 is a float32
/// identity after the rewrite, so the reference has no rounding there.
fn reference(x: &[f32], w: &[f32], b: &[f32]) -> Vec<f32> {
    let mut y = vec![0f32; 2 * OUT];
    for r in 0..2 {
        for c in 0..OUT {
            let mut s = 0f64;
            for k in 0..IN {
                s += f64::from(x[r * IN + k]) * f64::from(w[k * OUT + c]);
            }
            y[r * OUT + c] = (((s as f32) + b[c]) * 0.5).tanh();
        }
    }
    y
}

#[test]
fn a_bf16_graph_rewritten_to_f32_runs_on_the_cpu_and_matches_f32() {
    let Some(py) = python() else {
        eprintln!("skipped: $PIR2_PYTHON (a Python with `onnx`) is not set; source .native/env.sh");
        return;
    };
    let dir = scratch("onnx-f32");
    let w = values(1, IN * OUT, 0.2);
    let b = values(2, OUT, 0.5);
    let x = values(3, 2 * IN, 1.0);
    let want = reference(&x, &w, &b);
    for mode in ["inline", "external"] {
        let src = write_graph(&py, &dir, &w, &b, mode);
        assert!(has_bf16(&src).unwrap());
        // ONNX Runtime's CPU provider cannot run the bfloat16 graph (no bf16 MatMul).
        match run_cpu(&src, &x) {
            Err(e) => eprintln!("{mode}: the bf16 graph on the CPU: {e}"),
            Ok(_) => eprintln!("{mode}: this ONNX Runtime ran the bf16 graph on the CPU"),
        }
        let dst = dir.join(format!("llm_fp32_{mode}.onnx"));
        let report = convert_bf16_to_f32(&src, &dst).unwrap();
        eprintln!("{mode}: {report:?}");
        // W, b, the Constant's tensor; one Cast; x and the five value infos.
        assert_eq!(report.tensors, 3, "{report:?}");
        assert_eq!(report.attributes, 1, "{report:?}");
        assert_eq!(report.types, 6, "{report:?}");
        // W (8 KiB as f32) goes to the data file; b (128 B) stays inline unless it was
        // external in the input.
        // (`onnx`'s external-data writer with threshold 0 also moves the Constant's tensor.)
        let expect_external = if mode == "external" { 2 } else { 1 };
        assert!(report.external >= expect_external, "{report:?}");
        assert_eq!(
            report.data_file.as_deref(),
            Some(dir.join(format!("llm_fp32_{mode}.onnx.data")).as_path())
        );
        assert!(!has_bf16(&dst).unwrap());
        let got = run_cpu(&dst, &x).unwrap();
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        eprintln!("{mode}: max |f32 graph − reference| = {worst:e}");
        assert!(worst < 1e-5, "{mode}: {worst}");
        // Nothing a user wrote is overwritten.
        let again = convert_bf16_to_f32(&src, &dst).unwrap_err();
        assert!(matches!(again, Error::OnnxRewrite { .. }), "{again}");
        assert!(again.to_string().contains("already exists"), "{again}");
    }
    // External data that is not next to the file: one error naming the tensor.
    let src = dir.join("llm_bf16_external.onnx");
    std::fs::rename(
        dir.join("llm_bf16_external.onnx.weights"),
        dir.join("moved.weights"),
    )
    .unwrap();
    let e = convert_bf16_to_f32(&src, &dir.join("broken.onnx")).unwrap_err();
    let m = e.to_string();
    assert!(
        m.contains("llm_bf16_external.onnx") && m.contains("cannot be read"),
        "{m}"
    );
    assert!(!dir.join("broken.onnx").exists() && !dir.join("broken.onnx.data").exists());
    // Not a protobuf.
    std::fs::write(dir.join("junk.onnx"), [0xffu8, 0xff, 0xff]).unwrap();
    let e = convert_bf16_to_f32(&dir.join("junk.onnx"), &dir.join("junk2.onnx")).unwrap_err();
    assert!(e.to_string().contains("junk.onnx"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
