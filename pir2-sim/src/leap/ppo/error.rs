//! Errors of the PPO trainer and of the PPO expert.

use std::path::PathBuf;

use crate::leap::LeapError;

/// Errors raised while training, checkpointing or loading a PPO policy.
#[derive(Debug, thiserror::Error)]
pub enum PpoError {
    /// The environment could not be built.
    #[error(transparent)]
    Leap(#[from] LeapError),
    /// A configuration value is out of range.
    #[error("invalid PPO configuration: {0}")]
    Config(String),
    /// Reading or writing a file failed.
    #[error("{action} {path}: {source}")]
    Io {
        /// What was being done ("cannot write", ...).
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A weights or checkpoint file is malformed or does not match the configuration.
    #[error("{path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// Training produced a non-finite loss, gradient or parameter (fail closed: the
    /// checkpoint on disk is the last good state).
    #[error("training diverged at iteration {iteration}: {what} is not finite")]
    Diverged {
        /// The PPO iteration.
        iteration: u64,
        /// Which quantity.
        what: &'static str,
    },
}

/// Result alias of the PPO module.
pub type Result<T> = std::result::Result<T, PpoError>;
