//! [`Threaded`]: a [`Robot`] driven on its own thread, so slow I/O never holds up a control
//! tick.
//!
//! A serial device such as the XHand answers every command with its state: one transaction
//! per tick, normally ~1 ms at 1 Mbit/s, but a stalled adapter or a retransmission can take
//! the full reply timeout (100 ms). Called from the control thread, that stall makes the tick
//! late, and so every actuator of the robot. Behind [`Threaded`] the control thread only
//! copies: [`Robot::send_targets`] leaves the newest targets in a mailbox and
//! [`Robot::read_state`] returns the newest state with the time it was measured. The driver
//! thread sends the newest targets as soon as they arrive (targets superseded during a
//! stall are dropped, counted), and re-reads the state every [`ThreadedConfig::period`]
//! when no targets come. A stall thus costs stale states, which the safety layer's state
//! watchdog sees by their timestamps, not a late tick.
//!
//! # Failing closed
//!
//! - An error of the device (timeout, disconnect, a CRC error...) or a panic inside the
//!   device's driver ends the driver thread. The thread then sends the device's stop
//!   command, and the next call on the control side returns the error (a panic becomes
//!   [`Error::Stopped`] naming the thread and the panic message); every later call returns
//!   [`Error::Stopped`].
//! - [`Robot::stop`] asks the thread to stop the device and waits up to
//!   [`ThreadedConfig::stop_wait`]. If the device is inside a stalled call, `stop` returns an
//!   error saying so; the stop command still goes out as soon as the stalled call returns.
//! - Dropping a [`Threaded`] stops the device the same way.
//! - The first [`Robot::read_state`] waits up to [`ThreadedConfig::first_state_timeout`] for
//!   the device's first state; later reads never wait.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use pir2_runtime::{panic_message, Nanos};

use crate::error::{Error, Result};
use crate::robot::{Robot, StateLayout};

/// Settings of a [`Threaded`] robot.
#[derive(Debug, Clone)]
pub struct ThreadedConfig {
    /// The driver re-reads the state this often when no new targets arrive.
    pub period: Duration,
    /// How long the first `read_state` waits for the device's first state.
    pub first_state_timeout: Duration,
    /// How long `stop` waits for the driver thread to send the stop command.
    pub stop_wait: Duration,
}

impl Default for ThreadedConfig {
    fn default() -> Self {
        Self {
            period: Duration::from_millis(10),
            first_state_timeout: Duration::from_secs(1),
            stop_wait: Duration::from_millis(300),
        }
    }
}

/// Counters of a [`Threaded`] robot.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ThreadedStats {
    /// Target vectors sent to the device.
    pub sent: u64,
    /// Target vectors replaced by newer ones before the driver could send them (a stall).
    pub superseded: u64,
    /// States read from the device.
    pub states: u64,
    /// The longest single device call (send + read), ns.
    pub longest_call_ns: u64,
}

struct Mailbox {
    state: Vec<f32>,
    t_state: Option<Nanos>,
    targets: Vec<f32>,
    new_targets: bool,
    fault: Option<String>,
    /// The error that ended the driver thread, until a control-side call returns it.
    error: Option<Error>,
    /// Why the driver thread ended (kept for every later call).
    ended: Option<String>,
    stop: bool,
    /// The result of the device's stop command, once sent.
    stop_result: Option<Result<()>>,
    stats: ThreadedStats,
}

struct Shared {
    mail: Mutex<Mailbox>,
    cv: Condvar,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Mailbox> {
        self.mail.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Release `m` until notified or `left` has passed, and take it back.
    fn wait<'a>(&'a self, m: MutexGuard<'a, Mailbox>, left: Duration) -> MutexGuard<'a, Mailbox> {
        self.cv
            .wait_timeout(m, left)
            .unwrap_or_else(|p| p.into_inner())
            .0
    }
}

/// A [`Robot`] whose device calls run on a driver thread (see the module docs).
pub struct Threaded<R> {
    shared: Arc<Shared>,
    handle: Option<JoinHandle<()>>,
    name: &'static str,
    state_dim: usize,
    action_dim: usize,
    layout: StateLayout,
    cfg: ThreadedConfig,
    stopped: bool,
    _robot: std::marker::PhantomData<fn() -> R>,
}

impl<R> std::fmt::Debug for Threaded<R> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Threaded")
            .field("name", &self.name)
            .field("stopped", &self.stopped)
            .finish_non_exhaustive()
    }
}

impl<R: Robot + 'static> Threaded<R> {
    /// Move `robot` onto its own driver thread. No device traffic happens before the thread
    /// runs; it starts reading the state at once.
    pub fn spawn(robot: R, cfg: ThreadedConfig) -> Result<Self> {
        if cfg.period.is_zero() || cfg.stop_wait.is_zero() || cfg.first_state_timeout.is_zero() {
            return Err(Error::Config(
                "threaded driver: period, stop_wait and first_state_timeout must be > 0".into(),
            ));
        }
        let name = robot.name();
        let (state_dim, action_dim, layout) =
            (robot.state_dim(), robot.action_dim(), robot.layout());
        let shared = Arc::new(Shared {
            mail: Mutex::new(Mailbox {
                state: vec![0.0; state_dim],
                t_state: None,
                targets: vec![0.0; action_dim],
                new_targets: false,
                fault: None,
                error: None,
                ended: None,
                stop: false,
                stop_result: None,
                stats: ThreadedStats::default(),
            }),
            cv: Condvar::new(),
        });
        let sh = shared.clone();
        let period = cfg.period;
        let handle = std::thread::Builder::new()
            .name(format!("pir2-{}", name.to_lowercase()))
            .spawn(move || drive(robot, &sh, period))
            .map_err(|e| Error::io("driver thread", e))?;
        Ok(Self {
            shared,
            handle: Some(handle),
            name,
            state_dim,
            action_dim,
            layout,
            cfg,
            stopped: false,
            _robot: std::marker::PhantomData,
        })
    }

    /// Counters so far.
    pub fn stats(&self) -> ThreadedStats {
        self.shared.lock().stats
    }
}

impl<R> Threaded<R> {
    /// The error that ended the driver thread (returned once), else `Stopped` if it ended.
    fn ended(&self, m: &mut Mailbox) -> Result<()> {
        if let Some(e) = m.error.take() {
            return Err(e);
        }
        match &m.ended {
            Some(why) => Err(Error::Stopped {
                device: self.name,
                reason: why.clone(),
            }),
            None => Ok(()),
        }
    }

    fn stop_thread(&mut self) -> Result<()> {
        if self.stopped {
            return Ok(());
        }
        self.stopped = true;
        {
            let mut m = self.shared.lock();
            m.stop = true;
            if m.ended.is_none() {
                m.ended = Some("stop() was called".into());
            }
        }
        self.shared.cv.notify_all();
        let t0 = Instant::now();
        let mut m = self.shared.lock();
        while m.stop_result.is_none() {
            let left = self.cfg.stop_wait.saturating_sub(t0.elapsed());
            if left.is_zero() {
                return Err(Error::Timeout {
                    channel: self.name,
                    what: "the driver thread to send the stop command (the device is inside a \
                           stalled call; the stop goes out when it returns)"
                        .into(),
                    waited_ms: t0.elapsed().as_millis() as u64,
                });
            }
            m = self.shared.wait(m, left);
        }
        let r = m.stop_result.take().unwrap_or(Ok(()));
        drop(m);
        if let Some(h) = self.handle.take() {
            // The thread has sent the stop command and is returning.
            let _ = h.join();
        }
        r
    }
}

/// The driver thread: send the newest targets, read the state, publish; on an error or a
/// panic, record it; always end with the device's stop command.
fn drive<R: Robot>(mut robot: R, sh: &Shared, period: Duration) {
    let mut targets = vec![0.0; robot.action_dim()];
    let mut state = vec![0.0; robot.state_dim()];
    let mut last_pass = Instant::now() - period;
    loop {
        let send = {
            let mut m = sh.lock();
            loop {
                if m.stop {
                    break None;
                }
                if m.new_targets {
                    m.new_targets = false;
                    targets.copy_from_slice(&m.targets);
                    break Some(true);
                }
                let left = period.saturating_sub(last_pass.elapsed());
                if left.is_zero() {
                    break Some(false);
                }
                m = sh.wait(m, left);
            }
        };
        let Some(send) = send else { break };
        last_pass = Instant::now();
        let r = catch_unwind(AssertUnwindSafe(|| -> Result<Nanos> {
            if send {
                robot.send_targets(&targets)?;
            }
            robot.read_state(&mut state)
        }));
        let took = last_pass.elapsed().as_nanos() as u64;
        let mut m = sh.lock();
        m.stats.longest_call_ns = m.stats.longest_call_ns.max(took);
        match r {
            Ok(Ok(t)) => {
                if send {
                    m.stats.sent += 1;
                }
                m.stats.states += 1;
                m.state.copy_from_slice(&state);
                m.t_state = Some(t);
                m.fault = robot.fault();
                drop(m);
                sh.cv.notify_all();
            }
            Ok(Err(e)) => {
                m.ended = Some(format!("its driver thread ended on an error: {e}"));
                m.error = Some(e);
                break;
            }
            Err(p) => {
                let msg = panic_message(&*p);
                let why = format!("its driver thread panicked: {msg}");
                m.ended = Some(why.clone());
                m.error = Some(Error::Stopped {
                    device: robot.name(),
                    reason: why,
                });
                break;
            }
        }
    }
    let r = catch_unwind(AssertUnwindSafe(|| robot.stop())).unwrap_or_else(|p| {
        Err(Error::Stopped {
            device: robot.name(),
            reason: format!("its stop command panicked: {}", panic_message(&*p)),
        })
    });
    let mut m = sh.lock();
    m.stop_result = Some(r);
    drop(m);
    sh.cv.notify_all();
}

impl<R: Robot + 'static> Robot for Threaded<R> {
    fn name(&self) -> &'static str {
        self.name
    }
    fn state_dim(&self) -> usize {
        self.state_dim
    }
    fn action_dim(&self) -> usize {
        self.action_dim
    }
    fn layout(&self) -> StateLayout {
        self.layout.clone()
    }
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
        Error::check_dim("threaded state", self.state_dim, out.len())?;
        let t0 = Instant::now();
        let mut m = self.shared.lock();
        loop {
            self.ended(&mut m)?;
            if let Some(t) = m.t_state {
                out.copy_from_slice(&m.state);
                return Ok(t);
            }
            let left = self.cfg.first_state_timeout.saturating_sub(t0.elapsed());
            if left.is_zero() {
                return Err(Error::Timeout {
                    channel: self.name,
                    what: "the first state from the driver thread".into(),
                    waited_ms: t0.elapsed().as_millis() as u64,
                });
            }
            m = self.shared.wait(m, left);
        }
    }
    fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
        Error::check_dim("threaded targets", self.action_dim, targets.len())?;
        let mut m = self.shared.lock();
        self.ended(&mut m)?;
        if m.new_targets {
            m.stats.superseded += 1;
        }
        m.targets.copy_from_slice(targets);
        m.new_targets = true;
        drop(m);
        self.shared.cv.notify_all();
        Ok(())
    }
    fn stop(&mut self) -> Result<()> {
        self.stop_thread()
    }
    fn fault(&self) -> Option<String> {
        let m = self.shared.lock();
        m.fault.clone()
    }
}

impl<R> Drop for Threaded<R> {
    fn drop(&mut self) {
        let _ = self.stop_thread();
    }
}
