//! Loopback emulators for tests and dry runs: the xArm over TCP ([`xarm`]) and the XHand over
//! an in-memory serial line ([`duplex()`]) or a pseudo-terminal ([`xhand::spawn_pty`]). Both
//! take injected faults (disconnects, stalls, truncated or garbage frames, wrong CRC, wrong
//! transaction ids, controller error codes).

pub mod duplex;
pub mod rig;
pub mod xarm;
pub mod xhand;

pub use duplex::{duplex, DuplexPort};
pub use rig::{EmulatedArmHand, EmulatedArmHandConfig, EmulatedRobot};
pub use xarm::{run_xarm_emulator, XArmEmuHandle, XArmEmulator, XArmFault, XArmPorts};
#[cfg(unix)]
pub use xhand::run_xhand_emulator_pty;
pub use xhand::{XHandEmuHandle, XHandEmulator, XHandFault};
