//! The schedule crate's error type.

/// Errors of `pir2-schedule`: every invalid combination names the limit it broke.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// The chunk is too short for the requested delay.
    #[error("chunk length H = {h} is too short for delay d = {d} with the {alignment} alignment: need H >= {min_h}")]
    HorizonTooShort {
        /// Chunk length.
        h: usize,
        /// Delay.
        d: usize,
        /// Alignment name.
        alignment: &'static str,
        /// The smallest valid `H`.
        min_h: usize,
    },
    /// `n` (NFEs per action) is out of range.
    #[error("n = {n} NFEs per action is out of range for H = {h}, d = {d}: need 1 <= n <= n_max = {n_max}")]
    NfeOutOfRange {
        /// Requested NFEs per action.
        n: usize,
        /// Chunk length.
        h: usize,
        /// Delay.
        d: usize,
        /// Upper limit.
        n_max: usize,
    },
    /// A value is invalid; the message names the field and the allowed range.
    #[error("invalid `{field}`: {message}")]
    Invalid {
        /// The offending field.
        field: &'static str,
        /// What is allowed.
        message: String,
    },
    /// A slice had the wrong length.
    #[error("`{what}` has length {got}, expected {expected}")]
    Length {
        /// Which slice.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Received length.
        got: usize,
    },
}

/// Result alias for `pir2-schedule`.
pub type Result<T, E = Error> = std::result::Result<T, E>;

pub(crate) fn check_len(what: &'static str, got: usize, expected: usize) -> Result<()> {
    if got == expected {
        Ok(())
    } else {
        Err(Error::Length {
            what,
            expected,
            got,
        })
    }
}
