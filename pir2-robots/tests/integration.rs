//! The xArm6 + XHand composite driven through both emulators at 25 Hz with the safety layer
//! on, with actions fed through the runtime's `FastSource` / `Actuator` traits.

use std::sync::Arc;
use std::time::Duration;

use pir2_robots::emu::{
    EmulatedArmHand, EmulatedArmHandConfig, EmulatedRobot, XArmFault, XHandFault,
};
use pir2_robots::robot::{ARM_HAND_ACTION_DIM, ARM_HAND_STATE_DIM};
use pir2_robots::xarm::proto::state;
use pir2_robots::{split, SafetyConfig};
use pir2_runtime::{Actuator, Clock, FastSource, SystemClock};

const PERIOD_NS: u64 = 40_000_000; // 25 Hz

struct Rig {
    emu: EmulatedArmHand,
    clock: Arc<dyn Clock>,
    layer: EmulatedRobot,
}

fn rig(safety: SafetyConfig) -> Rig {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let cfg = EmulatedArmHandConfig {
        serial_latency: Duration::from_millis(10),
        safety,
        ..Default::default()
    };
    let (emu, layer) = EmulatedArmHand::start(&cfg, clock.clone()).unwrap();
    Rig { emu, clock, layer }
}

/// A smooth 18-d reference around the arm's home pose.
fn reference(k: usize, home: &[f32]) -> Vec<f32> {
    let t = k as f32 * 0.04;
    let mut a = vec![0f32; ARM_HAND_ACTION_DIM];
    for j in 0..6 {
        a[j] = home[j] + 0.15 * (0.8 * t + j as f32).sin() * (t / 1.0).min(1.0);
    }
    for j in 0..12 {
        a[6 + j] = 0.6 + 0.4 * (1.2 * t + 0.3 * j as f32).sin();
    }
    a
}

#[test]
fn composite_runs_at_25_hz_through_both_emulators_with_safety_on() {
    let Rig { emu, clock, layer } = rig(SafetyConfig::xarm6_xhand());
    let (mut source, mut actuator) = split(layer);
    assert_eq!(source.dim(), ARM_HAND_STATE_DIM);
    assert_eq!(actuator.dim(), ARM_HAND_ACTION_DIM);

    let mut obs = vec![0f32; ARM_HAND_STATE_DIM];
    source.read(&mut obs).unwrap();
    let home = obs[..6].to_vec();
    let ticks = 100; // 4 s at 25 Hz
    let mut last_t = 0;
    let mut next = clock.now();
    let mut last_action = Vec::new();
    for k in 0..ticks {
        let t = source.read(&mut obs).unwrap();
        assert!(t >= last_t, "state timestamps never go back");
        last_t = t;
        assert!(obs.iter().all(|x| x.is_finite()));
        last_action = reference(k, &home);
        actuator.send(&last_action).unwrap();
        next += PERIOD_NS;
        clock.sleep_until(next);
    }
    // Hold the last action briefly so both sides settle, then compare.
    for _ in 0..10 {
        source.read(&mut obs).unwrap();
        actuator.send(&last_action).unwrap();
        next += PERIOD_NS;
        clock.sleep_until(next);
    }
    source.read(&mut obs).unwrap();
    for j in 0..6 {
        assert!(
            (obs[j] - last_action[j]).abs() < 0.02,
            "arm joint {j}: {} vs {}",
            obs[j],
            last_action[j]
        );
    }
    for j in 0..12 {
        assert!(
            (obs[6 + j] - last_action[6 + j]).abs() < 0.05,
            "hand joint {j}: {} vs {}",
            obs[6 + j],
            last_action[6 + j]
        );
    }
    let stats = source.robot().lock().unwrap().stats();
    assert_eq!(stats.targets, ticks as u64 + 10);
    assert_eq!(stats.stops, 0, "{stats}");
    assert_eq!(
        stats.command_timeouts + stats.stale_states + stats.non_finite_targets,
        0,
        "{stats}"
    );
    // The arm was streamed at ~100 Hz: clearly more servo-j frames than policy targets.
    assert!(emu.arm.handle().sim().servoj > 2 * ticks as u64);
    assert!(emu.hand.handle().commands() >= ticks as u64);

    actuator.stop().unwrap();
    assert_eq!(emu.arm.handle().sim().state, state::STOP);
    assert!(actuator.send(&last_action).is_err());
}

#[test]
fn silent_policy_is_stopped_by_the_watchdog() {
    let Rig {
        emu,
        clock: _c,
        layer,
    } = rig(SafetyConfig::xarm6_xhand());
    let (mut source, mut actuator) = split(layer);
    let mut obs = vec![0f32; ARM_HAND_STATE_DIM];
    source.read(&mut obs).unwrap();
    let mut a = obs[..ARM_HAND_ACTION_DIM].to_vec();
    a[6..].fill(0.2);
    actuator.send(&a).unwrap();
    // The policy goes quiet; the watchdog (200 ms command timeout) stops arm and hand.
    let t0 = std::time::Instant::now();
    while emu.arm.handle().sim().state != state::STOP && t0.elapsed() < Duration::from_secs(3) {
        std::thread::sleep(Duration::from_millis(10));
    }
    assert_eq!(emu.arm.handle().sim().state, state::STOP);
    let err = actuator.send(&a).unwrap_err();
    assert!(
        matches!(err, pir2_runtime::Error::SafetyStop(ref m) if m.contains("no target")),
        "{err}"
    );
    assert_eq!(source.robot().lock().unwrap().stats().command_timeouts, 1);
}

#[test]
fn wild_policy_is_clamped_not_executed() {
    let Rig {
        emu,
        clock: _c,
        layer,
    } = rig(SafetyConfig::xarm6_xhand());
    let (mut source, mut actuator) = split(layer);
    let mut obs = vec![0f32; ARM_HAND_STATE_DIM];
    source.read(&mut obs).unwrap();
    let home = obs[..6].to_vec();
    let mut wild = vec![10.0f32; ARM_HAND_ACTION_DIM];
    wild[0] = f32::NAN;
    actuator.send(&wild).unwrap();
    let mut jump = vec![3.0f32; ARM_HAND_ACTION_DIM];
    jump[..6].copy_from_slice(&home);
    jump[0] += 1.0;
    actuator.send(&jump).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    let sim = emu.arm.handle().sim();
    assert!(
        (sim.target[0] - home[0]).abs() <= 0.05 + 1e-5,
        "arm moved at most one step: {}",
        sim.target[0]
    );
    assert!(
        emu.hand.handle().targets().iter().all(|&q| q <= 0.2 + 1e-5),
        "hand moved at most one step from 0"
    );
    let stats = source.robot().lock().unwrap().stats();
    assert_eq!(stats.non_finite_targets, 1);
    assert_eq!(stats.limit_clamps, 1);
    assert!(stats.rate_clamps >= 1);
}

/// A controller error on the arm (a collision, code 31) stops arm and hand at the first
/// call that sees it, through `Robot::fault`, not after several driver errors (before: the
/// arm's fault was a plain driver error, counted; the hand kept being driven meanwhile).
#[test]
fn arm_controller_error_stops_the_whole_robot_at_once() {
    let Rig { emu, clock, layer } = rig(SafetyConfig::xarm6_xhand());
    let (mut source, mut actuator) = split(layer);
    let mut obs = vec![0f32; ARM_HAND_STATE_DIM];
    source.read(&mut obs).unwrap();
    let home = obs[..6].to_vec();
    let mut next = clock.now();
    for k in 0..10 {
        source.read(&mut obs).unwrap();
        actuator.send(&reference(k, &home)).unwrap();
        next += PERIOD_NS;
        clock.sleep_until(next);
    }
    emu.arm.handle().inject(XArmFault::ErrorCode(31));
    let mut first_err = None;
    for k in 10..60 {
        let r = source
            .read(&mut obs)
            .map(|_| ())
            .and_then(|()| actuator.send(&reference(k, &home)));
        if let Err(e) = r {
            first_err = Some(e);
            break;
        }
        next += PERIOD_NS;
        clock.sleep_until(next);
    }
    let err = first_err.expect("the controller error was never noticed");
    assert!(
        matches!(err, pir2_runtime::Error::SafetyStop(ref m)
            if m.contains("reports a fault: arm:")),
        "{err}"
    );
    let stats = source.robot().lock().unwrap().stats();
    assert_eq!(stats.faults, 1, "{stats}");
    assert!(stats.robot_errors <= 1, "{stats}");
    assert_eq!(stats.stops, 1, "{stats}");
    assert!(actuator.send(&reference(0, &home)).is_err());
    let _ = emu;
}

/// A stalled XHand serial line (the emulator answers 50 ms late; with the 2 × 10 ms line
/// latency that is within the driver's 100 ms reply timeout) does not hold up the
/// composite's control calls: the hand runs on its own
/// driver thread, so a tick's read and send return while the hand is still stalled, with the
/// hand's part of the state as old as its last reply (before: the hand was called on the
/// control thread and every such tick waited for the reply).
#[test]
fn a_stalled_hand_line_does_not_hold_up_a_control_tick() {
    let Rig { emu, clock, layer } = rig(SafetyConfig::xarm6_xhand());
    let (mut source, mut actuator) = split(layer);
    let mut obs = vec![0f32; ARM_HAND_STATE_DIM];
    let t_before = source.read(&mut obs).unwrap();
    let mut action = obs[..6].to_vec();
    action.extend(obs[6..18].iter());
    actuator.send(&action).unwrap();
    // Let the hand driver finish the exchange in flight, then stall its next one.
    std::thread::sleep(Duration::from_millis(30));
    let hand = emu.hand.handle();
    hand.inject(XHandFault::Stall(Duration::from_millis(50)));
    // Wait until the stalled request has reached the emulator.
    let requests = hand.requests();
    let t0 = std::time::Instant::now();
    while hand.requests() == requests {
        assert!(t0.elapsed() < Duration::from_secs(2), "no hand request");
        std::thread::sleep(Duration::from_millis(1));
    }
    let commands = hand.commands();
    let t_tick = clock.now();
    for _ in 0..3 {
        source.read(&mut obs).unwrap();
        actuator.send(&action).unwrap();
    }
    // Still inside the stall: no reply has gone out since it began.
    assert_eq!(
        hand.commands(),
        commands,
        "the control calls waited for the stalled hand"
    );
    let t_state = source.read(&mut obs).unwrap();
    assert!(
        t_state >= t_before && t_state <= t_tick,
        "the state's time is its last reply's"
    );
    // After the stall, the hand answers again and the robot is still usable.
    std::thread::sleep(Duration::from_millis(150));
    assert!(source.read(&mut obs).unwrap() > t_tick);
    actuator.send(&action).unwrap();
}
