//! # pir2-cli
//!
//! The stock pipelines behind the `pir2` binary, callable from code: the study pipeline
//! ([`study`]: a [`study::Task`] collected, trained and evaluated under latency through the
//! lock-step runtime; [`study::dataset`]: a policy trained on a user's own state-only
//! LeRobotDataset v3.0 from a `task.toml`, validated on held-out episodes), plots, benchmarks,
//! and one function per subcommand ([`commands`]).
//! `main.rs` only parses arguments.

pub mod bench;
pub mod commands;
pub mod ep;
pub mod leap_cmd;
pub mod plot;
pub mod run;
pub mod serve;
pub mod signals;
pub mod study;
