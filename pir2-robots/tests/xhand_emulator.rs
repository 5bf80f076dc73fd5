//! The XHand driver against the emulator over an in-memory serial line and over a PTY,
//! including every injected fault: the driver reports an error naming the fault and the next
//! request works again (or, for a cut line, every request fails cleanly).

use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use pir2_robots::emu::{duplex, DuplexPort, XHandEmulator, XHandFault};
use pir2_robots::xhand::consts;
use pir2_robots::{Error, Robot, XHand, XHandConfig};
use pir2_runtime::{Clock, SystemClock};

fn clock() -> Arc<dyn Clock> {
    Arc::new(SystemClock::new())
}

fn setup() -> (XHand<DuplexPort>, XHandEmulator) {
    let (host, dev) = duplex(Duration::from_millis(10));
    let emu = XHandEmulator::spawn(
        dev,
        consts::DEFAULT_HAND_ID,
        Arc::new(AtomicBool::new(false)),
    )
    .unwrap();
    let cfg = XHandConfig {
        timeout: Duration::from_millis(150),
        ..Default::default()
    };
    (XHand::new(host, cfg, clock()), emu)
}

#[test]
fn version_state_and_position_commands() {
    let (mut hand, emu) = setup();
    assert_eq!(
        hand.version().unwrap(),
        pir2_robots::emu::xhand::XHAND_EMU_VERSION
    );
    let mut s = [0f32; 39];
    hand.read_state(&mut s).unwrap();
    assert!(s[..12].iter().all(|&q| q == 0.0));
    let target: Vec<f32> = (0..12).map(|i| 0.1 * i as f32).collect();
    let t0 = std::time::Instant::now();
    while t0.elapsed() < Duration::from_millis(400) {
        hand.send_targets(&target).unwrap();
        std::thread::sleep(Duration::from_millis(10));
    }
    hand.read_state(&mut s).unwrap();
    for i in 0..12 {
        assert!(
            (s[i] - target[i]).abs() < 0.01,
            "joint {i}: {} vs {}",
            s[i],
            target[i]
        );
    }
    // The paper's gains and torque limit went out in position mode.
    let cmds = emu.handle().last_commands();
    assert!(cmds
        .iter()
        .all(|c| c.kp == 100 && c.tor_max == 300 && c.mode == consts::MODE_POSITION));
    assert_eq!(cmds[11].id, 11);
    // Fingertip forces follow flexion in the emulator; torques are in the state.
    assert!(s[24..39].iter().any(|&f| f > 0.0));
}

#[test]
fn read_state_uses_the_cache_while_fresh() {
    let (mut hand, emu) = setup();
    let mut s = [0f32; 39];
    hand.send_targets(&[0.0; 12]).unwrap();
    let before = emu.handle().requests();
    // refresh_after is 5 ms by default: an immediate read is served from the cache.
    hand.read_state(&mut s).unwrap();
    assert_eq!(emu.handle().requests(), before);
    std::thread::sleep(Duration::from_millis(10));
    hand.read_state(&mut s).unwrap();
    assert_eq!(emu.handle().requests(), before + 1);
}

fn recovers(hand: &mut XHand<DuplexPort>) {
    hand.send_targets(&[0.2; 12])
        .expect("the request after a fault must work");
}

#[test]
fn no_reply_times_out_then_recovers() {
    let (mut hand, emu) = setup();
    emu.handle().inject(XHandFault::NoReply);
    let e = hand.send_targets(&[0.2; 12]).unwrap_err();
    assert!(
        matches!(e, Error::Timeout { ref what, .. } if what.contains("0x02")),
        "{e}"
    );
    recovers(&mut hand);
}

#[test]
fn stall_longer_than_the_timeout_times_out_then_recovers() {
    let (mut hand, emu) = setup();
    emu.handle()
        .inject(XHandFault::Stall(Duration::from_millis(300)));
    assert!(matches!(
        hand.send_targets(&[0.2; 12]),
        Err(Error::Timeout { .. })
    ));
    // The late reply arrives while the next request waits; it is dropped by the
    // "clear before send" rule or answers with the right command; either way no panic.
    std::thread::sleep(Duration::from_millis(250));
    recovers(&mut hand);
}

#[test]
fn truncated_reply_times_out_then_recovers() {
    let (mut hand, emu) = setup();
    emu.handle().inject(XHandFault::Truncated);
    assert!(matches!(
        hand.send_targets(&[0.2; 12]),
        Err(Error::Timeout { .. })
    ));
    recovers(&mut hand);
}

#[test]
fn garbage_reply_times_out_then_recovers() {
    let (mut hand, emu) = setup();
    emu.handle().inject(XHandFault::Garbage(vec![
        0x55, 0x00, 0xaa, 0x13, 0x37, 0x55,
    ]));
    assert!(matches!(
        hand.send_targets(&[0.2; 12]),
        Err(Error::Timeout { .. })
    ));
    recovers(&mut hand);
    // The garbage had no `55 AA` pair: all but a trailing 0x55 was skipped and counted.
    assert!(hand.stats().dropped_bytes >= 5, "{:?}", hand.stats());
}

#[test]
fn wrong_crc_is_named_then_recovers() {
    let (mut hand, emu) = setup();
    emu.handle().inject(XHandFault::BadCrc);
    let e = hand.send_targets(&[0.2; 12]).unwrap_err();
    assert!(matches!(e, Error::XHandCrc { command: 0x02, .. }), "{e}");
    recovers(&mut hand);
}

#[test]
fn reply_from_another_hand_is_ignored_and_times_out() {
    let (mut hand, emu) = setup();
    emu.handle().inject(XHandFault::WrongId);
    assert!(matches!(
        hand.send_targets(&[0.2; 12]),
        Err(Error::Timeout { .. })
    ));
    assert_eq!(hand.stats().foreign_frames, 1);
    recovers(&mut hand);
}

#[test]
fn finger_error_words_are_counted() {
    let (mut hand, emu) = setup();
    emu.handle().inject(XHandFault::FingerError(7));
    hand.send_targets(&[0.2; 12]).unwrap();
    assert_eq!(hand.last_state().unwrap().0.fingers[0].errors[0], 7);
    assert_eq!(hand.stats().finger_errors, 1);
}

#[test]
fn cut_line_fails_every_request_cleanly() {
    let (mut hand, emu) = setup();
    emu.handle().inject(XHandFault::Disconnect);
    let e = hand.send_targets(&[0.2; 12]).unwrap_err();
    assert!(
        matches!(e, Error::Disconnected { .. } | Error::Timeout { .. }),
        "{e}"
    );
    emu.shutdown();
    let e = hand.send_targets(&[0.2; 12]).unwrap_err();
    assert!(matches!(e, Error::Disconnected { .. }), "{e}");
}

#[test]
fn stop_holds_the_measured_position_and_refuses_targets() {
    let (mut hand, emu) = setup();
    for _ in 0..20 {
        hand.send_targets(&[0.5; 12]).unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    let measured = hand.last_state().unwrap().0.fingers[3].position;
    hand.stop().unwrap();
    let cmds = emu.handle().last_commands();
    assert_eq!(cmds[3].position, measured);
    assert_eq!(cmds[3].mode, consts::MODE_POSITION);
    assert!(matches!(
        hand.send_targets(&[0.5; 12]),
        Err(Error::Stopped { .. })
    ));
    hand.stop().unwrap();
}

#[test]
fn release_on_stop_makes_the_joints_powerless() {
    let (host, dev) = duplex(Duration::from_millis(10));
    let emu = XHandEmulator::spawn(dev, 0, Arc::new(AtomicBool::new(false))).unwrap();
    let cfg = XHandConfig {
        release_on_stop: true,
        timeout: Duration::from_millis(150),
        ..Default::default()
    };
    let mut hand = XHand::new(host, cfg, clock());
    hand.send_targets(&[0.1; 12]).unwrap();
    hand.stop().unwrap();
    assert!(emu
        .handle()
        .last_commands()
        .iter()
        .all(|c| c.mode == consts::MODE_POWERLESS));
}

#[cfg(unix)]
#[test]
fn driver_talks_to_the_emulator_through_a_pty() {
    use pir2_robots::xhand::tty::TtyPort;
    let stop = Arc::new(AtomicBool::new(false));
    let (emu, path) = pir2_robots::emu::xhand::spawn_pty(0, stop.clone()).unwrap();
    let port = TtyPort::open(&path, consts::BAUD).unwrap();
    let cfg = XHandConfig {
        timeout: Duration::from_millis(500),
        ..Default::default()
    };
    let mut hand = XHand::new(port, cfg, clock());
    assert_eq!(
        hand.version().unwrap(),
        pir2_robots::emu::xhand::XHAND_EMU_VERSION
    );
    // A 2208-byte state crosses the line intact.
    hand.send_targets(&[0.3; 12]).unwrap();
    let mut s = [0f32; 39];
    hand.read_state(&mut s).unwrap();
    assert_eq!(emu.handle().targets(), [0.3; 12]);
    // Faults over the PTY too.
    emu.handle().inject(XHandFault::BadCrc);
    assert!(matches!(
        hand.send_targets(&[0.3; 12]),
        Err(Error::XHandCrc { .. })
    ));
    hand.send_targets(&[0.3; 12]).unwrap();
    emu.shutdown();
}

#[cfg(unix)]
#[test]
fn run_xhand_emulator_pty_serves_until_stopped() {
    use std::sync::atomic::Ordering;
    let stop = Arc::new(AtomicBool::new(false));
    let path = pir2_robots::emu::run_xhand_emulator_pty(stop.clone()).unwrap();
    let report = pir2_robots::check(None, Some(&path)).unwrap();
    let h = report.xhand.as_ref().unwrap();
    assert_eq!(
        h.version.as_deref(),
        Ok(pir2_robots::emu::xhand::XHAND_EMU_VERSION)
    );
    assert_eq!(h.state.len(), 39);
    assert!(report.healthy());
    assert!(report.to_string().contains("XHand at"));
    stop.store(true, Ordering::SeqCst);
}

/// A finger error word stops the hand through the safety layer (before: it was counted and
/// the hand kept being driven).
#[test]
fn finger_error_word_stops_the_hand_through_the_safety_layer() {
    use pir2_robots::{SafetyConfig, SafetyLayer};
    let (hand, emu) = setup();
    let mut cfg = SafetyConfig::uniform(12, -0.5, 2.0, 5.0);
    cfg.state_timeout = Duration::from_secs(1);
    let mut l = SafetyLayer::new(hand, cfg, clock()).unwrap();
    let mut s = [0f32; 39];
    l.read_state(&mut s).unwrap();
    l.send_targets(&[0.1; 12]).unwrap();
    emu.handle().inject(XHandFault::FingerError(0x0004));
    let e = l.send_targets(&[0.1; 12]).unwrap_err();
    assert!(
        matches!(e, Error::SafetyStop(ref m) if m.contains("joint 0 error words 0004")),
        "{e}"
    );
    assert_eq!(l.stats().faults, 1);
    assert!(matches!(l.read_state(&mut s), Err(Error::SafetyStop(_))));
}

/// `stop()` never commands a non-finite position: a joint whose measured position is NaN
/// holds its last commanded target (before: the NaN was sent as the hold position).
#[test]
fn stop_is_finite_when_the_measured_position_is_nan() {
    let (mut hand, emu) = setup();
    let mut s = [0f32; 39];
    hand.read_state(&mut s).unwrap();
    let target: Vec<f32> = (0..12).map(|i| 0.05 * i as f32 + 0.3).collect();
    hand.send_targets(&target).unwrap();
    emu.handle().inject(XHandFault::NonFinitePosition(true));
    hand.send_targets(&target).unwrap();
    let (state, _) = hand.last_state().unwrap();
    assert!(state.fingers[0].position.is_nan());
    hand.stop().unwrap();
    let cmds = emu.handle().last_commands();
    assert!(
        cmds.iter().all(|c| c.position.is_finite()),
        "{:?}",
        cmds.iter().map(|c| c.position).collect::<Vec<_>>()
    );
    assert_eq!(cmds[0].position, target[0]);
    assert!(cmds.iter().all(|c| c.mode == consts::MODE_POSITION));
}
