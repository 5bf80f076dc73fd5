//! `pir2 bench`: measurements printed side by side in one run (medians and ratios).

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
