//! ONNX Runtime backend ([`OrtModel`], feature `ort`).
//!
//! One file on purpose (execution providers are in `provider.rs`): loading the library, the
//! session set-up, the contract check of a graph's inputs and outputs and [`OrtModel`]'s
//! `VelocityModel` calls share the session, its tensor list and its bound shapes, and must
//! change together.
//!
//! # The graph contract
//!
//! One ONNX graph per model, called once per NFE (see [`crate::export::contract`]):
//!
//! | name       | type    | shape                   |                                           |
//! |------------|---------|-------------------------|-------------------------------------------|
//! | `x`        | float32 | `[B, H, A]`             | required                                  |
//! | `tau`      | float32 | `[B, H]`                | required                                  |
//! | `obs_fast` | float32 | `[B, n_obs, F]`         | required                                  |
//! | `obs_slow` | float32 | `[B, S]` or `[B, T, D]` | optional (the model's slow input)         |
//! | `d_vis`    | int64   | `[B]`                   | optional (fed when declared)              |
//! | `v`        | float32 | `[B, H, A]`             | output                                    |
//!
//! `B` may be dynamic; `H, A, n_obs, F, S, T, D` must be fixed in the file. A loaded model is
//! checked against this table (names, element types, ranks, dimensions) and rejected with an
//! [`Error::OrtContract`] naming the file, the tensor and what was wrong. Files written by
//! [`crate::export`] follow the contract by construction.
//!
//! # Loading ONNX Runtime
//!
//! The shared library is loaded at run time, once per process, from the first of:
//! 1. the `ORT_DYLIB_PATH` environment variable (set by `source .native/env.sh`),
//! 2. the explicit path in [`OrtOptions::dylib_path`],
//! 3. the platform default (`libonnxruntime.so` / `libonnxruntime.dylib` / `onnxruntime.dll`
//!    on the loader's search path).
//!
//! Its version must be `1.31.x` or a newer `1.x` (the C API is backward compatible); the error
//! names the path tried and the expected version. After the first successful load, later calls
//! reuse that library whatever path they name (ONNX Runtime allows one environment per process).
//!
//! Sessions are single-threaded by default (`intra_op = inter_op = 1`, sequential execution):
//! one NFE at batch 1 is latency-bound, and the control loop's other threads must not be
//! starved by a thread pool spinning on the same cores.

use std::ffi::{c_char, CStr};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use ::ort::session::builder::GraphOptimizationLevel;
use ::ort::session::{Session, SessionInputValue};
use ::ort::value::{TensorElementType, TensorRef, ValueType};
use ndarray::{ArrayView1, ArrayView2, ArrayView3};
use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

use crate::error::{Error, Result};
use crate::export::contract::{self, describe_slow, ContractDims, SlowSpec};

mod provider;
pub use provider::Provider;

/// The ONNX Runtime version this backend is built and tested against.
pub const EXPECTED_VERSION: &str = "1.31.x";
const MIN_MINOR: u32 = 31;

/// Options for [`OrtModel`].
#[derive(Debug, Clone)]
pub struct OrtOptions {
    /// Explicit library path, used when `ORT_DYLIB_PATH` is not set.
    pub dylib_path: Option<PathBuf>,
    /// Intra-op threads (default 1).
    pub intra_threads: usize,
    /// Inter-op threads (default 1).
    pub inter_threads: usize,
    /// Check every output for NaN/inf and fail with [`pir2_runtime::Error::NonFinite`] (default on).
    pub check_finite: bool,
    /// Where the graphs run (default the CPU; see [`Provider`]).
    pub provider: Provider,
}

impl Default for OrtOptions {
    fn default() -> Self {
        OrtOptions {
            dylib_path: None,
            intra_threads: 1,
            inter_threads: 1,
            check_finite: true,
            provider: Provider::Cpu,
        }
    }
}

/// The loaded ONNX Runtime library and its (single, process-wide) environment.
pub struct OrtRuntime {
    path: PathBuf,
    version: String,
    env: ::ort::environment::Environment,
}

impl std::fmt::Debug for OrtRuntime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OrtRuntime")
            .field("path", &self.path)
            .field("version", &self.version)
            .finish()
    }
}

impl OrtRuntime {
    /// The library file loaded.
    pub fn path(&self) -> &Path {
        &self.path
    }
    /// Its version string, e.g. `1.31.1`.
    pub fn version(&self) -> &str {
        &self.version
    }
    /// The process-wide ONNX Runtime environment, for callers that build their own sessions
    /// (e.g. the multi-graph GR00T action head).
    pub fn environment(&self) -> &::ort::environment::Environment {
        &self.env
    }
}

static RUNTIME: Mutex<Option<&'static OrtRuntime>> = Mutex::new(None);

/// Resolve the library path: `ORT_DYLIB_PATH`, then `explicit`, then the platform default.
pub fn resolve_dylib_path(explicit: Option<&Path>) -> PathBuf {
    match std::env::var_os("ORT_DYLIB_PATH") {
        Some(p) if !p.is_empty() => PathBuf::from(p),
        _ => match explicit {
            Some(p) => p.to_path_buf(),
            None => PathBuf::from(format!(
                "{}onnxruntime{}",
                std::env::consts::DLL_PREFIX,
                std::env::consts::DLL_SUFFIX
            )),
        },
    }
}

/// `OrtApiBase` from `onnxruntime_c_api.h`: the only two entry points the library exports.
#[repr(C)]
struct OrtApiBase {
    _get_api: unsafe extern "system" fn(u32) -> *const std::ffi::c_void,
    get_version_string: unsafe extern "system" fn() -> *const c_char,
}

/// Read the version string of the ONNX Runtime library at `path` without initialising it
/// (diagnostics; [`runtime`] does the same check before loading).
pub fn probe_library(path: &Path) -> Result<String> {
    let load_err = |reason: String| Error::OrtLoad {
        path: path.to_path_buf(),
        expected: EXPECTED_VERSION,
        reason,
    };
    // SAFETY: loading ONNX Runtime runs only its (side-effect free) static initialisers.
    let lib = unsafe { libloading::Library::new(path) }.map_err(|e| load_err(e.to_string()))?;
    // SAFETY: `OrtGetApiBase` has this signature in every ONNX Runtime 1.x release.
    let get_base: libloading::Symbol<'_, unsafe extern "system" fn() -> *const OrtApiBase> =
        unsafe { lib.get(b"OrtGetApiBase") }.map_err(|e| {
            load_err(format!(
                "not an ONNX Runtime library (no `OrtGetApiBase`): {e}"
            ))
        })?;
    // SAFETY: the function takes no arguments and returns a pointer to a static struct.
    let base = unsafe { get_base() };
    if base.is_null() {
        return Err(load_err("`OrtGetApiBase` returned null".to_string()));
    }
    // SAFETY: `base` is non-null and points to a static `OrtApiBase`; the version string is a
    // static NUL-terminated C string.
    let version = unsafe { CStr::from_ptr(((*base).get_version_string)()) }
        .to_string_lossy()
        .into_owned();
    Ok(version)
}

fn version_ok(version: &str) -> bool {
    let mut it = version.split('.');
    let major = it.next().and_then(|s| s.parse::<u32>().ok());
    let minor = it.next().and_then(|s| s.parse::<u32>().ok());
    matches!((major, minor), (Some(1), Some(m)) if m >= MIN_MINOR)
}

/// Load ONNX Runtime once per process (see the module docs for the search order) and
/// return it; later calls return the same runtime.
pub fn runtime(explicit: Option<&Path>) -> Result<&'static OrtRuntime> {
    let mut guard = RUNTIME.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(rt) = *guard {
        return Ok(rt);
    }
    let path = resolve_dylib_path(explicit);
    let version = probe_library(&path)?;
    if !version_ok(&version) {
        return Err(Error::OrtVersion {
            path,
            found: version,
            expected: EXPECTED_VERSION,
        });
    }
    let builder = ::ort::init_from(&path).map_err(|e| Error::OrtLoad {
        path: path.clone(),
        expected: EXPECTED_VERSION,
        reason: e.to_string(),
    })?;
    let env = builder
        .with_name("pir2")
        .with_telemetry(false)
        .build()
        .map_err(|e| Error::OrtLoad {
            path: path.clone(),
            expected: EXPECTED_VERSION,
            reason: format!("cannot create the environment: {e}"),
        })?;
    let rt: &'static OrtRuntime = Box::leak(Box::new(OrtRuntime { path, version, env }));
    *guard = Some(rt);
    Ok(rt)
}

/// A session builder with `opts` applied: full graph optimisation, `intra`/`inter` threads,
/// sequential execution and the execution provider (an unavailable provider is an error,
/// never a silent fallback to the CPU). `path` names the model in errors.
pub fn session_builder(
    rt: &OrtRuntime,
    opts: &OrtOptions,
    path: &Path,
) -> Result<::ort::session::builder::SessionBuilder> {
    let err = |e: String| Error::OrtSession {
        path: path.to_path_buf(),
        message: e,
    };
    let builder = Session::builder(&rt.env)
        .map_err(|e| err(e.to_string()))?
        .with_optimization_level(GraphOptimizationLevel::All)
        .map_err(|e| err(e.to_string()))?
        .with_intra_threads(opts.intra_threads.max(1))
        .map_err(|e| err(e.to_string()))?
        .with_inter_threads(opts.inter_threads.max(1))
        .map_err(|e| err(e.to_string()))?
        .with_parallel_execution(false)
        .map_err(|e| err(e.to_string()))?;
    opts.provider.register(rt, builder)
}

/// A velocity model run by ONNX Runtime (see the module docs for the graph contract).
pub struct OrtModel {
    session: Session,
    dims: ContractDims,
    fixed_batch: Option<usize>,
    source: PathBuf,
    check_finite: bool,
    d_vis: Vec<i64>,
}

impl std::fmt::Debug for OrtModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OrtModel")
            .field("source", &self.source)
            .field("dims", &self.dims)
            .field("fixed_batch", &self.fixed_batch)
            .finish()
    }
}

impl OrtModel {
    /// Load an ONNX file with default options (single thread).
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        Self::load_with(path, &OrtOptions::default())
    }

    /// Load an ONNX file.
    pub fn load_with(path: impl AsRef<Path>, opts: &OrtOptions) -> Result<Self> {
        let path = path.as_ref();
        let rt = runtime(opts.dylib_path.as_deref())?;
        let session = Self::builder(rt, opts, path)?
            .commit_from_file(path)
            .map_err(|e| Error::OrtSession {
                path: path.to_path_buf(),
                message: e.to_string(),
            })?;
        Self::from_session(session, path.to_path_buf(), opts)
    }

    /// Load an ONNX model from bytes (e.g. straight from the exporter).
    pub fn from_bytes(bytes: &[u8], opts: &OrtOptions) -> Result<Self> {
        let path = PathBuf::from("<memory>");
        let rt = runtime(opts.dylib_path.as_deref())?;
        let session = Self::builder(rt, opts, &path)?
            .commit_from_memory(bytes)
            .map_err(|e| Error::OrtSession {
                path: path.clone(),
                message: e.to_string(),
            })?;
        Self::from_session(session, path, opts)
    }

    fn builder(
        rt: &OrtRuntime,
        opts: &OrtOptions,
        path: &Path,
    ) -> Result<::ort::session::builder::SessionBuilder> {
        session_builder(rt, opts, path)
    }

    fn from_session(session: Session, source: PathBuf, opts: &OrtOptions) -> Result<Self> {
        let (dims, fixed_batch) = validate_contract(&session, &source)?;
        Ok(OrtModel {
            session,
            dims,
            fixed_batch,
            source,
            check_finite: opts.check_finite,
            d_vis: Vec::new(),
        })
    }

    /// The model's fixed sizes, read from the file.
    pub fn dims(&self) -> &ContractDims {
        &self.dims
    }

    /// The file this model was loaded from (`<memory>` for [`OrtModel::from_bytes`]).
    pub fn source(&self) -> &Path {
        &self.source
    }

    fn check_input(&self, input: &ModelInput<'_>) -> pir2_runtime::Result<()> {
        input.validate()?;
        let d = &self.dims;
        let chk = |what: &str, want: usize, got: usize| {
            if want == got {
                Ok(())
            } else {
                Err(pir2_runtime::Error::shape(
                    format!("{what} (model `{}`)", self.source.display()),
                    want,
                    got,
                ))
            }
        };
        chk("horizon H", d.horizon, input.horizon)?;
        chk("action_dim A", d.action_dim, input.action_dim)?;
        chk("n_obs", d.n_obs, input.n_obs)?;
        chk("fast_dim F", d.fast_dim, input.fast_dim)?;
        if let Some(b) = self.fixed_batch {
            chk("batch B (fixed in the file)", b, input.batch)?;
        }
        if !d.slow.matches(&input.slow) {
            return Err(pir2_runtime::ShapeMismatch {
                what: format!("obs_slow (model `{}`)", self.source.display()),
                expected: d.slow.describe(),
                got: describe_slow(&input.slow),
            }
            .into());
        }
        if input.batch == 0 {
            return Err(pir2_runtime::Error::shape("batch B", ">= 1", 0));
        }
        Ok(())
    }
}

fn model_err(e: impl std::fmt::Display) -> pir2_runtime::Error {
    pir2_runtime::Error::Model(format!("onnxruntime: {e}"))
}

fn shape_err(what: &str, e: ndarray::ShapeError) -> pir2_runtime::Error {
    pir2_runtime::Error::Model(format!(
        "onnxruntime: cannot view `{what}` as an array: {e}"
    ))
}

impl VelocityModel for OrtModel {
    fn backend(&self) -> &'static str {
        "onnxruntime"
    }

    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        self.check_input(input)?;
        let (b, h, a) = (input.batch, input.horizon, input.action_dim);
        if out.len() != b * h * a {
            return Err(pir2_runtime::Error::shape(
                "out [B,H,A]",
                b * h * a,
                out.len(),
            ));
        }
        self.d_vis.clear();
        self.d_vis.extend(input.d_vis.iter().map(|&d| i64::from(d)));

        let x = ArrayView3::from_shape((b, h, a), input.x).map_err(|e| shape_err("x", e))?;
        let tau = ArrayView2::from_shape((b, h), input.tau).map_err(|e| shape_err("tau", e))?;
        let obs = ArrayView3::from_shape((b, input.n_obs, input.fast_dim), input.obs_fast)
            .map_err(|e| shape_err("obs_fast", e))?;
        let mut feeds: Vec<(std::borrow::Cow<'_, str>, SessionInputValue<'_>)> =
            Vec::with_capacity(5);
        feeds.push((
            contract::X.into(),
            TensorRef::from_array_view(x).map_err(model_err)?.into(),
        ));
        feeds.push((
            contract::TAU.into(),
            TensorRef::from_array_view(tau).map_err(model_err)?.into(),
        ));
        feeds.push((
            contract::OBS_FAST.into(),
            TensorRef::from_array_view(obs).map_err(model_err)?.into(),
        ));
        match input.slow {
            SlowInput::None => {}
            SlowInput::Vector { data, dim } => {
                let s =
                    ArrayView2::from_shape((b, dim), data).map_err(|e| shape_err("obs_slow", e))?;
                feeds.push((
                    contract::OBS_SLOW.into(),
                    TensorRef::from_array_view(s).map_err(model_err)?.into(),
                ));
            }
            SlowInput::Tokens { data, tokens, dim } => {
                let s = ArrayView3::from_shape((b, tokens, dim), data)
                    .map_err(|e| shape_err("obs_slow", e))?;
                feeds.push((
                    contract::OBS_SLOW.into(),
                    TensorRef::from_array_view(s).map_err(model_err)?.into(),
                ));
            }
        }
        if self.dims.has_d_vis {
            let dv =
                ArrayView1::from_shape(b, &self.d_vis[..]).map_err(|e| shape_err("d_vis", e))?;
            feeds.push((
                contract::D_VIS.into(),
                TensorRef::from_array_view(dv).map_err(model_err)?.into(),
            ));
        }
        let outputs = self.session.run(feeds).map_err(model_err)?;
        let v = outputs
            .get(contract::V)
            .ok_or_else(|| model_err("the run returned no `v`"))?;
        let v = v.try_extract_array::<f32>().map_err(model_err)?;
        if v.shape() != [b, h, a] {
            return Err(pir2_runtime::Error::shape(
                "model output v [B,H,A]",
                [b, h, a],
                v.shape(),
            ));
        }
        for (o, &x) in out.iter_mut().zip(v.iter()) {
            *o = x;
        }
        if self.check_finite {
            if let Some(index) = out.iter().position(|x| !x.is_finite()) {
                return Err(pir2_runtime::Error::NonFinite { index });
            }
        }
        Ok(())
    }
}

/// Check a session's inputs/outputs against the contract; return the fixed sizes and the
/// batch size if it is fixed in the file.
fn validate_contract(session: &Session, path: &Path) -> Result<(ContractDims, Option<usize>)> {
    let bad = |message: String| Error::OrtContract {
        path: path.to_path_buf(),
        message,
    };
    let describe = |name: &str, ty: &ValueType| -> Result<(TensorElementType, Vec<i64>)> {
        match (ty.tensor_type(), ty.tensor_shape()) {
            (Some(t), Some(s)) => Ok((t, s.iter().copied().collect())),
            _ => Err(bad(format!("`{name}` must be a tensor, found {ty:?}"))),
        }
    };
    let mut found: Vec<(String, TensorElementType, Vec<i64>)> = Vec::new();
    for i in session.inputs() {
        let (t, s) = describe(i.name(), i.dtype())?;
        found.push((i.name().to_string(), t, s));
    }
    let allowed = [
        contract::X,
        contract::TAU,
        contract::OBS_FAST,
        contract::OBS_SLOW,
        contract::D_VIS,
    ];
    for (n, _, _) in &found {
        if !allowed.contains(&n.as_str()) {
            return Err(bad(format!(
                "unexpected input `{n}` (inputs must be among {allowed:?})"
            )));
        }
    }
    let get = |name: &str| found.iter().find(|(n, _, _)| n == name);
    let mut batch: Option<i64> = None;
    // Checks element type and rank; returns the non-batch dims (must be fixed and positive).
    let mut check = |name: &str,
                     want_ty: TensorElementType,
                     ranks: &[usize],
                     shape: &[i64],
                     ty: TensorElementType|
     -> Result<Vec<usize>> {
        if ty != want_ty {
            return Err(bad(format!(
                "`{name}` has element type {ty:?}, expected {want_ty:?}"
            )));
        }
        if !ranks.contains(&shape.len()) {
            return Err(bad(format!(
                "`{name}` has rank {} (shape {shape:?}), expected rank {ranks:?}",
                shape.len()
            )));
        }
        let b = shape[0];
        if b > 0 {
            match batch {
                Some(prev) if prev > 0 && prev != b => {
                    return Err(bad(format!(
                        "`{name}` has batch {b}, another input has batch {prev}"
                    )));
                }
                _ => batch = Some(b),
            }
        }
        shape[1..]
            .iter()
            .map(|&d| {
                if d > 0 {
                    Ok(d as usize)
                } else {
                    Err(bad(format!("`{name}` has a dynamic dimension (shape {shape:?}); only the batch may be dynamic")))
                }
            })
            .collect()
    };
    let req = |name: &str| get(name).ok_or_else(|| bad(format!("missing input `{name}`")));
    let (_, t, s) = req(contract::X)?;
    let xd = check(contract::X, TensorElementType::Float32, &[3], s, *t)?;
    let (horizon, action_dim) = (xd[0], xd[1]);
    let (_, t, s) = req(contract::TAU)?;
    let td = check(contract::TAU, TensorElementType::Float32, &[2], s, *t)?;
    if td[0] != horizon {
        return Err(bad(format!(
            "`tau` is [B, {}] but `x` has H = {horizon}",
            td[0]
        )));
    }
    let (_, t, s) = req(contract::OBS_FAST)?;
    let od = check(contract::OBS_FAST, TensorElementType::Float32, &[3], s, *t)?;
    let slow = match get(contract::OBS_SLOW) {
        None => SlowSpec::None,
        Some((_, t, s)) => {
            let sd = check(
                contract::OBS_SLOW,
                TensorElementType::Float32,
                &[2, 3],
                s,
                *t,
            )?;
            if sd.len() == 1 {
                SlowSpec::Vector { dim: sd[0] }
            } else {
                SlowSpec::Tokens {
                    tokens: sd[0],
                    dim: sd[1],
                }
            }
        }
    };
    let has_d_vis = match get(contract::D_VIS) {
        None => false,
        Some((_, t, s)) => {
            check(contract::D_VIS, TensorElementType::Int64, &[1], s, *t)?;
            true
        }
    };
    let out = session
        .outputs()
        .iter()
        .find(|o| o.name() == contract::V)
        .ok_or_else(|| {
            bad(format!(
                "missing output `v` (outputs: {:?})",
                session
                    .outputs()
                    .iter()
                    .map(|o| o.name())
                    .collect::<Vec<_>>()
            ))
        })?;
    let (t, s) = describe(contract::V, out.dtype())?;
    if t != TensorElementType::Float32 {
        return Err(bad(format!(
            "output `v` has element type {t:?}, expected Float32"
        )));
    }
    // Shape inference may leave output dims unknown (-1); known dims must agree.
    let ok = s.len() == 3
        && (s[1] <= 0 || s[1] as usize == horizon)
        && (s[2] <= 0 || s[2] as usize == action_dim);
    if !ok {
        return Err(bad(format!(
            "output `v` has shape {s:?}, expected [B, {horizon}, {action_dim}]"
        )));
    }
    let dims = ContractDims {
        horizon,
        action_dim,
        n_obs: od[0],
        fast_dim: od[1],
        slow,
        has_d_vis,
    };
    Ok((dims, batch.filter(|&b| b > 0).map(|b| b as usize)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn version_check_accepts_1_31_and_newer_1_x_only() {
        assert!(version_ok("1.31.1"));
        assert!(version_ok("1.32.0"));
        assert!(!version_ok("1.30.2"));
        assert!(!version_ok("2.0.0"));
        assert!(!version_ok("garbage"));
    }

    #[test]
    fn load_error_names_the_path_and_the_expected_version() {
        let e = probe_library(Path::new("/nonexistent/libonnxruntime.so")).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("/nonexistent/libonnxruntime.so"), "{msg}");
        assert!(msg.contains("1.31.x"), "{msg}");
    }

    #[test]
    fn a_library_that_is_not_onnxruntime_is_named_as_such() {
        // libm exists on every Linux system and has no `OrtGetApiBase`.
        if cfg!(target_os = "linux") {
            let e = probe_library(Path::new("libm.so.6")).unwrap_err();
            assert!(e.to_string().contains("not an ONNX Runtime library"), "{e}");
        }
    }

    #[test]
    fn explicit_path_is_used_only_without_the_environment_variable() {
        let explicit = Path::new("/opt/ort/libonnxruntime.so");
        let got = resolve_dylib_path(Some(explicit));
        match std::env::var_os("ORT_DYLIB_PATH") {
            Some(p) if !p.is_empty() => assert_eq!(got, PathBuf::from(p)),
            _ => assert_eq!(got, explicit),
        }
    }
}
