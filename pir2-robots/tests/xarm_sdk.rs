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
            e.report_addr(ReportKind::Normal),
            e.report_addr(ReportKind::Rich),
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
    // Output goes to files, not pipes: the SDK logs a lot, and a full pipe would block it.
    let dir = std::env::temp_dir();
    let tag = format!(
        "pir2-xarm-sdk-{}-{}",
        std::process::id(),
        e.cmd_addr().port()
    );
    let out_path = dir.join(format!("{tag}.out"));
    let err_path = dir.join(format!("{tag}.err"));
    let mut child = Command::new(python)
        .arg(script)
        .args(["--cmd-port", &e.cmd_addr().port().to_string()])
        .args(["--normal-port", &port(e.report_addr(ReportKind::Normal))])
        .args(["--rich-port", &port(e.report_addr(ReportKind::Rich))])
        .args(["--real-port", &port(e.real_report_addr())])
        .stdout(std::fs::File::create(&out_path).unwrap())
        .stderr(std::fs::File::create(&err_path).unwrap())
        .spawn()
        .expect("starting the SDK session script");
    // The script aborts itself after 45 s; this is the backstop.
    let t0 = Instant::now();
    let mut killed = false;
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > Duration::from_secs(90) {
            let _ = child.kill();
            killed = true;
            break child.wait().unwrap();
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let stdout = std::fs::read_to_string(&out_path).unwrap_or_default();
    let stderr = std::fs::read_to_string(&err_path).unwrap_or_default();
    let _ = std::fs::remove_file(&out_path);
    let _ = std::fs::remove_file(&err_path);
    println!("{stdout}");
    assert!(
        status.success() && !killed,
        "the SDK session failed ({status}{}):\n{stdout}\n--- stderr (tail) ---\n{}",
        if killed { ", killed after 90 s" } else { "" },
        tail(&stderr, 60)
    );
}

fn tail(s: &str, n: usize) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}
