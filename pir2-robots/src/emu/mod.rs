//! Loopback emulators for tests and dry runs: the xArm over TCP ([`xarm`]) and the XHand over
//! an in-memory serial line ([`duplex()`]) or a pseudo-terminal ([`xhand::spawn_pty`]). Both
//! take injected faults (disconnects, stalls, truncated or garbage frames, wrong CRC, wrong
//! transaction ids, controller error codes).

pub mod duplex;
pub mod rig;
pub mod xarm;
pub mod xhand;

pub use duplex::{duplex, DuplexPort};

/// What one read of an emulator's transport gave.
pub(crate) enum Got {
    /// `n ≥ 1` bytes.
    Bytes(usize),
    /// Nothing: end of stream on a stream socket, an empty read on a serial line.
    Empty,
    /// Nothing yet: the read timed out or was interrupted.
    Idle,
    /// The transport failed for good.
    Failed,
}

/// One read of `r` into `buf`, the time-outs and interrupts an emulator's poll loop expects
/// told apart from a transport that failed.
pub(crate) fn read_some(r: &mut impl std::io::Read, buf: &mut [u8]) -> Got {
    use std::io::ErrorKind;
    match r.read(buf) {
        Ok(0) => Got::Empty,
        Ok(n) => Got::Bytes(n),
        Err(e)
            if matches!(
                e.kind(),
                ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
            ) =>
        {
            Got::Idle
        }
        Err(_) => Got::Failed,
    }
}
pub use rig::{EmulatedArmHand, EmulatedArmHandConfig, EmulatedRobot};
pub use xarm::{run_xarm_emulator, XArmEmuHandle, XArmEmulator, XArmFault, XArmPorts};
#[cfg(unix)]
pub use xhand::run_xhand_emulator_pty;
pub use xhand::{XHandEmuHandle, XHandEmulator, XHandFault};
