//! The backends' error type: one sectioned enum and a [`Result`] alias.

use std::path::PathBuf;

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
    /// An input slice had the wrong length.
    #[error("shape mismatch for `{what}`: expected {expected}, got {got}")]
    Shape {
        /// The tensor or slice.
        what: String,
        /// Expected length/shape.
        expected: String,
        /// Received length/shape.
        got: String,
    },
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

    // ---- export and native backends ----
    /// ONNX export failed (names the model and the weight or option).
    #[error(transparent)]
    Export(#[from] crate::export::ExportError),
    /// The ONNX Runtime backend could not load its library or a model.
    #[cfg(feature = "ort")]
    #[error(transparent)]
    Ort(#[from] crate::ort::OrtError),
    /// The libtorch backend could not load, trace or save a module.
    #[cfg(feature = "tch")]
    #[error(transparent)]
    Tch(#[from] crate::tch::TchError),

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
    /// Convenience constructor for [`Error::Shape`].
    pub fn shape(
        what: impl Into<String>,
        expected: impl std::fmt::Debug,
        got: impl std::fmt::Debug,
    ) -> Self {
        Error::Shape {
            what: what.into(),
            expected: format!("{expected:?}"),
            got: format!("{got:?}"),
        }
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
            Error::Shape {
                what,
                expected,
                got,
            } => pir2_runtime::Error::Shape {
                what,
                expected,
                got,
            },
            Error::Schedule(s) => pir2_runtime::Error::Schedule(s),
            other => pir2_runtime::Error::Model(other.to_string()),
        }
    }
}
