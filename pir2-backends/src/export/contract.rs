//! The single-graph ONNX contract shared by the exporter and the ONNX Runtime backend.
//!
//! | name       | type    | shape                        | notes                                  |
//! |------------|---------|------------------------------|----------------------------------------|
//! | `x`        | float32 | `[B, H, A]`                  | noisy chunk                            |
//! | `tau`      | float32 | `[B, H]`                     | per-position noise level (−1 = hidden) |
//! | `obs_fast` | float32 | `[B, n_obs, F]`              | fast observation history, oldest first |
//! | `obs_slow` | float32 | `[B, S]` or `[B, T, D]`      | optional: slow features                |
//! | `d_vis`    | int64   | `[B]`                        | optional: slow-feature age in ticks    |
//! | `v` (out)  | float32 | `[B, H, A]`                  | velocity                               |
//!
//! `B` is dynamic (a symbolic dimension, e.g. `"batch"`, or `-1`); every other dimension
//! must be fixed in the file. Graphs written by [`crate::export`] always declare `d_vis`
//! (it may be unused by the graph) and declare `obs_slow` exactly when the model has a
//! slow input.

use pir2_runtime::SlowInput;

/// Input name of the noisy chunk.
pub const X: &str = "x";
/// Input name of the per-position noise level.
pub const TAU: &str = "tau";
/// Input name of the fast observation history.
pub const OBS_FAST: &str = "obs_fast";
/// Input name of the (optional) slow features.
pub const OBS_SLOW: &str = "obs_slow";
/// Input name of the (optional) slow-feature age.
pub const D_VIS: &str = "d_vis";
/// Output name of the velocity.
pub const V: &str = "v";
/// The symbolic name exported graphs give the batch dimension.
pub const BATCH: &str = "batch";

pub use pir2_runtime::SlowSpec;

/// Describe a call's slow input the same way as [`SlowSpec::describe`].
pub fn describe_slow(slow: &SlowInput<'_>) -> String {
    match slow {
        SlowInput::None => "none".to_string(),
        SlowInput::Vector { dim, .. } => format!("[B, {dim}]"),
        SlowInput::Tokens { tokens, dim, .. } => format!("[B, {tokens}, {dim}]"),
    }
}

/// The fixed sizes of one model's inputs (everything but the batch).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ContractDims {
    /// Chunk length `H`.
    pub horizon: usize,
    /// Action dimension `A`.
    pub action_dim: usize,
    /// Observation history length `n_obs`.
    pub n_obs: usize,
    /// Fast observation width `F`.
    pub fast_dim: usize,
    /// Slow input.
    pub slow: SlowSpec,
    /// Does the graph declare `d_vis`?
    pub has_d_vis: bool,
}
