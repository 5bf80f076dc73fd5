//! `pir2 robot check` against the xArm emulator on ephemeral ports: an arm left in motion
//! is a problem (exit status 1), and a client that dies while the arm moves leaves the
//! emulated arm stopped, which the next check reports as such (before: a killed process left
//! the arm in state 1 and the next check said OK, exit status 0 either way).

use std::net::{IpAddr, Ipv4Addr};
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

use pir2_robots::emu::{XArmEmulator, XArmPorts};
use pir2_robots::xarm::proto::state;
use pir2_robots::xarm::XArmClient;
use pir2_runtime::SystemClock;

fn check(addr: std::net::SocketAddr) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["robot", "check", "--xarm", &addr.to_string()])
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[test]
fn an_arm_left_in_motion_fails_the_check_and_a_dead_client_leaves_it_stopped() {
    let e = XArmEmulator::spawn(IpAddr::V4(Ipv4Addr::LOCALHOST), XArmPorts::ephemeral()).unwrap();
    let mut c = XArmClient::connect(
        e.cmd_addr(),
        Duration::from_millis(300),
        Arc::new(SystemClock::new()),
    )
    .unwrap();
    c.identify().unwrap();
    c.motion_enable(true).unwrap();
    c.set_mode(1).unwrap();
    c.set_state(0).unwrap();
    c.servo_j(&[0.1, -0.3, -0.5, 0.0, 0.8, 0.0]).unwrap();

    let (ok, text) = check(e.cmd_addr());
    assert!(!ok, "{text}");
    assert!(
        text.contains("in motion (state 1)") && text.contains("found problems"),
        "{text}"
    );

    // The client dies (its socket closes) without stopping the arm.
    drop(c);
    let t0 = Instant::now();
    while e.handle().sim().state != state::STOP {
        assert!(t0.elapsed() < Duration::from_secs(2), "the arm still moves");
        std::thread::sleep(Duration::from_millis(5));
    }
    let (ok, text) = check(e.cmd_addr());
    assert!(ok, "{text}");
    assert!(text.contains("state 4 error 0"), "{text}");
}
