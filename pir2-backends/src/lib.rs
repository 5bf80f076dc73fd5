//! # pir2-backends
//!
//! Velocity-model backends for πR². The default `candle` feature provides pure-Rust models
//! (MLP, conditional U-Net 1D with per-position FiLM, DiT with per-position AdaLN) that
//! implement [`pir2_runtime::model::VelocityModel`], checkpoints (safetensors + JSON), and the
//! trainer ([`train`]). Native backends sit behind their own features: ONNX Runtime (`ort`,
//! `ort::OrtModel`) and libtorch (`tch`, `tch::TchModel`). ONNX export ([`export`]) is pure
//! Rust and always available. Everything GR00T lives in one module, [`gr00t`]: N1.7's action
//! head in candle with its exporter and its πR² trainer (`gr00t::n17`, feature `candle`),
//! loaded straight from a GR00T checkpoint's safetensors, and the xArm6 + XHand deployment
//! stack over ONNX Runtime (feature `gr00t`, `docs/gr00t-contract.md`).
//!
//! Models work in normalised action space; see [`config`].
#![warn(missing_docs)]

pub mod checkpoint;
pub mod config;
pub mod error;
pub mod export;
#[cfg(any(feature = "candle", feature = "gr00t"))]
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
