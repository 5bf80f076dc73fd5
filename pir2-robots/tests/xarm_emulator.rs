//! The xArm client and the `XArm6` robot against the loopback emulator on ephemeral ports,
//! including every injected fault: the driver either survives or stops cleanly with an error
//! that names the fault.

use std::net::{IpAddr, Ipv4Addr};
use std::sync::Arc;
use std::time::Duration;

use pir2_robots::emu::xarm::XArmEmuOptions;
use pir2_robots::emu::{XArmEmulator, XArmFault, XArmPorts};
use pir2_robots::xarm::proto::{state, ReportKind};
use pir2_robots::xarm::{ReportReader, XArmClient};
use pir2_robots::{Error, Robot, XArm6, XArm6Config};
use pir2_runtime::{Clock, SystemClock};

const LOCAL: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

fn clock() -> Arc<dyn Clock> {
    Arc::new(SystemClock::new())
}

fn emu() -> XArmEmulator {
    XArmEmulator::spawn(LOCAL, XArmPorts::ephemeral()).unwrap()
}

fn client(e: &XArmEmulator) -> XArmClient {
    XArmClient::connect(e.cmd_addr(), Duration::from_millis(300), clock()).unwrap()
}

fn arm_cfg(e: &XArmEmulator) -> XArm6Config {
    let mut c = XArm6Config::new(LOCAL);
    c.cmd_addr = e.cmd_addr();
    c.report_addr = e.real_report_addr();
    c.stream_hz = 200.0;
    c.timeout = Duration::from_millis(300);
    c
}

fn wait_until(mut f: impl FnMut() -> bool, limit: Duration) -> bool {
    let t0 = std::time::Instant::now();
    while t0.elapsed() < limit {
        if f() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    false
}

#[test]
fn answers_what_a_client_asks_at_connect() {
    let e = emu();
    let mut c = client(&e);
    assert_eq!(
        c.version().unwrap(),
        pir2_robots::emu::xarm::XARM_EMU_VERSION
    );
    assert_eq!(c.state().unwrap(), state::STOP);
    assert_eq!(c.error_codes().unwrap(), (0, 0));
    let q = c.joint_positions().unwrap();
    assert_eq!(q, pir2_robots::emu::xarm::ARM_HOME);
    assert_eq!(c.joint_torques().unwrap().len(), 7);
    // Servo-j before enabling is refused with the not-ready bit and ignored.
    let st = c.servo_j(&[0.1; 6]).unwrap();
    assert_ne!(st & pir2_robots::xarm::proto::status::NOT_READY, 0);
    assert_eq!(e.handle().sim().servoj, 0);
    // Enable, servo mode, go: now servo-j is applied.
    c.motion_enable(true).unwrap();
    c.set_mode(1).unwrap();
    c.set_state(0).unwrap();
    assert_eq!(c.state().unwrap(), state::SLEEPING);
    assert_eq!(c.servo_j(&[0.0, -0.3, -0.5, 0.0, 0.8, 0.1]).unwrap(), 0);
    assert_eq!(e.handle().sim().servoj, 1);
    assert_eq!(c.state().unwrap(), state::MOVING);
    // Report streams: real and normal, each with its size header.
    let mut rr = ReportReader::connect(
        e.real_report_addr().unwrap(),
        ReportKind::Real,
        Duration::from_millis(300),
    )
    .unwrap();
    let r = rr
        .next(&SystemClock::new(), Duration::from_secs(2))
        .unwrap();
    assert_eq!(r.mode, 1);
    assert_eq!(r.size, 135);
    let normal = e.report_addr(ReportKind::Normal).unwrap();
    let mut rn =
        ReportReader::connect(normal, ReportKind::Normal, Duration::from_millis(300)).unwrap();
    assert_eq!(
        rn.next(&SystemClock::new(), Duration::from_secs(2))
            .unwrap()
            .error,
        0
    );
    let rich = e.report_addr(ReportKind::Rich).unwrap();
    let mut rx = ReportReader::connect(rich, ReportKind::Rich, Duration::from_millis(300)).unwrap();
    let r = rx
        .next(&SystemClock::new(), Duration::from_secs(2))
        .unwrap();
    assert_eq!(r.size, 587);
    let info = r.rich.unwrap();
    assert_eq!(
        (info.arm_type, info.axis, info.simulation),
        (6, 6, Some(false))
    );
    assert_eq!((r.collision_sens, r.teach_sens), (3, 3));
}

fn emu_with(opts: XArmEmuOptions) -> XArmEmulator {
    XArmEmulator::spawn_with(
        LOCAL,
        XArmPorts::ephemeral(),
        Arc::new(std::sync::atomic::AtomicBool::new(false)),
        opts,
    )
    .unwrap()
}

#[test]
fn legacy_report_sizes_are_read_and_the_driver_runs_on_them() {
    let e = emu_with(XArmEmuOptions {
        legacy_reports: true,
        ..Default::default()
    });
    for (kind, size) in [
        (ReportKind::Real, 87),
        (ReportKind::Normal, 133),
        (ReportKind::Rich, 233),
    ] {
        let mut rr = ReportReader::connect(
            e.report_addr(kind).unwrap(),
            kind,
            Duration::from_millis(300),
        )
        .unwrap();
        let r = rr
            .next(&SystemClock::new(), Duration::from_secs(2))
            .unwrap();
        assert_eq!(r.size, size, "{kind:?}");
        assert_eq!(r.angles, pir2_robots::emu::xarm::ARM_HOME);
    }
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    let target = [0.1, -0.25, -0.45, 0.05, 0.75, 0.05];
    for _ in 0..10 {
        arm.send_targets(&target).unwrap();
        std::thread::sleep(Duration::from_millis(40));
    }
    let mut s = [0f32; 12];
    assert!(wait_until(
        || {
            arm.read_state(&mut s).unwrap();
            s[..6].iter().zip(target).all(|(a, b)| (a - b).abs() < 1e-3)
        },
        Duration::from_secs(3)
    ));
    arm.stop().unwrap();
}

#[test]
fn connect_speaks_what_the_firmware_expects() {
    // Current firmware (2.6.0): protocol id 3 after the version, two-byte SET_MODE.
    let e = emu();
    let arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    assert_eq!(arm.firmware().number, (2, 6, 0));
    let sim = e.handle().sim();
    assert_eq!(sim.last_proto, 3);
    assert_eq!(sim.set_mode_params, vec![1, 0]);
    assert_eq!(sim.clean_err, 0);
    drop(arm);
    // Firmware 1.6.9 (a real xArm6's string): protocol id 2, one-byte SET_MODE.
    let e = emu_with(XArmEmuOptions {
        version: "6,6,XI1203,XX0000,v1.6.9".into(),
        ..Default::default()
    });
    let mut cfg = arm_cfg(&e);
    cfg.report_addr = None; // and the state is polled with GET_JOINT_POS + GET_JOINT_TAU
    let mut arm = XArm6::connect(cfg, clock()).unwrap();
    let sim = e.handle().sim();
    assert_eq!(sim.last_proto, 2);
    assert_eq!(sim.set_mode_params, vec![1]);
    let mut s = [0f32; 12];
    let t0 = arm.read_state(&mut s).unwrap();
    assert!(wait_until(
        || arm.read_state(&mut s).unwrap() > t0,
        Duration::from_secs(2)
    ));
}

#[test]
fn connect_refuses_an_arm_that_is_not_6_axis_or_not_v1_firmware() {
    for (version, what) in [
        ("7,7,XS1304,AC1303,v2.5.5", "7 axes"),
        ("xArm-Controller-2018-12-20", "version"),
    ] {
        let e = emu_with(XArmEmuOptions {
            version: version.into(),
            ..Default::default()
        });
        let err = XArm6::connect(arm_cfg(&e), clock()).unwrap_err();
        assert!(err.to_string().contains(what), "{version}: {err}");
        assert!(!e.handle().sim().enabled, "{version}: never enabled");
    }
}

#[test]
fn unknown_register_is_reported_invalid() {
    let e = emu();
    let mut c = client(&e);
    let err = c.request(200, &[]).unwrap_err();
    assert!(
        matches!(err, Error::XArmInvalid { register: 200, .. }),
        "{err}"
    );
    // The connection stays usable.
    assert!(c.version().is_ok());
}

#[test]
fn late_reply_with_another_tid_is_skipped() {
    let e = emu();
    let mut c = client(&e);
    e.handle().inject(XArmFault::WrongTid);
    assert_eq!(c.state().unwrap(), state::STOP);
    assert_eq!(c.stats().stale_replies, 1);
}

#[test]
fn stalled_reply_times_out_and_closes() {
    let e = emu();
    let mut c = XArmClient::connect(e.cmd_addr(), Duration::from_millis(100), clock()).unwrap();
    e.handle()
        .inject(XArmFault::Stall(Duration::from_millis(400)));
    let err = c.state().unwrap_err();
    assert!(
        matches!(err, Error::Timeout { ref what, .. } if what.contains("register 13")),
        "{err}"
    );
    assert!(!c.is_open());
    assert!(matches!(c.state(), Err(Error::Disconnected { .. })));
}

#[test]
fn dropped_connection_is_reported() {
    let e = emu();
    let mut c = client(&e);
    e.handle().inject(XArmFault::DropConnection);
    let err = c.state().unwrap_err();
    assert!(
        matches!(err, Error::Disconnected { .. } | Error::Io { .. }),
        "{err}"
    );
    assert!(!c.is_open());
}

#[test]
fn truncated_reply_is_reported() {
    let e = emu();
    let mut c = client(&e);
    e.handle().inject(XArmFault::Truncated);
    let err = c.joint_positions().unwrap_err();
    assert!(
        matches!(
            err,
            Error::Disconnected { .. } | Error::Io { .. } | Error::Timeout { .. }
        ),
        "{err}"
    );
}

#[test]
fn garbage_reply_is_a_frame_error() {
    let e = emu();
    let mut c = client(&e);
    e.handle().inject(XArmFault::Garbage(vec![
        0xde, 0xad, 0xbe, 0xef, 0xff, 0xff, 0x00, 0x01,
    ]));
    let err = c.state().unwrap_err();
    assert!(matches!(err, Error::XArmFrame { .. }), "{err}");
    assert!(!c.is_open());
}

#[test]
fn wrong_protocol_id_is_named() {
    let e = emu();
    let mut c = client(&e);
    e.handle().inject(XArmFault::WrongProtocol);
    let err = c.state().unwrap_err();
    assert!(
        matches!(
            err,
            Error::XArmProtocolId {
                register: 13,
                expected: 2,
                got: 3
            }
        ),
        "{err}"
    );
}

#[test]
fn xarm6_streams_interpolated_targets_and_the_arm_follows() {
    let e = emu();
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    let mut s = [0f32; 12];
    arm.read_state(&mut s).unwrap();
    assert!((s[1] - -0.3).abs() < 1e-6);
    let target = [0.2, -0.2, -0.4, 0.1, 0.7, -0.1];
    for _ in 0..10 {
        arm.send_targets(&target).unwrap();
        std::thread::sleep(Duration::from_millis(40));
    }
    assert!(wait_until(
        || {
            arm.read_state(&mut s).unwrap();
            s[..6].iter().zip(target).all(|(a, b)| (a - b).abs() < 1e-3)
        },
        Duration::from_secs(3)
    ));
    // Several servo-j frames per policy target.
    assert!(arm.streamed() > 10, "streamed {}", arm.streamed());
    arm.stop().unwrap();
    assert_eq!(e.handle().sim().state, state::STOP);
    assert!(matches!(
        arm.send_targets(&target),
        Err(Error::Stopped { .. })
    ));
    // Stop is idempotent.
    arm.stop().unwrap();
}

#[test]
fn xarm6_without_report_stream_polls_state_on_the_command_port() {
    let e = emu();
    let mut cfg = arm_cfg(&e);
    cfg.report_addr = None;
    let mut arm = XArm6::connect(cfg, clock()).unwrap();
    let mut s = [0f32; 12];
    let t0 = arm.read_state(&mut s).unwrap();
    assert!(wait_until(
        || arm.read_state(&mut s).unwrap() > t0,
        Duration::from_secs(2)
    ));
}

#[test]
fn controller_error_ends_streaming_and_fails_the_next_call() {
    let e = emu();
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    e.handle().inject(XArmFault::ErrorCode(31));
    let mut s = [0f32; 12];
    assert!(wait_until(
        || arm.read_state(&mut s).is_err(),
        Duration::from_secs(2)
    ));
    let err = arm.send_targets(&[0.0; 6]).unwrap_err();
    assert!(
        matches!(err, Error::Stopped { ref reason, .. } if reason.contains("error code 31")),
        "{err}"
    );
    // Stop still reaches the controller.
    arm.stop().unwrap();
}

#[test]
fn connect_reports_a_latched_error_and_leaves_it_latched() {
    // A collision (31) or emergency stop (1) from before the connect: reported, not cleared,
    // motors never enabled.
    for code in [31u8, 1] {
        let e = emu();
        e.handle().inject(XArmFault::ErrorCode(code));
        let err = XArm6::connect(arm_cfg(&e), clock()).unwrap_err();
        assert!(
            matches!(err, Error::Stopped { ref reason, .. }
                if reason.contains(&format!("error code {code}")) && reason.contains("--clear-errors")),
            "{err}"
        );
        let sim = e.handle().sim();
        assert_eq!(sim.error, code);
        assert_eq!(sim.clean_err, 0);
        assert!(!sim.enabled);
    }
}

#[test]
fn connect_clears_a_latched_error_only_when_asked() {
    let e = emu();
    e.handle().inject(XArmFault::ErrorCode(31));
    e.handle().set_warning(11);
    let mut cfg = arm_cfg(&e);
    cfg.clear_errors = true;
    let mut arm = XArm6::connect(cfg, clock()).unwrap();
    assert_eq!(arm.cleared_at_connect(), Some((31, 11)));
    let sim = e.handle().sim();
    assert_eq!((sim.error, sim.warning, sim.clean_err), (0, 0, 1));
    assert!(sim.enabled);
    arm.stop().unwrap();
    // A warning alone does not stop a connect and is left alone without clear_errors.
    let e = emu();
    e.handle().set_warning(11);
    let arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    assert_eq!(arm.cleared_at_connect(), None);
    assert_eq!(e.handle().sim().warning, 11);
}

#[test]
fn command_port_drop_while_streaming_is_reported() {
    let e = emu();
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    e.handle().inject(XArmFault::DropConnection);
    let mut s = [0f32; 12];
    assert!(wait_until(
        || arm.read_state(&mut s).is_err(),
        Duration::from_secs(2)
    ));
    // The stop reopens the command port and gets SET_STATE 4 confirmed (before: it gave up
    // because the port was closed and left the outcome to chance).
    arm.stop().unwrap();
    let sim = e.handle().sim();
    assert_eq!(sim.state, state::STOP);
    // The emulator had stopped the arm already: the connection that moved it closed.
    assert_eq!(sim.client_loss_stops, 1);
    assert!(matches!(
        arm.send_targets(&[0.0; 6]),
        Err(Error::Stopped { .. })
    ));
}

/// A stop whose first SET_STATE 4 times out is retried on a fresh connection until the
/// controller confirms state 4 (before: the first failure was final and only counted).
#[test]
fn a_stop_that_times_out_is_retried_until_confirmed() {
    let e = emu();
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    arm.send_targets(&[0.1, -0.3, -0.5, 0.0, 0.8, 0.0]).unwrap();
    assert!(wait_until(
        || e.handle().sim().state == state::MOVING,
        Duration::from_secs(2)
    ));
    // Longer than the 300 ms request timeout; the streaming thread is halted before the stop
    // request, so the stall hits SET_STATE 4.
    e.handle()
        .inject(XArmFault::Stall(Duration::from_millis(600)));
    arm.stop().unwrap();
    assert_eq!(e.handle().sim().state, state::STOP);
}

/// A controller that never confirms the stop: `stop` keeps trying for about a second, then
/// fails naming the attempts, so the caller knows the arm may still hold servo mode.
#[test]
fn a_stop_the_controller_never_confirms_fails_naming_the_attempts() {
    let e = emu();
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    for _ in 0..400 {
        e.handle().inject(XArmFault::DropConnection);
    }
    let t0 = std::time::Instant::now();
    let err = arm.stop().unwrap_err();
    let took = t0.elapsed();
    assert!(
        matches!(err, Error::Stopped { ref reason, .. }
            if reason.contains("SET_STATE 4 was not confirmed") && reason.contains("attempts")),
        "{err}"
    );
    assert!(
        took >= Duration::from_millis(900) && took < Duration::from_secs(5),
        "{took:?}"
    );
    assert!(matches!(
        arm.send_targets(&[0.0; 6]),
        Err(Error::Stopped { .. })
    ));
}

/// A client that dies while the arm moves (its sockets close) leaves the emulated arm stopped;
/// while a client streams, `robot check` reports the arm in motion as a problem (before: a
/// killed process left the arm in state 1 and the next check said OK).
#[test]
fn a_client_that_dies_while_moving_leaves_the_arm_stopped() {
    let e = emu();
    let mut c = client(&e);
    c.identify().unwrap();
    c.motion_enable(true).unwrap();
    c.set_mode(1).unwrap();
    c.set_state(0).unwrap();
    c.servo_j(&[0.1, -0.3, -0.5, 0.0, 0.8, 0.0]).unwrap();
    assert_eq!(e.handle().sim().state, state::MOVING);
    let report = pir2_robots::check::check(Some(e.cmd_addr()), None).unwrap();
    assert!(!report.healthy(), "{report}");
    assert!(
        report.to_string().contains("in motion (state 1)"),
        "{report}"
    );
    drop(c);
    assert!(wait_until(
        || e.handle().sim().state == state::STOP,
        Duration::from_secs(2)
    ));
    assert_eq!(e.handle().sim().client_loss_stops, 1);
    let report = pir2_robots::check::check(Some(e.cmd_addr()), None).unwrap();
    assert!(report.healthy(), "{report}");
}

#[test]
fn report_stream_faults_are_reported() {
    for fault in [XArmFault::ReportDisconnect, XArmFault::ReportGarbage] {
        let e = emu();
        let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
        e.handle().inject(fault.clone());
        let mut s = [0f32; 12];
        assert!(
            wait_until(|| arm.read_state(&mut s).is_err(), Duration::from_secs(2)),
            "{fault:?}"
        );
        let err = arm.read_state(&mut s).unwrap_err();
        assert!(
            matches!(err, Error::Stopped { ref reason, .. } if reason.contains("report stream")),
            "{err}"
        );
    }
}

#[test]
fn report_stall_leaves_the_state_timestamp_behind() {
    let e = emu();
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    let c = SystemClock::new();
    let mut s = [0f32; 12];
    e.handle()
        .inject(XArmFault::ReportStall(Duration::from_millis(300)));
    // During the stall the newest state grows old (the safety layer turns that into a stop).
    let mut max_age = 0;
    let t_end = c.now() + 250_000_000;
    while c.now() < t_end {
        let t = arm.read_state(&mut s).unwrap();
        max_age = max_age.max(c.now().saturating_sub(t));
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(max_age > 100_000_000, "max age {max_age} ns");
}

#[test]
fn run_xarm_emulator_returns_when_stopped() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let stop = Arc::new(AtomicBool::new(false));
    let s2 = stop.clone();
    let j = std::thread::spawn(move || {
        pir2_robots::emu::run_xarm_emulator(LOCAL, XArmPorts::ephemeral(), s2)
    });
    std::thread::sleep(Duration::from_millis(50));
    stop.store(true, Ordering::SeqCst);
    j.join().unwrap().unwrap();
}

#[test]
fn check_reports_an_emulated_arm_without_moving_it() {
    let e = emu();
    let mut opts = pir2_robots::CheckOptions::new(Some(e.cmd_addr()), None);
    assert_eq!(
        opts.xarm_report, None,
        "no report port guessed for a non-standard command port"
    );
    opts.xarm_report = e.real_report_addr();
    let r = pir2_robots::check_with(&opts).unwrap();
    let a = r.xarm.as_ref().unwrap();
    assert_eq!(a.version, pir2_robots::emu::xarm::XARM_EMU_VERSION);
    assert_eq!(a.state, state::STOP);
    assert!(matches!(a.report, Some(Ok(_))));
    assert!(r.healthy());
    assert!(r.to_string().ends_with("OK"));
    assert!(!e.handle().sim().enabled, "check never enables the motors");
    // A controller error shows up as unhealthy, and stays latched.
    e.handle().inject(XArmFault::ErrorCode(12));
    let r = pir2_robots::check_with(&opts).unwrap();
    assert_eq!(r.xarm.as_ref().unwrap().error, 12);
    assert!(!r.healthy());
    assert_eq!(e.handle().sim().error, 12);
    // Asked to clear it: cleared, reported, healthy.
    opts.clear_errors = true;
    let r = pir2_robots::check_with(&opts).unwrap();
    assert_eq!(r.xarm.as_ref().unwrap().error, 12);
    assert_eq!(r.xarm.as_ref().unwrap().after_clear, Some((0, 0)));
    assert!(r.healthy(), "{r}");
    assert!(r.to_string().contains("cleared"));
    assert_eq!(e.handle().sim().error, 0);
    // Nobody listening: an error naming the address.
    let addr = e.cmd_addr();
    e.shutdown();
    std::thread::sleep(Duration::from_millis(50));
    let err = pir2_robots::check(Some(addr), None).unwrap_err();
    assert!(matches!(err, Error::Connect { .. }), "{err}");
}

#[test]
fn controller_side_stop_is_detected_from_the_report_stream() {
    let e = emu();
    let mut arm = XArm6::connect(arm_cfg(&e), clock()).unwrap();
    let mut s = [0f32; 12];
    arm.read_state(&mut s).unwrap();
    e.handle().inject(XArmFault::EmergencyStop);
    assert!(wait_until(
        || arm.read_state(&mut s).is_err(),
        Duration::from_secs(2)
    ));
    let err = arm.send_targets(&[0.0; 6]).unwrap_err();
    assert!(
        matches!(err, Error::Stopped { ref reason, .. } if reason.contains("state 4")),
        "{err}"
    );
}

#[test]
fn controller_side_stop_is_detected_from_servoj_replies_without_reports() {
    let e = emu();
    let mut cfg = arm_cfg(&e);
    cfg.report_addr = None;
    let mut arm = XArm6::connect(cfg, clock()).unwrap();
    e.handle().inject(XArmFault::EmergencyStop);
    let mut s = [0f32; 12];
    assert!(wait_until(
        || arm.read_state(&mut s).is_err(),
        Duration::from_secs(2)
    ));
    let err = arm.read_state(&mut s).unwrap_err();
    assert!(
        matches!(err, Error::Stopped { ref reason, .. } if reason.contains("not ready")),
        "{err}"
    );
}
