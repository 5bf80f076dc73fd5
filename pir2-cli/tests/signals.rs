//! SIGINT / SIGTERM handling of the `pir2` binary (`pir2_cli::signals`): SIGTERM is a clean
//! stop, not a kill; a second signal runs the registered emergency stop and exits with 130.

use std::io::{BufRead, BufReader};
use std::os::unix::process::ExitStatusExt;
use std::process::{Command, Stdio};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// SIGTERM to a running `pir2 robot emulate xhand --pty` ends it through its stop flag (exit
/// status 0, its pseudo-terminal released). Before: SIGTERM had the default action and killed
/// the process (only SIGINT was handled).
#[test]
fn sigterm_stops_a_command_cleanly() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["robot", "emulate", "xhand", "--pty"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    assert!(line.contains("XHand emulator on"), "{line:?}");
    // SAFETY: plain kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > Duration::from_secs(10) {
            let _ = child.kill();
            panic!("still running 10 s after SIGTERM");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert_eq!(status.signal(), None, "killed by a signal: {err}");
    assert!(status.success(), "{status:?}: {err}");
    assert!(err.contains("signal received: stopping"), "{err}");
    // No robot registered an emergency stop here: the message promises no robot stop.
    assert!(err.contains("a second signal exits at once"), "{err}");
}

const CHILD: &str = "PIR2_SIGNALS_TEST_CHILD";

/// The first signal only sets the stop flag; the second runs the registered emergency stop
/// and exits with status 130. Runs itself as a child process (signals are process-wide).
#[test]
fn a_second_signal_runs_the_emergency_stop_and_exits() {
    if std::env::var_os(CHILD).is_some() {
        let stop = pir2_cli::signals::stop_flag();
        assert!(Arc::ptr_eq(&stop, &pir2_cli::signals::stop_flag()));
        pir2_cli::signals::on_second_signal(|| println!("emergency stop ran"));
        // SAFETY: raise(3) on this process; the handler is installed.
        unsafe { libc::raise(libc::SIGTERM) };
        let t0 = Instant::now();
        while !stop.load(Ordering::SeqCst) {
            assert!(t0.elapsed() < Duration::from_secs(5), "flag not set");
            std::thread::sleep(Duration::from_millis(1));
        }
        // The first signal must not exit.
        std::thread::sleep(Duration::from_millis(100));
        println!("first signal: flag set, still running");
        // SAFETY: as above.
        unsafe { libc::raise(libc::SIGINT) };
        std::thread::sleep(Duration::from_secs(10));
        println!("not exited");
        return;
    }
    let out = Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "a_second_signal_runs_the_emergency_stop_and_exits",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD, "1")
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{text}");
    assert!(
        text.contains("first signal: flag set, still running"),
        "{text}"
    );
    assert!(text.contains("emergency stop ran"), "{text}");
    assert!(
        text.contains("a second signal stops the robot and exits at once"),
        "{text}"
    );
    assert!(!text.contains("not exited"), "{text}");
}
