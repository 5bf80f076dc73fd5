//! libtorch backend ([`TchModel`], feature `tch`): runs a TorchScript module.
//!
//! # The module contract
//!
//! `forward(x, tau, obs_fast, obs_slow, d_vis) -> v`, the same tensors as the ONNX contract
//! ([`crate::export::contract`]): `x [B,H,A]` f32, `tau [B,H]` f32, `obs_fast [B,n_obs,F]` f32,
//! `obs_slow` f32 `[B,S]` or `[B,T,D]` (a `[B,0]` tensor when the model has no slow input),
//! `d_vis [B]` int64; returns `v [B,H,A]` f32. TorchScript files carry no shapes, so the output
//! shape is checked on every call.
//!
//! Such a module can come from `torch.jit.trace`/`torch.jit.script` in Python or, without
//! Python, from [`tch::CModule::create_by_tracing`] on a Rust closure (see [`trace_to_file`]).
//!
//! libtorch's thread pools are process-wide: [`TchModel::load`] sets the intra-op pool to
//! [`TchOptions::threads`] (default 1) and, once per process, the inter-op pool to 1.

use std::path::{Path, PathBuf};
use std::sync::Once;

mod ops;
pub use ops::{TchOps, TchValue};

use ::tch::{CModule, Device, Kind, Tensor};
use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

use crate::error::{Error, Result};

/// Options for [`TchModel`].
#[derive(Debug, Clone)]
pub struct TchOptions {
    /// Intra-op threads (process-wide in libtorch; default 1).
    pub threads: usize,
    /// Check every output for NaN/inf (default on).
    pub check_finite: bool,
}

impl Default for TchOptions {
    fn default() -> Self {
        TchOptions {
            threads: 1,
            check_finite: true,
        }
    }
}

/// A velocity model run by libtorch (see the module docs for the contract).
#[derive(Debug)]
pub struct TchModel {
    module: CModule,
    source: PathBuf,
    check_finite: bool,
    d_vis: Vec<i64>,
}

static INTEROP: Once = Once::new();

fn set_threads(threads: usize) {
    ::tch::set_num_threads(threads.max(1) as i32);
    INTEROP.call_once(|| {
        // libtorch refuses a second call (or a call after parallel work started); it is
        // only a latency preference, so a refusal is ignored.
        if ::tch::get_num_interop_threads() != 1 {
            let _ = std::panic::catch_unwind(|| ::tch::set_num_interop_threads(1));
        }
    });
}

impl TchModel {
    /// Load a TorchScript file with default options (single thread).
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        Self::load_with(path, &TchOptions::default())
    }

    /// Load a TorchScript file.
    pub fn load_with(path: impl AsRef<Path>, opts: &TchOptions) -> Result<Self> {
        let path = path.as_ref();
        set_threads(opts.threads);
        let mut module =
            CModule::load_on_device(path, Device::Cpu).map_err(|e| Error::TchLoad {
                path: path.to_path_buf(),
                message: e.to_string(),
            })?;
        module.f_set_eval().map_err(|e| Error::TchLoad {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        Ok(TchModel {
            module,
            source: path.to_path_buf(),
            check_finite: opts.check_finite,
            d_vis: Vec::new(),
        })
    }

    /// The file this model was loaded from.
    pub fn source(&self) -> &Path {
        &self.source
    }
}

fn model_err(e: impl std::fmt::Display) -> pir2_runtime::Error {
    pir2_runtime::Error::Model(format!("libtorch: {e}"))
}

fn tensor(data: &[f32], shape: &[i64]) -> pir2_runtime::Result<Tensor> {
    Tensor::f_from_slice(data)
        .and_then(|t| t.f_reshape(shape))
        .map_err(model_err)
}

impl VelocityModel for TchModel {
    fn backend(&self) -> &'static str {
        "libtorch"
    }

    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        input.validate()?;
        let (b, h, a) = (input.batch, input.horizon, input.action_dim);
        if b == 0 {
            return Err(pir2_runtime::Error::shape("batch B", ">= 1", 0));
        }
        if out.len() != b * h * a {
            return Err(pir2_runtime::Error::shape(
                "out [B,H,A]",
                b * h * a,
                out.len(),
            ));
        }
        let _guard = ::tch::no_grad_guard();
        let bi = b as i64;
        let x = tensor(input.x, &[bi, h as i64, a as i64])?;
        let tau = tensor(input.tau, &[bi, h as i64])?;
        let obs = tensor(
            input.obs_fast,
            &[bi, input.n_obs as i64, input.fast_dim as i64],
        )?;
        let slow = match input.slow {
            SlowInput::None => {
                Tensor::f_zeros([bi, 0], (Kind::Float, Device::Cpu)).map_err(model_err)?
            }
            SlowInput::Vector { data, dim } => tensor(data, &[bi, dim as i64])?,
            SlowInput::Tokens { data, tokens, dim } => {
                tensor(data, &[bi, tokens as i64, dim as i64])?
            }
        };
        self.d_vis.clear();
        self.d_vis.extend(input.d_vis.iter().map(|&d| i64::from(d)));
        let d_vis = Tensor::f_from_slice(&self.d_vis).map_err(model_err)?;
        let v = self
            .module
            .forward_ts(&[x, tau, obs, slow, d_vis])
            .map_err(model_err)?;
        let size = v.size();
        if size != [bi, h as i64, a as i64] {
            return Err(pir2_runtime::Error::shape(
                format!("module output v [B,H,A] (`{}`)", self.source.display()),
                [b, h, a],
                size,
            ));
        }
        let v = v
            .f_to_kind(Kind::Float)
            .and_then(|t| t.f_contiguous())
            .map_err(model_err)?;
        v.f_copy_data(out, b * h * a).map_err(model_err)?;
        if self.check_finite {
            if let Some(index) = out.iter().position(|x| !x.is_finite()) {
                return Err(pir2_runtime::Error::NonFinite { index });
            }
        }
        Ok(())
    }
}

/// Trace `forward` (a closure over the five contract tensors) into a TorchScript module and
/// save it to `path`. `example` gives the example inputs `[x, tau, obs_fast, obs_slow, d_vis]`
/// used for tracing (the batch size stays dynamic only if `forward` uses no batch-size constants).
pub fn trace_to_file<F>(path: &Path, example: &[Tensor; 5], mut forward: F) -> Result<()>
where
    F: FnMut(&Tensor, &Tensor, &Tensor, &Tensor, &Tensor) -> Tensor,
{
    let err = |e: ::tch::TchError| Error::TchTrace {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let _guard = ::tch::no_grad_guard();
    let mut closure = |xs: &[Tensor]| vec![forward(&xs[0], &xs[1], &xs[2], &xs[3], &xs[4])];
    let module = CModule::create_by_tracing("Pir2Velocity", "forward", example, &mut closure)
        .map_err(err)?;
    module.save(path).map_err(err)
}

/// Example inputs (batch 2, zeros) with the contract shapes of `dims`, for tracing.
pub fn example_inputs(dims: &crate::export::ContractDims) -> [Tensor; 5] {
    use crate::export::SlowSpec;
    let f = (Kind::Float, Device::Cpu);
    let (h, a) = (dims.horizon as i64, dims.action_dim as i64);
    let slow = match dims.slow {
        SlowSpec::None => Tensor::zeros([2, 0], f),
        SlowSpec::Vector { dim } => Tensor::zeros([2, dim as i64], f),
        SlowSpec::Tokens { tokens, dim } => Tensor::zeros([2, tokens as i64, dim as i64], f),
    };
    [
        Tensor::zeros([2, h, a], f),
        Tensor::zeros([2, h], f),
        Tensor::zeros([2, dims.n_obs as i64, dims.fast_dim as i64], f),
        slow,
        Tensor::zeros([2], (Kind::Int64, Device::Cpu)),
    ]
}

/// Trace a model definition ([`crate::export::ModelSpec`], the same one the ONNX exporter
/// writes) with `weights` into a TorchScript file that [`TchModel`] loads.
pub fn export_torchscript<W: crate::export::ops::WeightSource>(
    spec: &crate::export::ModelSpec,
    weights: &W,
    path: &Path,
) -> Result<()> {
    use crate::export::models::Inputs;
    use crate::export::SlowSpec;
    let has_slow = spec.dims().slow != SlowSpec::None;
    let example = example_inputs(spec.dims());
    let inputs = |xs: &[Tensor]| Inputs {
        x: TchValue(xs[0].shallow_clone()),
        tau: TchValue(xs[1].shallow_clone()),
        obs_fast: TchValue(xs[2].shallow_clone()),
        obs_slow: has_slow.then(|| TchValue(xs[3].shallow_clone())),
        d_vis: Some(TchValue(xs[4].shallow_clone())),
    };
    // Eager run first: validates the weights and creates every constant outside the trace.
    let mut rec = TchOps::record();
    {
        let _guard = ::tch::no_grad_guard();
        spec.forward(&mut rec, weights, &inputs(&example))?;
    }
    let mut ops = TchOps::replay(rec);
    let mut failure: Option<Error> = None;
    trace_to_file(path, &example, |x, tau, obs, slow, d_vis| {
        let xs = [
            x.shallow_clone(),
            tau.shallow_clone(),
            obs.shallow_clone(),
            slow.shallow_clone(),
            d_vis.shallow_clone(),
        ];
        match spec.forward(&mut ops, weights, &inputs(&xs)) {
            Ok(v) => v.0,
            Err(e) => {
                failure = Some(e);
                x.shallow_clone()
            }
        }
    })?;
    match failure {
        Some(e) => Err(e),
        None => Ok(()),
    }
}
