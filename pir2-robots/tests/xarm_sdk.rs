//! UFACTORY's own Python SDK (`xarm-python-sdk==1.18.4`) as a client of the xArm emulator:
//! `tests/sdk/xarm_sdk_session.py` connects, enables, switches to servo mode, streams 3 s
//! of servo-j at 100 Hz and checks tracking, hold and every return code.
//!
//! Needs `PIR2_PYTHON` (a Python with the SDK installed, from `scripts/setup-native.sh`);
//! ignored by default, run by `.ci/native-tests` with `--ignored`.

use std::net::{IpAddr, Ipv4Addr};
use std::process::Command;
use std::time::{Duration, Instant};

use pir2_robots::emu::{XArmEmulator, XArmPorts};
use pir2_robots::xarm::proto::ReportKind;

const LOCAL: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

/// An emulator on ephemeral ports where no report port is the command port + 1 (the SDK
/// treats that port as a second command port).
fn emulator() -> XArmEmulator {
    loop {
        let e = XArmEmulator::spawn(LOCAL, XArmPorts::ephemeral()).unwrap();
        let next = e.cmd_addr().port().wrapping_add(1);
        let clash = [
            e.report_addr(ReportKind::Normal, 133),
            e.report_addr(ReportKind::Normal, 233),
            e.real_report_addr(),
        ]
        .iter()
        .any(|a| a.map(|a| a.port()) == Some(next));
        if !clash {
            return e;
        }
    }
}

#[test]
#[ignore = "needs PIR2_PYTHON with xarm-python-sdk==1.18.4 (scripts/setup-native.sh)"]
fn official_sdk_runs_a_servo_session_against_the_emulator() {
    let python = std::env::var("PIR2_PYTHON")
        .expect("PIR2_PYTHON must name a Python with xarm-python-sdk==1.18.4");
    let e = emulator();
    let port = |a: Option<std::net::SocketAddr>| a.expect("report port").port().to_string();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/sdk/xarm_sdk_session.py");
    let mut child = Command::new(python)
        .arg(script)
        .args(["--cmd-port", &e.cmd_addr().port().to_string()])
        .args(["--normal-port", &port(e.report_addr(ReportKind::Normal, 133))])
        .args(["--rich-port", &port(e.report_addr(ReportKind::Normal, 233))])
        .args(["--real-port", &port(e.real_report_addr())])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("starting the SDK session script");
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            panic!("the SDK session did not finish within 60 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let out = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    println!("{stdout}");
    assert!(
        status.success(),
        "the SDK session failed ({status}):\n{stdout}\n--- stderr (tail) ---\n{}",
        tail(&stderr, 40)
    );
}

fn tail(s: &str, n: usize) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}
