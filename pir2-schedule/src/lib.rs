//! # pir2-schedule
//!
//! The math of πR² (Reactive Real-time Flow Policies): per-position noise schedules
//! (the *staircase*), the streaming inference buffer that runs one denoising step per
//! call and emits `d` clean actions, training draws, and the baseline schedules.
//! Pure Rust, no heavy dependencies. The binding definitions (staircase family, invariants,
//! the rule for a changing `d`, front visibility) are in `docs/method.md` §1 of the repository.
#![warn(missing_docs)]

pub mod baselines;
pub mod buffer;
pub mod error;
pub mod rng;
pub mod staircase;
pub mod train;

pub use buffer::{Emitted, FrontMode, StreamBuffer, StreamConfig};
pub use error::{Error, Result};
pub use rng::Rng;
pub use staircase::{Alignment, Staircase};

/// The `τ` value a model sees on a *hidden* front slot (its `x` is zeroed). It lies outside
/// `[0, 1]`, so it doubles as the "hidden" indicator for the model's per-position embedding.
pub const HIDDEN_FRONT_TAU: f32 = -1.0;
