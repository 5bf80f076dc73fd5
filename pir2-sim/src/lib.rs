//! # pir2-sim
//!
//! Simulated tasks for the πR² stack, their experts, and the dataset format shared by the
//! demonstration pipelines:
//!
//! - [`ballplate`]: the 2-DoF ball-on-plate task (50 Hz, pushes, fast/slow observation
//!   split) on which πR²'s advantage was measured; implements
//!   [`pir2_runtime::Environment`].
//! - [`expert`]: the discrete-LQR expert of that task (gain from the Riccati equation) and
//!   the [`expert::Expert`] trait.
//! - [`dataset`]: demonstration collection into in-memory [`dataset::Episode`]s and
//!   LeRobotDataset v3.0 (state-only) writing and reading.
//! - `leap` (feature `mujoco`): the 16-DoF LEAP hand cube-reorientation task (MuJoCo
//!   Playground's LeapCubeReorient, the paper's 50 Hz blue-side-up variant) and its
//!   sampling-based MPC expert.
#![warn(missing_docs)]

pub mod ballplate;
pub mod dataset;
pub mod error;
pub mod expert;
#[cfg(feature = "mujoco")]
pub mod leap;

pub use ballplate::{BallPlate, BallPlateConfig, BallPlateState};
pub use error::{Error, Result};
pub use expert::{Expert, LqrConfig, LqrExpert};
