//! The safety layer on a scripted robot and a mock clock: every intervention happens when it
//! should, is counted, and a stop latches.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use pir2_robots::{Error, Robot, SafetyConfig, SafetyLayer, StateLayout};
use pir2_runtime::{Clock, MockClock, Nanos};

/// State `[q0, q1, tau0, tau1]`, action `[q0, q1]`; records targets and stops.
#[derive(Debug, Clone, Default)]
struct Log {
    sent: Vec<Vec<f32>>,
    stops: usize,
}

#[derive(Debug)]
struct Scripted {
    clock: MockClock,
    state: [f32; 4],
    /// Age of the state when read, ns.
    lag: Nanos,
    /// Fail this many of the next reads.
    fail_reads: u32,
    log: Arc<Mutex<Log>>,
}

impl Robot for Scripted {
    fn name(&self) -> &'static str {
        "scripted"
    }
    fn state_dim(&self) -> usize {
        4
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn layout(&self) -> StateLayout {
        StateLayout {
            positions: 0..2,
            torques: Some(2..4),
        }
    }
    fn read_state(&mut self, out: &mut [f32]) -> pir2_robots::Result<Nanos> {
        if self.fail_reads > 0 {
            self.fail_reads -= 1;
            return Err(Error::Timeout {
                channel: "scripted",
                what: "state".into(),
                waited_ms: 10,
            });
        }
        out.copy_from_slice(&self.state);
        Ok(self.clock.now().saturating_sub(self.lag))
    }
    fn send_targets(&mut self, t: &[f32]) -> pir2_robots::Result<()> {
        self.log.lock().unwrap().sent.push(t.to_vec());
        Ok(())
    }
    fn stop(&mut self) -> pir2_robots::Result<()> {
        self.log.lock().unwrap().stops += 1;
        Ok(())
    }
}

/// Nominal period of the tests' safety layer.
const PERIOD: Nanos = 40_000_000;

fn cfg() -> SafetyConfig {
    // 2.5 rad/s at 40 ms: 0.1 rad per target.
    let mut c = SafetyConfig::uniform(2, -1.0, 1.0, 2.5);
    c.torque_limit = 10.0;
    c.torque_stop_reads = 3;
    c.state_timeout = Duration::from_millis(100);
    c.command_timeout = Duration::from_millis(100);
    c
}

fn layer(state: [f32; 4]) -> (SafetyLayer<Scripted>, MockClock, Arc<Mutex<Log>>) {
    let clock = MockClock::new();
    clock.set(1_000_000_000);
    let log = Arc::new(Mutex::new(Log::default()));
    let r = Scripted {
        clock: clock.clone(),
        state,
        lag: 0,
        fail_reads: 0,
        log: log.clone(),
    };
    let l = SafetyLayer::new(r, cfg(), Arc::new(clock.clone())).unwrap();
    (l, clock, log)
}

fn last(log: &Arc<Mutex<Log>>) -> Vec<f32> {
    log.lock().unwrap().sent.last().cloned().unwrap()
}

#[track_caller]
fn assert_near(got: Vec<f32>, want: &[f32]) {
    assert!(
        got.len() == want.len() && got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-5),
        "{got:?} != {want:?}"
    );
}

#[test]
fn first_target_is_rate_limited_from_the_measured_position() {
    let (mut l, _c, log) = layer([0.5, -0.5, 0.0, 0.0]);
    l.send_targets(&[0.9, -0.5]).unwrap();
    assert_near(last(&log), &[0.6, -0.5]);
    assert_eq!(l.stats().rate_clamps, 1);
    assert_eq!(l.stats().limit_clamps, 0);
}

#[test]
fn joint_limits_clamp_and_rate_limit_follows() {
    let (mut l, _c, log) = layer([0.95, 0.0, 0.0, 0.0]);
    let mut s = [0f32; 4];
    l.read_state(&mut s).unwrap();
    l.send_targets(&[5.0, 0.05]).unwrap();
    assert_near(last(&log), &[1.0, 0.05]);
    let st = l.stats();
    assert_eq!((st.limit_clamps, st.rate_clamps), (1, 0));
    // A target within limits and within one step passes untouched.
    _c.advance(PERIOD);
    l.send_targets(&[0.95, 0.1]).unwrap();
    assert_near(last(&log), &[0.95, 0.1]);
    assert_eq!(l.stats().interventions(), 1);
}

#[test]
fn nan_and_inf_targets_hold_the_last_safe_target() {
    let (mut l, _c, log) = layer([0.0, 0.0, 0.0, 0.0]);
    l.send_targets(&[0.05, 0.05]).unwrap();
    _c.advance(PERIOD);
    l.send_targets(&[f32::NAN, 0.0]).unwrap();
    assert_near(last(&log), &[0.05, 0.05]);
    l.send_targets(&[0.0, f32::INFINITY]).unwrap();
    assert_near(last(&log), &[0.05, 0.05]);
    assert_eq!(l.stats().non_finite_targets, 2);
    // A NaN as the very first target holds the measured position.
    let (mut l2, _c2, log2) = layer([0.3, 0.2, 0.0, 0.0]);
    l2.send_targets(&[f32::NAN, f32::NAN]).unwrap();
    assert_near(last(&log2), &[0.3, 0.2]);
}

#[test]
fn non_finite_state_is_rejected() {
    let (mut l, _c, _log) = layer([f32::NAN, 0.0, 0.0, 0.0]);
    let mut s = [0f32; 4];
    assert!(l.read_state(&mut s).is_err());
    assert_eq!(l.stats().non_finite_states, 1);
}

#[test]
fn torque_over_limit_holds_then_stops() {
    let (mut l, _c, log) = layer([0.0, 0.0, 0.0, 0.0]);
    let mut s = [0f32; 4];
    l.send_targets(&[0.1, 0.1]).unwrap();
    l.with_robot(|r| r.state[3] = -11.0);
    l.read_state(&mut s).unwrap();
    l.send_targets(&[0.2, 0.2]).unwrap();
    assert_near(last(&log), &[0.1, 0.1]);
    assert_eq!(l.stats().torque_holds, 1);
    l.read_state(&mut s).unwrap();
    let e = l.read_state(&mut s).unwrap_err();
    assert!(
        matches!(e, Error::SafetyStop(ref m) if m.contains("torque")),
        "{e}"
    );
    assert_eq!(log.lock().unwrap().stops, 1);
    assert_eq!(l.stats().torque_over, 3);
    // Latched.
    assert!(matches!(
        l.send_targets(&[0.0, 0.0]),
        Err(Error::SafetyStop(_))
    ));
}

#[test]
fn torque_back_under_the_limit_releases_the_hold() {
    let (mut l, _c, log) = layer([0.0, 0.0, 20.0, 0.0]);
    let mut s = [0f32; 4];
    l.read_state(&mut s).unwrap();
    l.send_targets(&[0.1, 0.1]).unwrap();
    assert_near(last(&log), &[0.0, 0.0]);
    l.with_robot(|r| r.state[2] = 1.0);
    l.read_state(&mut s).unwrap();
    _c.advance(PERIOD);
    l.send_targets(&[0.1, 0.1]).unwrap();
    assert_near(last(&log), &[0.1, 0.1]);
}

#[test]
fn stale_state_stops_the_robot() {
    let (mut l, _c, log) = layer([0.0; 4]);
    l.with_robot(|r| r.lag = 150_000_000);
    let mut s = [0f32; 4];
    let e = l.read_state(&mut s).unwrap_err();
    assert!(
        matches!(e, Error::SafetyStop(ref m) if m.contains("150 ms old")),
        "{e}"
    );
    assert_eq!(l.stats().stale_states, 1);
    assert_eq!(log.lock().unwrap().stops, 1);
}

#[test]
fn watchdog_stops_when_the_policy_stops_sending() {
    let (mut l, clock, log) = layer([0.0; 4]);
    let mut s = [0f32; 4];
    l.read_state(&mut s).unwrap();
    l.send_targets(&[0.0, 0.0]).unwrap();
    clock.advance(50_000_000);
    l.read_state(&mut s).unwrap();
    l.check_watchdog().unwrap();
    clock.advance(60_000_000);
    l.read_state(&mut s).unwrap();
    let e = l.check_watchdog().unwrap_err();
    assert!(
        matches!(e, Error::SafetyStop(ref m) if m.contains("no target")),
        "{e}"
    );
    assert_eq!(l.stats().command_timeouts, 1);
    assert_eq!(log.lock().unwrap().stops, 1);
    // Reset re-arms.
    l.reset();
    l.read_state(&mut s).unwrap();
    l.send_targets(&[0.0, 0.0]).unwrap();
    assert!(l.stop_reason().is_none());
}

#[test]
fn watchdog_stops_when_state_stops_arriving() {
    let (mut l, clock, _log) = layer([0.0; 4]);
    let mut s = [0f32; 4];
    l.read_state(&mut s).unwrap();
    for _ in 0..3 {
        clock.advance(40_000_000);
        l.send_targets(&[0.0, 0.0]).unwrap();
    }
    let e = l.check_watchdog().unwrap_err();
    assert!(
        matches!(e, Error::SafetyStop(ref m) if m.contains("no fresh state")),
        "{e}"
    );
    assert_eq!(l.stats().stale_states, 1);
}

#[test]
fn watchdog_thread_stops_a_silent_policy() {
    use pir2_runtime::SystemClock;
    let clock = Arc::new(SystemClock::new());
    let log = Arc::new(Mutex::new(Log::default()));
    // The scripted robot stamps its state at mock time 0; the long state timeout keeps that
    // fresh enough on the real clock, so only the command deadline can fire.
    let r = Scripted {
        clock: MockClock::new(),
        state: [0.0; 4],
        lag: 0,
        fail_reads: 0,
        log: log.clone(),
    };
    let mut c = cfg();
    c.state_timeout = Duration::from_secs(5);
    c.command_timeout = Duration::from_millis(30);
    let mut l = SafetyLayer::new(r, c, clock).unwrap();
    l.spawn_watchdog(Duration::from_millis(5)).unwrap();
    l.send_targets(&[0.0, 0.0]).unwrap();
    let t0 = std::time::Instant::now();
    while l.stop_reason().is_none() && t0.elapsed() < Duration::from_secs(3) {
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(l.stop_reason().unwrap().contains("no target"));
    assert_eq!(log.lock().unwrap().stops, 1);
}

#[test]
fn explicit_stop_is_counted_and_latched() {
    let (mut l, _c, log) = layer([0.0; 4]);
    l.stop().unwrap();
    assert_eq!(l.stats().stops, 1);
    assert_eq!(log.lock().unwrap().stops, 1);
    assert!(matches!(
        l.send_targets(&[0.0, 0.0]),
        Err(Error::SafetyStop(_))
    ));
    let text = l.stats().to_string();
    assert!(text.contains("stops 1"), "{text}");
}

#[test]
fn config_is_checked_against_the_robot() {
    let clock = MockClock::new();
    let r = Scripted {
        clock: clock.clone(),
        state: [0.0; 4],
        lag: 0,
        fail_reads: 0,
        log: Arc::default(),
    };
    let bad = SafetyConfig::uniform(3, -1.0, 1.0, 0.1);
    assert!(matches!(
        SafetyLayer::new(r, bad, Arc::new(clock)),
        Err(Error::Dim { .. })
    ));
    let mut inverted = SafetyConfig::uniform(2, 1.0, -1.0, 0.1);
    assert!(inverted.validate(2).is_err());
    inverted = SafetyConfig::xarm6_xhand();
    assert!(inverted.validate(18).is_ok());
}

/// The xArm6 + XHand composite's shape with perfect tracking: the measured positions are the
/// last targets sent.
#[derive(Debug)]
struct Follower {
    clock: MockClock,
    q: [f32; 18],
    sent: Arc<Mutex<Vec<Vec<f32>>>>,
}

impl Robot for Follower {
    fn name(&self) -> &'static str {
        "follower"
    }
    fn state_dim(&self) -> usize {
        45
    }
    fn action_dim(&self) -> usize {
        18
    }
    fn layout(&self) -> StateLayout {
        StateLayout {
            positions: 0..18,
            torques: Some(18..30),
        }
    }
    fn read_state(&mut self, out: &mut [f32]) -> pir2_robots::Result<Nanos> {
        out.fill(0.0);
        out[..18].copy_from_slice(&self.q);
        Ok(self.clock.now())
    }
    fn send_targets(&mut self, t: &[f32]) -> pir2_robots::Result<()> {
        self.q.copy_from_slice(t);
        self.sent.lock().unwrap().push(t.to_vec());
        Ok(())
    }
    fn stop(&mut self) -> pir2_robots::Result<()> {
        Ok(())
    }
}

/// The default xArm6 + XHand limits are speeds: at 100 Hz (4× the nominal rate) the arm
/// still moves at most 1.25 rad/s (before: 0.05 rad per target whatever the rate, 5 rad/s).
#[test]
fn arm_speed_is_bounded_in_rad_per_s_at_any_control_rate() {
    let clock = MockClock::new();
    clock.set(1_000_000_000);
    let sent = Arc::new(Mutex::new(Vec::new()));
    let r = Follower {
        clock: clock.clone(),
        q: [0.0; 18],
        sent: sent.clone(),
    };
    let mut l = SafetyLayer::new(r, SafetyConfig::xarm6_xhand(), Arc::new(clock.clone())).unwrap();
    let mut s = [0f32; 45];
    let mut target = [0f32; 18];
    target[0] = 1.5;
    let dt = 0.01;
    for _ in 0..100 {
        clock.advance(10_000_000);
        l.read_state(&mut s).unwrap();
        l.send_targets(&target).unwrap();
    }
    let sent = sent.lock().unwrap();
    let top = sent
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).abs() / dt)
        .fold(0.0f32, f32::max);
    assert!(top <= 1.25 + 1e-3, "arm joint moved at {top} rad/s");
    // ... and it did get going: 1 s at up to 1.25 rad/s (20 rad/s² ramp) covers > 1 rad.
    assert!(sent.last().unwrap()[0] > 1.0, "{:?}", sent.last());
}

/// From rest a joint's speed ramps at most `max_accel`; braking is not limited.
#[test]
fn acceleration_is_bounded_from_rest() {
    let (mut l, c, log) = layer([0.0; 4]);
    drop(l);
    let mut cfg = cfg();
    cfg.max_accel = vec![10.0; 2];
    let r = Scripted {
        clock: c.clone(),
        state: [0.0; 4],
        lag: 0,
        fail_reads: 0,
        log: log.clone(),
    };
    l = SafetyLayer::new(r, cfg, Arc::new(c.clone())).unwrap();
    let mut prev = 0.0f32;
    let mut speeds = Vec::new();
    for _ in 0..8 {
        c.advance(PERIOD);
        l.send_targets(&[1.0, 0.0]).unwrap();
        let x = last(&log)[0];
        speeds.push((x - prev) / 0.04);
        prev = x;
    }
    // 10 rad/s² · 40 ms = 0.4 rad/s more per target, up to 2.5 rad/s.
    for (k, v) in speeds.iter().enumerate() {
        let cap = (0.4 * (k + 1) as f32).min(2.5);
        assert!(*v <= cap + 1e-3, "target {k}: {v} rad/s > {cap}");
    }
    assert!(speeds[7] > 2.4, "{speeds:?}");
    // Braking to a hold is immediate: a target at the current position is sent as is.
    c.advance(PERIOD);
    l.send_targets(&[prev, 0.0]).unwrap();
    assert_near(last(&log), &[prev, 0.0]);
}

/// A joint that does not follow its target stops the robot after the configured reads
/// (before: the tracking error was unbounded).
#[test]
fn tracking_error_stops_the_robot() {
    let (l0, c, log) = layer([0.0; 4]);
    drop(l0);
    let mut cfg = cfg();
    cfg.tracking_error = vec![0.15; 2];
    cfg.tracking_stop_reads = 3;
    let r = Scripted {
        clock: c.clone(),
        state: [0.0; 4],
        lag: 0,
        fail_reads: 0,
        log: log.clone(),
    };
    let mut l = SafetyLayer::new(r, cfg, Arc::new(c.clone())).unwrap();
    let mut s = [0f32; 4];
    let mut stopped = None;
    for k in 0..10 {
        c.advance(PERIOD);
        if let Err(e) = l.read_state(&mut s) {
            stopped = Some((k, e));
            break;
        }
        l.send_targets(&[1.0, 0.0]).unwrap();
    }
    // Targets 0.1, 0.2, 0.3, …; the stuck joint is over 0.15 from the 2nd target on.
    let (k, e) = stopped.expect("a stuck joint must stop the robot");
    assert!(
        matches!(e, Error::SafetyStop(ref m) if m.contains("from its target")),
        "{e}"
    );
    assert_eq!(k, 4);
    assert_eq!(l.stats().tracking_over, 3);
    assert_eq!(log.lock().unwrap().stops, 1);
}

/// Driver errors in a row stop the robot; one transient error does not.
#[test]
fn consecutive_driver_errors_stop_the_robot() {
    let (mut l, _c, log) = layer([0.0; 4]);
    let mut s = [0f32; 4];
    l.with_robot(|r| r.fail_reads = 1);
    assert!(matches!(l.read_state(&mut s), Err(Error::Timeout { .. })));
    l.read_state(&mut s).unwrap();
    l.with_robot(|r| r.fail_reads = 3);
    assert!(matches!(l.read_state(&mut s), Err(Error::Timeout { .. })));
    assert!(matches!(l.read_state(&mut s), Err(Error::Timeout { .. })));
    let e = l.read_state(&mut s).unwrap_err();
    assert!(
        matches!(e, Error::SafetyStop(ref m) if m.contains("3 driver errors")),
        "{e}"
    );
    assert_eq!(log.lock().unwrap().stops, 1);
    assert_eq!(l.stats().robot_errors, 4);
}

/// The robot's ceiling bounds every configuration: tightening passes, any looser limit (or a
/// NaN) is reported with its joint and field (before: ±100 rad, 1000 rad/s and 1e9 rad/s² in
/// a checkpoint's `[safety]` ran).
#[test]
fn a_configuration_may_only_tighten_the_robots_ceiling() {
    let ceiling = SafetyConfig::xarm6_xhand_ceiling_at(25.0);
    // The defaults in force sit inside the ceiling, and the ceiling inside itself.
    assert_eq!(SafetyConfig::xarm6_xhand().widening(&ceiling), None);
    assert_eq!(ceiling.widening(&ceiling), None);
    let mut tight = SafetyConfig::xarm6_xhand();
    tight.upper[7] = 1.0;
    tight.max_velocity[0] = 0.5;
    tight.tracking_error[10] = 0.1;
    assert_eq!(tight.widening(&ceiling), None);
    type Edit = fn(&mut SafetyConfig);
    let cases: [(Edit, usize, &str); 6] = [
        (|c| c.lower[1] = -100.0, 1, "lower"),
        (|c| c.upper[17] = 100.0, 17, "upper"),
        (|c| c.max_velocity[3] = 1000.0, 3, "max_velocity"),
        (|c| c.max_accel[8] = 1e9, 8, "max_accel"),
        (|c| c.tracking_error[0] = 2.0, 0, "tracking_error"),
        (|c| c.max_velocity[12] = f32::NAN, 12, "max_velocity"),
    ];
    for (edit, joint, field) in cases {
        let mut c = SafetyConfig::xarm6_xhand();
        edit(&mut c);
        let w = c.widening(&ceiling).expect(field);
        assert_eq!((w.joint, w.field), (joint, field), "{w:?}");
    }
}
