//! Tests against real hardware. Ignored by default; run on the robot PC with
//! `PIR2_XARM=<ip> PIR2_XHAND=/dev/ttyUSB0 cargo test -p pir2-robots --test hardware -- --ignored`.
//! They never move the robot except `xarm6_holds_position_in_servo_mode`, which streams the
//! measured position back (no motion) for one second.

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use pir2_robots::{Robot, XArm6, XArm6Config};
use pir2_runtime::SystemClock;

fn arm_ip() -> IpAddr {
    std::env::var("PIR2_XARM")
        .expect("set PIR2_XARM=<arm ip>")
        .parse()
        .expect("PIR2_XARM is an IP address")
}

fn hand_path() -> PathBuf {
    PathBuf::from(std::env::var("PIR2_XHAND").expect("set PIR2_XHAND=<serial device>"))
}

#[test]
#[ignore = "needs a real xArm6 (PIR2_XARM)"]
fn xarm6_check_reads_version_state_and_report() {
    let r = pir2_robots::check(Some(SocketAddr::new(arm_ip(), 502)), None).unwrap();
    println!("{r}");
    let a = r.xarm.unwrap();
    assert!(!a.version.is_empty());
    assert!(matches!(a.report, Some(Ok(_))));
}

#[test]
#[ignore = "needs a real XHand (PIR2_XHAND)"]
fn xhand_check_reads_state() {
    let p = hand_path();
    let r = pir2_robots::check(None, Some(&p)).unwrap();
    println!("{r}");
    assert_eq!(r.xhand.unwrap().state.len(), 39);
}

#[test]
#[ignore = "needs a real xArm6 (PIR2_XARM); enables motors, holds position"]
fn xarm6_holds_position_in_servo_mode() {
    let mut arm = XArm6::connect(XArm6Config::new(arm_ip()), Arc::new(SystemClock::new())).unwrap();
    let mut s = [0f32; 12];
    arm.read_state(&mut s).unwrap();
    let hold = s[..6].to_vec();
    for _ in 0..25 {
        arm.send_targets(&hold).unwrap();
        std::thread::sleep(Duration::from_millis(40));
    }
    arm.read_state(&mut s).unwrap();
    for j in 0..6 {
        assert!((s[j] - hold[j]).abs() < 0.01);
    }
    arm.stop().unwrap();
}
