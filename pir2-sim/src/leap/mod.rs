//! The LEAP-hand cube reorientation task in MuJoCo (feature `mujoco`) and its MPC expert.
//!
//! * [`scene`]: loads MuJoCo Playground's LeapCubeReorient scene from `$PIR2_LEAP_CUBE_DIR`
//!   (installed by `scripts/setup-native.sh`), stripping visual-only meshes that ship in no
//!   package, in memory.
//! * [`LeapModel`]: the compiled model plus the addresses the task needs.
//! * [`LeapCubeEnv`]: a [`pir2_runtime::Environment`] in two configurations, the playground's
//!   original ([`LeapConfig::playground`]) and the paper's 50 Hz blue-side-up variant
//!   ([`LeapConfig::paper`]).
//! * [`MpcExpert`]: sampling-based predictive control over MuJoCo rollouts, on parallel
//!   threads, with privileged state.
//! * [`collect`]: roll the expert and record per-frame observations and actions.
//! * [`ppo`]: PPO training of a learnable expert (a deterministic function of the noisy
//!   observation) and its weights file.

mod collect;
mod env;
pub mod math;
mod model;
mod mpc;
pub mod ppo;
pub mod scene;

pub use collect::{collect, collect_with, episode_seeds, CollectConfig, Episode, Expert, Frame};
pub use env::{LeapConfig, LeapCubeEnv, LeapEnvState, NoiseConfig, Variant};
pub use model::{LeapModel, NU};
pub use mpc::{MpcConfig, MpcExpert, MpcSnapshot};
