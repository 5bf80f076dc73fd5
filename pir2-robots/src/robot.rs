//! The [`Robot`] trait, the xArm6 + XHand composite, and adapters to the runtime's
//! [`FastSource`] / [`Actuator`].
//!
//! A robot reads a flat state vector with the time it was measured and takes a flat vector of
//! absolute joint targets. [`StateLayout`] says where the measured joint positions (in the
//! order of the action) and torques sit in the state, which is all the safety layer needs.
//!
//! The composite [`ArmHand`] has the paper's 45-d proprioception and 18-d action:
//!
//! | state index | content                                   |
//! |-------------|-------------------------------------------|
//! | 0..6        | xArm6 joint angles, rad                   |
//! | 6..18       | XHand joint angles, rad                   |
//! | 18..30      | XHand joint torques (driver units)        |
//! | 30..45      | XHand fingertip forces, 5 tips × (x, y, z)|
//!
//! Action: `[arm j1..j6, hand j0..j11]`, absolute joint targets in rad.

use std::ops::Range;
use std::sync::{Arc, Mutex};

use pir2_runtime::{Actuator, FastSource, Nanos};

use crate::error::{Error, Result};

/// Where the measured joint positions and torques sit in a robot's state vector.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StateLayout {
    /// Measured positions, in the same order as the action (length = action dim).
    pub positions: Range<usize>,
    /// Measured torques the safety layer limits, if the robot reports any.
    pub torques: Option<Range<usize>>,
}

/// A robot: read state with a timestamp, send absolute joint targets, stop.
pub trait Robot: Send {
    /// Short name for logs and errors.
    fn name(&self) -> &'static str;
    /// Length of the state vector.
    fn state_dim(&self) -> usize;
    /// Length of the action (joint target) vector.
    fn action_dim(&self) -> usize;
    /// Where positions and torques are in the state.
    fn layout(&self) -> StateLayout;
    /// Write the newest state into `out` and return when it was measured (runtime clock).
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos>;
    /// Command absolute joint targets (`targets.len() == action_dim()`).
    fn send_targets(&mut self, targets: &[f32]) -> Result<()>;
    /// Stop safely: stop streaming and hold / disable motion. Idempotent. The stop command
    /// is always finite: a joint whose measured position is not finite holds its last
    /// finite target instead.
    fn stop(&mut self) -> Result<()>;
    /// A fault the device reported with its newest state (a finger's error word, a
    /// controller error code), if any. The safety layer stops the robot on one.
    fn fault(&self) -> Option<String> {
        None
    }
}

impl<R: Robot + ?Sized> Robot for Box<R> {
    fn name(&self) -> &'static str {
        (**self).name()
    }
    fn state_dim(&self) -> usize {
        (**self).state_dim()
    }
    fn action_dim(&self) -> usize {
        (**self).action_dim()
    }
    fn layout(&self) -> StateLayout {
        (**self).layout()
    }
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
        (**self).read_state(out)
    }
    fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
        (**self).send_targets(targets)
    }
    fn stop(&mut self) -> Result<()> {
        (**self).stop()
    }
    fn fault(&self) -> Option<String> {
        (**self).fault()
    }
}

// ---------------------------------------------------------------------------------------------
// Composite
// ---------------------------------------------------------------------------------------------

/// Arm joints in the composite.
pub const ARM_DOF: usize = 6;
/// Hand joints in the composite.
pub const HAND_DOF: usize = 12;
/// Fingertip force values (5 tips × 3 axes).
pub const TIP_FORCES: usize = 15;
/// The paper's proprioception size: 6 + 12 + 12 + 15.
pub const ARM_HAND_STATE_DIM: usize = ARM_DOF + 2 * HAND_DOF + TIP_FORCES;
/// The paper's action size: 6 + 12.
pub const ARM_HAND_ACTION_DIM: usize = ARM_DOF + HAND_DOF;

/// An arm (first 6 state entries = joint angles, 6 targets) plus a hand whose state is
/// `[12 positions, 12 torques, 15 tip forces]` and whose action is 12 targets: the xArm6 +
/// XHand of the paper. Generic so emulated or mocked parts can stand in.
#[derive(Debug)]
pub struct ArmHand<A, H> {
    arm: A,
    hand: H,
    arm_buf: Vec<f32>,
}

impl<A: Robot, H: Robot> ArmHand<A, H> {
    /// Combine an arm with `ARM_DOF` targets and a hand with `HAND_DOF` targets and a
    /// 39-value state.
    pub fn new(arm: A, hand: H) -> Result<Self> {
        Error::check_dim("composite arm action", ARM_DOF, arm.action_dim())?;
        if arm.state_dim() < ARM_DOF {
            return Err(Error::Dim {
                what: "composite arm state",
                expected: ARM_DOF,
                got: arm.state_dim(),
            });
        }
        Error::check_dim("composite hand action", HAND_DOF, hand.action_dim())?;
        Error::check_dim(
            "composite hand state",
            2 * HAND_DOF + TIP_FORCES,
            hand.state_dim(),
        )?;
        let arm_buf = vec![0.0; arm.state_dim()];
        Ok(Self { arm, hand, arm_buf })
    }
    /// The arm.
    pub fn arm(&mut self) -> &mut A {
        &mut self.arm
    }
    /// The hand.
    pub fn hand(&mut self) -> &mut H {
        &mut self.hand
    }
    /// Both parts back.
    pub fn into_parts(self) -> (A, H) {
        (self.arm, self.hand)
    }
}

impl<A: Robot, H: Robot> Robot for ArmHand<A, H> {
    fn name(&self) -> &'static str {
        "xArm6+XHand"
    }
    fn state_dim(&self) -> usize {
        ARM_HAND_STATE_DIM
    }
    fn action_dim(&self) -> usize {
        ARM_HAND_ACTION_DIM
    }
    fn layout(&self) -> StateLayout {
        StateLayout {
            positions: 0..ARM_HAND_ACTION_DIM,
            torques: Some(ARM_HAND_ACTION_DIM..ARM_HAND_ACTION_DIM + HAND_DOF),
        }
    }
    /// The timestamp is the older of the two parts' (the state is as fresh as its stalest part).
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
        Error::check_dim("composite state", ARM_HAND_STATE_DIM, out.len())?;
        let ta = self.arm.read_state(&mut self.arm_buf)?;
        out[..ARM_DOF].copy_from_slice(&self.arm_buf[..ARM_DOF]);
        let th = self.hand.read_state(&mut out[ARM_DOF..])?;
        Ok(ta.min(th))
    }
    fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
        Error::check_dim("composite targets", ARM_HAND_ACTION_DIM, targets.len())?;
        // Send both even if the first fails, so the parts never diverge by a whole tick.
        let ra = self.arm.send_targets(&targets[..ARM_DOF]);
        let rh = self.hand.send_targets(&targets[ARM_DOF..]);
        ra.and(rh)
    }
    fn stop(&mut self) -> Result<()> {
        let ra = self.arm.stop();
        let rh = self.hand.stop();
        ra.and(rh)
    }
    fn fault(&self) -> Option<String> {
        match (self.arm.fault(), self.hand.fault()) {
            (Some(a), Some(h)) => Some(format!("arm: {a}; hand: {h}")),
            (Some(a), None) => Some(format!("arm: {a}")),
            (None, Some(h)) => Some(format!("hand: {h}")),
            (None, None) => None,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Runtime adapters
// ---------------------------------------------------------------------------------------------

/// A robot shared between a [`RobotSource`] and a [`RobotActuator`].
pub type SharedRobot<R> = Arc<Mutex<R>>;

/// Split a robot into the runtime's fast source (its state) and actuator (its targets).
pub fn split<R: Robot>(robot: R) -> (RobotSource<R>, RobotActuator<R>) {
    let shared = Arc::new(Mutex::new(robot));
    (RobotSource::new(shared.clone()), RobotActuator::new(shared))
}

fn lock<R>(r: &SharedRobot<R>) -> std::sync::MutexGuard<'_, R> {
    // A panic while holding the lock cannot leave a robot half-updated in a way that matters
    // more than stopping it: keep going with the inner value.
    r.lock().unwrap_or_else(|p| p.into_inner())
}

/// A [`Robot`]'s state as the runtime's [`FastSource`].
#[derive(Debug)]
pub struct RobotSource<R> {
    robot: SharedRobot<R>,
    dim: usize,
}

impl<R: Robot> RobotSource<R> {
    /// Wrap a shared robot.
    pub fn new(robot: SharedRobot<R>) -> Self {
        let dim = lock(&robot).state_dim();
        Self { robot, dim }
    }
    /// The shared robot.
    pub fn robot(&self) -> &SharedRobot<R> {
        &self.robot
    }
}

impl<R: Robot> FastSource for RobotSource<R> {
    fn dim(&self) -> usize {
        self.dim
    }
    fn read(&mut self, out: &mut [f32]) -> pir2_runtime::Result<Nanos> {
        Ok(lock(&self.robot).read_state(out)?)
    }
}

/// A [`Robot`]'s targets as the runtime's [`Actuator`].
#[derive(Debug)]
pub struct RobotActuator<R> {
    robot: SharedRobot<R>,
    dim: usize,
}

impl<R: Robot> RobotActuator<R> {
    /// Wrap a shared robot.
    pub fn new(robot: SharedRobot<R>) -> Self {
        let dim = lock(&robot).action_dim();
        Self { robot, dim }
    }
    /// The shared robot.
    pub fn robot(&self) -> &SharedRobot<R> {
        &self.robot
    }
}

impl<R: Robot> Actuator for RobotActuator<R> {
    fn dim(&self) -> usize {
        self.dim
    }
    fn send(&mut self, action: &[f32]) -> pir2_runtime::Result<()> {
        Ok(lock(&self.robot).send_targets(action)?)
    }
    fn stop(&mut self) -> pir2_runtime::Result<()> {
        Ok(lock(&self.robot).stop()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A robot that records what it was sent and reports a fixed state.
    #[derive(Debug)]
    struct Fake {
        state: Vec<f32>,
        actions: usize,
        sent: Vec<Vec<f32>>,
        t: Nanos,
    }

    impl Robot for Fake {
        fn name(&self) -> &'static str {
            "fake"
        }
        fn state_dim(&self) -> usize {
            self.state.len()
        }
        fn action_dim(&self) -> usize {
            self.actions
        }
        fn layout(&self) -> StateLayout {
            StateLayout {
                positions: 0..self.actions,
                torques: None,
            }
        }
        fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
            out.copy_from_slice(&self.state);
            Ok(self.t)
        }
        fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
            self.sent.push(targets.to_vec());
            Ok(())
        }
        fn stop(&mut self) -> Result<()> {
            Ok(())
        }
    }

    #[test]
    fn composite_state_is_45d_in_paper_order_with_oldest_timestamp() {
        let arm = Fake {
            state: (0..12).map(|i| i as f32).collect(),
            actions: 6,
            sent: vec![],
            t: 50,
        };
        let hand = Fake {
            state: (0..39).map(|i| 100.0 + i as f32).collect(),
            actions: 12,
            sent: vec![],
            t: 40,
        };
        let mut c = ArmHand::new(arm, hand).unwrap();
        let mut s = vec![0.0; 45];
        assert_eq!(c.read_state(&mut s).unwrap(), 40);
        assert_eq!(&s[..6], &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(s[6], 100.0);
        assert_eq!(s[44], 138.0);
        let a: Vec<f32> = (0..18).map(|i| i as f32).collect();
        c.send_targets(&a).unwrap();
        let (arm, hand) = c.into_parts();
        assert_eq!(arm.sent[0], a[..6].to_vec());
        assert_eq!(hand.sent[0], a[6..].to_vec());
    }

    #[test]
    fn composite_rejects_wrong_part_sizes() {
        let arm = Fake {
            state: vec![0.0; 12],
            actions: 7,
            sent: vec![],
            t: 0,
        };
        let hand = Fake {
            state: vec![0.0; 39],
            actions: 12,
            sent: vec![],
            t: 0,
        };
        assert!(matches!(
            ArmHand::new(arm, hand),
            Err(Error::Dim {
                expected: 6,
                got: 7,
                ..
            })
        ));
    }

    #[test]
    fn adapters_forward_to_the_robot_and_map_dim_errors() {
        let r = Fake {
            state: vec![1.0, 2.0],
            actions: 2,
            sent: vec![],
            t: 7,
        };
        let (mut src, mut act) = split(r);
        assert_eq!(src.dim(), 2);
        assert_eq!(act.dim(), 2);
        let mut out = [0.0; 2];
        assert_eq!(src.read(&mut out).unwrap(), 7);
        assert_eq!(out, [1.0, 2.0]);
        act.send(&[3.0, 4.0]).unwrap();
        assert_eq!(lock(act.robot()).sent, vec![vec![3.0, 4.0]]);
    }
}
