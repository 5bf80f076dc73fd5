//! The backends' error type: one sectioned enum (configuration, shapes and tensors, training,
//! files, ONNX export, the native backends, the GR00T stack) and a [`Result`] alias.
//!
//! The GR00T stack's variants exist with feature `gr00t`; those whose bare name would say
//! less than the crate's own (`Config`, `Contract`, `Candle`) carry a `Gr00t` prefix. Errors
//! leave the crate one way only: into the runtime's [`pir2_runtime::Error`] when they cross
//! its traits; the runtime's errors come in unchanged (`Error::Runtime`, with `gr00t`) and
//! go back out as themselves.

use std::fmt::Debug;
use std::path::PathBuf;

use pir2_runtime::ShapeMismatch;

/// Errors of model construction, checkpoints, inference and training.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    // ---- configuration ----
    /// A configuration value is invalid; names the field.
    #[error("invalid model/training configuration `{field}`: {message}")]
    Config {
        /// The offending field.
        field: &'static str,
        /// What is wrong and the allowed range.
        message: String,
    },
    /// A checkpoint was built for a different spec than the caller expects.
    #[error("checkpoint spec mismatch in `{field}`: expected {expected}, checkpoint has {found}")]
    SpecMismatch {
        /// The spec field that differs.
        field: &'static str,
        /// What the caller expects.
        expected: String,
        /// What the checkpoint declares.
        found: String,
    },
    /// A schedule error from `pir2-schedule`.
    #[error(transparent)]
    Schedule(#[from] pir2_schedule::Error),

    // ---- shapes and tensors ----
    /// An input slice had the wrong length (the runtime's payload, handed on unchanged).
    #[error(transparent)]
    Shape(#[from] ShapeMismatch),
    /// A checkpoint lacks a tensor the model needs.
    #[error("checkpoint {path}: missing tensor `{name}`")]
    MissingTensor {
        /// Checkpoint file.
        path: PathBuf,
        /// The tensor's name.
        name: String,
    },
    /// A checkpoint tensor has the wrong shape or dtype.
    #[error(
        "checkpoint {path}: tensor `{name}` has shape {got:?}, the model expects {expected:?}"
    )]
    TensorShape {
        /// Checkpoint file.
        path: PathBuf,
        /// The tensor's name.
        name: String,
        /// Shape the model expects.
        expected: Vec<usize>,
        /// Shape found.
        got: Vec<usize>,
    },
    /// A checkpoint holds a tensor the model does not know (wrong config?).
    #[error("checkpoint {path}: unexpected tensor `{name}` (does the config match the weights?)")]
    UnexpectedTensor {
        /// Checkpoint file.
        path: PathBuf,
        /// The tensor's name.
        name: String,
    },

    /// Training was stopped from outside ([`crate::train::Trainer::stop_on`]); with an output
    /// directory the training state at `step` is on disk and a resumed run continues from it.
    #[error(
        "training interrupted at step {step}{}; run again with resume to continue from there",
        match .resume_point { Some(p) => format!(" (training state saved in {})", p.display()), None => String::new() }
    )]
    Interrupted {
        /// Steps done.
        step: usize,
        /// The checkpoint a resumed run continues from, if any was written.
        resume_point: Option<PathBuf>,
    },

    // ---- files ----
    /// Refusing to overwrite an existing checkpoint directory.
    #[error("checkpoint directory {0} already exists; refusing to overwrite it")]
    CheckpointExists(PathBuf),
    /// File I/O failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A JSON/TOML file could not be parsed or written.
    #[error("{path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// Parser message.
        message: String,
    },
    /// The safetensors file is malformed.
    #[error("{path}: safetensors: {message}")]
    Safetensors {
        /// The file.
        path: PathBuf,
        /// Library message.
        message: String,
    },

    // ---- ONNX export ([`crate::export`]) ----
    /// A weight the exporter needs is missing from the checkpoint.
    #[error("ONNX export of {model}: weight `{name}` is missing")]
    MissingWeight {
        /// The model kind.
        model: &'static str,
        /// The weight's name.
        name: String,
    },
    /// A weight has the wrong shape.
    #[error("ONNX export of {model}: weight `{name}` has shape {got:?}, expected {expected:?}")]
    WeightShape {
        /// The model kind.
        model: &'static str,
        /// The weight's name.
        name: String,
        /// Expected shape.
        expected: Vec<usize>,
        /// Shape found.
        got: Vec<usize>,
    },
    /// The model's configuration cannot be expressed in ONNX (e.g. an unsupported option).
    #[error("ONNX export of {model}: {message}")]
    Unsupported {
        /// The model kind.
        model: &'static str,
        /// What is not supported.
        message: String,
    },
    /// Writing an ONNX file failed.
    #[error("cannot write ONNX file {path}: {source}")]
    OnnxWrite {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },

    // ---- ONNX Runtime backend ([`crate::ort`], feature `ort`) ----
    /// The ONNX Runtime shared library could not be loaded.
    #[cfg(feature = "ort")]
    #[error(
        "cannot load ONNX Runtime from `{path}` (expected version {expected}; set ORT_DYLIB_PATH, \
         e.g. `source .native/env.sh` after scripts/setup-native.sh): {reason}"
    )]
    OrtLoad {
        /// The path tried.
        path: PathBuf,
        /// The expected version.
        expected: &'static str,
        /// Why it failed.
        reason: String,
    },
    /// The ONNX Runtime shared library has the wrong version.
    #[cfg(feature = "ort")]
    #[error("ONNX Runtime at `{path}` is version {found}, expected {expected}")]
    OrtVersion {
        /// The library loaded.
        path: PathBuf,
        /// Its version string.
        found: String,
        /// The expected version.
        expected: &'static str,
    },
    /// ONNX Runtime refused to create a session (bad file, unsupported operator, …).
    #[cfg(feature = "ort")]
    #[error("ONNX Runtime could not load the model `{path}`: {message}")]
    OrtSession {
        /// The model file (or `<memory>`).
        path: PathBuf,
        /// ONNX Runtime's message.
        message: String,
    },
    /// The execution provider asked for is not in the loaded library or cannot start.
    #[cfg(feature = "ort")]
    #[error("ONNX Runtime {version} at `{path}` cannot run on {provider}: {reason}")]
    OrtProvider {
        /// ONNX Runtime's name of the provider.
        provider: &'static str,
        /// The library loaded.
        path: PathBuf,
        /// Its version.
        version: String,
        /// Why (what the library offers instead, or ONNX Runtime's message).
        reason: String,
    },
    /// The model does not follow the graph contract ([`crate::export::contract`]).
    #[cfg(feature = "ort")]
    #[error("ONNX model `{path}` does not follow the pir2 contract: {message}")]
    OrtContract {
        /// The model file (or `<memory>`).
        path: PathBuf,
        /// What is wrong.
        message: String,
    },

    // ---- libtorch backend ([`crate::tch`], feature `tch`) ----
    /// The TorchScript file could not be loaded.
    #[cfg(feature = "tch")]
    #[error("libtorch could not load the TorchScript module `{path}`: {message}")]
    TchLoad {
        /// The file.
        path: PathBuf,
        /// libtorch's message.
        message: String,
    },
    /// Tracing a closure into a module, or saving it, failed.
    #[cfg(feature = "tch")]
    #[error("libtorch could not trace/save the module `{path}`: {message}")]
    TchTrace {
        /// The destination file.
        path: PathBuf,
        /// libtorch's message.
        message: String,
    },

    // ---- backend / training ----
    /// The candle backend failed.
    #[cfg(feature = "candle")]
    #[error("candle: {0}")]
    Candle(#[from] candle_core::Error),
    /// Training diverged (non-finite loss).
    #[error("training diverged at step {step}: loss = {loss}")]
    Diverged {
        /// The step.
        step: usize,
        /// The loss seen.
        loss: f32,
    },
    /// The dataset cannot feed the trainer.
    #[error("dataset: {0}")]
    Dataset(String),

    // ---- the GR00T stack ([`crate::gr00t`], feature `gr00t`) ----
    // -- files --
    /// A file could not be read.
    #[cfg(feature = "gr00t")]
    #[error("cannot read `{path}`: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A file could not be parsed (JSON, TOML, safetensors, vocabulary, tokenizer).
    #[cfg(feature = "gr00t")]
    #[error("cannot parse `{path}`: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A recorded call of the GR00T action head (`Gr00tActionHead::record_nfe`) could not
    /// be written.
    #[cfg(feature = "gr00t")]
    #[error("cannot write the recorded NFE `{path}`: {message}")]
    NfeRecord {
        /// The file (or the directory).
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// The checkpoint has no tokenizer file.
    #[cfg(feature = "gr00t")]
    #[error("no tokenizer: neither `{tokenizer}` nor `{vocab}` exists")]
    NoTokenizer {
        /// The VLM's Hugging Face tokenizer (preferred).
        tokenizer: PathBuf,
        /// The vocabulary file of older pir2 checkpoints.
        vocab: PathBuf,
    },
    /// The embodiment configuration is inconsistent.
    #[cfg(feature = "gr00t")]
    #[error("invalid GR00T embodiment configuration: {0}")]
    Gr00tConfig(String),
    /// A normalisation statistic is missing or malformed.
    #[cfg(feature = "gr00t")]
    #[error("statistics file `{path}`: `{key}` {problem}")]
    Statistics {
        /// The statistics file.
        path: PathBuf,
        /// `embodiment.modality.group.stat`.
        key: String,
        /// What is wrong.
        problem: String,
    },
    /// A weight in the pir2 side file (`pir2_gr00t.safetensors`) is missing or malformed.
    #[cfg(feature = "gr00t")]
    #[error("weights file `{path}`: tensor `{tensor}` {problem}")]
    Weights {
        /// The safetensors file.
        path: PathBuf,
        /// The tensor name.
        tensor: String,
        /// What is wrong.
        problem: String,
    },

    /// The checkpoint's backbone files do not form one backbone: the fused `backbone.onnx`
    /// and the split ViT + LLM set both present, or a split set with a file missing.
    #[cfg(feature = "gr00t")]
    #[error("backbone files of `{dir}`: {problem}")]
    BackboneFiles {
        /// The checkpoint directory.
        dir: PathBuf,
        /// Which files are present and which are missing.
        problem: String,
    },

    /// A GR00T checkpoint being imported (`gr00t::import`) has a file or a field pir2
    /// cannot map: the file, the field (a JSON path, or a tensor name) and why.
    #[cfg(feature = "gr00t")]
    #[error("import: `{path}`: `{field}` {problem}")]
    Import {
        /// The file of the GR00T checkpoint (or the output directory).
        path: PathBuf,
        /// The field (`processor_kwargs.modality_configs.TAG.action.delta_indices`), the
        /// tensor name, or the file's own name when the file is missing.
        field: String,
        /// What is wrong and, where there is one, the way out.
        problem: String,
    },
    /// An ONNX file could not be rewritten from bfloat16 to float32 (`gr00t::onnx_f32`).
    #[cfg(feature = "gr00t")]
    #[error("ONNX model `{path}`: {what}: {problem}")]
    OnnxRewrite {
        /// The ONNX file (or its external-data file).
        path: PathBuf,
        /// The message or tensor concerned, e.g. "initializer `w`".
        what: String,
        /// What is wrong.
        problem: String,
    },

    // -- ONNX contract --
    /// An ONNX file does not meet the GR00T export contract (see `docs/gr00t-contract.md`).
    #[cfg(feature = "gr00t")]
    #[error("ONNX model `{path}` breaks the GR00T contract at `{tensor}`: {problem}")]
    Gr00tContract {
        /// The ONNX file.
        path: PathBuf,
        /// The input/output name concerned.
        tensor: String,
        /// What is wrong.
        problem: String,
    },
    /// The execution provider has no kernel for an op of a graph at its element types (e.g.
    /// a `bfloat16` graph on the CPU provider).
    #[cfg(feature = "gr00t")]
    #[error(
        "ONNX model `{path}` ({role}) cannot run on {provider}: ONNX Runtime has no kernel \
         for {op} there; {hint}"
    )]
    NoKernel {
        /// The ONNX file.
        path: PathBuf,
        /// Its role, e.g. "LLM".
        role: &'static str,
        /// ONNX Runtime's name of the provider, e.g. `CPUExecutionProvider`.
        provider: &'static str,
        /// The op with its opset version and the node, as ONNX Runtime names them, e.g.
        /// "MatMul(13) at node `/layers.0/mlp/MatMul`".
        op: String,
        /// What to do.
        hint: String,
    },
    /// Running an ONNX graph failed.
    #[cfg(feature = "gr00t")]
    #[error("running `{path}`: {message}")]
    Run {
        /// The ONNX file.
        path: PathBuf,
        /// ONNX Runtime's message.
        message: String,
    },

    // -- inputs --
    /// The prompt tokenizer failed.
    #[cfg(feature = "gr00t")]
    #[error("tokenizer: {0}")]
    Tokenizer(String),
    /// An input had the wrong size.
    #[cfg(feature = "gr00t")]
    #[error("GR00T input `{what}`: expected {expected}, got {got}")]
    Input {
        /// What was being checked.
        what: String,
        /// Expected.
        expected: String,
        /// Received.
        got: String,
    },

    /// Writing the example checkpoint (`pir2 gr00t example`) failed.
    #[cfg(feature = "gr00t")]
    #[error("example checkpoint `{path}`: {message}")]
    Example {
        /// The file or directory concerned.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },

    // -- test support --
    /// Writing a synthetic test checkpoint failed (`gr00t::testing`).
    #[cfg(feature = "gr00t")]
    #[error("synthetic GR00T checkpoint: {0}")]
    Fixture(String),

    // -- runtime --
    /// An error of the runtime (driver, robot, camera).
    #[cfg(feature = "gr00t")]
    #[error(transparent)]
    Runtime(#[from] pir2_runtime::Error),
    /// The candle action head (`Gr00tCandleHead`) failed to load or to run.
    #[cfg(feature = "gr00t")]
    #[error("candle GR00T N1.7 head `{path}`: {source}")]
    Gr00tCandle {
        /// The step / checkpoint directory of the head.
        path: PathBuf,
        /// What candle reported.
        source: Box<Error>,
    },
}

/// Result alias for the backends.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// [`Error::Shape`] of [`ShapeMismatch::new`].
    pub fn shape(what: impl Into<String>, expected: impl Debug, got: impl Debug) -> Self {
        ShapeMismatch::new(what, expected, got).into()
    }
    /// Convenience constructor for [`Error::Io`].
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
    /// Convenience constructor for [`Error::Config`].
    pub fn config(field: &'static str, message: impl Into<String>) -> Self {
        Error::Config {
            field,
            message: message.into(),
        }
    }
    /// [`Error::Input`]: a GR00T input of the wrong size.
    #[cfg(feature = "gr00t")]
    pub(crate) fn input(
        what: impl Into<String>,
        expected: impl std::fmt::Display,
        got: impl std::fmt::Display,
    ) -> Self {
        Error::Input {
            what: what.into(),
            expected: expected.to_string(),
            got: got.to_string(),
        }
    }
    /// Whether this is an error of the GR00T stack (its messages cross into the runtime
    /// prefixed `gr00t: `).
    #[cfg(feature = "gr00t")]
    fn is_gr00t(&self) -> bool {
        matches!(
            self,
            Error::Read { .. }
                | Error::Parse { .. }
                | Error::NoTokenizer { .. }
                | Error::Gr00tConfig(_)
                | Error::Statistics { .. }
                | Error::Weights { .. }
                | Error::BackboneFiles { .. }
                | Error::Import { .. }
                | Error::OnnxRewrite { .. }
                | Error::Gr00tContract { .. }
                | Error::NoKernel { .. }
                | Error::Run { .. }
                | Error::Tokenizer(_)
                | Error::Input { .. }
                | Error::Example { .. }
                | Error::Fixture(_)
                | Error::Gr00tCandle { .. }
                | Error::NfeRecord { .. }
        )
    }
    /// Without feature `gr00t` there is no GR00T stack.
    #[cfg(not(feature = "gr00t"))]
    fn is_gr00t(&self) -> bool {
        false
    }
}

/// Errors crossing into the runtime's traits become [`pir2_runtime::Error`]s that keep the
/// message; the runtime's own errors, shapes and schedules go back unchanged, a GR00T input
/// of the wrong size as a [`pir2_runtime::Error::Shape`].
impl From<Error> for pir2_runtime::Error {
    fn from(e: Error) -> Self {
        match e {
            Error::Shape(s) => pir2_runtime::Error::Shape(s),
            Error::Schedule(s) => pir2_runtime::Error::Schedule(s),
            #[cfg(feature = "gr00t")]
            Error::Runtime(r) => r,
            #[cfg(feature = "gr00t")]
            Error::Input {
                what,
                expected,
                got,
            } => pir2_runtime::Error::Shape(ShapeMismatch {
                what,
                expected,
                got,
            }),
            other if other.is_gr00t() => pir2_runtime::Error::Model(format!("gr00t: {other}")),
            other => pir2_runtime::Error::Model(other.to_string()),
        }
    }
}
