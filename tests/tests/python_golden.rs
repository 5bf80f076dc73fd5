//! Golden draws of the Python bindings, computed here by the pure-Rust crates.
//!
//! `bindings/python/tests/golden_draws.json` holds SHA-256 digests (and a few raw values)
//! of thousands of training draws per schedule, of GR00T N1.7 flow times, of the generator's
//! uniform/normal streams, of a streaming-buffer trajectory and of latency-window delays,
//! each for a fixed seed. This test recomputes them with `pir2-schedule` / `pir2-runtime`
//! and fails if the file differs, so the file is always what Rust draws; the Python tests
//! (`bindings/python/tests/test_golden.py`) draw the same through the `pir2` package and
//! compare bit for bit. Regenerate after an intended change of the draws with
//! `PIR2_BLESS=1 cargo test -p pir2-tests --test python_golden`.

use pir2_runtime::policy::{Policy, Recipe};
use pir2_runtime::LatencyWindow;
use pir2_schedule::train::{
    gr00t_n17_tau, DelayDist, Draw, FrontVisibility, PiR2Draws, TrainSchedule,
};
use pir2_schedule::{Alignment, Rng, StreamBuffer, StreamConfig};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};

const N: usize = 4096;

fn hex(bytes: impl AsRef<[u8]>) -> String {
    let d = Sha256::digest(bytes.as_ref());
    d.iter().map(|b| format!("{b:02x}")).collect()
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn schedule_case(name: &str, s: TrainSchedule, h: usize, seed: u64) -> Value {
    s.validate(h).unwrap();
    let mut rng = Rng::new(seed);
    let mut d = Draw::new(h);
    let (mut tau, mut mask, mut delay, mut hidden) = (vec![], vec![], vec![], vec![]);
    for _ in 0..N {
        s.draw(&mut rng, &mut d).unwrap();
        tau.extend_from_slice(&d.tau);
        mask.extend_from_slice(&d.mask);
        delay.extend((d.delay as i64).to_le_bytes());
        hidden.push(d.hidden as u8);
    }
    json!({
        "name": name,
        "schedule": serde_json::to_value(s).unwrap(),
        "horizon": h,
        "seed": seed,
        "batch": N,
        "tau_sha256": hex(f32_bytes(&tau)),
        "mask_sha256": hex(f32_bytes(&mask)),
        "delay_sha256": hex(&delay),
        "hidden_sha256": hex(&hidden),
        "tau_first_row": &tau[..h],
        "state_after": rng.state().iter().map(|x| x.to_string()).collect::<Vec<_>>(),
    })
}

/// The velocity of the buffer trajectory: exactly representable in `f32`, so Python builds
/// the same bits (`((p·A + j) mod 7)·0.25 − 0.75`).
fn velocity(h: usize, a: usize) -> Vec<f32> {
    (0..h * a).map(|i| (i % 7) as f32 * 0.25 - 0.75).collect()
}

fn buffer_case() -> Value {
    let (h, a, calls) = (16, 3, 60);
    let cfg = StreamConfig {
        horizon: h,
        action_dim: a,
        nfe: Some(2),
        max_delay: 3,
        ..StreamConfig::default()
    };
    let mut b = StreamBuffer::new(cfg, 11).unwrap();
    let clean: Vec<f32> = (0..h * a).map(|i| i as f32 * 0.125 - 1.0).collect();
    b.warm_start(1, &clean).unwrap();
    let v = velocity(h, a);
    let mut bytes = Vec::new();
    let mut emitted = Vec::new();
    for k in 0..calls {
        let d = k % 3 + 1;
        b.plan(d).unwrap();
        let e = b.step(&v).unwrap();
        emitted.push(json!([e.start, e.len]));
        bytes.extend(f32_bytes(b.x()));
        bytes.extend(f32_bytes(b.tau()));
        bytes.extend(f32_bytes(b.xhat()));
        b.slide(e.len).unwrap();
    }
    bytes.extend(f32_bytes(b.x()));
    json!({
        "horizon": h, "action_dim": a, "nfe": 2, "max_delay": 3, "seed": 11, "calls": calls,
        "delays": "k % 3 + 1", "clean": "i * 0.125 - 1.0", "velocity": "(i % 7) * 0.25 - 0.75",
        "emitted": emitted,
        "sha256": hex(&bytes),
    })
}

fn golden() -> Value {
    let h = 16;
    let pir2 = |c: PiR2Draws| TrainSchedule::PiR2(c);
    let recipe = Recipe::default();
    let mut cases = vec![
        schedule_case("pi_r2_default", pir2(PiR2Draws::default()), h, 0),
        schedule_case(
            "pi_r2_n2_jitter_dropped_exponential",
            pir2(PiR2Draws {
                n: Some(2),
                jitter: 0.1,
                front: FrontVisibility::Dropped { p: 0.3 },
                delay: DelayDist::Exponential { max: 5, rate: 1.0 },
                ..PiR2Draws::default()
            }),
            h,
            1,
        ),
        schedule_case(
            "pi_r2_paper",
            pir2(PiR2Draws {
                alignment: Alignment::Paper,
                ..PiR2Draws::default()
            }),
            h,
            2,
        ),
        schedule_case(
            "train_time_rtc",
            TrainSchedule::TrainTimeRtc {
                delay: DelayDist::Uniform { max: 10 },
            },
            h,
            4,
        ),
        schedule_case("standard_flow", TrainSchedule::StandardFlow, h, 5),
        schedule_case("gr00t_flow", TrainSchedule::Gr00tFlow, h, 6),
        schedule_case(
            "streaming_diffusion",
            TrainSchedule::StreamingDiffusion,
            h,
            7,
        ),
    ];
    for (i, p) in Policy::ALL.iter().enumerate() {
        let name = serde_json::to_value(p).unwrap();
        let name = format!("policy_{}", name.as_str().unwrap());
        cases.push(schedule_case(
            &name,
            p.schedule(&recipe),
            32,
            100 + i as u64,
        ));
    }
    let mut rng = Rng::new(20_260_526);
    let g: Vec<f32> = (0..100_000).map(|_| gr00t_n17_tau(&mut rng)).collect();
    let mut rng = Rng::new(9);
    let u: Vec<f32> = (0..100_000).map(|_| rng.uniform()).collect();
    let mut z = vec![0.0f32; 100_000];
    rng.fill_normal(&mut z);
    let mut w = LatencyWindow::new(4, 1, 20_000_000, 5);
    let mut delays = Vec::new();
    for i in 0..40u64 {
        w.push(900_000_000 * (i == 0) as u64 + (i * 7_000_000) % 110_000_000);
        delays.push(w.delay());
    }
    json!({
        "about": "Written by tests/tests/python_golden.rs from the pure-Rust crates (PIR2_BLESS=1 regenerates); checked by tests/test_golden.py through the Python package.",
        "schedules": cases,
        "gr00t_n17_tau": { "seed": 20_260_526, "count": g.len(), "sha256": hex(f32_bytes(&g)), "first": &g[..4] },
        "rng": { "seed": 9, "uniform_count": u.len(), "uniform_sha256": hex(f32_bytes(&u)),
                 "normal_count_after_uniform": z.len(), "normal_sha256": hex(f32_bytes(&z)) },
        "stream_buffer": buffer_case(),
        "latency_window": { "w": 4, "warmup": 1, "period_ns": 20_000_000, "d_max": 5,
                            "pushes": "900_000_000 * (i == 0) + (i * 7_000_000) % 110_000_000 for i in 0..40",
                            "delays": delays },
    })
}

#[test]
fn python_golden_draws_match_rust() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../bindings/python/tests/golden_draws.json");
    let want = serde_json::to_string_pretty(&golden()).unwrap() + "\n";
    if std::env::var_os("PIR2_BLESS").is_some() {
        std::fs::write(&path, &want).unwrap();
        return;
    }
    let have = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        have == want,
        "{} differs from the draws of the Rust crates; if the change of the draws is intended, \
         regenerate it with PIR2_BLESS=1 cargo test -p pir2-tests --test python_golden",
        path.display()
    );
}
