//! SIGINT and SIGTERM for the `pir2` binary.
//!
//! The first signal sets a stop flag that the running command polls, so the robot is stopped
//! through the command's normal path in any phase (warm-up included) and the process ends
//! with its usual report. A second signal runs the registered emergency stop (for
//! `pir2 gr00t run`, the robot's `stop`) and exits at once with status 130.
//!
//! The handlers only count signals (one atomic add, async-signal-safe); a watcher thread
//! turns the count into the flag and the emergency exit.

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

/// Exit status after a second signal (128 + SIGINT, the shell's convention).
pub const EMERGENCY_EXIT: i32 = 130;

static SIGNALS: AtomicU32 = AtomicU32::new(0);
static FLAG: OnceLock<Arc<AtomicBool>> = OnceLock::new();

type Hook = Box<dyn FnOnce() + Send>;
static EMERGENCY: Mutex<Option<Hook>> = Mutex::new(None);

extern "C" fn on_signal(_: libc::c_int) {
    SIGNALS.fetch_add(1, Ordering::SeqCst);
}

/// Install the SIGINT and SIGTERM handlers (once per process) and return the stop flag the
/// first of them sets. Every call returns the same flag.
pub fn stop_flag() -> Arc<AtomicBool> {
    FLAG.get_or_init(|| {
        let stop = Arc::new(AtomicBool::new(false));
        for sig in [libc::SIGINT, libc::SIGTERM] {
            // SAFETY: the handler is async-signal-safe (one atomic add, no allocation,
            // no lock); `signal` on Linux keeps it installed after it runs.
            unsafe {
                libc::signal(sig, on_signal as *const () as libc::sighandler_t);
            }
        }
        let s = stop.clone();
        std::thread::Builder::new()
            .name("pir2 signals".into())
            .spawn(move || watch(&s))
            .expect("spawning the signal watcher thread");
        stop
    })
    .clone()
}

fn watch(stop: &AtomicBool) {
    loop {
        let n = SIGNALS.load(Ordering::SeqCst);
        if n >= 1 && !stop.swap(true, Ordering::SeqCst) {
            eprintln!("{}", first_signal_message(has_emergency_hook()));
        }
        if n >= 2 {
            eprintln!("second signal: emergency stop, exiting");
            let hook = EMERGENCY.lock().unwrap_or_else(|p| p.into_inner()).take();
            if let Some(hook) = hook {
                hook();
            }
            std::process::exit(EMERGENCY_EXIT);
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// What the first signal prints: a command driving a robot (one that registered an emergency
/// stop) says the second signal stops it; any other command (training, collection, an
/// evaluation in simulation) says only that it exits.
fn first_signal_message(robot: bool) -> &'static str {
    if robot {
        "signal received: stopping (a second signal stops the robot and exits at once)"
    } else {
        "signal received: stopping after the current step (a second signal exits at once)"
    }
}

fn has_emergency_hook() -> bool {
    EMERGENCY
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .is_some()
}

/// Register what a second signal runs before the process exits (replaces an earlier hook).
/// It runs on the watcher thread and must return quickly (bound any wait for a lock).
pub fn on_second_signal(hook: impl FnOnce() + Send + 'static) {
    *EMERGENCY.lock().unwrap_or_else(|p| p.into_inner()) = Some(Box::new(hook));
}

/// Forget the registered emergency stop (its robot is gone).
pub fn clear_second_signal() {
    *EMERGENCY.lock().unwrap_or_else(|p| p.into_inner()) = None;
}
