//! The emulated xArm6 + XHand behind the safety layer: the one set-up that tests, examples
//! and `pir2 gr00t run --emulate` use. The arm emulator listens on ephemeral loopback ports, the
//! hand emulator sits on an in-memory serial line, and the client side is the same
//! [`ArmHand`] composite and [`SafetyLayer`] a real robot gets.

use std::net::{IpAddr, Ipv4Addr};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::Clock;

use super::{duplex, DuplexPort, XArmEmulator, XArmPorts, XHandEmulator};
use crate::error::Result;
use crate::robot::ArmHand;
use crate::safety::{SafetyConfig, SafetyLayer};
use crate::threaded::{Threaded, ThreadedConfig};
use crate::xarm::{XArm6, XArm6Config};
use crate::xhand::{XHand, XHandConfig};

/// The robot the emulated rig hands out: arm + hand behind the safety layer.
pub type EmulatedRobot = SafetyLayer<ArmHand<XArm6, Threaded<XHand<DuplexPort>>>>;

/// Options of [`EmulatedArmHand::start`].
#[derive(Debug, Clone)]
pub struct EmulatedArmHandConfig {
    /// One-way latency of the in-memory serial line to the hand.
    pub serial_latency: Duration,
    /// The arm client's action period (`None`: the client's default).
    pub action_period: Option<Duration>,
    /// Safety limits of the layer.
    pub safety: SafetyConfig,
    /// Period of the safety layer's watchdog.
    pub watchdog: Duration,
    /// Clear a latched arm error at connect (`--clear-errors`) instead of refusing to start.
    pub clear_errors: bool,
}

impl Default for EmulatedArmHandConfig {
    fn default() -> Self {
        Self {
            serial_latency: Duration::from_millis(5),
            action_period: None,
            safety: SafetyConfig::xarm6_xhand(),
            watchdog: Duration::from_millis(10),
            clear_errors: false,
        }
    }
}

/// Both emulators of a running rig; dropping it stops them.
#[derive(Debug)]
pub struct EmulatedArmHand {
    /// The xArm emulator (its handle injects faults and reads the simulated arm).
    pub arm: XArmEmulator,
    /// The XHand emulator (its handle counts commands and injects faults).
    pub hand: XHandEmulator,
    stop: Arc<AtomicBool>,
}

impl EmulatedArmHand {
    /// Start both emulators and connect the arm + hand composite to them behind a safety
    /// layer whose watchdog runs. Returns the emulators and the robot.
    pub fn start(
        cfg: &EmulatedArmHandConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<(Self, EmulatedRobot)> {
        let local = IpAddr::V4(Ipv4Addr::LOCALHOST);
        let stop = Arc::new(AtomicBool::new(false));
        let arm_emu = XArmEmulator::spawn_with_stop(local, XArmPorts::ephemeral(), stop.clone())?;
        let (host, dev) = duplex(cfg.serial_latency);
        let hand_emu = XHandEmulator::spawn(dev, 0, stop.clone())?;
        let rig = EmulatedArmHand {
            arm: arm_emu,
            hand: hand_emu,
            stop,
        };
        let mut acfg = XArm6Config::new(local);
        acfg.cmd_addr = rig.arm.cmd_addr();
        acfg.report_addr = rig.arm.real_report_addr();
        acfg.stream_hz = 100.0;
        acfg.clear_errors = cfg.clear_errors;
        if let Some(p) = cfg.action_period {
            acfg.action_period = p;
        }
        let arm = XArm6::connect(acfg, clock.clone())?;
        let hand = Threaded::spawn(
            XHand::new(
                host,
                XHandConfig {
                    timeout: Duration::from_millis(100),
                    ..Default::default()
                },
                clock.clone(),
            ),
            ThreadedConfig::default(),
        )?;
        let mut layer = SafetyLayer::new(ArmHand::new(arm, hand)?, cfg.safety.clone(), clock)?;
        layer.spawn_watchdog(cfg.watchdog)?;
        Ok((rig, layer))
    }

    /// Commands the hand emulator has received.
    pub fn hand_commands(&self) -> u64 {
        self.hand.handle().commands()
    }
}

impl Drop for EmulatedArmHand {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}
