//! One conformance suite for every enabled backend: the same weights and the same inputs must
//! give the same velocity within [`RTOL`]/[`ATOL`] (`|a − b| ≤ ATOL + RTOL·|b|`, `b` the
//! reference), at batch 1 and batch > 1; wrong shapes are typed errors; NaN outputs are
//! reported; repeated calls are bit-identical.
//!
//! With default features only the pure-Rust parts run (the reference and the exporter's
//! encoding); `--features ort` adds ONNX Runtime, `--features tch` adds libtorch.
//!
//! One file of about a thousand lines on purpose: every backend's section runs the same
//! reference models, inputs and tolerances defined here, so a change of the contract shows
//! up in one place.

#![allow(missing_docs)]

use pir2_backends::export::{self, ContractDims, SlowSpec};
use pir2_runtime::{ModelInput, SlowInput, VelocityModel};
use pir2_schedule::Rng;

/// Relative tolerance of the comparison.
const RTOL: f32 = 1e-4;
/// Absolute tolerance of the comparison.
const ATOL: f32 = 1e-5;

fn assert_close(what: &str, got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let mut worst = (0usize, 0f32);
    for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
        assert!(g.is_finite(), "{what}: non-finite output at {i}");
        let err = (g - w).abs();
        let tol = ATOL + RTOL * w.abs();
        if err - tol > worst.1 {
            worst = (i, err - tol);
        }
        assert!(
            err <= tol,
            "{what}: element {i}: got {g}, want {w} (|diff| {err} > {tol})"
        );
    }
}

/// Owned inputs of one call.
#[derive(Debug, Clone)]
struct Inputs {
    batch: usize,
    dims: ContractDims,
    x: Vec<f32>,
    tau: Vec<f32>,
    obs_fast: Vec<f32>,
    obs_slow: Vec<f32>,
    d_vis: Vec<u32>,
}

impl Inputs {
    fn random(dims: ContractDims, batch: usize, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let mut normal = |n: usize| {
            let mut v = vec![0f32; n];
            rng.fill_normal(&mut v);
            v
        };
        let (h, a) = (dims.horizon, dims.action_dim);
        let x = normal(batch * h * a);
        let obs_fast = normal(batch * dims.n_obs * dims.fast_dim);
        let obs_slow = match dims.slow {
            SlowSpec::None => vec![],
            SlowSpec::Vector { dim } => normal(batch * dim),
            SlowSpec::Tokens { tokens, dim } => normal(batch * tokens * dim),
        };
        let mut rng = Rng::new(seed ^ 0x5eed);
        // A staircase-like τ with a hidden front slot in the first sample.
        let mut tau = Vec::with_capacity(batch * h);
        for b in 0..batch {
            for p in 0..h {
                let t = if b == 0 && p == 0 {
                    pir2_schedule::HIDDEN_FRONT_TAU
                } else {
                    rng.uniform()
                };
                tau.push(t);
            }
        }
        let d_vis = (0..batch).map(|b| (b % 4) as u32).collect();
        Inputs {
            batch,
            dims,
            x,
            tau,
            obs_fast,
            obs_slow,
            d_vis,
        }
    }

    fn view(&self) -> ModelInput<'_> {
        let slow = match self.dims.slow {
            SlowSpec::None => SlowInput::None,
            SlowSpec::Vector { dim } => SlowInput::Vector {
                data: &self.obs_slow,
                dim,
            },
            SlowSpec::Tokens { tokens, dim } => SlowInput::Tokens {
                data: &self.obs_slow,
                tokens,
                dim,
            },
        };
        ModelInput {
            batch: self.batch,
            horizon: self.dims.horizon,
            action_dim: self.dims.action_dim,
            x: &self.x,
            tau: &self.tau,
            obs_fast: &self.obs_fast,
            n_obs: self.dims.n_obs,
            fast_dim: self.dims.fast_dim,
            slow,
            d_vis: &self.d_vis,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The probe model: a small graph that touches every contract input, written three ways (plain
// Rust reference, ONNX graph, traced libtorch closure) from the same weights:
//   z = concat(flat(x), tau, flat(obs_fast), flat(obs_slow), d_vis as f32)      [B, Z]
//   h = mish(z·W1ᵀ + b1);  v = reshape(h·W2ᵀ + b2, [B,H,A])
// ---------------------------------------------------------------------------------------------

#[derive(Debug, Clone)]
struct Probe {
    dims: ContractDims,
    hidden: usize,
    w1: Vec<f32>,
    b1: Vec<f32>,
    w2: Vec<f32>,
    b2: Vec<f32>,
}

impl Probe {
    fn z_dim(d: &ContractDims) -> usize {
        let slow = match d.slow {
            SlowSpec::None => 0,
            SlowSpec::Vector { dim } => dim,
            SlowSpec::Tokens { tokens, dim } => tokens * dim,
        };
        d.horizon * d.action_dim + d.horizon + d.n_obs * d.fast_dim + slow + 1
    }

    fn new(dims: ContractDims, hidden: usize, seed: u64) -> Self {
        let z = Self::z_dim(&dims);
        let out = dims.horizon * dims.action_dim;
        let mut rng = Rng::new(seed);
        let mut init = |n: usize, fan_in: usize| {
            let s = 1.0 / (fan_in as f32).sqrt();
            (0..n).map(|_| rng.uniform_range(-s, s)).collect::<Vec<_>>()
        };
        let w1 = init(hidden * z, z);
        let b1 = init(hidden, z);
        let w2 = init(out * hidden, hidden);
        let b2 = init(out, hidden);
        Probe {
            dims,
            hidden,
            w1,
            b1,
            w2,
            b2,
        }
    }

    fn reference(&self, inp: &ModelInput<'_>, out: &mut [f32]) {
        let z_dim = Self::z_dim(&self.dims);
        let o_dim = self.dims.horizon * self.dims.action_dim;
        let slow: &[f32] = match inp.slow {
            SlowInput::None => &[],
            SlowInput::Vector { data, .. } | SlowInput::Tokens { data, .. } => data,
        };
        let sw = slow.len() / inp.batch;
        for b in 0..inp.batch {
            let mut z = Vec::with_capacity(z_dim);
            z.extend_from_slice(&inp.x[b * o_dim..(b + 1) * o_dim]);
            z.extend_from_slice(&inp.tau[b * inp.horizon..(b + 1) * inp.horizon]);
            let f = inp.n_obs * inp.fast_dim;
            z.extend_from_slice(&inp.obs_fast[b * f..(b + 1) * f]);
            z.extend_from_slice(&slow[b * sw..(b + 1) * sw]);
            z.push(inp.d_vis[b] as f32);
            let h: Vec<f32> = (0..self.hidden)
                .map(|j| {
                    let s = self.b1[j]
                        + (0..z_dim)
                            .map(|i| self.w1[j * z_dim + i] * z[i])
                            .sum::<f32>();
                    s * (s.exp().ln_1p()).tanh()
                })
                .collect();
            for o in 0..o_dim {
                out[b * o_dim + o] = self.b2[o]
                    + (0..self.hidden)
                        .map(|j| self.w2[o * self.hidden + j] * h[j])
                        .sum::<f32>();
            }
        }
    }

    fn onnx_bytes(&self) -> Vec<u8> {
        let d = &self.dims;
        let (mut g, v) = export::contract_graph("probe", d);
        let xf = g.reshape(&v.x, &[0, -1]);
        let of = g.reshape(&v.obs_fast, &[0, -1]);
        let dv = g.cast_f32(v.d_vis.as_deref().expect("probe declares d_vis"));
        let dv = g.unsqueeze(&dv, &[1]);
        let mut parts = vec![xf, v.tau.clone(), of];
        if let Some(s) = &v.obs_slow {
            parts.push(g.reshape(s, &[0, -1]));
        }
        parts.push(dv);
        let refs: Vec<&str> = parts.iter().map(String::as_str).collect();
        let z = g.concat(&refs, 1);
        let z_dim = Self::z_dim(d);
        let h = g.linear(&z, "l1", &self.w1, Some(&self.b1), z_dim, self.hidden);
        let h = g.mish(&h);
        let o = g.linear(
            &h,
            "l2",
            &self.w2,
            Some(&self.b2),
            self.hidden,
            d.horizon * d.action_dim,
        );
        let o = g.reshape(&o, &[0, d.horizon as i64, d.action_dim as i64]);
        export::finish_contract(g, &o, d, "probe").encode()
    }
}

fn probe_dims(slow: SlowSpec) -> ContractDims {
    ContractDims {
        horizon: 4,
        action_dim: 3,
        n_obs: 2,
        fast_dim: 5,
        slow,
        has_d_vis: true,
    }
}

fn slow_variants() -> [SlowSpec; 3] {
    [
        SlowSpec::None,
        SlowSpec::Vector { dim: 6 },
        SlowSpec::Tokens { tokens: 2, dim: 3 },
    ]
}

#[test]
fn onnx_export_encodes_the_contract_inputs_and_outputs() {
    // The encoder's output must at least contain the contract names and the opset import.
    let p = Probe::new(probe_dims(SlowSpec::Vector { dim: 6 }), 8, 1);
    let bytes = p.onnx_bytes();
    for name in [
        "x",
        "tau",
        "obs_fast",
        "obs_slow",
        "d_vis",
        "l1.weight_t",
        "Softplus",
        "MatMul",
    ] {
        assert!(
            bytes.windows(name.len()).any(|w| w == name.as_bytes()),
            "`{name}` missing from the encoded model"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// The suite, run against every backend constructor.
// ---------------------------------------------------------------------------------------------

type Factory<'a> = dyn Fn(&Probe) -> Box<dyn VelocityModel> + 'a;

fn run_suite(name: &str, make: &Factory<'_>) {
    for slow in slow_variants() {
        let probe = Probe::new(probe_dims(slow), 16, 7);
        let mut model = make(&probe);
        for batch in [1, 5] {
            let inp = Inputs::random(probe.dims, batch, 100 + batch as u64);
            let view = inp.view();
            let n = batch * probe.dims.horizon * probe.dims.action_dim;
            let mut want = vec![0f32; n];
            probe.reference(&view, &mut want);
            let mut got = vec![0f32; n];
            model
                .velocity(&view, &mut got)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_close(&format!("{name} slow={slow:?} batch={batch}"), &got, &want);
            // Determinism: a second call gives the same bits.
            let mut again = vec![0f32; n];
            model.velocity(&view, &mut again).unwrap();
            assert_eq!(
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                again.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "{name}: not deterministic"
            );
        }
        // Batch rows are independent: row 0 of a batch-5 call equals the batch-1 call on it.
        let inp5 = Inputs::random(probe.dims, 5, 55);
        let n1 = probe.dims.horizon * probe.dims.action_dim;
        let mut out5 = vec![0f32; 5 * n1];
        model.velocity(&inp5.view(), &mut out5).unwrap();
        let mut inp1 = inp5.clone();
        inp1.batch = 1;
        let f = probe.dims.n_obs * probe.dims.fast_dim;
        inp1.x.truncate(n1);
        inp1.tau.truncate(probe.dims.horizon);
        inp1.obs_fast.truncate(f);
        inp1.obs_slow.truncate(inp5.obs_slow.len() / 5);
        inp1.d_vis.truncate(1);
        let mut out1 = vec![0f32; n1];
        model.velocity(&inp1.view(), &mut out1).unwrap();
        assert_close(
            &format!("{name}: batch row independence"),
            &out5[..n1],
            &out1,
        );
    }
}

fn run_error_suite(name: &str, make: &Factory<'_>) {
    let probe = Probe::new(probe_dims(SlowSpec::Vector { dim: 6 }), 8, 3);
    let mut model = make(&probe);
    let good = Inputs::random(probe.dims, 2, 9);
    let n = 2 * probe.dims.horizon * probe.dims.action_dim;
    let mut out = vec![0f32; n];

    // x too short.
    let mut bad = good.clone();
    bad.x.pop();
    let e = model
        .velocity(&bad.view(), &mut out)
        .expect_err("short x must fail");
    assert!(
        matches!(e, pir2_runtime::Error::Shape { .. }),
        "{name}: {e}"
    );
    assert!(
        e.to_string().contains("x [B,H,A]"),
        "{name}: error does not name x: {e}"
    );

    // Output buffer of the wrong size.
    let mut short = vec![0f32; n - 1];
    let e = model
        .velocity(&good.view(), &mut short)
        .expect_err("short out must fail");
    assert!(
        matches!(e, pir2_runtime::Error::Shape { .. }),
        "{name}: {e}"
    );

    // NaN in → NaN out → reported as non-finite, with the index of the first bad element.
    let mut nan = good.clone();
    nan.x[0] = f32::NAN;
    let e = model
        .velocity(&nan.view(), &mut out)
        .expect_err("NaN output must be reported");
    assert!(
        matches!(e, pir2_runtime::Error::NonFinite { index: 0 }),
        "{name}: {e}"
    );
}

#[test]
fn reference_is_deterministic_and_batch_independent() {
    // The pure-Rust reference, wrapped as a backend: exercises the suite itself with default
    // features (so the suite is known to run and to be able to fail elsewhere).
    struct RefModel(Probe);
    impl VelocityModel for RefModel {
        fn backend(&self) -> &'static str {
            "reference"
        }
        fn velocity(
            &mut self,
            input: &ModelInput<'_>,
            out: &mut [f32],
        ) -> pir2_runtime::Result<()> {
            input.validate()?;
            let n = input.batch * input.horizon * input.action_dim;
            if out.len() != n {
                return Err(pir2_runtime::Error::shape("out [B,H,A]", n, out.len()));
            }
            self.0.reference(input, out);
            if let Some(index) = out.iter().position(|v| !v.is_finite()) {
                return Err(pir2_runtime::Error::NonFinite { index });
            }
            Ok(())
        }
    }
    let make = |p: &Probe| Box::new(RefModel(p.clone())) as Box<dyn VelocityModel>;
    run_suite("reference", &make);
    run_error_suite("reference", &make);
}

#[test]
fn assert_close_rejects_a_difference_above_tolerance() {
    let r = std::panic::catch_unwind(|| assert_close("t", &[1.0 + 1e-3], &[1.0]));
    assert!(r.is_err());
    assert_close("t", &[1.0 + 5e-5], &[1.0]);
}

#[cfg(feature = "ort")]
mod ort_backend {
    use super::*;
    use pir2_backends::export::proto::{DataType, Dim};
    use pir2_backends::ort::{OrtModel, OrtOptions};

    fn make(p: &Probe) -> Box<dyn VelocityModel> {
        Box::new(
            OrtModel::from_bytes(&p.onnx_bytes(), &OrtOptions::default())
                .expect("load probe into onnxruntime"),
        )
    }

    #[test]
    fn ort_matches_reference() {
        run_suite("onnxruntime", &make);
    }

    #[test]
    fn ort_reports_shape_and_nan_errors() {
        run_error_suite("onnxruntime", &make);
    }

    #[test]
    fn ort_reads_dims_from_the_file_and_rejects_mismatched_calls() {
        let p = Probe::new(probe_dims(SlowSpec::Tokens { tokens: 2, dim: 3 }), 8, 1);
        let mut m = OrtModel::from_bytes(&p.onnx_bytes(), &OrtOptions::default()).unwrap();
        assert_eq!(*m.dims(), p.dims);
        // A call with a different horizon names the horizon.
        let other = ContractDims {
            horizon: 5,
            ..p.dims
        };
        let inp = Inputs::random(other, 1, 1);
        let mut out = vec![0f32; 5 * 3];
        let e = m.velocity(&inp.view(), &mut out).unwrap_err();
        assert!(e.to_string().contains("horizon"), "{e}");
        // A call with the wrong slow layout names obs_slow.
        let other = ContractDims {
            slow: SlowSpec::Vector { dim: 6 },
            ..p.dims
        };
        let inp = Inputs::random(other, 1, 1);
        let mut out = vec![0f32; 4 * 3];
        let e = m.velocity(&inp.view(), &mut out).unwrap_err();
        assert!(e.to_string().contains("obs_slow"), "{e}");
    }

    #[test]
    fn ort_rejects_a_graph_that_breaks_the_contract() {
        use pir2_backends::export::GraphBuilder;
        // Input named `obs` instead of `obs_fast`.
        let mut g = GraphBuilder::new("bad");
        let x = g.input(
            "x",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4), Dim::Fixed(3)],
        );
        g.input(
            "tau",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4)],
        );
        g.input(
            "obs",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(2), Dim::Fixed(5)],
        );
        g.output(
            &x,
            "v",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4), Dim::Fixed(3)],
        );
        let e =
            OrtModel::from_bytes(&g.finish(vec![]).encode(), &OrtOptions::default()).unwrap_err();
        assert!(e.to_string().contains("unexpected input `obs`"), "{e}");

        // `tau` with the wrong horizon.
        let mut g = GraphBuilder::new("bad");
        let x = g.input(
            "x",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4), Dim::Fixed(3)],
        );
        g.input(
            "tau",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(7)],
        );
        g.input(
            "obs_fast",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(2), Dim::Fixed(5)],
        );
        g.output(
            &x,
            "v",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4), Dim::Fixed(3)],
        );
        let e =
            OrtModel::from_bytes(&g.finish(vec![]).encode(), &OrtOptions::default()).unwrap_err();
        assert!(e.to_string().contains("`tau` is [B, 7]"), "{e}");

        // `d_vis` as float.
        let mut g = GraphBuilder::new("bad");
        let x = g.input(
            "x",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4), Dim::Fixed(3)],
        );
        g.input(
            "tau",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4)],
        );
        g.input(
            "obs_fast",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(2), Dim::Fixed(5)],
        );
        g.input("d_vis", DataType::Float, vec![Dim::Symbolic("b".into())]);
        g.output(
            &x,
            "v",
            DataType::Float,
            vec![Dim::Symbolic("b".into()), Dim::Fixed(4), Dim::Fixed(3)],
        );
        let e =
            OrtModel::from_bytes(&g.finish(vec![]).encode(), &OrtOptions::default()).unwrap_err();
        assert!(e.to_string().contains("`d_vis` has element type"), "{e}");
    }

    #[test]
    fn ort_runtime_reports_version_and_path() {
        let rt = pir2_backends::ort::runtime(None).unwrap();
        assert!(rt.version().starts_with("1."), "{}", rt.version());
        assert!(!rt.path().as_os_str().is_empty());
    }

    /// The CPU build of ONNX Runtime (what CI installs) has no GPU provider: asking for one is
    /// one error naming the library, the provider and what the library offers; it never
    /// runs on the CPU instead. On a GPU build with a device, the same request loads.
    #[test]
    fn an_unavailable_gpu_provider_is_one_clear_error() {
        use pir2_backends::{ort::Provider, Error};
        let rt = pir2_backends::ort::runtime(None).unwrap();
        let probe = Probe::new(probe_dims(SlowSpec::None), 8, 3);
        for provider in [
            Provider::Cuda { device: 0 },
            Provider::TensorRt {
                device: 0,
                cache_dir: None,
            },
        ] {
            if provider.is_available(rt) {
                eprintln!(
                    "{} is in this library: not checking the error",
                    provider.ort_name()
                );
                continue;
            }
            let opts = OrtOptions {
                provider: provider.clone(),
                ..OrtOptions::default()
            };
            let e = OrtModel::from_bytes(&probe.onnx_bytes(), &opts).unwrap_err();
            assert!(matches!(e, Error::OrtProvider { .. }), "{e:?}");
            let msg = e.to_string();
            for part in [
                provider.ort_name(),
                &rt.path().display().to_string(),
                "CPUExecutionProvider",
                "onnxruntime-gpu",
            ] {
                assert!(msg.contains(part), "`{part}` missing from: {msg}");
            }
        }
        // The CPU provider, asked for explicitly, is the default.
        let opts = OrtOptions {
            provider: Provider::Cpu,
            ..OrtOptions::default()
        };
        assert!(OrtModel::from_bytes(&probe.onnx_bytes(), &opts).is_ok());
    }
}

#[cfg(feature = "tch")]
mod tch_backend {
    use super::*;
    use pir2_backends::tch::{trace_to_file, TchModel};
    use tch::{Kind, Tensor};

    /// The probe as libtorch ops, traced into TorchScript.
    fn make(p: &Probe) -> Box<dyn VelocityModel> {
        let d = p.dims;
        let z_dim = Probe::z_dim(&d) as i64;
        let t = |v: &[f32], s: &[i64]| Tensor::from_slice(v).reshape(s);
        let w1 = t(&p.w1, &[p.hidden as i64, z_dim]);
        let b1 = t(&p.b1, &[p.hidden as i64]);
        let o = (d.horizon * d.action_dim) as i64;
        let w2 = t(&p.w2, &[o, p.hidden as i64]);
        let b2 = t(&p.b2, &[o]);
        let ex = Inputs::random(d, 2, 1);
        let slow_shape: Vec<i64> = match d.slow {
            SlowSpec::None => vec![2, 0],
            SlowSpec::Vector { dim } => vec![2, dim as i64],
            SlowSpec::Tokens { tokens, dim } => vec![2, tokens as i64, dim as i64],
        };
        let example = [
            t(&ex.x, &[2, d.horizon as i64, d.action_dim as i64]),
            t(&ex.tau, &[2, d.horizon as i64]),
            t(&ex.obs_fast, &[2, d.n_obs as i64, d.fast_dim as i64]),
            if ex.obs_slow.is_empty() {
                Tensor::zeros(&slow_shape[..], (Kind::Float, tch::Device::Cpu))
            } else {
                t(&ex.obs_slow, &slow_shape)
            },
            Tensor::from_slice(&[0i64, 1]),
        ];
        let dir = std::env::temp_dir().join(format!("pir2-conformance-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path =
            dir.join(format!("probe-{:?}.pt", d.slow).replace([' ', '{', '}', ':', ','], ""));
        trace_to_file(&path, &example, |x, tau, obs, slow, dv| {
            // Batch-agnostic ops only: a size read here would be traced as a constant.
            let z = Tensor::cat(
                &[
                    x.flatten(1, -1),
                    tau.shallow_clone(),
                    obs.flatten(1, -1),
                    slow.flatten(1, -1),
                    dv.to_kind(Kind::Float).unsqueeze(1),
                ],
                1,
            );
            let h = z.linear(&w1, Some(&b1));
            let h = &h * h.softplus().tanh();
            h.linear(&w2, Some(&b2))
                .reshape([-1, d.horizon as i64, d.action_dim as i64])
        })
        .unwrap();
        Box::new(TchModel::load(&path).unwrap())
    }

    #[test]
    fn tch_matches_reference() {
        run_suite("libtorch", &make);
    }

    #[test]
    fn tch_reports_shape_and_nan_errors() {
        run_error_suite("libtorch", &make);
    }

    #[test]
    fn tch_load_error_names_the_file() {
        let e = TchModel::load("/nonexistent/model.pt").unwrap_err();
        assert!(e.to_string().contains("/nonexistent/model.pt"), "{e}");
    }
}

// ---------------------------------------------------------------------------------------------
// Exported model definitions (MLP, U-Net): every enabled native backend runs the same
// definition with the same weights; with both enabled they must agree with each other.
// ---------------------------------------------------------------------------------------------

mod exported {
    use super::*;
    use pir2_backends::export::models::{Film, MlpSpec, ObsNorm, UnetSpec};
    use pir2_backends::export::ops::NamedWeights;
    use pir2_backends::export::ModelSpec;

    pub(super) fn dims(slow: SlowSpec) -> ContractDims {
        ContractDims {
            horizon: 8,
            action_dim: 3,
            n_obs: 2,
            fast_dim: 4,
            slow,
            has_d_vis: true,
        }
    }

    pub(super) fn norm(d: &ContractDims) -> ObsNorm {
        // Non-trivial statistics so the in-graph normalisation is exercised.
        let mut n = ObsNorm::identity(d);
        for (i, v) in n.fast.0.iter_mut().enumerate() {
            *v = 0.1 * i as f32;
        }
        for (i, v) in n.fast.1.iter_mut().enumerate() {
            *v = 0.5 + 0.25 * i as f32;
        }
        for v in n.fast_diff.1.iter_mut() {
            *v = 2.0;
        }
        for (i, v) in n.slow.0.iter_mut().enumerate() {
            *v = -0.2 * i as f32;
        }
        for v in n.slow.1.iter_mut() {
            *v = 3.0;
        }
        n
    }

    pub(super) fn specs() -> Vec<ModelSpec> {
        let mut v = Vec::new();
        for slow in slow_variants() {
            let d = dims(slow);
            v.push(ModelSpec::Mlp(MlpSpec {
                dims: d,
                width: 32,
                depth: 2,
                tau_freqs: 2,
                dvis_dim: 4,
                d_vis_max: 2,
                norm: norm(&d),
            }));
        }
        for (slow, film) in [
            (SlowSpec::Vector { dim: 6 }, Film::PerPositionHeads),
            (SlowSpec::Tokens { tokens: 2, dim: 3 }, Film::Shared),
            (SlowSpec::None, Film::PerPositionTau),
            (
                SlowSpec::Tokens { tokens: 2, dim: 3 },
                Film::PerPositionHeads,
            ),
        ] {
            let d = dims(slow);
            v.push(ModelSpec::Unet(UnetSpec {
                dims: d,
                widths: vec![8, 16],
                kernel: 3,
                groups: 4,
                tau_dim: 8,
                dvis_dim: 2,
                d_vis_max: 2,
                film,
                norm: norm(&d),
            }));
        }
        v
    }

    pub(super) fn weights(spec: &ModelSpec) -> NamedWeights {
        NamedWeights::random(&spec.weight_shapes(), 11)
    }

    #[test]
    fn weight_shapes_name_every_weight_the_definition_reads() {
        // Exporting with one weight missing must fail and name that weight.
        for spec in specs() {
            let shapes = spec.weight_shapes();
            let w = weights(&spec);
            assert!(export::export(&spec, &w).is_ok(), "{}", spec.kind());
            let (drop, _) = &shapes[shapes.len() / 2];
            let mut partial = NamedWeights::new();
            for (n, s, d) in w.iter().filter(|(n, _, _)| n != drop) {
                partial.insert(n, s.to_vec(), d.to_vec());
            }
            let e = export::export(&spec, &partial).unwrap_err();
            assert!(e.to_string().contains(drop.as_str()), "{e}");
        }
    }

    #[test]
    fn export_rejects_a_misshapen_weight() {
        let spec = &specs()[0];
        let mut w = weights(spec);
        w.insert("mlp.out.bias", vec![7], vec![0.0; 7]);
        let e = export::export(spec, &w).unwrap_err();
        assert!(
            e.to_string().contains("mlp.out.bias") && e.to_string().contains("[7]"),
            "{e}"
        );
    }
}

#[cfg(all(feature = "ort", feature = "tch"))]
mod exported_ort_vs_tch {
    use super::exported::{specs, weights};
    use super::*;
    use pir2_backends::ort::{OrtModel, OrtOptions};
    use pir2_backends::tch::{export_torchscript, TchModel};

    #[test]
    fn ort_and_tch_agree_on_every_exported_definition() {
        let dir =
            std::env::temp_dir().join(format!("pir2-conformance-spec-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (i, spec) in specs().iter().enumerate() {
            let w = weights(spec);
            let mut ort = OrtModel::from_bytes(
                &export::export(spec, &w).unwrap().encode(),
                &OrtOptions::default(),
            )
            .unwrap();
            let path = dir.join(format!("{}-{i}.pt", spec.kind()));
            export_torchscript(spec, &w, &path).unwrap();
            let mut tch = TchModel::load(&path).unwrap();
            for batch in [1, 4] {
                let inp = Inputs::random(*spec.dims(), batch, 3 + batch as u64);
                let n = batch * spec.dims().horizon * spec.dims().action_dim;
                let (mut a, mut b) = (vec![0f32; n], vec![0f32; n]);
                ort.velocity(&inp.view(), &mut a).unwrap();
                tch.velocity(&inp.view(), &mut b).unwrap();
                assert!(
                    a.iter().any(|v| v.abs() > 1e-3),
                    "{}: degenerate output",
                    spec.kind()
                );
                assert_close(
                    &format!(
                        "{} #{i} batch {batch}: onnxruntime vs libtorch",
                        spec.kind()
                    ),
                    &a,
                    &b,
                );
            }
        }
    }
}

/// Writes the exported test models to `$PIR2_DUMP_ONNX` (a directory) so an external checker
/// (`python -c "import onnx; onnx.checker.check_model(...)"`) can validate them; a no-op otherwise.
#[test]
fn dump_exported_models_for_external_checking() {
    let Some(dir) = std::env::var_os("PIR2_DUMP_ONNX") else {
        return;
    };
    let dir = std::path::PathBuf::from(dir);
    std::fs::create_dir_all(&dir).unwrap();
    for (i, spec) in exported::specs().iter().enumerate() {
        let path = dir.join(format!("{}-{i}.onnx", spec.kind()));
        export::export_to_file(spec, &exported::weights(spec), &path).unwrap();
        assert!(std::fs::metadata(&path).unwrap().len() > 100);
    }
}

// ---------------------------------------------------------------------------------------------
// candle (the trained models) vs the exported definitions, on the same candle weights.
// ---------------------------------------------------------------------------------------------

#[cfg(feature = "candle")]
mod candle_models {
    use super::*;
    use pir2_backends::candle::CandleModel;
    use pir2_backends::config::{
        self, Config, FilmMode, MlpConfig, ModelConfig, Norm, Spec, Stats, UNetConfig,
    };

    fn spec(slow: config::SlowSpec) -> Spec {
        Spec {
            horizon: 8,
            action_dim: 3,
            n_obs: 2,
            fast_dim: 4,
            slow,
            d_vis_max: 2,
        }
    }

    fn stats(s: &Spec) -> Stats {
        let mut st = Stats::identity(s);
        st.fast = Norm {
            mean: (0..s.fast_dim).map(|i| 0.1 * i as f32).collect(),
            std: (0..s.fast_dim).map(|i| 0.5 + 0.25 * i as f32).collect(),
        };
        st.fast_diff.std = vec![2.0; s.fast_dim];
        let w = s.slow.width();
        st.slow = Norm {
            mean: (0..w).map(|i| -0.2 * i as f32).collect(),
            std: vec![3.0; w],
        };
        st
    }

    /// Every candle configuration the exporter supports, with all weights perturbed away from
    /// their (partly zero) initial values so every path (d_vis embedding, per-position FiLM)
    /// contributes.
    pub(super) fn models() -> Vec<CandleModel> {
        let slows = [
            config::SlowSpec::None,
            config::SlowSpec::Vector { dim: 6 },
            config::SlowSpec::Tokens { tokens: 2, dim: 3 },
        ];
        let mut out = Vec::new();
        for (i, slow) in slows.into_iter().enumerate() {
            let s = spec(slow);
            let mlp = Config {
                spec: s,
                model: ModelConfig::Mlp(MlpConfig {
                    width: 32,
                    depth: 2,
                    tau_freqs: 2,
                    dvis_dim: 4,
                }),
            };
            let film = match i {
                2 => FilmMode::Shared,
                1 => FilmMode::PerPositionTau,
                _ => FilmMode::PerPositionHeads,
            };
            let unet = Config {
                spec: s,
                model: ModelConfig::UNet(UNetConfig {
                    widths: vec![8, 16],
                    kernel: 3,
                    groups: 4,
                    tau_dim: 8,
                    dvis_dim: 2,
                    film,
                }),
            };
            for cfg in [mlp, unet] {
                let m = CandleModel::new(cfg, stats(&s), 5).unwrap();
                let mut rng = Rng::new(77 + i as u64);
                for (_, var) in m.vars() {
                    let t = var.as_tensor();
                    let n = t.elem_count();
                    let noise: Vec<f32> = (0..n).map(|_| rng.uniform_range(-0.3, 0.3)).collect();
                    let noise = candle_core::Tensor::from_vec(noise, t.dims(), t.device()).unwrap();
                    var.set(&(t + noise).unwrap()).unwrap();
                }
                out.push(m);
            }
        }
        out
    }

    #[cfg(any(feature = "ort", feature = "tch"))]
    pub(super) fn dims_of(m: &CandleModel) -> ContractDims {
        *pir2_backends::candle::export::spec_from_config(m.config(), m.stats())
            .unwrap()
            .dims()
    }

    #[cfg(any(feature = "ort", feature = "tch"))]
    pub(super) fn check_against_candle(
        name: &str,
        m: &mut CandleModel,
        other: &mut dyn VelocityModel,
    ) {
        let d = dims_of(m);
        for batch in [1, 5] {
            let inp = Inputs::random(d, batch, 40 + batch as u64);
            let n = batch * d.horizon * d.action_dim;
            let (mut want, mut got) = (vec![0f32; n], vec![0f32; n]);
            m.velocity(&inp.view(), &mut want).unwrap();
            other.velocity(&inp.view(), &mut got).unwrap();
            assert!(
                want.iter().any(|v| v.abs() > 1e-3),
                "degenerate candle output"
            );
            assert_close(
                &format!("{name} vs candle ({:?}, batch {batch})", m.config().model),
                &got,
                &want,
            );
        }
    }

    #[test]
    fn candle_models_export_to_valid_contract_graphs() {
        for m in models() {
            let spec =
                pir2_backends::candle::export::spec_from_config(m.config(), m.stats()).unwrap();
            let model = export::export(&spec, &m).unwrap();
            assert_eq!(model.graph.outputs[0].name, "v");
        }
    }

    #[cfg(feature = "ort")]
    #[test]
    fn ort_matches_candle_on_the_same_weights() {
        use pir2_backends::ort::{OrtModel, OrtOptions};
        for mut m in models() {
            let spec =
                pir2_backends::candle::export::spec_from_config(m.config(), m.stats()).unwrap();
            let bytes = export::export(&spec, &m).unwrap().encode();
            let mut ort = OrtModel::from_bytes(&bytes, &OrtOptions::default()).unwrap();
            check_against_candle("onnxruntime", &mut m, &mut ort);
        }
    }

    #[cfg(feature = "tch")]
    #[test]
    fn tch_matches_candle_on_the_same_weights() {
        use pir2_backends::tch::{export_torchscript, TchModel};
        let dir =
            std::env::temp_dir().join(format!("pir2-conformance-candle-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (i, mut m) in models().into_iter().enumerate() {
            let spec =
                pir2_backends::candle::export::spec_from_config(m.config(), m.stats()).unwrap();
            let path = dir.join(format!("m{i}.pt"));
            export_torchscript(&spec, &m, &path).unwrap();
            let mut t = TchModel::load(&path).unwrap();
            check_against_candle("libtorch", &mut m, &mut t);
        }
    }

    #[test]
    fn a_saved_checkpoint_exports_the_same_graph_as_the_live_model() {
        // The path `pir2 export --onnx <checkpoint>` takes: save, load, export.
        let mut all = models();
        let m = &mut all[1]; // a U-Net with per-position FiLM
        let dir =
            std::env::temp_dir().join(format!("pir2-conformance-ckpt-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        m.save(&dir).unwrap();
        let ck = pir2_backends::checkpoint::Checkpoint::load(&dir).unwrap();
        let from_ck = dir.join("exported.onnx");
        pir2_backends::candle::export::export_checkpoint(&ck, &from_ck).unwrap();
        let live = dir.join("live.onnx");
        pir2_backends::candle::export::export_candle_model(m, &live).unwrap();
        assert_eq!(
            std::fs::read(&from_ck).unwrap(),
            std::fs::read(&live).unwrap(),
            "checkpoint and live export differ"
        );
        #[cfg(feature = "ort")]
        {
            let mut ort = pir2_backends::ort::OrtModel::load(&from_ck).unwrap();
            check_against_candle("onnxruntime (from checkpoint file)", m, &mut ort);
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn dit_export_is_reported_unsupported() {
        let s = spec(config::SlowSpec::Tokens { tokens: 2, dim: 3 });
        let cfg = Config {
            spec: s,
            model: ModelConfig::Dit(Default::default()),
        };
        let e = pir2_backends::candle::export::spec_from_config(&cfg, &Stats::identity(&s))
            .unwrap_err();
        assert!(e.to_string().contains("DiT"), "{e}");
    }
}
