//! Per-call cost of plan + Euler step + slide (the schedule's share of one πR² call).
use criterion::{criterion_group, criterion_main, Criterion};
use pir2_schedule::{StreamBuffer, StreamConfig};

fn bench(c: &mut Criterion) {
    for (h, a, d, n) in [(16usize, 16usize, 1usize, 2usize), (50, 18, 3, 2)] {
        let cfg = StreamConfig {
            horizon: h,
            action_dim: a,
            nfe: Some(n),
            max_delay: d,
            ..Default::default()
        };
        let mut buf = StreamBuffer::new(cfg, 0).unwrap();
        buf.warm_start(d, &vec![0.0; h * a]).unwrap();
        let v = vec![0.01f32; h * a];
        c.bench_function(&format!("plan+step+slide H={h} A={a} d={d}"), |b| {
            b.iter(|| {
                buf.plan(d).unwrap();
                buf.step(std::hint::black_box(&v)).unwrap();
                buf.slide(d).unwrap();
            })
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
