//! Real-time driver tests with sleeping fake models (bounded: a few seconds in total).

use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::realtime::{run, RealtimeConfig, SlowChannel};
use pir2_runtime::testing::{CameraStub, FakeRobot, PassThroughEncoder, SleepyModel};
use pir2_runtime::*;
use pir2_schedule::{Alignment, FrontMode};

const PERIOD: Nanos = 20_000_000;

fn go(model_ms: u64, ticks: u64, slow: bool) -> RunMetrics {
    let model = SleepyModel {
        latency: Duration::from_millis(model_ms),
    };
    let (m, _) = drive(model, ticks, slow, RealtimeConfig::default().stall_limit);
    m.unwrap()
}

/// `model` in πR² async (H = 16, 3 actions, d_max 5) on a [`FakeRobot`] for `ticks` 20 ms
/// ticks, with a slow channel if `slow`: the run's metrics (or error) and the robot.
fn drive<M: VelocityModel>(
    model: M,
    ticks: u64,
    slow: bool,
    stall_limit: Option<Duration>,
) -> (pir2_runtime::Result<RunMetrics>, FakeRobot) {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let spec = HeadSpec {
        horizon: 16,
        action_dim: 3,
        n_obs: 2,
        fast_dim: 6,
        slow_dim: if slow { 4 } else { 0 },
        period: PERIOD,
        d_max: 5,
        d_vis_max: 5,
    };
    let mode = HeadMode::PiR2 {
        nfe: Some(2),
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
        warm_start_steps: 2,
    };
    let head = ActionHead::new(
        model,
        spec,
        mode,
        LatencyWindow::new(20, 2, PERIOD, spec.d_max),
        0,
    )
    .unwrap();
    let robot = FakeRobot::new(3, clock.clone());
    let control = ControlConfig {
        horizon: 16,
        action_dim: 3,
        policy: CallPolicy::Async,
        ensemble: None,
        output: Default::default(),
    };
    let slow_ch = if slow {
        SlowChannel::Async {
            source: Box::new(CameraStub::new(clock.clone(), Duration::from_millis(30), 4)),
            encoder: Box::new(PassThroughEncoder {
                latency: Duration::from_millis(10),
            }),
        }
    } else {
        SlowChannel::None
    };
    let cfg = RealtimeConfig {
        period: PERIOD,
        max_ticks: Some(ticks),
        stall_limit,
        ..Default::default()
    };
    let r = run(
        head,
        control,
        robot.clone(),
        robot.clone(),
        slow_ch,
        clock,
        cfg,
        Arc::new(AtomicBool::new(false)),
    );
    (r.map(|(m, _)| m), robot)
}

fn median_d(m: &RunMetrics) -> usize {
    let mut ds: Vec<usize> = m.calls.iter().skip(25).map(|c| c.d).collect();
    ds.sort();
    ds[ds.len() / 2]
}

#[test]
fn measures_d_from_call_latency() {
    // 2 ms calls at 20 ms ticks → d = 1; 45 ms calls → 2.25 ticks → d = 2.
    let fast = go(2, 60, false);
    assert_eq!(
        median_d(&fast),
        1,
        "{:?}",
        fast.calls.iter().map(|c| c.d).collect::<Vec<_>>()
    );
    assert!(fast.swaps >= 50, "swaps {}", fast.swaps);
    let slow = go(45, 90, false);
    assert_eq!(
        median_d(&slow),
        2,
        "{:?}",
        slow.calls
            .iter()
            .map(|c| (c.d, c.latency / 1_000_000))
            .collect::<Vec<_>>()
    );
    // Swaps at the elapsed index: ≥ 3 ticks for 45 ms calls.
    assert!(
        slow.calls.iter().skip(5).all(|c| c.elapsed >= 2),
        "{:?}",
        slow.calls.iter().map(|c| c.elapsed).collect::<Vec<_>>()
    );
}

#[test]
fn slow_worker_feeds_d_vis() {
    let m = go(2, 60, true);
    // Frames every ~40 ms (30 ms capture + 10 ms encode), stamped at capture: d_vis ∈ [0, 3].
    let dv: Vec<usize> = m.calls.iter().skip(10).map(|c| c.d_vis).collect();
    // A loaded machine can stall the slow worker for a few ticks (seen in CI: three calls at
    // 5); features that stopped refreshing would sit at the clamp for every later call.
    let fresh = dv.iter().filter(|&&d| d <= 4).count();
    assert!(fresh * 10 >= dv.len() * 9, "{dv:?}");
    assert!(dv.iter().rev().take(5).all(|&d| d <= 4), "{dv:?}");
    assert!(
        dv.iter().any(|&d| d >= 1),
        "slow features never aged: {dv:?}"
    );
}

/// A robot whose state stream records when it was read.
struct Recorded {
    inner: FakeRobot,
    reads: Arc<std::sync::Mutex<Vec<Nanos>>>,
}

impl FastSource for Recorded {
    fn dim(&self) -> usize {
        FastSource::dim(&self.inner)
    }
    fn read(&mut self, out: &mut [f32]) -> Result<Nanos> {
        let t = self.inner.read(out)?;
        self.reads.lock().unwrap().push(t);
        Ok(t)
    }
}

/// A slow first frame (150 ms encoder) and a slow warm start (3 × 60 ms calls) must not leave
/// the robot's state stream unread for longer than a few ticks: robot drivers and the safety
/// layer stop the robot on a stale state (200 ms by default).
#[test]
fn state_is_read_every_tick_while_warming_up() {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let spec = HeadSpec {
        horizon: 16,
        action_dim: 3,
        n_obs: 2,
        fast_dim: 6,
        slow_dim: 4,
        period: PERIOD,
        d_max: 5,
        d_vis_max: 5,
    };
    let mode = HeadMode::PiR2 {
        nfe: Some(2),
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
        warm_start_steps: 3,
    };
    let head = ActionHead::new(
        SleepyModel {
            latency: Duration::from_millis(60),
        },
        spec,
        mode,
        LatencyWindow::new(20, 2, PERIOD, spec.d_max),
        0,
    )
    .unwrap();
    let robot = FakeRobot::new(3, clock.clone());
    let reads = Arc::new(std::sync::Mutex::new(Vec::new()));
    let source = Recorded {
        inner: robot.clone(),
        reads: reads.clone(),
    };
    let control = ControlConfig {
        horizon: 16,
        action_dim: 3,
        policy: CallPolicy::Async,
        ensemble: None,
        output: Default::default(),
    };
    let slow = SlowChannel::Async {
        source: Box::new(CameraStub::new(clock.clone(), Duration::from_millis(30), 4)),
        encoder: Box::new(PassThroughEncoder {
            latency: Duration::from_millis(150),
        }),
    };
    let cfg = RealtimeConfig {
        period: PERIOD,
        max_ticks: Some(10),
        ..Default::default()
    };
    let t0 = clock.now();
    run(
        head,
        control,
        source,
        robot,
        slow,
        clock.clone(),
        cfg,
        Arc::new(AtomicBool::new(false)),
    )
    .unwrap();
    let reads = reads.lock().unwrap();
    let mut prev = t0;
    let mut max_gap = 0;
    for &t in reads.iter() {
        max_gap = max_gap.max(t - prev);
        prev = t;
    }
    // The warm-up alone took ≥ 150 + 3 × 60 ms; reads kept coming at about one per tick.
    assert!(reads.len() >= 10 + 10, "{} reads", reads.len());
    assert!(
        max_gap < 5 * PERIOD,
        "state unread for {} ms",
        max_gap / 1_000_000
    );
}

// ---- fail closed -------------------------------------------------------------------------

fn small_spec(slow_dim: usize) -> HeadSpec {
    HeadSpec {
        horizon: 16,
        action_dim: 3,
        n_obs: 2,
        fast_dim: 6,
        slow_dim,
        period: PERIOD,
        d_max: 5,
        d_vis_max: 5,
    }
}

fn small_head<M: VelocityModel>(model: M, spec: HeadSpec) -> ActionHead<M> {
    let mode = HeadMode::PiR2 {
        nfe: Some(2),
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
        warm_start_steps: 2,
    };
    ActionHead::new(
        model,
        spec,
        mode,
        LatencyWindow::new(20, 2, PERIOD, spec.d_max),
        0,
    )
    .unwrap()
}

fn small_control() -> ControlConfig {
    ControlConfig {
        horizon: 16,
        action_dim: 3,
        policy: CallPolicy::Async,
        ensemble: None,
        output: Default::default(),
    }
}

/// Run `f` on a thread; `None` if it has not returned within `limit` (the run hangs).
fn bounded<T: Send + 'static>(
    limit: Duration,
    f: impl FnOnce() -> T + Send + 'static,
) -> Option<T> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(limit).ok()
}

/// A model that panics on its `n`-th call.
struct PanicsAt {
    n: u32,
    calls: u32,
}

impl VelocityModel for PanicsAt {
    fn backend(&self) -> &'static str {
        "panics"
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        self.calls += 1;
        if self.calls == self.n {
            panic!("model exploded at call {}", self.calls);
        }
        std::thread::sleep(Duration::from_millis(2));
        for (o, x) in out.iter_mut().zip(input.x) {
            *o = -x;
        }
        Ok(())
    }
}

/// A panic in the user's model on the action worker stops the robot and ends the run with an
/// error naming the worker (before: the panic was swallowed, the control thread kept
/// replaying the last chunk to the end, and the run returned Ok).
#[test]
fn a_panicking_model_stops_the_robot_and_names_the_action_worker() {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let spec = small_spec(0);
    // Warm start makes 2 calls; the 6th call is on the action worker.
    let head = small_head(PanicsAt { n: 6, calls: 0 }, spec);
    let robot = FakeRobot::new(3, clock.clone());
    let (sent, stops) = (robot.sent.clone(), robot.stops.clone());
    let cfg = RealtimeConfig {
        period: PERIOD,
        max_ticks: Some(100),
        ..Default::default()
    };
    let r = bounded(Duration::from_secs(20), move || {
        run(
            head,
            small_control(),
            robot.clone(),
            robot,
            SlowChannel::None,
            clock,
            cfg,
            Arc::new(AtomicBool::new(false)),
        )
        .map(|_| ())
    })
    .expect("the run hung");
    let e = r.expect_err("a panicking model must end the run with an error");
    assert!(
        matches!(&e, Error::Panicked { thread: "action worker", message } if message.contains("model exploded")),
        "{e}"
    );
    assert_eq!(stops.load(std::sync::atomic::Ordering::Relaxed), 1);
    assert!(
        sent.load(std::sync::atomic::Ordering::Relaxed) < 100,
        "the robot kept moving after the panic"
    );
}

/// An actuator that panics on its `n`-th send.
#[derive(Clone)]
struct PanickyArm {
    inner: FakeRobot,
    n: u64,
}

impl Actuator for PanickyArm {
    fn dim(&self) -> usize {
        Actuator::dim(&self.inner)
    }
    fn send(&mut self, action: &[f32]) -> Result<()> {
        if self.inner.sent.load(std::sync::atomic::Ordering::Relaxed) + 1 == self.n {
            panic!("actuator driver bug");
        }
        self.inner.send(action)
    }
    fn stop(&mut self) -> Result<()> {
        self.inner.stop()
    }
}

/// A panic in the user's actuator on the control thread stops the robot and returns an error
/// naming the control thread (before: the panic left the action worker waiting forever and
/// the process hung).
#[test]
fn a_panicking_actuator_ends_the_run_instead_of_hanging() {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let head = small_head(
        SleepyModel {
            latency: Duration::from_millis(2),
        },
        small_spec(0),
    );
    let robot = FakeRobot::new(3, clock.clone());
    let stops = robot.stops.clone();
    let arm = PanickyArm {
        inner: robot.clone(),
        n: 5,
    };
    let cfg = RealtimeConfig {
        period: PERIOD,
        max_ticks: Some(50),
        ..Default::default()
    };
    let r = bounded(Duration::from_secs(20), move || {
        run(
            head,
            small_control(),
            robot,
            arm,
            SlowChannel::None,
            clock,
            cfg,
            Arc::new(AtomicBool::new(false)),
        )
        .map(|_| ())
    })
    .expect("the run hung after a panic on the control thread");
    let e = r.expect_err("a panicking actuator must end the run with an error");
    assert!(
        matches!(&e, Error::Panicked { thread: "control thread", message } if message.contains("actuator driver bug")),
        "{e}"
    );
    assert_eq!(stops.load(std::sync::atomic::Ordering::Relaxed), 1);
}

/// A camera whose first frame takes 5 s.
struct SlowFirstFrame(Arc<dyn Clock>);

#[async_trait::async_trait]
impl SlowSource for SlowFirstFrame {
    async fn capture(&mut self) -> Result<SlowFrame> {
        std::thread::sleep(Duration::from_secs(5));
        Ok(SlowFrame {
            t_capture: self.0.now(),
            values: vec![0.0; 4],
            ..Default::default()
        })
    }
}

/// The stop flag is honoured while waiting for the first slow features: the robot is stopped
/// and the run returns at once (before: the flag was ignored until the warm-up ended, here
/// 5 s, up to the 60 s slow timeout of `pir2 gr00t run`).
#[test]
fn stop_during_warm_up_stops_the_robot_at_once() {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let head = small_head(
        SleepyModel {
            latency: Duration::from_millis(1),
        },
        small_spec(4),
    );
    let robot = FakeRobot::new(3, clock.clone());
    let (sent, stops) = (robot.sent.clone(), robot.stops.clone());
    let slow = SlowChannel::Async {
        source: Box::new(SlowFirstFrame(clock.clone())),
        encoder: Box::new(PassThroughEncoder {
            latency: Duration::ZERO,
        }),
    };
    let cfg = RealtimeConfig {
        period: PERIOD,
        max_ticks: Some(50),
        slow_timeout: Duration::from_secs(60),
        ..Default::default()
    };
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(100));
        flag.store(true, std::sync::atomic::Ordering::SeqCst);
    });
    let t0 = std::time::Instant::now();
    let (m, _) = run(
        head,
        small_control(),
        robot.clone(),
        robot,
        slow,
        clock,
        cfg,
        stop,
    )
    .unwrap();
    let took = t0.elapsed();
    assert!(took < Duration::from_secs(3), "returned after {took:?}");
    assert_eq!(stops.load(std::sync::atomic::Ordering::Relaxed), 1);
    assert_eq!(sent.load(std::sync::atomic::Ordering::Relaxed), 0);
    assert_eq!(m.ticks, 0);
    assert!(
        m.events.iter().any(|e| e.contains("warm-up")),
        "{:?}",
        m.events
    );
}

/// An actuator that records the (mock) time of each send and stalls the clock by 3.5
/// periods after its `stall_at`-th send (the control thread was descheduled).
struct Timed {
    inner: FakeRobot,
    clock: MockClock,
    at: Arc<std::sync::Mutex<Vec<Nanos>>>,
    stall_at: usize,
}

impl Actuator for Timed {
    fn dim(&self) -> usize {
        Actuator::dim(&self.inner)
    }
    fn send(&mut self, action: &[f32]) -> Result<()> {
        let mut at = self.at.lock().unwrap();
        at.push(self.clock.now());
        if at.len() == self.stall_at {
            self.clock.advance(7 * PERIOD / 2);
        }
        self.inner.send(action)
    }
    fn stop(&mut self) -> Result<()> {
        self.inner.stop()
    }
}

/// After a late tick the missed deadlines are skipped: no two sends closer than a period
/// (before: the three missed ticks fired back to back at the same instant).
#[test]
fn an_overrun_is_not_caught_up_in_a_burst() {
    let mock = MockClock::new();
    let clock: Arc<dyn Clock> = Arc::new(mock.clone());
    let head = small_head(
        SleepyModel {
            latency: Duration::ZERO,
        },
        small_spec(0),
    );
    let robot = FakeRobot::new(3, clock.clone());
    let at = Arc::new(std::sync::Mutex::new(Vec::new()));
    let act = Timed {
        inner: robot.clone(),
        clock: mock,
        at: at.clone(),
        stall_at: 10,
    };
    let cfg = RealtimeConfig {
        period: PERIOD,
        max_ticks: Some(30),
        ..Default::default()
    };
    let (m, _) = run(
        head,
        small_control(),
        robot,
        act,
        SlowChannel::None,
        clock,
        cfg,
        Arc::new(AtomicBool::new(false)),
    )
    .unwrap();
    let at = at.lock().unwrap();
    assert_eq!(at.len(), 30);
    let min_gap = at.windows(2).map(|w| w[1] - w[0]).min().unwrap();
    assert!(min_gap >= PERIOD, "sends {} ns apart", min_gap);
    assert_eq!(m.late_ticks, 1);
}

/// A model that answers in 2 ms for `healthy` calls, then hangs for `hang` on every call.
struct HangsAfter {
    healthy: usize,
    calls: usize,
    hang: Duration,
}

impl VelocityModel for HangsAfter {
    fn backend(&self) -> &'static str {
        "hangs-after"
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        self.calls += 1;
        std::thread::sleep(if self.calls > self.healthy {
            self.hang
        } else {
            Duration::from_millis(2)
        });
        for (o, x) in out.iter_mut().zip(input.x) {
            *o = -x;
        }
        Ok(())
    }
}

/// The control watchdog: a policy whose calls stop returning runs its chunk out and then
/// holds; past `stall_limit` without a clean action the run stops the robot with a safety
/// stop naming the watchdog (before: the last action was held until the run's end, forever
/// without `--ticks`). Without the bound the same run holds to its end.
#[test]
fn a_stalled_policy_is_stopped_by_the_control_watchdog() {
    let go = |stall_limit: Option<Duration>| {
        let model = HangsAfter {
            healthy: 30,
            calls: 0,
            hang: Duration::from_secs(3),
        };
        drive(model, 100, false, stall_limit)
    };
    use std::sync::atomic::Ordering;
    let (r, robot) = go(Some(Duration::from_millis(200)));
    let e = r.unwrap_err();
    assert!(
        matches!(&e, Error::SafetyStop(m) if m.contains("control watchdog")),
        "{e}"
    );
    assert!(
        robot.stops.load(Ordering::Relaxed) >= 1,
        "the robot was not stopped"
    );
    // ~30 ticks of 2-ms calls, the rest of the last chunk, then 200 ms (10 ticks) without a
    // clean action: well before the run's 100 ticks.
    let sent = robot.sent.load(Ordering::Relaxed);
    assert!(sent < 80, "sent {sent} commands");
    // Without the watchdog the run holds to its last tick.
    let (r, _) = go(None);
    let m = r.unwrap();
    assert_eq!(m.ticks, 100);
    assert!(m.holds > 10, "holds {}", m.holds);
}
