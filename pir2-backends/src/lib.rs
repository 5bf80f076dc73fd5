//! # pir2-backends
//!
//! Velocity-model backends implementing [`pir2_runtime::VelocityModel`]:
//! candle (default, pure Rust), ONNX Runtime (feature `ort`, [`ort::OrtModel`]) and libtorch
//! (feature `tch`, [`tch::TchModel`]); and ONNX export without Python ([`onnx`]).
//! The GR00T-N1.7 xArm6 + XHand stack is behind feature `gr00t` (module `gr00t`).
#![warn(missing_docs)]

pub mod error;
#[cfg(feature = "gr00t")]
pub mod gr00t;
pub mod onnx;
#[cfg(feature = "ort")]
pub mod ort;
#[cfg(feature = "tch")]
pub mod tch;

pub use error::{Error, Result};
