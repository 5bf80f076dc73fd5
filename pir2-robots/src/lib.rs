//! # pir2-robots
//!
//! Drivers for the paper's real robot (UFACTORY xArm6 over TCP, XHand over RS-485), the
//! [`Robot`] trait with its 45-d xArm6 + XHand composite ([`ArmHand`]), a [`SafetyLayer`]
//! that wraps any robot, adapters that make any robot a `pir2-runtime`
//! [`FastSource`](pir2_runtime::FastSource) + [`Actuator`](pir2_runtime::Actuator)
//! ([`split`]), and loopback emulators of both devices with fault injection ([`emu`]).
//!
//! Frame layouts and register tables are in [`xarm::proto`] and [`xhand::proto`]; every
//! uncertain XHand protocol choice is in [`xhand::consts`]. The safety behaviour on stop is
//! described in [`safety`], [`xarm`] and [`xhand`].
//!
//! Entry points for the CLI:
//! - [`check()`] / [`check_with`]: connect without moving, read versions, states, errors and
//!   joint positions, and return a printable [`CheckReport`].
//! - [`emu::run_xarm_emulator`]: serve an emulated xArm (standard or ephemeral ports) until a
//!   stop flag is set.
//! - [`emu::run_xhand_emulator_pty`]: serve an emulated XHand on a new pseudo-terminal and
//!   return its device path.
//! - [`connect_arm_hand`]: the xArm6 + XHand composite behind the safety layer, ready for
//!   [`split`].
//! - Cameras for the slow channel: [`FolderCamera`] (recorded frames) and, on Linux,
//!   `V4l2Camera` (a live USB/V4L2 camera with driver capture timestamps, module `v4l2`).
#![warn(missing_docs)]

pub mod camera;
pub mod check;
pub mod emu;
pub mod error;
pub mod robot;
pub mod safety;
pub mod threaded;
#[cfg(target_os = "linux")]
pub mod v4l2;
pub mod xarm;
pub mod xhand;

pub use camera::FolderCamera;
pub use check::{check, check_with, CheckOptions, CheckReport};
#[cfg(unix)]
pub use emu::run_xhand_emulator_pty;
pub use emu::{run_xarm_emulator, XArmPorts};
pub use error::{Error, Result};
pub use robot::{
    split, ArmHand, Robot, RobotActuator, RobotSource, StateLayout, ARM_DOF, ARM_HAND_ACTION_DIM,
    HAND_DOF,
};
pub use safety::{SafetyConfig, SafetyLayer, SafetyStats, Widening};
pub use threaded::{Threaded, ThreadedConfig, ThreadedStats};
#[cfg(target_os = "linux")]
pub use v4l2::{V4l2Camera, V4l2Config};
pub use xarm::{XArm6, XArm6Config};
pub use xhand::{XHand, XHandConfig};

#[cfg(unix)]
pub use check::connect_arm_hand;
