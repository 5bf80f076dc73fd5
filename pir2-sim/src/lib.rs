//! pir2-sim: simulated tasks and their experts.
//!
//! With the `mujoco` feature: [`leap`], the 16-DoF LEAP hand cube-reorientation task
//! (MuJoCo Playground's LeapCubeReorient and the paper's 50 Hz blue-side-up variant) and
//! its sampling-based MPC expert.

#[cfg(feature = "mujoco")]
pub mod leap;
