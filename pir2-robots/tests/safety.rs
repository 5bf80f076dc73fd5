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

fn cfg() -> SafetyConfig {
    let mut c = SafetyConfig::uniform(2, -1.0, 1.0, 0.1);
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
        log: log.clone(),
    };
    let l = SafetyLayer::new(r, cfg(), Arc::new(clock.clone())).unwrap();
    (l, clock, log)
}

fn last(log: &Arc<Mutex<Log>>) -> Vec<f32> {
    log.lock().unwrap().sent.last().cloned().unwrap()
}

#[test]
fn first_target_is_rate_limited_from_the_measured_position() {
    let (mut l, _c, log) = layer([0.5, -0.5, 0.0, 0.0]);
    l.send_targets(&[0.9, -0.5]).unwrap();
    assert_eq!(last(&log), vec![0.6, -0.5]);
    assert_eq!(l.stats().rate_clamps, 1);
    assert_eq!(l.stats().limit_clamps, 0);
}

#[test]
fn joint_limits_clamp_and_rate_limit_follows() {
    let (mut l, _c, log) = layer([0.95, 0.0, 0.0, 0.0]);
    let mut s = [0f32; 4];
    l.read_state(&mut s).unwrap();
    l.send_targets(&[5.0, 0.05]).unwrap();
    assert_eq!(last(&log), vec![1.0, 0.05]);
    let st = l.stats();
    assert_eq!((st.limit_clamps, st.rate_clamps), (1, 0));
    // A target within limits and within one step passes untouched.
    l.send_targets(&[0.95, 0.1]).unwrap();
    assert_eq!(last(&log), vec![0.95, 0.1]);
    assert_eq!(l.stats().interventions(), 1);
}

#[test]
fn nan_and_inf_targets_hold_the_last_safe_target() {
    let (mut l, _c, log) = layer([0.0, 0.0, 0.0, 0.0]);
    l.send_targets(&[0.05, 0.05]).unwrap();
    l.send_targets(&[f32::NAN, 0.0]).unwrap();
    assert_eq!(last(&log), vec![0.05, 0.05]);
    l.send_targets(&[0.0, f32::INFINITY]).unwrap();
    assert_eq!(last(&log), vec![0.05, 0.05]);
    assert_eq!(l.stats().non_finite_targets, 2);
    // A NaN as the very first target holds the measured position.
    let (mut l2, _c2, log2) = layer([0.3, 0.2, 0.0, 0.0]);
    l2.send_targets(&[f32::NAN, f32::NAN]).unwrap();
    assert_eq!(last(&log2), vec![0.3, 0.2]);
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
    assert_eq!(
        last(&log),
        vec![0.1, 0.1],
        "held while over the torque limit"
    );
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
    assert_eq!(last(&log), vec![0.0, 0.0]);
    l.with_robot(|r| r.state[2] = 1.0);
    l.read_state(&mut s).unwrap();
    l.send_targets(&[0.1, 0.1]).unwrap();
    assert_eq!(last(&log), vec![0.1, 0.1]);
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
