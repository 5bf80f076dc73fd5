//! The runtime's error type.

use std::fmt::Debug;

/// Errors returned by the runtime and by implementors of its traits.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    // ---- configuration ----
    /// A configuration value is invalid; the message names the field and the limit.
    #[error("invalid runtime configuration: {0}")]
    Config(String),
    /// A schedule error bubbled up from `pir2-schedule`.
    #[error(transparent)]
    Schedule(#[from] pir2_schedule::Error),

    // ---- shapes ----
    /// A tensor or slice had the wrong length/shape.
    #[error(transparent)]
    Shape(#[from] ShapeMismatch),

    // ---- model ----
    /// The velocity model failed.
    #[error("velocity model failed: {0}")]
    Model(String),
    /// A capability the backend does not provide.
    #[error("`{capability}` is not supported by the {backend} backend")]
    Unsupported {
        /// The capability requested (e.g. "training").
        capability: &'static str,
        /// The backend's name.
        backend: &'static str,
    },
    /// The model produced a non-finite value.
    #[error("velocity model produced a non-finite value at {index}")]
    NonFinite {
        /// Flat index of the first non-finite element.
        index: usize,
    },

    // ---- I/O ----
    /// A source, encoder or actuator failed (robot, camera, transport).
    #[error("{device}: {message}")]
    Io {
        /// Which device or channel.
        device: String,
        /// What went wrong.
        message: String,
    },
    /// A model call given up because the run is stopping ([`crate::StopSignal`]); the
    /// real-time driver does not report it as the run's error.
    #[error("the call was abandoned: the run is stopping")]
    Abandoned,
    /// A worker thread stopped unexpectedly.
    #[error("worker `{0}` stopped")]
    WorkerStopped(&'static str),
    /// A thread of the run panicked (a worker, or a user's model, source or actuator called
    /// on it). The robot was stopped; `message` is the panic's payload.
    #[error("thread `{thread}` panicked: {message}")]
    Panicked {
        /// The thread: `action worker`, `slow worker`, `warm start` or `control thread`.
        thread: &'static str,
        /// The panic message.
        message: String,
    },
    /// Safety stop: the runtime stopped the robot.
    #[error("safety stop: {0}")]
    SafetyStop(String),
}

/// Result alias for the runtime.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// A tensor or slice had the wrong length/shape: the payload of [`Error::Shape`], and of the
/// `Shape` error of the crates above (the backends), which hand it on unchanged.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("shape mismatch for `{what}`: expected {expected}, got {got}")]
pub struct ShapeMismatch {
    /// What was being checked.
    pub what: String,
    /// The expected shape, printed.
    pub expected: String,
    /// The shape received, printed.
    pub got: String,
}

impl ShapeMismatch {
    /// `what` with the expected and received shapes printed with `{:?}`.
    pub fn new(what: impl Into<String>, expected: impl Debug, got: impl Debug) -> Self {
        ShapeMismatch {
            what: what.into(),
            expected: format!("{expected:?}"),
            got: format!("{got:?}"),
        }
    }
}

impl Error {
    /// [`Error::Shape`] of [`ShapeMismatch::new`].
    pub fn shape(what: impl Into<String>, expected: impl Debug, got: impl Debug) -> Self {
        ShapeMismatch::new(what, expected, got).into()
    }
    /// [`Error::Panicked`] from a caught panic payload.
    pub fn panicked(thread: &'static str, payload: &(dyn std::any::Any + Send)) -> Self {
        Error::Panicked {
            thread,
            message: panic_message(payload),
        }
    }
    /// Convenience constructor for [`Error::Io`].
    pub fn io(device: impl Into<String>, message: impl std::fmt::Display) -> Self {
        Error::Io {
            device: device.into(),
            message: message.to_string(),
        }
    }
}

/// The message of a caught panic payload (`&str` or `String`; otherwise a placeholder).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "non-string panic payload".to_string()
    }
}
