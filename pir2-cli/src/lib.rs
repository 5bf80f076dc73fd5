//! # pir2-cli
//!
//! The stock pipelines behind the `pir2` binary, callable from code: deployment studies
//! through the lock-step runtime, plots, and benchmarks. `main.rs` is a thin argument parser.

pub mod bench;
pub mod demo;
#[cfg(feature = "mujoco")]
pub mod leap;
pub mod leap_cmd;
pub mod pipeline;
pub mod plot;
pub mod run;
pub mod serve;
pub mod study;
