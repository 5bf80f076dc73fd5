//! # pir2-backends
//!
//! Velocity-model backends for πR². The default `candle` feature provides pure-Rust models
//! (MLP, conditional U-Net 1D with per-position FiLM, DiT with per-position AdaLN) that
//! implement [`pir2_runtime::model::VelocityModel`], checkpoints (safetensors + JSON), and the
//! trainer ([`train`]). Native backends (ONNX Runtime, libtorch) sit behind their own features.
//!
//! Models work in normalised action space; see [`config`].
#![warn(missing_docs)]

pub mod checkpoint;
pub mod config;
pub mod error;

#[cfg(feature = "candle")]
pub mod candle;
#[cfg(feature = "candle")]
pub mod train;

pub use config::{Config, ModelConfig, Spec, Stats};
pub use error::{Error, Result};
