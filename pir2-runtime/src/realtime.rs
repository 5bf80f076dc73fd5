//! The real-time driver: a control thread at `T_ctrl` (deadline-based sleep, no drift), an
//! action worker, and an optional slow worker — the same state machine as the lock-step
//! driver.
//!
//! ```text
//!  control thread (every T_ctrl)          action worker                 slow worker
//!  read fast obs ─ publish ─────────────► snapshot (fast + slow cache)  capture → encode
//!  swap in delivered chunk ◄───────────── one call (1 NFE for πR²)      replace cache
//!  send one action                        push latency → d              (features, t_capture)
//! ```
//!
//! The control step neither allocates nor blocks: the observation is published with
//! `try_lock` (if the worker is copying, this tick's frame is skipped; the worker reads the
//! next one), and chunks are handed over by swapping preallocated storage.
//!
//! Fail closed: a panic on any thread (a worker, or a user's [`VelocityModel`],
//! [`FastSource`], [`Actuator`], [`SlowSource`] or [`SlowEncoder`] running on it) stops the
//! robot and ends the run with [`Error::Panicked`] naming the thread. The stop flag is
//! honoured in every phase, the warm-up included: the actuator's `stop` is called as soon as
//! it is seen, before the workers are wound down. A tick that starts more than one period
//! late sends one action and restarts the schedule from there (counted in
//! [`RunMetrics::late_ticks`]): missed deadlines are skipped, never fired back to back.
//!
//! One file on purpose: the control thread, the two workers and [`run`]'s start and wind-down
//! share one stop-and-panic protocol (who stops the actuator, in which phase, and which error
//! ends the run), which is only checkable when read together.

use std::future::Future;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::pin::pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::task::{Context, Poll, Wake, Waker};
use std::time::{Duration, Instant};

use crate::chunk::Chunk;
use crate::clock::{Clock, Nanos};
use crate::control::{ControlConfig, ControlState};
use crate::error::{Error, Result};
use crate::head::{ActionHead, Snapshot};
use crate::io::{Actuator, FastSource, SlowEncoder, SlowFeatures, SlowSource};
use crate::metrics::RunMetrics;
use crate::model::VelocityModel;

/// Run a future to completion on the current thread (the slow channel's async traits need
/// no runtime beyond this: a source or encoder may block or await its own I/O).
pub fn block_on<F: Future>(fut: F) -> F::Output {
    struct ThreadWaker(std::thread::Thread);
    impl Wake for ThreadWaker {
        fn wake(self: Arc<Self>) {
            self.0.unpark();
        }
    }
    let waker = Waker::from(Arc::new(ThreadWaker(std::thread::current())));
    let mut cx = Context::from_waker(&waker);
    let mut fut = pin!(fut);
    loop {
        match fut.as_mut().poll(&mut cx) {
            Poll::Ready(v) => return v,
            Poll::Pending => std::thread::park(),
        }
    }
}

/// Where the slow features come from.
pub enum SlowChannel {
    /// The model takes no slow input.
    None,
    /// A slow worker thread captures and encodes continuously; calls read its cache.
    Async {
        /// Camera/prompt source.
        source: Box<dyn SlowSource>,
        /// Backbone.
        encoder: Box<dyn SlowEncoder>,
    },
    /// Each call captures and encodes first (πR² without async); its time counts in `d`.
    Inline {
        /// Camera/prompt source.
        source: Box<dyn SlowSource>,
        /// Backbone.
        encoder: Box<dyn SlowEncoder>,
    },
}

impl std::fmt::Debug for SlowChannel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SlowChannel::None => "SlowChannel::None",
            SlowChannel::Async { .. } => "SlowChannel::Async",
            SlowChannel::Inline { .. } => "SlowChannel::Inline",
        })
    }
}

/// Real-time run settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RealtimeConfig {
    /// Control period `T_ctrl`, ns.
    pub period: Nanos,
    /// Stop after this many ticks (`None` = until the stop flag is set).
    pub max_ticks: Option<u64>,
    /// Delay assumed by the warm start.
    pub initial_delay: usize,
    /// How long to wait for the first slow features before giving up.
    pub slow_timeout: Duration,
    /// Run the control thread under `SCHED_FIFO` with this priority (1–99; Linux, needs
    /// `CAP_SYS_NICE`). If the request is refused the run continues at normal priority and
    /// records the refusal in the metrics' events.
    pub rt_priority: Option<i32>,
    /// Control watchdog: once the robot has taken a first action from a chunk, this long
    /// without a clean action (consecutive holds, overruns or ticks past the end of the
    /// chunk, [`ControlState::stalled_ticks`]) stops the robot and ends the run with
    /// [`Error::SafetyStop`]. `None` disables it (tests of overrun behaviour only).
    pub stall_limit: Option<Duration>,
}

/// Default of [`RealtimeConfig::stall_limit`]: one second without a clean action.
pub const DEFAULT_STALL_LIMIT: Duration = Duration::from_secs(1);

/// Ceiling of the control watchdog an operator may set (e.g. to ride through a policy-server
/// restart): past five seconds of overruns and holds the robot has been acting on estimates
/// or standing still long enough that the run should end and be restarted on purpose.
pub const MAX_STALL_LIMIT: Duration = Duration::from_secs(5);

impl Default for RealtimeConfig {
    fn default() -> Self {
        Self {
            period: 20_000_000,
            max_ticks: None,
            initial_delay: 1,
            slow_timeout: Duration::from_secs(10),
            rt_priority: None,
            stall_limit: Some(DEFAULT_STALL_LIMIT),
        }
    }
}

struct FastMail {
    seq: u64,
    tick: u64,
    t_state: Nanos,
    hist: Vec<f32>,
}

struct ChunkMail {
    full: bool,
    /// The number of the call that produced `chunk` (1, 2, …; 0 before the first).
    seq: u64,
    chunk: Chunk,
}

/// State shared between the control thread and the workers.
pub struct Shared {
    fast: Mutex<FastMail>,
    fast_cv: Condvar,
    chunk: Mutex<ChunkMail>,
    slow: Mutex<SlowFeatures>,
    slow_seen: AtomicBool,
    wants_call: AtomicBool,
    /// The number of the last call the action worker started.
    call_started: AtomicU64,
    /// A finished chunk waits in `chunk` for the control thread: the worker starts no new
    /// call until it is taken, so no chunk (nor its trace record) is ever overwritten.
    chunk_pending: AtomicBool,
    stop: AtomicBool,
    error: Mutex<Option<Error>>,
}

impl std::fmt::Debug for Shared {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Shared")
            .field("stop", &self.stop.load(Ordering::Relaxed))
            .finish_non_exhaustive()
    }
}

impl Shared {
    /// Shared state for a control loop with these sizes.
    pub fn new(n_obs: usize, fast_dim: usize, horizon: usize, action_dim: usize) -> Arc<Self> {
        Arc::new(Self {
            fast: Mutex::new(FastMail {
                seq: 0,
                tick: 0,
                t_state: 0,
                hist: vec![0.0; n_obs * fast_dim],
            }),
            fast_cv: Condvar::new(),
            chunk: Mutex::new(ChunkMail {
                full: false,
                seq: 0,
                chunk: Chunk::new(horizon, action_dim),
            }),
            slow: Mutex::new(SlowFeatures::default()),
            slow_seen: AtomicBool::new(false),
            wants_call: AtomicBool::new(true),
            call_started: AtomicU64::new(0),
            chunk_pending: AtomicBool::new(false),
            stop: AtomicBool::new(false),
            error: Mutex::new(None),
        })
    }

    /// The action worker starts call `n` (numbers increase by one from 1).
    fn begin_call(&self, n: u64) {
        self.call_started.store(n, Ordering::Release);
    }

    /// The action worker hands over the chunk of call `n` (`out` gets the old storage).
    fn publish_chunk(&self, n: u64, out: &mut Chunk) {
        let mut m = self.chunk.lock().unwrap_or_else(|p| p.into_inner());
        std::mem::swap(&mut m.chunk, out);
        m.seq = n;
        m.full = true;
        self.chunk_pending.store(true, Ordering::Release);
    }

    fn fail(&self, e: Error) {
        let mut g = self.error.lock().unwrap_or_else(|p| p.into_inner());
        if g.is_none() {
            *g = Some(e);
        }
        self.stop.store(true, Ordering::SeqCst);
        self.fast_cv.notify_all();
    }
}

/// The control thread's side: history, the control state, and the per-tick step.
#[derive(Debug)]
pub struct ControlLoop {
    /// The control state (metrics live in `control.metrics`).
    pub control: ControlState,
    hist: Vec<f32>,
    obs: Vec<f32>,
    n_obs: usize,
    /// The number of the last call whose chunk was delivered.
    delivered_seq: u64,
    /// Stop the robot past this many stalled ticks ([`RealtimeConfig::stall_limit`]).
    max_stalled: Option<u64>,
}

impl ControlLoop {
    /// A control loop with `n_obs × fast_dim` history.
    pub fn new(control: ControlState, n_obs: usize, fast_dim: usize) -> Self {
        Self {
            control,
            hist: vec![0.0; n_obs * fast_dim],
            obs: vec![0.0; fast_dim],
            n_obs,
            delivered_seq: 0,
            max_stalled: None,
        }
    }

    /// Stop the robot after `ticks` consecutive ticks without a clean action
    /// ([`ControlState::stalled_ticks`]); `None`: never.
    pub fn with_stall_limit(mut self, ticks: Option<u64>) -> Self {
        self.max_stalled = ticks;
        self
    }

    /// Fill the whole history with one observation (before the first tick).
    pub fn prime(&mut self, obs: &[f32]) {
        let f = self.obs.len();
        for k in 0..self.n_obs {
            self.hist[k * f..(k + 1) * f].copy_from_slice(obs);
        }
    }

    /// The fast history, oldest first.
    pub fn history(&self) -> &[f32] {
        &self.hist
    }

    /// One control tick at time `now`: read, publish, swap, send. No allocation, no
    /// blocking lock.
    pub fn tick<F: FastSource + ?Sized, A: Actuator + ?Sized>(
        &mut self,
        shared: &Shared,
        fast: &mut F,
        act: &mut A,
    ) -> Result<()> {
        let t_state = fast.read(&mut self.obs)?;
        let f = self.obs.len();
        self.hist.copy_within(f.., 0);
        self.hist[(self.n_obs - 1) * f..].copy_from_slice(&self.obs);
        let tick = self.control.tick();
        if let Ok(mut m) = shared.fast.try_lock() {
            m.hist.copy_from_slice(&self.hist);
            m.tick = tick;
            m.t_state = t_state;
            m.seq += 1;
            drop(m);
            shared.fast_cv.notify_one();
        }
        if let Ok(mut m) = shared.chunk.try_lock() {
            if m.full {
                self.control.deliver(&mut m.chunk);
                self.delivered_seq = m.seq;
                m.full = false;
                shared.chunk_pending.store(false, Ordering::Release);
            }
        }
        // A call is in flight while the worker has started one whose chunk has not been
        // delivered. Counting (not "did the number change") keeps this right when a call
        // ends and the next one starts between two ticks.
        if shared.call_started.load(Ordering::Acquire) > self.delivered_seq {
            self.control.call_started();
        }
        self.control.action();
        if let Some(limit) = self.max_stalled {
            let stalled = self.control.stalled_ticks();
            if stalled > limit {
                let m = &self.control.metrics;
                return Err(Error::SafetyStop(format!(
                    "control watchdog: no clean action for {stalled} consecutive ticks (bound \
                     {limit}; {} holds and {} overruns in the run): the policy's chunks ran \
                     out or its calls stalled",
                    m.holds, m.overruns
                )));
            }
        }
        act.send(self.control.command())?;
        shared
            .wants_call
            .store(self.control.wants_call(), Ordering::Release);
        Ok(())
    }
}

/// How long the end of a run waits for the slow worker to finish its current capture or
/// encode before leaving it behind (it exits on its own once that returns).
const SLOW_JOIN_WAIT: Duration = Duration::from_millis(500);

fn slow_worker(shared: &Shared, source: Box<dyn SlowSource>, encoder: Box<dyn SlowEncoder>) {
    if let Err(p) = catch_unwind(AssertUnwindSafe(|| slow_loop(shared, source, encoder))) {
        shared.fail(Error::panicked("slow worker", &*p));
    }
}

fn slow_loop(shared: &Shared, mut source: Box<dyn SlowSource>, mut encoder: Box<dyn SlowEncoder>) {
    while !shared.stop.load(Ordering::Acquire) {
        let r = block_on(async {
            let frame = source.capture().await?;
            encoder.encode(frame).await
        });
        match r {
            Ok(mut feats) => {
                let mut g = shared.slow.lock().unwrap_or_else(|p| p.into_inner());
                std::mem::swap(&mut *g, &mut feats);
                shared.slow_seen.store(true, Ordering::Release);
            }
            Err(e) => {
                shared.fail(e);
                return;
            }
        }
    }
}

fn copy_slow(dst: &mut Snapshot, feats: &SlowFeatures, slow_dim: usize) -> Result<()> {
    if feats.data.len() != slow_dim {
        return Err(Error::shape("slow features", slow_dim, feats.data.len()));
    }
    dst.slow.copy_from_slice(&feats.data);
    dst.t_slow = feats.t_capture;
    Ok(())
}

fn action_worker<M: VelocityModel>(
    shared: &Shared,
    head: &mut ActionHead<M>,
    clock: &dyn Clock,
    mut inline: Option<(Box<dyn SlowSource>, Box<dyn SlowEncoder>)>,
) -> Result<()> {
    let spec = *head.spec();
    let mut snap = Snapshot::new(&spec);
    let mut out = Chunk::new(spec.horizon, spec.action_dim);
    let mut last_seq = 0;
    let mut n_calls = 0u64;
    loop {
        {
            let mut m = shared.fast.lock().unwrap_or_else(|p| p.into_inner());
            loop {
                if shared.stop.load(Ordering::Acquire) {
                    return Ok(());
                }
                if m.seq != last_seq
                    && shared.wants_call.load(Ordering::Acquire)
                    && !shared.chunk_pending.load(Ordering::Acquire)
                {
                    break;
                }
                m = shared
                    .fast_cv
                    .wait_timeout(m, Duration::from_millis(5))
                    .unwrap_or_else(|p| p.into_inner())
                    .0;
            }
            last_seq = m.seq;
            snap.tick = m.tick;
            snap.t_state = m.t_state;
            snap.fast.copy_from_slice(&m.hist);
        }
        n_calls += 1;
        shared.begin_call(n_calls);
        let t0 = clock.now();
        if spec.slow_dim > 0 {
            if let Some((source, encoder)) = inline.as_mut() {
                let feats = block_on(async {
                    let frame = source.capture().await?;
                    encoder.encode(frame).await
                })?;
                copy_slow(&mut snap, &feats, spec.slow_dim)?;
            } else {
                let g = shared.slow.lock().unwrap_or_else(|p| p.into_inner());
                copy_slow(&mut snap, &g, spec.slow_dim)?;
            }
        }
        head.call(&snap, &mut out)?;
        let latency = clock.now().saturating_sub(t0);
        head.record_latency(latency);
        out.call.latency = latency;
        shared.publish_chunk(n_calls, &mut out);
    }
}

/// Put the calling thread under `SCHED_FIFO` at `prio`.
pub fn set_fifo_priority(prio: i32) -> std::io::Result<()> {
    #[cfg(target_os = "linux")]
    {
        let param = libc::sched_param {
            sched_priority: prio,
        };
        // SAFETY: plain syscall on the current thread with a valid parameter struct.
        let r =
            unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
        if r == 0 {
            Ok(())
        } else {
            Err(std::io::Error::from_raw_os_error(r))
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = prio;
        Err(std::io::Error::new(
            std::io::ErrorKind::Unsupported,
            "SCHED_FIFO is Linux-only here",
        ))
    }
}

/// Call the actuator's `stop` once (later calls are no-ops), catching a panic in it.
fn stop_once<A: Actuator + ?Sized>(act: &mut A, done: &mut Option<Result<()>>) {
    if done.is_none() {
        *done = Some(match catch_unwind(AssertUnwindSafe(|| act.stop())) {
            Ok(r) => r,
            Err(p) => Err(Error::panicked("control thread", &*p)),
        });
    }
}

/// A real-time run that ended in an error, with the metrics of the ticks it ran (`None` if
/// it failed before the control loop started or the control thread panicked): the trace a
/// post-mortem of a safety stop needs.
#[derive(Debug)]
pub struct RunFailed {
    /// What ended the run.
    pub error: Error,
    /// The run's metrics up to the error.
    pub metrics: Option<Box<RunMetrics>>,
}

/// Run the real-time driver until `max_ticks` or until `stop` is set. The robot is stopped
/// (actuator `stop`) on every exit path, panics included, before the workers are joined.
/// Returns the run's metrics; the first error of any thread is returned instead (after the
/// safe stop). A stop requested during the warm-up ends the run before the robot moves,
/// with an event saying so. [`run_keeping_metrics`] also returns the metrics of a failed run.
#[allow(clippy::too_many_arguments)]
pub fn run<M, F, A>(
    head: ActionHead<M>,
    control: ControlConfig,
    fast: F,
    actuator: A,
    slow: SlowChannel,
    clock: Arc<dyn Clock>,
    cfg: RealtimeConfig,
    stop: Arc<AtomicBool>,
) -> Result<(RunMetrics, ActionHead<M>)>
where
    M: VelocityModel,
    F: FastSource,
    A: Actuator,
{
    run_keeping_metrics(head, control, fast, actuator, slow, clock, cfg, stop).map_err(|f| f.error)
}

/// [`run`], returning with an error the metrics of the ticks that ran ([`RunFailed`]).
#[allow(clippy::too_many_arguments)]
pub fn run_keeping_metrics<M, F, A>(
    head: ActionHead<M>,
    control: ControlConfig,
    fast: F,
    actuator: A,
    slow: SlowChannel,
    clock: Arc<dyn Clock>,
    cfg: RealtimeConfig,
    stop: Arc<AtomicBool>,
) -> std::result::Result<(RunMetrics, ActionHead<M>), RunFailed>
where
    M: VelocityModel,
    F: FastSource,
    A: Actuator,
{
    let mut failed = None;
    run_inner(
        head,
        control,
        fast,
        actuator,
        slow,
        clock,
        cfg,
        stop,
        &mut failed,
    )
    .map_err(|error| RunFailed {
        error,
        metrics: failed.map(Box::new),
    })
}

/// [`run`]; on an error after the control loop ran, its metrics go to `failed`.
#[allow(clippy::too_many_arguments)]
fn run_inner<M, F, A>(
    mut head: ActionHead<M>,
    control: ControlConfig,
    mut fast: F,
    mut actuator: A,
    slow: SlowChannel,
    clock: Arc<dyn Clock>,
    cfg: RealtimeConfig,
    stop: Arc<AtomicBool>,
    failed: &mut Option<RunMetrics>,
) -> Result<(RunMetrics, ActionHead<M>)>
where
    M: VelocityModel,
    F: FastSource,
    A: Actuator,
{
    let spec = *head.spec();
    if spec.d_max == 0 {
        return Err(Error::Config(
            "a zero-delay policy (d_max = 0) runs only in lock-step with zero-latency calls; \
             a real-time call always takes at least one tick"
                .into(),
        ));
    }
    if fast.dim() != spec.fast_dim {
        return Err(Error::shape("fast source dim", spec.fast_dim, fast.dim()));
    }
    if actuator.dim() != spec.action_dim {
        return Err(Error::shape(
            "actuator dim",
            spec.action_dim,
            actuator.dim(),
        ));
    }
    if cfg.period != spec.period {
        return Err(Error::Config(format!(
            "realtime period {} ns != head period {} ns",
            cfg.period, spec.period
        )));
    }
    head.set_output(&control.output)?;
    let shared = Shared::new(spec.n_obs, spec.fast_dim, spec.horizon, spec.action_dim);
    let stall_ticks = cfg
        .stall_limit
        .map(|d| (d.as_nanos() / u128::from(cfg.period.max(1))).max(1) as u64);
    let mut lp = ControlLoop::new(ControlState::new(control)?, spec.n_obs, spec.fast_dim)
        .with_stall_limit(stall_ticks);
    let (slow_async, mut slow_inline) = match slow {
        SlowChannel::None => (None, None),
        SlowChannel::Async { source, encoder } => (Some((source, encoder)), None),
        SlowChannel::Inline { source, encoder } => (None, Some((source, encoder))),
    };
    if spec.slow_dim > 0 && slow_async.is_none() && slow_inline.is_none() {
        return Err(Error::Config(format!(
            "the model takes {} slow features but no slow channel is given",
            spec.slow_dim
        )));
    }

    // The slow worker owns its source and encoder and may sit in a long capture (a camera,
    // a network read): it is not scoped, so the end of a run never waits on it for long.
    let slow_handle = match slow_async {
        Some((src, enc)) => {
            let sh = shared.clone();
            Some(
                std::thread::Builder::new()
                    .name("pir2-slow".into())
                    .spawn(move || slow_worker(&sh, src, enc))
                    .map_err(|e| Error::io("slow worker thread", e))?,
            )
        }
        None => None,
    };
    let mut stopped: Option<Result<()>> = None;
    let stop_signal = crate::StopSignal::new();
    let result = std::thread::scope(|s| -> Result<RunMetrics> {
        let mut worker = None;
        let body = catch_unwind(AssertUnwindSafe(|| -> Result<RunMetrics> {
            // Warm start (before the robot moves): the first slow features, then the first
            // observation, then the warm-start chunk. Both waits can last far longer than a
            // tick (a backbone's first frame, a warm start over the network), so the robot's
            // state is read once per period meanwhile: a robot driver or safety layer with a
            // stale-state watchdog must not trip before the run has begun. Those reads are
            // discarded. The stop flag is checked throughout.
            let mut scratch = vec![0.0; spec.fast_dim];
            let mut last_read = clock.now();
            let mut keepalive = |fast: &mut F| -> Result<()> {
                if clock.now().saturating_sub(last_read) >= cfg.period {
                    fast.read(&mut scratch)?;
                    last_read = clock.now();
                }
                Ok(())
            };
            let requested = || stop.load(Ordering::Acquire);
            let warm = (|| -> Result<Option<Chunk>> {
                let mut snap = Snapshot::new(&spec);
                if spec.slow_dim > 0 {
                    if let Some((source, encoder)) = slow_inline.as_mut() {
                        let feats = block_on(async {
                            let frame = source.capture().await?;
                            encoder.encode(frame).await
                        })?;
                        copy_slow(&mut snap, &feats, spec.slow_dim)?;
                    } else {
                        let t_wait = clock.now();
                        while !shared.slow_seen.load(Ordering::Acquire) {
                            if requested() {
                                return Ok(None);
                            }
                            if shared.stop.load(Ordering::Acquire) {
                                return Err(shared
                                    .error
                                    .lock()
                                    .unwrap_or_else(|p| p.into_inner())
                                    .take()
                                    .unwrap_or(Error::WorkerStopped("slow")));
                            }
                            if clock.now() - t_wait > cfg.slow_timeout.as_nanos() as Nanos {
                                return Err(Error::io(
                                    "slow channel",
                                    "no features before the timeout",
                                ));
                            }
                            keepalive(&mut fast)?;
                            std::thread::sleep(Duration::from_millis(1));
                        }
                        copy_slow(
                            &mut snap,
                            &shared.slow.lock().unwrap_or_else(|p| p.into_inner()),
                            spec.slow_dim,
                        )?;
                    }
                }
                if requested() {
                    return Ok(None);
                }
                let mut obs = vec![0.0; spec.fast_dim];
                let t_state = fast.read(&mut obs)?;
                lp.prime(&obs);
                snap.fast.copy_from_slice(lp.history());
                snap.t_state = t_state;
                let mut first = Chunk::new(spec.horizon, spec.action_dim);
                let head_ref = &mut head;
                let first_ref = &mut first;
                let snap_ref = &snap;
                let mut interrupted = false;
                std::thread::scope(|ws| -> Result<()> {
                    let h = ws
                        .spawn(move || head_ref.warm_start(snap_ref, cfg.initial_delay, first_ref));
                    let mut kept = Ok(());
                    while !h.is_finished() {
                        if !interrupted && requested() {
                            // The warm start cannot be cut short; the robot is told to stop
                            // now rather than when it returns.
                            interrupted = true;
                            stop_once(&mut actuator, &mut stopped);
                        }
                        if kept.is_ok() {
                            kept = keepalive(&mut fast);
                        }
                        std::thread::sleep(Duration::from_millis(1));
                    }
                    h.join().map_err(|p| Error::panicked("warm start", &*p))??;
                    kept
                })?;
                Ok((!interrupted && !requested()).then_some(first))
            })();
            let mut first = match warm {
                Ok(Some(c)) => c,
                Ok(None) => {
                    lp.control
                        .metrics
                        .events
                        .push("stop requested during the warm-up; the robot never moved".into());
                    return Ok(std::mem::take(&mut lp.control.metrics));
                }
                Err(e) => return Err(e),
            };
            lp.control.deliver(&mut first);
            head.watch_stop(stop_signal.clone());
            let head_ref = &mut head;
            let clock_ref: &dyn Clock = &*clock;
            let sh = &*shared;
            worker = Some(s.spawn(move || {
                let r = catch_unwind(AssertUnwindSafe(|| {
                    action_worker(sh, head_ref, clock_ref, slow_inline)
                }));
                match r {
                    // A call the model gave up because the run is stopping is no error.
                    Ok(Ok(())) | Ok(Err(Error::Abandoned)) => {}
                    Ok(Err(e)) => sh.fail(e),
                    Err(p) => sh.fail(Error::panicked("action worker", &*p)),
                }
            }));

            if let Some(prio) = cfg.rt_priority {
                if let Err(e) = set_fifo_priority(prio) {
                    lp.control
                        .metrics
                        .events
                        .push(format!("SCHED_FIFO priority {prio} refused: {e}"));
                }
            }
            // Deadlines run from `anchor`; a tick more than a period late moves the anchor to
            // itself, so missed deadlines are dropped instead of fired back to back.
            let mut anchor = clock.now();
            let mut k = 0u64;
            let mut tick = 0u64;
            loop {
                if stop.load(Ordering::Acquire) || shared.stop.load(Ordering::Acquire) {
                    break;
                }
                if cfg.max_ticks.is_some_and(|m| tick >= m) {
                    break;
                }
                let deadline = anchor + k * cfg.period;
                clock.sleep_until(deadline);
                let now = clock.now();
                let late = now.saturating_sub(deadline);
                lp.control.metrics.tick_jitter.record(late);
                if late >= cfg.period {
                    lp.control.metrics.late_ticks += 1;
                    anchor = now;
                    k = 0;
                }
                if let Err(e) = lp.tick(&shared, &mut fast, &mut actuator) {
                    shared.fail(e);
                    break;
                }
                lp.control
                    .metrics
                    .tick_overhead
                    .record(clock.now().saturating_sub(now));
                k += 1;
                tick += 1;
            }
            Ok(std::mem::take(&mut lp.control.metrics))
        }));
        // Stop the robot first, then wind the workers down (a worker may be inside a long
        // model call or capture).
        stop_once(&mut actuator, &mut stopped);
        shared.stop.store(true, Ordering::SeqCst);
        stop_signal.raise();
        shared.fast_cv.notify_all();
        if let Some(w) = worker {
            if let Err(p) = w.join() {
                shared.fail(Error::panicked("action worker", &*p));
            }
        }
        body.unwrap_or_else(|p| Err(Error::panicked("control thread", &*p)))
    });
    stop_once(&mut actuator, &mut stopped);
    let mut left_behind = false;
    if let Some(h) = slow_handle {
        let t0 = Instant::now();
        while !h.is_finished() && t0.elapsed() < SLOW_JOIN_WAIT {
            std::thread::sleep(Duration::from_millis(1));
        }
        if h.is_finished() {
            if let Err(p) = h.join() {
                shared.fail(Error::panicked("slow worker", &*p));
            }
        } else {
            left_behind = true;
        }
    }
    let mut metrics = result?;
    if let Some(e) = shared
        .error
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .take()
    {
        *failed = Some(metrics);
        return Err(e);
    }
    if let Err(e) = stopped.unwrap_or(Ok(())) {
        *failed = Some(metrics);
        return Err(e);
    }
    if left_behind {
        metrics
            .events
            .push("the slow worker was still capturing at the end; left to finish".into());
    }
    Ok((metrics, head))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::MockClock;
    use crate::control::CallPolicy;
    use crate::testing::FakeRobot;

    fn setup() -> (Arc<Shared>, ControlLoop, FakeRobot) {
        let (h, a, f, n_obs) = (16, 3, 6, 2);
        let clock: Arc<dyn Clock> = Arc::new(MockClock::new());
        let robot = FakeRobot::new(a, clock);
        let cfg = ControlConfig {
            horizon: h,
            action_dim: a,
            policy: CallPolicy::Async,
            ensemble: None,
            output: Default::default(),
        };
        let mut lp = ControlLoop::new(ControlState::new(cfg).unwrap(), n_obs, f);
        let mut first = Chunk::new(h, a);
        first.clean.fill(true);
        lp.control.deliver(&mut first);
        (Shared::new(n_obs, f, h, a), lp, robot)
    }

    fn chunk(latency: Nanos) -> Chunk {
        let mut c = Chunk::new(16, 3);
        c.clean.fill(true);
        c.call.latency = latency;
        c
    }

    /// Call 1 ends and call 2 starts between two ticks: the tick delivers call 1 and still
    /// knows call 2 is in flight (before: "the number changed" marked a call in flight,
    /// then the delivery of call 1 cleared it, so the control thread asked for calls while
    /// call 2 ran, and call 2's chunk was overwritten by call 3's before it was taken; a
    /// 1.6 s call through a policy-server outage vanished from the trace that way).
    #[test]
    fn a_call_started_between_ticks_stays_in_flight_after_the_previous_delivery() {
        let (shared, mut lp, mut robot) = setup();
        let mut act = robot.clone();
        lp.tick(&shared, &mut robot, &mut act).unwrap();
        assert!(shared.wants_call.load(Ordering::Acquire));

        shared.begin_call(1);
        shared.publish_chunk(1, &mut chunk(1_000_000));
        shared.begin_call(2);
        lp.tick(&shared, &mut robot, &mut act).unwrap();
        // The warm-start chunk (latency 0) and call 1.
        assert_eq!(lp.control.metrics.calls.len(), 2);
        assert!(
            !shared.wants_call.load(Ordering::Acquire),
            "call 2 is in flight: no new call may be asked for"
        );
        assert!(!shared.chunk_pending.load(Ordering::Acquire));

        // Call 2 takes many ticks; nothing is asked for meanwhile.
        for _ in 0..5 {
            lp.tick(&shared, &mut robot, &mut act).unwrap();
            assert!(!shared.wants_call.load(Ordering::Acquire));
        }
        shared.publish_chunk(2, &mut chunk(1_600_000_000));
        assert!(shared.chunk_pending.load(Ordering::Acquire));
        lp.tick(&shared, &mut robot, &mut act).unwrap();
        assert!(shared.wants_call.load(Ordering::Acquire));
        let lat: Vec<Nanos> = lp.control.metrics.calls.iter().map(|c| c.latency).collect();
        assert_eq!(lat, [0, 1_000_000, 1_600_000_000]);
    }

    /// A finished chunk the control thread has not taken holds the worker back: the worker
    /// waits on `chunk_pending`, so the next chunk never replaces it.
    #[test]
    fn a_pending_chunk_is_taken_once_and_then_released() {
        let (shared, mut lp, mut robot) = setup();
        let mut act = robot.clone();
        shared.begin_call(1);
        shared.publish_chunk(1, &mut chunk(5));
        assert!(shared.chunk_pending.load(Ordering::Acquire));
        // The control thread is inside a tick holding nothing; a try_lock miss leaves it.
        {
            let _g = shared.chunk.lock().unwrap();
            lp.tick(&shared, &mut robot, &mut act).unwrap();
        }
        assert!(shared.chunk_pending.load(Ordering::Acquire));
        assert!(
            !shared.wants_call.load(Ordering::Acquire),
            "call 1 not delivered yet"
        );
        lp.tick(&shared, &mut robot, &mut act).unwrap();
        assert!(!shared.chunk_pending.load(Ordering::Acquire));
        assert!(shared.wants_call.load(Ordering::Acquire));
        assert_eq!(lp.control.metrics.calls.len(), 2);
    }
}
