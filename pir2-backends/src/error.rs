//! The crate's error type.

/// Errors of `pir2-backends`.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    // ---- export ----
    /// ONNX export failed.
    #[error(transparent)]
    Export(#[from] crate::onnx::ExportError),

    // ---- native backends ----
    /// The ONNX Runtime backend failed to load a library or model.
    #[cfg(feature = "ort")]
    #[error(transparent)]
    Ort(#[from] crate::ort::OrtError),
    /// The libtorch backend failed to load a module.
    #[cfg(feature = "tch")]
    #[error(transparent)]
    Tch(#[from] crate::tch::TchError),

    // ---- runtime ----
    /// An error from the runtime's model contract (shapes, non-finite outputs).
    #[error(transparent)]
    Runtime(#[from] pir2_runtime::Error),
}

/// Result alias for `pir2-backends`.
pub type Result<T, E = Error> = std::result::Result<T, E>;
