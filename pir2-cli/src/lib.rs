//! # pir2-cli
//!
//! The stock pipelines behind the `pir2` binary, callable from code: the study pipeline
//! ([`study`]: a [`study::Task`] collected, trained and evaluated under latency through the
//! lock-step runtime; [`study::dataset`]: a policy trained on a user's own state-only
//! LeRobotDataset v3.0 from a `task.toml`, validated on held-out episodes), plots, benchmarks,
//! and one function per subcommand: [`tasks`] (`collect|train|eval|report TASK`, the stock
//! tasks from one registry), [`gr00t`] (`pir2 gr00t …`), [`run`], [`serve`] (with
//! [`remote`], the robot side and TLS options it shares with the others) and
//! [`commands`] (the rest). Each subcommand's options are a struct deriving clap's `Args`
//! (the doc comments are the help), so `main.rs` only parses and dispatches.

pub mod bench;
pub mod commands;
pub mod ep;
pub mod gr00t;
pub mod identity;
pub mod onnx_checkpoint;
pub mod plot;
pub mod remote;
pub mod run;
pub mod serve;
pub mod signals;
pub mod study;
pub mod tasks;
