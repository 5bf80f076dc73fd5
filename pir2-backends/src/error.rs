//! The backends' error type: one sectioned enum (configuration, shapes and tensors, training,
//! files, ONNX export, the native backends) and a [`Result`] alias.

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
}

impl From<Error> for pir2_runtime::Error {
    fn from(e: Error) -> Self {
        match e {
            Error::Shape(s) => pir2_runtime::Error::Shape(s),
            Error::Schedule(s) => pir2_runtime::Error::Schedule(s),
            other => pir2_runtime::Error::Model(other.to_string()),
        }
    }
}
