//! `pir2 bench` (and `pir2 gr00t bench`): measurements printed side by side in one run (medians
//! and ratios).

use std::time::{Duration, Instant};

use anyhow::Result;

use pir2_schedule::{StreamBuffer, StreamConfig};

/// Median ns per call of `f` over `rounds` rounds of `iters` calls.
pub fn median_ns(rounds: usize, iters: usize, mut f: impl FnMut()) -> f64 {
    let mut v: Vec<f64> = (0..rounds)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..iters {
                f();
            }
            t.elapsed().as_nanos() as f64 / iters as f64
        })
        .collect();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Schedule cost per call (plan + Euler + slide) for the two stock shapes.
pub fn schedule() -> Result<String> {
    let mut out =
        String::from("schedule: plan + Euler step + slide per call (median of 31 rounds)\n");
    for (h, a, d) in [(16usize, 16usize, 1usize), (50, 18, 3)] {
        let cfg = StreamConfig {
            horizon: h,
            action_dim: a,
            nfe: Some(2),
            max_delay: d,
            ..Default::default()
        };
        let mut buf = StreamBuffer::new(cfg, 0)?;
        buf.warm_start(d, &vec![0.0; h * a])?;
        let v = vec![0.01f32; h * a];
        let ns = median_ns(31, 20_000, || {
            buf.plan(d).unwrap();
            buf.step(std::hint::black_box(&v)).unwrap();
            buf.slide(d).unwrap();
        });
        out += &format!(
            "  H={h:<3} A={a:<3} d={d}: {:>7.0} ns/call   (target ≤ 1000 ns: {:.2}×)\n",
            ns,
            ns / 1000.0
        );
    }
    Ok(out)
}

/// Runtime overhead and jitter at 50 Hz and 500 Hz with a fake model.
pub fn runtime(seconds: f64) -> Result<String> {
    let mut out = String::from(
        "runtime: real-time driver, fake 18-DoF robot, fake model (1 ms/call at 50 Hz, 0.3 ms at 500 Hz), H = 16\n",
    );
    out += "  rate    priority      ticks  overhead p50/p99 (µs)  jitter p50/p99 (µs)  overruns\n";
    for (rate, prio) in [
        (50.0, None),
        (50.0, Some(80)),
        (500.0, None),
        (500.0, Some(80)),
    ] {
        let lat = if rate > 100.0 {
            Duration::from_micros(300)
        } else {
            Duration::from_millis(1)
        };
        let b = pir2_runtime::bench::run_bench(rate, seconds, lat, prio)?;
        let p = match (prio, b.events.is_empty()) {
            (None, _) => "normal".to_string(),
            (Some(p), true) => format!("SCHED_FIFO {p}"),
            (Some(_), false) => "FIFO refused".to_string(),
        };
        out += &format!(
            "  {:>4} Hz {:<13} {:>6}  {:>8.1} / {:<8.1}        {:>7.1} / {:<8.1}    {}\n",
            rate,
            p,
            b.ticks,
            b.overhead.p50 as f64 / 1e3,
            b.overhead.p99 as f64 / 1e3,
            b.jitter.p50 as f64 / 1e3,
            b.jitter.p99 as f64 / 1e3,
            b.overruns
        );
    }
    out += "  goals: overhead ≤ 20 µs, jitter p99 ≤ 500 µs at 50 Hz\n";
    Ok(out)
}

/// `pir2 gr00t bench`: one-NFE latency of a GR00T export's action head (batch 1, on the
/// execution provider asked for) and the `d` it implies at 25 Hz (the paper's robot rate)
/// and at the embodiment's rate; with a backbone (`backbone.onnx`, or GR00T's split
/// `vit_*.onnx` + `llm_*.onnx`), the latency of one frame's features
/// too (the slow channel's age). Inputs are seeded pseudo-random values of the right shapes.
#[cfg(feature = "gr00t")]
pub fn gr00t(
    checkpoint: &std::path::Path,
    task: &str,
    ep: &crate::ep::EpOptions,
    seconds: f64,
) -> Result<String> {
    use anyhow::Context;
    use pir2_backends::gr00t::{load_action_head, CheckpointFiles, Gr00tBackbone};
    use pir2_runtime::window::LatencyWindow;
    use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

    let ort = ep.ort()?;
    let files = CheckpointFiles::in_dir(checkpoint);
    let cfg = files.embodiment_config()?;
    let (mut head, prompt) = load_action_head(checkpoint, task, &ort)
        .with_context(|| format!("loading the action head of {}", checkpoint.display()))?;
    let d = *head.dims();
    let tokens = head
        .vl_layout()
        .map(|l| l.image_mask.len())
        .or(d.vl_tokens)
        .context("the action head has no token layout")?;
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    };
    let x: Vec<f32> = (0..d.horizon * d.action_dim).map(|_| next()).collect();
    let tau: Vec<f32> = (0..d.horizon)
        .map(|p| 1.0 - p as f32 / d.horizon as f32)
        .collect();
    let obs: Vec<f32> = (0..d.n_obs * d.state_dim).map(|_| next()).collect();
    let vl: Vec<f32> = (0..tokens * d.d_vl).map(|_| next()).collect();
    let d_vis = [0u32];
    let input = ModelInput {
        batch: 1,
        horizon: d.horizon,
        action_dim: d.action_dim,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: d.n_obs,
        fast_dim: d.state_dim,
        slow: SlowInput::Tokens {
            data: &vl,
            tokens,
            dim: d.d_vl,
        },
        d_vis: &d_vis,
    };
    let mut v = vec![0.0f32; d.horizon * d.action_dim];
    let nfe = time_calls(seconds, || {
        head.velocity(&input, &mut v)
            .map_err(|e| anyhow::anyhow!("{e}"))
    })?;
    let mut out = format!(
        "gr00t: {} on {} (H {}, A {}, T {tokens}, D_vl {}), prompt {prompt:?}\n",
        checkpoint.display(),
        ort.provider.describe(),
        d.horizon,
        d.action_dim,
        d.d_vl
    );
    out += &format!(
        "  one NFE (batch 1): median {:.2} ms, p90 {:.2} ms, max {:.2} ms over {} calls\n",
        nfe.median_ms, nfe.p90_ms, nfe.max_ms, nfe.calls
    );
    let implied = |per_call: &[f64], hz: f64| {
        let period = (1e9 / hz).round() as u64;
        let mut w = LatencyWindow::new(per_call.len().max(1), 0, period, 1000);
        for &ms in per_call {
            w.push((ms * 1e6).round() as u64);
        }
        w.delay()
    };
    let k = cfg.policy.flow_steps.max(1);
    let flow_calls: Vec<f64> = nfe.all_ms.iter().map(|ms| ms * k as f64).collect();
    let mut rates = vec![25.0];
    if (cfg.control_hz - 25.0).abs() > 1e-9 {
        rates.push(cfg.control_hz);
    }
    for hz in rates {
        out += &format!(
            "  at {hz:.0} Hz: πR² (one NFE per call) d = {}; flow baselines (K = {k} NFEs per call) d = {}\n",
            implied(&nfe.all_ms, hz),
            implied(&flow_calls, hz)
        );
    }
    if files.backbone.exists() || files.vit.exists() || files.llm.exists() {
        let (mut bb, _) = Gr00tBackbone::for_checkpoint(checkpoint, task, &ort)
            .with_context(|| format!("loading the backbone of {}", checkpoint.display()))?;
        let (h, w) = (480usize, 640usize);
        let image: Vec<u8> = (0..h * w * 3).map(|i| (i % 251) as u8).collect();
        let views: Vec<pir2_runtime::View> = (0..bb.views())
            .map(|_| pir2_runtime::View {
                image: image.clone(),
                hw: (h, w),
            })
            .collect();
        let enc = time_calls(seconds, || {
            bb.encode_views(&views)
                .map(|_| ())
                .map_err(anyhow::Error::from)
        })?;
        out += &format!(
            "  backbone ({}), one frame of {} 640×480 view(s): median {:.2} ms, p90 {:.2} ms ({:.1} ticks of feature age at 25 Hz)\n",
            bb.describe(),
            views.len(),
            enc.median_ms,
            enc.p90_ms,
            enc.median_ms / 40.0
        );
    }
    Ok(out)
}

/// Latencies of repeated calls (3 warm-up calls not counted).
#[cfg(feature = "gr00t")]
struct Timed {
    calls: usize,
    median_ms: f64,
    p90_ms: f64,
    max_ms: f64,
    all_ms: Vec<f64>,
}

/// Call `f` for about `seconds` (at least 10 and at most 10,000 timed calls).
#[cfg(feature = "gr00t")]
fn time_calls(seconds: f64, mut f: impl FnMut() -> Result<()>) -> Result<Timed> {
    for _ in 0..3 {
        f()?;
    }
    let budget = Duration::from_secs_f64(seconds.max(0.0));
    let t0 = Instant::now();
    let mut all_ms = Vec::new();
    while all_ms.len() < 10 || (t0.elapsed() < budget && all_ms.len() < 10_000) {
        let t = Instant::now();
        f()?;
        all_ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let mut s = all_ms.clone();
    s.sort_by(f64::total_cmp);
    let q = |p: f64| s[((s.len() - 1) as f64 * p).round() as usize];
    Ok(Timed {
        calls: s.len(),
        median_ms: q(0.5),
        p90_ms: q(0.9),
        max_ms: q(1.0),
        all_ms,
    })
}
