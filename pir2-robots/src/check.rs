//! `pir2 robots check`: talk to the devices without moving them, and connecting the
//! composite for a run.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::{Clock, SystemClock};

use crate::error::Result;
use crate::xarm::proto::{self, Report, ReportKind};
use crate::xarm::{ReportReader, XArmClient};
use crate::xhand::{self, consts};

/// What to check.
#[derive(Debug, Clone)]
pub struct CheckOptions {
    /// xArm command address (`<ip>:502`).
    pub xarm: Option<SocketAddr>,
    /// xArm real-time report address; `None` skips the report stream.
    pub xarm_report: Option<SocketAddr>,
    /// XHand serial device (or an emulator's PTY).
    pub xhand: Option<PathBuf>,
    /// XHand bus id.
    pub hand_id: u8,
    /// XHand baud rate.
    pub baud: u32,
    /// Timeout of every request.
    pub timeout: Duration,
    /// Clear a latched xArm error/warning (`CLEAN_ERR`, `CLEAN_WAR`) after reading it.
    pub clear_errors: bool,
}

impl CheckOptions {
    /// Options for an arm at `xarm` (report stream at the same IP, port 30003, when `xarm`
    /// uses the standard port 502) and a hand at `xhand`.
    pub fn new(xarm: Option<SocketAddr>, xhand: Option<&Path>) -> Self {
        let xarm_report = xarm
            .filter(|a| a.port() == proto::PORT_CMD)
            .map(|a| SocketAddr::new(a.ip(), proto::PORT_REPORT_REAL));
        Self {
            xarm,
            xarm_report,
            xhand: xhand.map(Path::to_path_buf),
            hand_id: consts::DEFAULT_HAND_ID,
            baud: consts::BAUD,
            timeout: Duration::from_millis(500),
            clear_errors: false,
        }
    }
}

/// What the arm answered.
#[derive(Debug, Clone)]
pub struct XArmCheck {
    /// Command address.
    pub addr: SocketAddr,
    /// Firmware version.
    pub version: String,
    /// Motion state (GET_STATE).
    pub state: u8,
    /// Controller error code.
    pub error: u8,
    /// Controller warning code.
    pub warning: u8,
    /// Joint positions, rad.
    pub joints: [f32; 7],
    /// Joint torques.
    pub torques: [f32; 7],
    /// One real-time report, or why none could be read; `None` when not asked.
    pub report: Option<std::result::Result<Report, String>>,
    /// With [`CheckOptions::clear_errors`]: the codes after clearing.
    pub after_clear: Option<(u8, u8)>,
}

/// What the hand answered.
#[derive(Debug, Clone)]
pub struct XHandCheck {
    /// Device path.
    pub path: PathBuf,
    /// Firmware version, or why it could not be read.
    pub version: std::result::Result<String, String>,
    /// The 39-value state: 12 positions, 12 torques, 15 tip forces.
    pub state: Vec<f32>,
    /// Joints reporting a non-zero error word: `(joint, errors)`.
    pub finger_errors: Vec<(usize, [u16; 3])>,
}

/// The result of [`check`].
#[derive(Debug, Clone, Default)]
pub struct CheckReport {
    /// The arm, if asked.
    pub xarm: Option<XArmCheck>,
    /// The hand, if asked.
    pub xhand: Option<XHandCheck>,
}

impl CheckReport {
    /// Whether everything asked answered without an error code.
    pub fn healthy(&self) -> bool {
        let arm_ok = self.xarm.as_ref().is_none_or(|a| {
            a.after_clear.map_or(a.error, |c| c.0) == 0
                && !matches!(a.report, Some(Err(_)))
                && a.state != crate::xarm::proto::state::MOVING
        });
        let hand_ok = self
            .xhand
            .as_ref()
            .is_none_or(|h| h.finger_errors.is_empty());
        arm_ok && hand_ok
    }
}

impl std::fmt::Display for CheckReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if let Some(a) = &self.xarm {
            writeln!(f, "xArm at {}: version {:?}", a.addr, a.version)?;
            writeln!(
                f,
                "  state {} error {} warning {}",
                a.state, a.error, a.warning
            )?;
            if a.state == crate::xarm::proto::state::MOVING {
                writeln!(
                    f,
                    "  the arm is in motion (state 1): another client is streaming to it, or a \
                     process died without stopping it (it holds its last servo target); stop \
                     it before a run"
                )?;
            }
            if let Some((e, w)) = a.after_clear {
                writeln!(
                    f,
                    "  cleared: error {e} warning {w} after CLEAN_ERR/CLEAN_WAR"
                )?;
            }
            writeln!(f, "  joints (rad) {:.3?}", &a.joints[..6])?;
            writeln!(f, "  torques      {:.3?}", &a.torques[..6])?;
            match &a.report {
                Some(Ok(r)) => writeln!(
                    f,
                    "  report 30003: state {} mode {} joints {:.3?}",
                    r.state,
                    r.mode,
                    &r.angles[..6]
                )?,
                Some(Err(e)) => writeln!(f, "  report 30003: FAILED: {e}")?,
                None => writeln!(f, "  report 30003: not checked")?,
            }
        }
        if let Some(h) = &self.xhand {
            match &h.version {
                Ok(v) => writeln!(f, "XHand at {}: version {v:?}", h.path.display())?,
                Err(e) => writeln!(f, "XHand at {}: version unknown ({e})", h.path.display())?,
            }
            writeln!(f, "  joints (rad) {:.3?}", &h.state[..12])?;
            writeln!(f, "  torques      {:.1?}", &h.state[12..24])?;
            writeln!(f, "  tip forces   {:.1?}", &h.state[24..39])?;
            for (j, e) in &h.finger_errors {
                writeln!(f, "  joint {j}: error words {e:?}")?;
            }
        }
        write!(
            f,
            "{}",
            if self.healthy() {
                "OK"
            } else {
                "PROBLEMS FOUND"
            }
        )
    }
}

/// Check an arm at `xarm` (`<ip>:502`) and/or a hand on the serial device `xhand`, without
/// enabling or moving anything. See [`check_with`].
pub fn check(xarm: Option<SocketAddr>, xhand: Option<&Path>) -> Result<CheckReport> {
    check_with(&CheckOptions::new(xarm, xhand))
}

/// Check the devices in `opts`: the arm's version, state, error/warning codes, joint
/// positions and torques, and one report; the hand's version and state. Errors if a device
/// asked for does not answer at all; a report stream that fails is recorded in the report.
pub fn check_with(opts: &CheckOptions) -> Result<CheckReport> {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let mut out = CheckReport::default();
    if let Some(addr) = opts.xarm {
        let mut c = XArmClient::connect(addr, opts.timeout, clock.clone())?;
        let version = c.identify()?.text;
        let state = c.state()?;
        let (error, warning) = c.error_codes()?;
        let after_clear = if opts.clear_errors && (error != 0 || warning != 0) {
            c.clean_error()?;
            c.clean_warning()?;
            Some(c.error_codes()?)
        } else {
            None
        };
        let joints = c.joint_positions()?;
        let torques = c.joint_torques()?;
        let report = opts.xarm_report.map(|ra| {
            ReportReader::connect(ra, ReportKind::Real, opts.timeout)
                .and_then(|mut r| r.next(clock.as_ref(), opts.timeout))
                .map_err(|e| e.to_string())
        });
        out.xarm = Some(XArmCheck {
            addr,
            version,
            state,
            error,
            warning,
            joints,
            torques,
            report,
            after_clear,
        });
    }
    #[cfg(unix)]
    if let Some(path) = &opts.xhand {
        let port = xhand::tty::TtyPort::open(path, opts.baud)?;
        let cfg = xhand::XHandConfig {
            hand_id: opts.hand_id,
            timeout: opts.timeout,
            ..Default::default()
        };
        let mut hand = xhand::XHand::new(port, cfg, clock.clone());
        let version = hand.version().map_err(|e| e.to_string());
        let s = hand.query_state()?.clone();
        let mut state = vec![0.0; 39];
        s.write_vector(&mut state);
        let finger_errors = s
            .fingers
            .iter()
            .enumerate()
            .filter(|(_, f)| f.errors.iter().any(|&e| e != 0))
            .map(|(i, f)| (i, f.errors))
            .collect();
        out.xhand = Some(XHandCheck {
            path: path.clone(),
            version,
            state,
            finger_errors,
        });
    }
    #[cfg(not(unix))]
    if opts.xhand.is_some() {
        return Err(crate::Error::Config(
            "XHand serial access is only implemented on unix".into(),
        ));
    }
    Ok(out)
}

/// The XHand on its own driver thread, as the composite of a run holds it.
pub type ThreadedHand<T> = crate::Threaded<crate::XHand<T>>;

/// The paper's robot, ready for a run: connect the xArm6 (servo mode, streaming) and the
/// XHand on `hand_path` (on its own driver thread, [`crate::Threaded`], so a serial stall
/// never makes a control tick late), combine them into the 45-d / 18-d composite and wrap it
/// in the safety layer with its watchdog running (polling every 10 ms). Hand it to
/// [`crate::split`] for the runtime.
#[cfg(unix)]
pub fn connect_arm_hand(
    arm: crate::XArm6Config,
    hand_path: &Path,
    hand: crate::XHandConfig,
    safety: crate::SafetyConfig,
    clock: Arc<dyn Clock>,
) -> Result<crate::SafetyLayer<crate::ArmHand<crate::XArm6, ThreadedHand<xhand::tty::TtyPort>>>> {
    let port = xhand::tty::TtyPort::open(hand_path, consts::BAUD)?;
    let hand = crate::Threaded::spawn(
        crate::XHand::new(port, hand, clock.clone()),
        crate::ThreadedConfig::default(),
    )?;
    let arm = crate::XArm6::connect(arm, clock.clone())?;
    let composite = crate::ArmHand::new(arm, hand)?;
    let mut layer = crate::SafetyLayer::new(composite, safety, clock)?;
    layer.spawn_watchdog(Duration::from_millis(10))?;
    Ok(layer)
}
