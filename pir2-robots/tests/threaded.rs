//! `Threaded`: a device call that stalls never holds up the control side, and every way the
//! driver thread can end stops the device.

use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use pir2_robots::robot::StateLayout;
use pir2_robots::threaded::{Threaded, ThreadedConfig};
use pir2_robots::{Error, Result, Robot};
use pir2_runtime::Nanos;

#[derive(Default)]
struct Log {
    sent: Vec<f32>,
    reads: u64,
    stops: u64,
}

/// A 1-joint device. `gate` is locked around every device call (the test holds it to stall
/// the device); it fails with a timeout on read `fail_at` and panics on read `panic_at`.
struct Mock {
    log: Arc<Mutex<Log>>,
    gate: Arc<Mutex<()>>,
    fail_at: Option<u64>,
    panic_at: Option<u64>,
}

impl Robot for Mock {
    fn name(&self) -> &'static str {
        "Mock"
    }
    fn state_dim(&self) -> usize {
        2
    }
    fn action_dim(&self) -> usize {
        1
    }
    fn layout(&self) -> StateLayout {
        StateLayout {
            positions: 0..1,
            torques: None,
        }
    }
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
        let _g = self.gate.lock().unwrap();
        let mut l = self.log.lock().unwrap();
        l.reads += 1;
        if Some(l.reads) == self.fail_at {
            return Err(Error::Timeout {
                channel: "mock line",
                what: "a reply".into(),
                waited_ms: 100,
            });
        }
        if Some(l.reads) == self.panic_at {
            drop(l);
            panic!("mock driver bug");
        }
        out[0] = l.sent.last().copied().unwrap_or(0.0);
        out[1] = l.reads as f32;
        // The measurement time: one "ms" per read.
        Ok(l.reads * 1_000_000)
    }
    fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
        let _g = self.gate.lock().unwrap();
        self.log.lock().unwrap().sent.push(targets[0]);
        Ok(())
    }
    fn stop(&mut self) -> Result<()> {
        self.log.lock().unwrap().stops += 1;
        Ok(())
    }
}

fn mock(fail_at: Option<u64>, panic_at: Option<u64>) -> (Mock, Arc<Mutex<Log>>, Arc<Mutex<()>>) {
    let log = Arc::new(Mutex::new(Log::default()));
    let gate = Arc::new(Mutex::new(()));
    let m = Mock {
        log: log.clone(),
        gate: gate.clone(),
        fail_at,
        panic_at,
    };
    (m, log, gate)
}

fn cfg() -> ThreadedConfig {
    ThreadedConfig {
        period: Duration::from_millis(2),
        first_state_timeout: Duration::from_secs(5),
        stop_wait: Duration::from_millis(300),
    }
}

/// Run `f` on a thread; `None` if it has not returned within 5 s (it blocked).
fn bounded<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Option<T> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(5)).ok()
}

fn wait_until(what: &str, mut ok: impl FnMut() -> bool) {
    let t0 = std::time::Instant::now();
    while !ok() {
        assert!(
            t0.elapsed() < Duration::from_secs(5),
            "timed out waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// While the device is stuck inside a call (a stalled serial line), the control side's
/// reads and sends return at once: reads give the last state with its old timestamp, sends
/// replace the waiting targets. When the stall ends, the newest targets go out and the
/// superseded ones are counted (before: the XHand was called on the control thread, so a
/// stall was a late tick for the whole robot).
#[test]
fn a_stalled_device_call_does_not_hold_up_the_control_side() {
    let (m, log, gate) = mock(None, None);
    let mut r = Threaded::spawn(m, cfg()).unwrap();
    let mut s = [0f32; 2];
    r.read_state(&mut s).unwrap();
    r.send_targets(&[1.0]).unwrap();
    wait_until("the first target", || log.lock().unwrap().sent == [1.0]);

    let stall = gate.lock().unwrap();
    // Let the driver enter its next device call and block on the gate.
    std::thread::sleep(Duration::from_millis(20));
    let reads_before = log.lock().unwrap().reads;
    let out = bounded(move || {
        let mut s = [0f32; 2];
        let mut stamps = Vec::new();
        for k in 2..=21 {
            r.send_targets(&[k as f32]).unwrap();
            stamps.push(r.read_state(&mut s).unwrap());
        }
        (r, stamps)
    });
    let (mut r, stamps) = out.expect("the control side blocked on a stalled device call");
    assert!(
        stamps.windows(2).all(|w| w[0] == w[1]),
        "the state's time must not move during the stall: {stamps:?}"
    );
    assert_eq!(
        log.lock().unwrap().reads,
        reads_before,
        "the device was stalled"
    );
    drop(stall);
    wait_until("the newest target", || {
        log.lock().unwrap().sent.last() == Some(&21.0)
    });
    let sent = log.lock().unwrap().sent.clone();
    assert!(
        !sent.contains(&10.0),
        "targets superseded during the stall are not replayed: {sent:?}"
    );
    let st = r.stats();
    assert!(st.superseded >= 18, "{st:?}");
    let t_after = {
        wait_until("a fresh state", || {
            let mut s = [0f32; 2];
            r.read_state(&mut s).unwrap() > stamps[0]
        });
        r.read_state(&mut s).unwrap()
    };
    assert!(t_after > stamps[0]);
    r.stop().unwrap();
    assert_eq!(log.lock().unwrap().stops, 1);
}

/// A device error ends the driver thread, which sends the stop command; the next call on
/// the control side returns that error, and every call after says the device is stopped.
#[test]
fn a_device_error_stops_the_device_and_is_returned_once() {
    let (m, log, _gate) = mock(Some(5), None);
    let mut r = Threaded::spawn(m, cfg()).unwrap();
    let mut s = [0f32; 2];
    r.read_state(&mut s).unwrap();
    wait_until("the stop after the error", || {
        log.lock().unwrap().stops == 1
    });
    let e = r.send_targets(&[1.0]).unwrap_err();
    assert!(matches!(e, Error::Timeout { .. }), "{e}");
    let e = r.read_state(&mut s).unwrap_err();
    assert!(
        e.to_string().contains("driver thread ended on an error")
            && e.to_string().contains("timed out"),
        "{e}"
    );
    r.stop().unwrap();
    assert_eq!(
        log.lock().unwrap().stops,
        1,
        "the stop command goes out once"
    );
}

/// A panic inside the device's driver is caught on the driver thread: the device is
/// stopped and the control side gets one error naming the thread and the panic.
#[test]
fn a_panic_in_the_device_driver_stops_the_device_and_names_the_thread() {
    let (m, log, _gate) = mock(None, Some(4));
    let mut r = Threaded::spawn(m, cfg()).unwrap();
    wait_until("the stop after the panic", || {
        log.lock().unwrap().stops == 1
    });
    let mut s = [0f32; 2];
    let e = r.read_state(&mut s).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("driver thread panicked") && msg.contains("mock driver bug"),
        "{msg}"
    );
    assert!(r.send_targets(&[0.0]).is_err());
}

/// `stop` while the device is stalled returns within `stop_wait` with an error that says
/// so; the stop command goes out as soon as the stalled call returns.
#[test]
fn stop_during_a_stall_says_so_and_the_stop_follows_the_stall() {
    let (m, log, gate) = mock(None, None);
    let mut r = Threaded::spawn(m, cfg()).unwrap();
    let mut s = [0f32; 2];
    r.read_state(&mut s).unwrap();
    let stall = gate.lock().unwrap();
    std::thread::sleep(Duration::from_millis(20));
    let (r, e) = bounded(move || {
        let e = r.stop();
        (r, e)
    })
    .expect("stop blocked on the stalled device");
    let e = e.unwrap_err();
    assert!(e.to_string().contains("stalled call"), "{e}");
    assert_eq!(log.lock().unwrap().stops, 0);
    drop(stall);
    wait_until("the stop after the stall", || {
        log.lock().unwrap().stops == 1
    });
    drop(r);
    assert_eq!(log.lock().unwrap().stops, 1);
}

/// Dropping the robot stops the device.
#[test]
fn drop_stops_the_device() {
    let (m, log, _gate) = mock(None, None);
    let r = Threaded::spawn(m, cfg()).unwrap();
    drop(r);
    assert_eq!(log.lock().unwrap().stops, 1);
}
