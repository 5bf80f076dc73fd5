//! # pir2-backends
//!
//! Velocity-model backends for πR². The default `candle` feature provides pure-Rust models
//! (MLP, conditional U-Net 1D with per-position FiLM, DiT with per-position AdaLN) that
//! implement [`pir2_runtime::model::VelocityModel`], checkpoints (safetensors + JSON), and the
//! trainer ([`train`]). Native backends sit behind their own features: ONNX Runtime (`ort`,
//! `ort::OrtModel`) and libtorch (`tch`, `tch::TchModel`). ONNX export ([`export`]) is pure
//! Rust and always available. The GR00T-N1.7 xArm6 + XHand stack is behind feature `gr00t`
//! (module `gr00t`, `docs/gr00t-contract.md`). GR00T N1.7's action head itself also runs in
//! candle ([`candle::gr00t_n17`]), loaded straight from a GR00T checkpoint's safetensors,
//! with πR²'s per-position timesteps.
//!
//! Models work in normalised action space; see [`config`].
#![warn(missing_docs)]

pub mod checkpoint;
pub mod config;
pub mod error;
pub mod export;
#[cfg(feature = "gr00t")]
pub mod gr00t;

#[cfg(feature = "candle")]
pub mod candle;
#[cfg(feature = "ort")]
pub mod ort;
#[cfg(feature = "tch")]
pub mod tch;
#[cfg(feature = "candle")]
pub mod train;

pub use config::{Config, ModelConfig, Spec, Stats};
pub use error::{Error, Result};
