//! The GR00T stack's error type.

use std::path::PathBuf;

/// Errors of the GR00T stack (feature `gr00t`).
#[derive(Debug, thiserror::Error)]
pub enum Gr00tError {
    // ---- files ----
    /// A file could not be read.
    #[error("cannot read `{path}`: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A file could not be parsed (JSON, TOML, safetensors, vocabulary, tokenizer).
    #[error("cannot parse `{path}`: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// The checkpoint has no tokenizer file.
    #[error("no tokenizer: neither `{tokenizer}` nor `{vocab}` exists")]
    NoTokenizer {
        /// The VLM's Hugging Face tokenizer (preferred).
        tokenizer: PathBuf,
        /// The vocabulary file of older pir2 checkpoints.
        vocab: PathBuf,
    },
    /// The embodiment configuration is inconsistent.
    #[error("invalid GR00T embodiment configuration: {0}")]
    Config(String),
    /// A normalisation statistic is missing or malformed.
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
    #[error("backbone files of `{dir}`: {problem}")]
    BackboneFiles {
        /// The checkpoint directory.
        dir: PathBuf,
        /// Which files are present and which are missing.
        problem: String,
    },

    /// A GR00T checkpoint being imported (`gr00t::import`) has a file or a field pir2
    /// cannot map: the file, the field (a JSON path, or a tensor name) and why.
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
    #[error("ONNX model `{path}`: {what}: {problem}")]
    OnnxRewrite {
        /// The ONNX file (or its external-data file).
        path: PathBuf,
        /// The message or tensor concerned, e.g. "initializer `w`".
        what: String,
        /// What is wrong.
        problem: String,
    },

    // ---- ONNX contract ----
    /// An ONNX file does not meet the GR00T export contract (see `docs/gr00t-contract.md`).
    #[error("ONNX model `{path}` breaks the GR00T contract at `{tensor}`: {problem}")]
    Contract {
        /// The ONNX file.
        path: PathBuf,
        /// The input/output name concerned.
        tensor: String,
        /// What is wrong.
        problem: String,
    },
    /// The execution provider has no kernel for an op of a graph at its element types (e.g.
    /// a `bfloat16` graph on the CPU provider).
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
    /// ONNX Runtime failed (loading the library, creating a session, running a graph).
    #[error(transparent)]
    Ort(#[from] crate::error::Error),
    /// Running an ONNX graph failed.
    #[error("running `{path}`: {message}")]
    Run {
        /// The ONNX file.
        path: PathBuf,
        /// ONNX Runtime's message.
        message: String,
    },

    // ---- inputs ----
    /// The prompt tokenizer failed.
    #[error("tokenizer: {0}")]
    Tokenizer(String),
    /// An input had the wrong size.
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
    #[error("example checkpoint `{path}`: {message}")]
    Example {
        /// The file or directory concerned.
        path: std::path::PathBuf,
        /// What went wrong.
        message: String,
    },

    // ---- test support ----
    /// Writing a synthetic test checkpoint failed ([`super::testing`]).
    #[error("synthetic GR00T checkpoint: {0}")]
    Fixture(String),

    // ---- runtime ----
    /// An error of the runtime (driver, robot, camera).
    #[error(transparent)]
    Runtime(#[from] pir2_runtime::Error),
    /// The candle action head (`Gr00tCandleHead`) failed to load or to run.
    #[error("candle GR00T N1.7 head `{path}`: {source}")]
    Candle {
        /// The step / checkpoint directory of the head.
        path: std::path::PathBuf,
        /// What candle reported.
        source: Box<crate::error::Error>,
    },
}

impl Gr00tError {
    pub(crate) fn input(
        what: impl Into<String>,
        expected: impl std::fmt::Display,
        got: impl std::fmt::Display,
    ) -> Self {
        Gr00tError::Input {
            what: what.into(),
            expected: expected.to_string(),
            got: got.to_string(),
        }
    }
}

/// Errors crossing into the runtime's traits become [`pir2_runtime::Error`]s that keep the
/// message (and the runtime's own errors unchanged).
impl From<Gr00tError> for pir2_runtime::Error {
    fn from(e: Gr00tError) -> Self {
        match e {
            Gr00tError::Runtime(r) => r,
            Gr00tError::Input {
                what,
                expected,
                got,
            } => pir2_runtime::Error::Shape(pir2_runtime::ShapeMismatch {
                what,
                expected,
                got,
            }),
            other => pir2_runtime::Error::Model(format!("gr00t: {other}")),
        }
    }
}

/// Result alias of the GR00T stack.
pub type Result<T, E = Gr00tError> = std::result::Result<T, E>;
