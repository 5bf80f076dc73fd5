//! The remote slow channel and action head end to end: `realtime::run` with a fake robot on
//! one side, `serve_policy` / `serve_slow` on the other, over TCP on 127.0.0.1 (test-chosen
//! free ports). Servers run in threads with their own Zenoh sessions; "killing" a server
//! stops it and closes its session. Bounded: each test runs a few seconds at most.
#![cfg(feature = "remote")]

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use pir2_runtime::realtime::{run, RealtimeConfig, SlowChannel};
use pir2_runtime::remote::{
    remote_slow_channel, serve_policy, serve_slow, Link, PolicyServerConfig, RemoteModel,
    RemoteModelConfig, RemoteSlowConfig, RemoteStats, SlowServerConfig,
};
use pir2_runtime::testing::{CameraStub, FakeRobot, PassThroughEncoder, SleepyModel};
use pir2_runtime::*;
use pir2_schedule::{Alignment, FrontMode};

const PERIOD: Nanos = 20_000_000;
const SEC: Nanos = 1_000_000_000;

/// A clock `offset` ns ahead of a shared base: two "machines" whose true offset is known.
#[derive(Debug)]
struct OffsetClock {
    base: Arc<SystemClock>,
    offset: Nanos,
}

impl Clock for OffsetClock {
    fn now(&self) -> Nanos {
        self.base.now() + self.offset
    }
    fn sleep_until(&self, deadline: Nanos) {
        self.base.sleep_until(deadline.saturating_sub(self.offset));
    }
}

fn clock(base: &Arc<SystemClock>, offset: Nanos) -> Arc<dyn Clock> {
    Arc::new(OffsetClock {
        base: base.clone(),
        offset,
    })
}

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

fn ep(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

struct Server {
    stop: Arc<AtomicBool>,
    handle: JoinHandle<pir2_runtime::remote::Result<()>>,
}

impl Server {
    /// Stop the server and close its session (the robot sees it vanish).
    fn kill(self) {
        self.stop.store(true, Ordering::SeqCst);
        self.handle.join().unwrap().unwrap();
    }
}

fn policy_server(port: u16, model_ms: u64, reply_delay: Duration) -> Server {
    let stop = Arc::new(AtomicBool::new(false));
    let cfg = PolicyServerConfig {
        link: Link::listen(ep(port)),
        key: "test/policy".into(),
        reply_delay,
        ..Default::default()
    };
    let s = stop.clone();
    let handle = std::thread::spawn(move || {
        serve_policy(
            SleepyModel {
                latency: Duration::from_millis(model_ms),
            },
            &cfg,
            s,
        )
    });
    Server { stop, handle }
}

fn slow_server(port: u16, clock: Arc<dyn Clock>) -> Server {
    let stop = Arc::new(AtomicBool::new(false));
    let cfg = SlowServerConfig {
        link: Link::listen(ep(port)),
        key: "test/slow".into(),
    };
    let s = stop.clone();
    let handle = std::thread::spawn(move || {
        serve_slow(
            Box::new(CameraStub::new(clock.clone(), Duration::from_millis(30), 4)),
            Box::new(PassThroughEncoder {
                latency: Duration::from_millis(10),
            }),
            clock,
            &cfg,
            s,
        )
    });
    Server { stop, handle }
}

fn remote_model(port: u16, timeout_ms: u64, max_failed: u32) -> RemoteModel {
    RemoteModel::connect(RemoteModelConfig {
        link: Link {
            retry: Duration::from_millis(20),
            ..Link::connect(ep(port))
        },
        key: "test/policy".into(),
        timeout: Duration::from_millis(timeout_ms),
        max_failed_calls: max_failed,
        connect_timeout: Duration::from_secs(5),
    })
    .unwrap()
}

fn remote_slow(port: u16, robot_clock: Arc<dyn Clock>) -> (SlowChannel, Arc<RemoteStats>) {
    remote_slow_channel(
        RemoteSlowConfig {
            link: Link {
                retry: Duration::from_millis(20),
                ..Link::connect(ep(port))
            },
            key: "test/slow".into(),
            stale_poll: Duration::from_millis(100), // frames every ~40 ms
            first_timeout: Duration::from_secs(5),
            ..Default::default()
        },
        robot_clock,
    )
    .unwrap()
}

struct Run {
    result: Result<(RunMetrics, ActionHead<RemoteModel>)>,
    sent: u64,
}

fn go(
    model: RemoteModel,
    slow: Option<SlowChannel>,
    robot_clock: Arc<dyn Clock>,
    ticks: u64,
    slow_grace: Option<Nanos>,
) -> Run {
    let spec = HeadSpec {
        horizon: 16,
        action_dim: 3,
        n_obs: 2,
        fast_dim: 6,
        slow_dim: if slow.is_some() { 4 } else { 0 },
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
    let mut head = ActionHead::new(
        model,
        spec,
        mode,
        LatencyWindow::new(20, 2, PERIOD, spec.d_max),
        0,
    )
    .unwrap();
    head.set_slow_grace(slow_grace);
    let robot = FakeRobot::new(3, robot_clock.clone());
    let sent = robot.sent.clone();
    let control = ControlConfig {
        horizon: 16,
        action_dim: 3,
        policy: CallPolicy::Async,
        ensemble: None,
        output: Default::default(),
    };
    let cfg = RealtimeConfig {
        period: PERIOD,
        max_ticks: Some(ticks),
        ..Default::default()
    };
    let result = run(
        head,
        control,
        robot.clone(),
        robot,
        slow.unwrap_or(SlowChannel::None),
        robot_clock,
        cfg,
        Arc::new(AtomicBool::new(false)),
    );
    Run {
        result,
        sent: sent.load(Ordering::SeqCst),
    }
}

fn median(mut v: Vec<usize>) -> usize {
    v.sort_unstable();
    v[v.len() / 2]
}

#[test]
fn remote_realtime_run_end_to_end_converts_capture_times() {
    let base = Arc::new(SystemClock::new());
    // The robot's clock is 3 s ahead of the servers': without the offset correction every
    // slow feature would look 150 ticks old (d_vis clamped to 5).
    let robot_clock = clock(&base, 3 * SEC);
    let (pp, sp) = (free_port(), free_port());
    let policy = policy_server(pp, 2, Duration::ZERO);
    let slow = slow_server(sp, clock(&base, 0));
    let model = remote_model(pp, 500, 10);
    let policy_stats = model.stats();
    let (slow_ch, slow_stats) = remote_slow(sp, robot_clock.clone());
    let r = go(model, Some(slow_ch), robot_clock, 75, Some(SEC));
    let (m, _) = r.result.expect("remote run");
    policy.kill();
    slow.kill();

    assert_eq!(m.ticks, 75);
    assert!(m.swaps >= 10, "swaps {}", m.swaps);
    let p = policy_stats.counters();
    assert!(p.calls >= m.swaps, "{p:?}");
    assert_eq!(
        (p.timeouts, p.failed_calls, p.server_errors),
        (0, 0, 0),
        "{p:?}"
    );
    let s = slow_stats.counters();
    assert!(s.frames >= 5, "{s:?}");
    assert!(s.clock_syncs >= 1 && s.reconnects == 0, "{s:?}");
    // Min-RTT estimate: the error is at most half the chosen sample's round trip.
    let err = (s.offset_ns + 3 * SEC as i64).unsigned_abs();
    assert!(
        err <= s.offset_rtt_ns / 2 + 1,
        "offset error {err} ns > RTT/2 = {} ns",
        s.offset_rtt_ns / 2
    );
    // Camera 30 ms + backbone 10 ms + transport: a few ticks, never the clamp.
    let d_vis = median(m.calls.iter().map(|c| c.d_vis).collect());
    assert!(d_vis <= 3, "median d_vis {d_vis}");
}

#[test]
fn injected_network_delay_raises_d() {
    let (pp,) = (free_port(),);
    // Every reply waits 45 ms: a call takes > 2.25 ticks, so the window's d ≥ 2.
    let policy = policy_server(pp, 0, Duration::from_millis(45));
    let model = remote_model(pp, 500, 10);
    let r = go(model, None, Arc::new(SystemClock::new()), 50, None);
    let (m, _) = r.result.expect("remote run");
    policy.kill();
    let ds: Vec<usize> = m.calls.iter().skip(4).map(|c| c.d).collect();
    assert!(!ds.is_empty());
    assert!(ds.iter().all(|&d| d >= 2), "d per call {ds:?}");
    assert!(m.calls.iter().skip(1).all(|c| c.latency >= 45_000_000));
}

#[test]
fn policy_server_restart_mid_run_is_survived_and_counted() {
    let pp = free_port();
    let policy = policy_server(pp, 2, Duration::ZERO);
    let model = remote_model(pp, 50, 60);
    let stats = model.stats();
    let robot_clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let runner = std::thread::spawn(move || go(model, None, robot_clock, 100, None));
    // Kill the server once the run is ticking (the warm start is a few calls; a fixed sleep
    // could land in the warm start on a loaded machine, whose latency is not traced).
    let t0 = std::time::Instant::now();
    while stats.counters().calls < 15 {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "the run never started calling"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    std::thread::sleep(Duration::from_millis(200));
    policy.kill();
    std::thread::sleep(Duration::from_millis(400));
    let policy = policy_server(pp, 2, Duration::ZERO);
    let r = runner.join().unwrap();
    policy.kill();
    let (m, _) = r.result.expect("the run survives a policy server restart");
    let c = stats.counters();
    assert!(c.timeouts >= 1, "{c:?}");
    assert!(c.reconnects >= 1, "{c:?}");
    // The new instance refused the old session (a foreign reply): the client shook hands
    // with it again before using its replies.
    assert!(c.foreign_replies >= 1, "{c:?}");
    assert_eq!(c.failed_calls, 0, "{c:?}");
    assert_eq!(c.attempts, c.calls + c.timeouts, "{c:?}");
    // The 400 ms outage outlasts the clean slots: the overrun path ran.
    assert!(m.overruns > 0, "overruns {}", m.overruns);
    assert_eq!(r.sent, 100);
    // The outage call's latency is in the trace (the window saw it).
    let max_latency = m.calls.iter().map(|c| c.latency).max().unwrap();
    assert!(max_latency >= 300_000_000, "max latency {max_latency}");
}

#[test]
fn policy_server_gone_stops_the_robot_safely() {
    let pp = free_port();
    let policy = policy_server(pp, 2, Duration::ZERO);
    let model = remote_model(pp, 30, 3);
    let stats = model.stats();
    let robot_clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let runner = std::thread::spawn(move || go(model, None, robot_clock, 500, None));
    std::thread::sleep(Duration::from_millis(400));
    policy.kill();
    let r = runner.join().unwrap();
    match r.result {
        Err(Error::SafetyStop(msg)) => assert!(msg.contains("unreachable"), "{msg}"),
        Err(e) => panic!("expected a safety stop, got {e}"),
        Ok(_) => panic!("expected a safety stop, the run completed"),
    }
    let c = stats.counters();
    assert_eq!((c.timeouts, c.failed_calls), (3, 1), "{c:?}");
    assert!(r.sent < 500, "sent {}", r.sent);
}

/// A run stopped by its control watchdog while the action worker's call is still retrying a
/// server that is gone: the robot stops first, then the call is abandoned (counted) instead
/// of retrying for `max_failed_calls × timeout` (here 5,000 × 30 ms = 150 s), so the run
/// ends in the watchdog's error well before that.
#[test]
fn a_call_still_retrying_when_the_run_stops_is_abandoned() {
    let pp = free_port();
    let policy = policy_server(pp, 2, Duration::ZERO);
    let model = remote_model(pp, 30, 5_000);
    let stats = model.stats();
    let robot_clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let t0 = std::time::Instant::now();
    let runner = std::thread::spawn(move || go(model, None, robot_clock, 100_000, None));
    std::thread::sleep(Duration::from_millis(400));
    policy.kill();
    let r = runner.join().unwrap();
    let took = t0.elapsed();
    match r.result {
        Err(Error::SafetyStop(msg)) => assert!(msg.contains("watchdog"), "{msg}"),
        Err(e) => panic!("expected the control watchdog's safety stop, got {e}"),
        Ok(_) => panic!("expected a safety stop, the run completed"),
    }
    let c = stats.counters();
    assert_eq!((c.abandoned, c.failed_calls), (1, 0), "{c:?}");
    assert!(took < Duration::from_secs(60), "the run took {took:?}");
}

#[test]
fn slow_server_restart_resyncs_the_clock_and_resumes() {
    let base = Arc::new(SystemClock::new());
    let robot_clock = clock(&base, 5 * SEC);
    let (pp, sp) = (free_port(), free_port());
    let policy = policy_server(pp, 2, Duration::ZERO);
    // First server 2 s ahead of the base, the restarted one at the base: keeping the old
    // offset would make every new feature look 2 s old and trip the safety stop.
    let slow = slow_server(sp, clock(&base, 2 * SEC));
    let model = remote_model(pp, 500, 10);
    let (slow_ch, stats) = remote_slow(sp, robot_clock.clone());
    let rc = robot_clock.clone();
    let runner = std::thread::spawn(move || go(model, Some(slow_ch), rc, 100, Some(SEC / 2)));
    std::thread::sleep(Duration::from_millis(700));
    slow.kill();
    std::thread::sleep(Duration::from_millis(200));
    let slow = slow_server(sp, clock(&base, 0));
    let r = runner.join().unwrap();
    policy.kill();
    slow.kill();
    let (m, _) = r.result.expect("the run survives a slow server restart");
    let c = stats.counters();
    assert_eq!(c.reconnects, 1, "{c:?}");
    assert!(c.clock_syncs >= 2, "{c:?}");
    assert!(c.stale_polls >= 1 && c.stale_episodes >= 1, "{c:?}");
    let err = (c.offset_ns + 5 * SEC as i64).unsigned_abs();
    assert!(err <= c.offset_rtt_ns / 2 + 1, "offset {c:?}");
    // The outage shows in d_vis, and the features are fresh again at the end.
    let max_dvis = m.calls.iter().map(|c| c.d_vis).max().unwrap();
    assert!(max_dvis >= 5, "max d_vis {max_dvis}");
    let tail: Vec<usize> = m.calls.iter().rev().take(5).map(|c| c.d_vis).collect();
    assert!(tail.iter().all(|&d| d <= 4), "last d_vis {tail:?}");
}

#[test]
fn slow_server_gone_stops_the_robot_once_d_vis_exceeds_its_max() {
    let (pp, sp) = (free_port(), free_port());
    let robot_clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let policy = policy_server(pp, 2, Duration::ZERO);
    let slow = slow_server(sp, robot_clock.clone());
    let model = remote_model(pp, 500, 10);
    let (slow_ch, stats) = remote_slow(sp, robot_clock.clone());
    let rc = robot_clock.clone();
    let runner = std::thread::spawn(move || go(model, Some(slow_ch), rc, 500, Some(SEC / 10)));
    std::thread::sleep(Duration::from_millis(500));
    slow.kill();
    let r = runner.join().unwrap();
    policy.kill();
    match r.result {
        Err(Error::SafetyStop(msg)) => assert!(msg.contains("slow features"), "{msg}"),
        Err(e) => panic!("expected a safety stop, got {e}"),
        Ok(_) => panic!("expected a safety stop, the run completed"),
    }
    let c = stats.counters();
    assert!(c.stale_polls >= 1 && c.stale_episodes == 1, "{c:?}");
    // Stopped within (d_vis_max + ½)·T + grace ≈ 0.21 s of the outage, long before 500 ticks.
    assert!(r.sent < 500, "sent {}", r.sent);
}

/// With no stale-slow grace on the head, a dead slow server still ends the run: the source
/// stops handing out the last features after `max_stale` (before: it re-served them forever
/// and the run went to its end on frozen features).
#[test]
fn slow_server_gone_ends_the_run_even_without_a_grace() {
    let (pp, sp) = (free_port(), free_port());
    let robot_clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let policy = policy_server(pp, 2, Duration::ZERO);
    let slow = slow_server(sp, robot_clock.clone());
    let model = remote_model(pp, 500, 10);
    let (slow_ch, stats) = remote_slow_channel(
        RemoteSlowConfig {
            link: Link {
                retry: Duration::from_millis(20),
                ..Link::connect(ep(sp))
            },
            key: "test/slow".into(),
            stale_poll: Duration::from_millis(100),
            first_timeout: Duration::from_secs(5),
            max_stale: Duration::from_millis(300),
            ..Default::default()
        },
        robot_clock.clone(),
    )
    .unwrap();
    let rc = robot_clock.clone();
    let runner = std::thread::spawn(move || go(model, Some(slow_ch), rc, 500, None));
    std::thread::sleep(Duration::from_millis(500));
    slow.kill();
    let t_kill = std::time::Instant::now();
    let r = runner.join().unwrap();
    let took = t_kill.elapsed();
    policy.kill();
    let Err(e) = r.result else {
        panic!("a dead slow server must end the run");
    };
    assert!(e.to_string().contains("fresh slow features"), "{e}");
    let c = stats.counters();
    assert!(c.frames >= 1 && c.stale_polls >= 1, "{c:?}");
    assert!(r.sent < 500, "sent {}", r.sent);
    assert!(
        took < Duration::from_secs(3),
        "ended {took:?} after the kill"
    );
}

// ---- bad messages ------------------------------------------------------------------------

/// A bare Zenoh session (not pir2's) that listens on or connects to `port` on 127.0.0.1:
/// a rogue peer or client of the tests below.
fn test_session(side: &str, port: u16) -> zenoh::Session {
    use zenoh::Wait;
    let mut c = zenoh::Config::default();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    c.insert_json5(&format!("{side}/endpoints"), &format!("[\"{}\"]", ep(port)))
        .unwrap();
    zenoh::open(c).wait().unwrap()
}

/// A model that panics on a batch of 2 and negates `x` otherwise.
struct PanicsOnBatch2;

impl VelocityModel for PanicsOnBatch2 {
    fn backend(&self) -> &'static str {
        "panics-on-2"
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        assert!(input.batch != 2, "a batch of 2 breaks this model");
        for (o, x) in out.iter_mut().zip(input.x) {
            *o = -x;
        }
        Ok(())
    }
}

/// Call `m` with a batch of `b`, H = 4, A = 2, one fast frame of 3 and `slow` floats a sample.
fn call(m: &mut RemoteModel, b: usize, slow: usize) -> pir2_runtime::remote::Result<Vec<f32>> {
    let (h, a) = (4, 2);
    let x: Vec<f32> = (0..b * h * a).map(|i| i as f32).collect();
    let tau = vec![0.5; b * h];
    let obs = vec![0.1; b * 3];
    let d_vis = vec![0u32; b];
    let s = vec![0.25; b * slow];
    let input = ModelInput {
        batch: b,
        horizon: h,
        action_dim: a,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: 1,
        fast_dim: 3,
        slow: if slow == 0 {
            SlowInput::None
        } else {
            SlowInput::Vector {
                data: &s,
                dim: slow,
            }
        },
        d_vis: &d_vis,
    };
    let mut out = vec![0.0; b * h * a];
    m.call(&input, &mut out)?;
    Ok(out)
}

/// Oversized, malformed, too-large-batch and model-panicking requests each get an error
/// reply naming why and are counted; the server keeps serving (before: no size or batch
/// limit, a model panic killed the server, and a reply that could not be sent ended it).
#[test]
fn bad_requests_are_refused_counted_and_the_server_keeps_serving() {
    use pir2_runtime::remote::{serve_policy_counted, PolicyServerStats};
    use zenoh::Wait;

    let port = free_port();
    let stop = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(PolicyServerStats::default());
    let cfg = PolicyServerConfig {
        link: Link::listen(ep(port)),
        key: "test/policy".into(),
        max_request_bytes: 4096,
        max_batch: 2,
        ..Default::default()
    };
    let (s, st) = (stop.clone(), stats.clone());
    let server = Server {
        stop: stop.clone(),
        handle: std::thread::spawn(move || serve_policy_counted(PanicsOnBatch2, &cfg, s, st)),
    };
    let mut m = remote_model(port, 2000, 3);

    assert_eq!(call(&mut m, 1, 0).unwrap()[1], -1.0);
    let e = call(&mut m, 1, 2000).unwrap_err().to_string();
    assert!(
        e.contains("refused") && e.contains("at most 4096 bytes"),
        "{e}"
    );
    let e = call(&mut m, 3, 0).unwrap_err().to_string();
    assert!(e.contains("batch of 3 refused"), "{e}");
    let e = call(&mut m, 2, 0).unwrap_err().to_string();
    assert!(
        e.contains("panicked") && e.contains("breaks this model"),
        "{e}"
    );
    // Garbage on the server's key, from another session.
    let zs = test_session("connect", port);
    let replies = zs
        .get("test/policy")
        .payload(vec![0xde_u8, 0xad, 0xbe, 0xef, 1, 2, 3])
        .timeout(Duration::from_secs(2))
        .wait()
        .unwrap();
    let r = replies
        .recv()
        .expect("the server answers garbage with an error");
    let bytes = r.result().unwrap().payload().to_bytes();
    assert!(matches!(
        pir2_runtime::remote::wire::decode_reply(&bytes),
        Ok(pir2_runtime::remote::wire::Reply::Error(_))
    ));
    drop(replies);
    zs.close().wait().unwrap();
    // Still serving.
    assert_eq!(call(&mut m, 1, 0).unwrap()[2], -2.0);
    let c = stats.counters();
    assert_eq!(
        (
            c.answered,
            c.oversized,
            c.too_large_batch,
            c.model_panics,
            c.malformed
        ),
        (2, 1, 1, 1, 1),
        "{c:?}"
    );
    server.kill();
}

/// A slow-channel message that is not a feature message (another publisher on the key, a
/// damaged frame) is dropped and counted; the channel goes on with the server's frames
/// (before: the first such message ended the run).
#[test]
fn garbage_on_the_features_key_is_dropped_and_counted() {
    use zenoh::Wait;

    let (port, rogue_port) = (free_port(), free_port());
    let base = Arc::new(SystemClock::new());
    let server = slow_server(port, clock(&base, 0));
    // Another peer the robot also connects to, publishing garbage on the features key.
    let rogue = test_session("listen", rogue_port);
    let (slow, stats) = remote_slow_channel(
        RemoteSlowConfig {
            link: Link {
                retry: Duration::from_millis(20),
                connect: vec![ep(port), ep(rogue_port)],
                ..Link::connect(ep(port))
            },
            key: "test/slow".into(),
            stale_poll: Duration::from_millis(100),
            first_timeout: Duration::from_secs(5),
            ..Default::default()
        },
        clock(&base, 0),
    )
    .unwrap();
    let SlowChannel::Async { mut source, .. } = slow else {
        panic!("the remote slow channel is async");
    };
    assert_eq!(block_on_frame(&mut *source).values.len(), 4);
    let publisher = rogue.declare_publisher("test/slow").wait().unwrap();
    for _ in 0..5 {
        publisher.put(vec![1u8, 2, 3, 4, 5]).wait().unwrap();
        assert_eq!(block_on_frame(&mut *source).values.len(), 4);
    }
    let c = stats.counters();
    assert!(c.malformed >= 1, "{c:?}");
    assert!(c.frames >= 6, "{c:?}");
    drop(publisher);
    rogue.close().wait().unwrap();
    server.kill();
}

fn block_on_frame(source: &mut dyn SlowSource) -> SlowFrame {
    struct Noop;
    impl std::task::Wake for Noop {
        fn wake(self: Arc<Self>) {}
    }
    let waker = std::task::Waker::from(Arc::new(Noop));
    let mut cx = std::task::Context::from_waker(&waker);
    let mut fut = source.capture();
    loop {
        if let std::task::Poll::Ready(r) = fut.as_mut().poll(&mut cx) {
            return r.unwrap();
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Replies that cannot be used (garbage, or velocities for another request) are dropped and
/// counted; they count as failed attempts, so a server that only sends such replies ends the
/// call in a safety stop after `max_failed_calls` (before: the first one ended the run with
/// a decoding error, not a safety stop, and was not counted).
#[test]
fn unusable_replies_are_counted_and_end_in_a_safety_stop() {
    use pir2_runtime::remote::wire;
    use zenoh::Wait;

    let port = free_port();
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    // A server that answers pings properly and every request with garbage, or with the
    // velocities of another request (alternately).
    let rogue = std::thread::spawn(move || {
        let zs = test_session("listen", port);
        let q = zs.declare_queryable("test/policy").wait().unwrap();
        let mut n = 0u64;
        while !s.load(Ordering::Acquire) {
            let Ok(Some(query)) = q.recv_timeout(Duration::from_millis(20)) else {
                continue;
            };
            let bytes = query.payload().map(|p| p.to_bytes().to_vec()).unwrap();
            let (h, _) = wire::decode_header(&bytes).unwrap();
            let token = Some([9, 9, 9, 9]);
            let reply = if h.kind == wire::Kind::Ping {
                wire::encode_pong_with_token(9, &h, 0, None, token)
            } else {
                n += 1;
                if n % 2 == 1 {
                    vec![0xff; 40]
                } else {
                    let other = wire::Header {
                        seq: h.seq + 100,
                        ..h
                    };
                    wire::encode_reply_with_token(9, &other, 0, [1, 4, 2], &[0.0; 8], token)
                }
            };
            query.reply("test/policy", reply).wait().unwrap();
        }
        drop(q);
        zs.close().wait().unwrap();
    });
    let mut m = remote_model(port, 100, 4);
    let stats = m.stats();
    let e = call(&mut m, 1, 0).unwrap_err();
    assert!(
        matches!(e, pir2_runtime::remote::Error::Unusable { failed: 4, .. }),
        "{e}"
    );
    assert!(matches!(
        pir2_runtime::Error::from(e),
        pir2_runtime::Error::SafetyStop(_)
    ));
    let c = stats.counters();
    assert_eq!(
        (c.malformed, c.failed_calls, c.attempts),
        (4, 1, 4),
        "{c:?}"
    );
    stop.store(true, Ordering::SeqCst);
    rogue.join().unwrap();
}

/// A rogue peer on the policy key, answering every request faster than the server with
/// finite, well-shaped but wrong velocities (and pongs with a session token of its own):
/// the client pinned the server at its handshake, so it uses only the server's replies and
/// counts the rogue's; a client that shakes hands while both answer pins neither (before:
/// the first reply of any responder was used).
#[test]
fn replies_of_a_rogue_on_the_policy_key_are_counted_never_used() {
    use pir2_runtime::testing::rogue::{Attach, Rogue};

    let (port, rogue_port) = (free_port(), free_port());
    let server = policy_server(port, 20, Duration::ZERO);
    let link = Link {
        retry: Duration::from_millis(20),
        connect: vec![ep(port), ep(rogue_port)],
        ..Link::connect(ep(port))
    };
    let cfg = RemoteModelConfig {
        link,
        key: "test/policy".into(),
        timeout: Duration::from_millis(500),
        max_failed_calls: 3,
        connect_timeout: Duration::from_secs(5),
    };
    let mut m = RemoteModel::connect(cfg.clone()).unwrap();
    let stats = m.stats();
    let rogue =
        Rogue::policy_responder(&Attach::Listen(ep(rogue_port)), "test/policy", 42.0).unwrap();
    // Calls until the rogue (once its queryable is known to the client) answered 5 of them.
    let want: Vec<f32> = (0..8).map(|i| -(i as f32)).collect();
    while rogue.sent() < 5 {
        assert!(
            stats.counters().calls < 200,
            "the rogue never got a request"
        );
        assert_eq!(call(&mut m, 1, 0).unwrap(), want, "a rogue reply was used");
    }
    let c = stats.counters();
    assert!(c.foreign_replies >= 4, "{c:?}");
    assert_eq!((c.attempts, c.timeouts), (c.calls, 0), "{c:?}");
    // Both answer the handshake: the client refuses to pick one.
    let e = RemoteModel::connect(cfg).unwrap_err();
    assert!(
        matches!(
            e,
            pir2_runtime::remote::Error::Ambiguous { responders: 2, .. }
        ),
        "{e}"
    );
    drop(rogue);
    server.kill();
}

/// A rogue publishing well-formed features (another sender id) on the slow key while the
/// server publishes: the source stays with the server it synchronised with and counts the
/// rogue's frames.
#[test]
fn features_of_a_rogue_publisher_are_counted_never_used() {
    use pir2_runtime::remote::wire;
    use zenoh::Wait;

    let (port, rogue_port) = (free_port(), free_port());
    let base = Arc::new(SystemClock::new());
    let server = slow_server(port, clock(&base, 0));
    let rogue = test_session("listen", rogue_port);
    let (slow, stats) = remote_slow_channel(
        RemoteSlowConfig {
            link: Link {
                retry: Duration::from_millis(20),
                connect: vec![ep(port), ep(rogue_port)],
                ..Link::connect(ep(port))
            },
            key: "test/slow".into(),
            stale_poll: Duration::from_millis(200),
            first_timeout: Duration::from_secs(5),
            ..Default::default()
        },
        clock(&base, 0),
    )
    .unwrap();
    let SlowChannel::Async { mut source, .. } = slow else {
        panic!("the remote slow channel is async");
    };
    assert_eq!(block_on_frame(&mut *source).values.len(), 4);
    let publisher = rogue.declare_publisher("test/slow").wait().unwrap();
    // Until a few of the rogue's frames reached the source (its publisher needs a moment to
    // be known), none of them used.
    let mut seq = 0u64;
    while stats.counters().foreign_replies < 3 {
        seq += 1;
        assert!(seq < 200, "no rogue frame reached the source");
        let now = base.now();
        let fake = wire::encode_features(77, seq, now, now, 1, 4, &[1e6; 4]);
        publisher.put(fake).wait().unwrap();
        let f = block_on_frame(&mut *source);
        assert!(f.values.iter().all(|&v| v != 1e6), "a rogue frame was used");
    }
    let c = stats.counters();
    assert_eq!(c.reconnects, 0, "{c:?}");
    drop(publisher);
    rogue.close().wait().unwrap();
    server.kill();
}

/// A server that comes back announcing another identity (another checkpoint) is not used:
/// the new handshake sees the change and the call ends in a safety stop.
#[test]
fn a_restarted_server_with_another_identity_is_refused() {
    let port = free_port();
    let start = |identity: &str| {
        let stop = Arc::new(AtomicBool::new(false));
        let cfg = PolicyServerConfig {
            link: Link::listen(ep(port)),
            key: "test/policy".into(),
            identity: Some(identity.into()),
            ..Default::default()
        };
        let s = stop.clone();
        let handle = std::thread::spawn(move || {
            serve_policy(
                SleepyModel {
                    latency: Duration::ZERO,
                },
                &cfg,
                s,
            )
        });
        Server { stop, handle }
    };
    let server = start("weights A");
    let mut m = remote_model(port, 100, 20);
    assert_eq!(m.server_identity(), Some("weights A"));
    call(&mut m, 1, 0).unwrap();
    server.kill();
    let server = start("weights B");
    let e = call(&mut m, 1, 0).unwrap_err();
    server.kill();
    assert!(
        matches!(e, pir2_runtime::remote::Error::IdentityChanged { .. }),
        "{e}"
    );
    assert!(e.to_string().contains("weights B"), "{e}");
    assert!(matches!(
        pir2_runtime::Error::from(e),
        pir2_runtime::Error::SafetyStop(_)
    ));
}
