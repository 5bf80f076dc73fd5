//! Added latency of a remote action-head call over Zenoh on loopback, against the same call
//! in process, for the two shipped message sizes; and the clock-offset accuracy of the
//! remote slow channel.
//!
//! Run: `cargo run --release -p pir2-runtime --features remote --example remote_latency`
//! (optional argument: a free TCP port on 127.0.0.1 to start from, default 17447).
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use pir2_runtime::remote::{
    serve_policy, serve_slow, wire, Link, PolicyServerConfig, RemoteModel, RemoteModelConfig,
    RemoteSlowConfig, RemoteSlowSource, SlowServerConfig,
};
use pir2_runtime::testing::{CameraStub, PassThroughEncoder};
use pir2_runtime::{Clock, ModelInput, Nanos, SlowInput, SlowSource, SystemClock, VelocityModel};

/// The cheapest possible model (v = −x): what is left is the transport.
#[derive(Debug, Clone, Copy)]
struct Negate;

impl VelocityModel for Negate {
    fn backend(&self) -> &'static str {
        "negate"
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        for (o, x) in out.iter_mut().zip(input.x) {
            *o = -x;
        }
        Ok(())
    }
}

struct Case {
    name: &'static str,
    horizon: usize,
    action_dim: usize,
    n_obs: usize,
    fast_dim: usize,
    slow_tokens: usize,
    slow_dim: usize,
    calls: usize,
}

fn pct(v: &mut [Nanos], q: f64) -> f64 {
    v.sort_unstable();
    let i = ((q / 100.0) * (v.len() - 1) as f64).round() as usize;
    v[i] as f64 / 1e3
}

fn measure(case: &Case, port: u16) -> Result<(), Box<dyn std::error::Error>> {
    let (h, a) = (case.horizon, case.action_dim);
    let x: Vec<f32> = (0..h * a).map(|i| (i as f32 * 0.37).sin()).collect();
    let tau: Vec<f32> = (0..h).map(|p| 1.0 - p as f32 / h as f32).collect();
    let obs = vec![0.25f32; case.n_obs * case.fast_dim];
    let slow = vec![0.5f32; case.slow_tokens * case.slow_dim];
    let d_vis = [1u32];
    let input = ModelInput {
        batch: 1,
        horizon: h,
        action_dim: a,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: case.n_obs,
        fast_dim: case.fast_dim,
        slow: if case.slow_tokens == 1 {
            SlowInput::Vector {
                data: &slow,
                dim: case.slow_dim,
            }
        } else {
            SlowInput::Tokens {
                data: &slow,
                tokens: case.slow_tokens,
                dim: case.slow_dim,
            }
        },
        d_vis: &d_vis,
    };
    let req_bytes = wire::request_len(&input);
    let mut out = vec![0.0f32; h * a];

    let stop = Arc::new(AtomicBool::new(false));
    let cfg = PolicyServerConfig {
        link: Link::listen(format!("tcp/127.0.0.1:{port}")),
        ..Default::default()
    };
    let s = stop.clone();
    let server = std::thread::spawn(move || serve_policy(Negate, &cfg, s));
    let mut remote = RemoteModel::connect(RemoteModelConfig {
        link: Link::connect(format!("tcp/127.0.0.1:{port}")),
        timeout: Duration::from_secs(2),
        ..Default::default()
    })?;

    let mut local = Negate;
    let mut t_local = Vec::with_capacity(case.calls);
    let mut t_remote = Vec::with_capacity(case.calls);
    for i in 0..case.calls + 50 {
        let t0 = Instant::now();
        local.velocity(&input, &mut out)?;
        let l = t0.elapsed().as_nanos() as Nanos;
        let t0 = Instant::now();
        remote.velocity(&input, &mut out)?;
        let r = t0.elapsed().as_nanos() as Nanos;
        assert_eq!(out[1], -x[1]);
        if i >= 50 {
            t_local.push(l);
            t_remote.push(r);
        }
    }
    let mut added: Vec<Nanos> = t_remote
        .iter()
        .zip(&t_local)
        .map(|(r, l)| r.saturating_sub(*l))
        .collect();
    println!(
        "{:<6} {:>9} B {:>7} {:>10.1} {:>10.1} {:>10.1} {:>10.1} {:>10.1} {:>10.1}",
        case.name,
        req_bytes,
        case.calls,
        pct(&mut t_local, 50.0),
        pct(&mut t_local, 99.0),
        pct(&mut t_remote, 50.0),
        pct(&mut t_remote, 99.0),
        pct(&mut added, 50.0),
        pct(&mut added, 99.0),
    );
    stop.store(true, Ordering::SeqCst);
    drop(remote);
    server.join().map_err(|_| "policy server panicked")??;
    Ok(())
}

/// Clock offset: the slow server's clock is exactly 3 s behind the robot's (one base
/// clock), so every estimate's error is known.
fn offset_accuracy(port: u16) -> Result<(), Box<dyn std::error::Error>> {
    #[derive(Debug)]
    struct Ahead(Arc<SystemClock>, Nanos);
    impl Clock for Ahead {
        fn now(&self) -> Nanos {
            self.0.now() + self.1
        }
        fn sleep_until(&self, t: Nanos) {
            self.0.sleep_until(t.saturating_sub(self.1));
        }
    }
    let base = Arc::new(SystemClock::new());
    let server_clock: Arc<dyn Clock> = base.clone();
    let robot_clock: Arc<dyn Clock> = Arc::new(Ahead(base, 3_000_000_000));
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let cfg = SlowServerConfig {
        link: Link::listen(format!("tcp/127.0.0.1:{port}")),
        ..Default::default()
    };
    let server = std::thread::spawn(move || {
        serve_slow(
            Box::new(CameraStub::new(
                server_clock.clone(),
                Duration::from_millis(5),
                16,
            )),
            Box::new(PassThroughEncoder {
                latency: Duration::ZERO,
            }),
            server_clock,
            &cfg,
            s,
        )
    });
    let mut src = RemoteSlowSource::connect(
        RemoteSlowConfig {
            link: Link::connect(format!("tcp/127.0.0.1:{port}")),
            resync_every: Duration::ZERO, // estimate on every frame
            ..Default::default()
        },
        robot_clock,
    )?;
    let mut errs = Vec::new();
    let mut rtts = Vec::new();
    for _ in 0..40 {
        pir2_runtime::realtime::block_on(src.capture())?;
        let o = src.offset().ok_or("no offset")?;
        errs.push((o.offset_ns + 3_000_000_000).unsigned_abs());
        rtts.push(o.rtt_ns);
    }
    let max = *errs.iter().max().unwrap_or(&0) as f64 / 1e3;
    println!(
        "clock offset (16 pings/estimate, min RTT, 40 estimates): |error| median {:.1} µs, p99 {:.1} µs, max {max:.1} µs; chosen RTT median {:.1} µs",
        pct(&mut errs, 50.0),
        pct(&mut errs, 99.0),
        pct(&mut rtts, 50.0),
    );
    stop.store(true, Ordering::SeqCst);
    drop(src);
    server.join().map_err(|_| "slow server panicked")??;
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let port: u16 = std::env::args()
        .nth(1)
        .map(|p| p.parse())
        .transpose()?
        .unwrap_or(17447);
    let cases = [
        Case {
            name: "U-Net",
            horizon: 16,
            action_dim: 16,
            n_obs: 2,
            fast_dim: 32,
            slow_tokens: 1,
            slow_dim: 9,
            calls: 2000,
        },
        Case {
            name: "DiT",
            horizon: 50,
            action_dim: 18,
            n_obs: 1,
            fast_dim: 45,
            slow_tokens: 64,
            slow_dim: 1536,
            calls: 300,
        },
    ];
    println!("one NFE per call, zenoh over tcp/127.0.0.1, times in µs (added = remote − in-process, per call)");
    println!(
        "{:<6} {:>11} {:>7} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "case",
        "request",
        "calls",
        "local p50",
        "local p99",
        "remote p50",
        "remote p99",
        "added p50",
        "added p99"
    );
    for (i, c) in cases.iter().enumerate() {
        measure(c, port + i as u16)?;
    }
    offset_accuracy(port + 2)?;
    Ok(())
}
