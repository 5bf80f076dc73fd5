//! The batch-1 MLP path allocates nothing after the first call (STYLE §10).

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use common::*;
use pir2_backends::candle::CandleModel;
use pir2_runtime::model::{ModelInput, SlowInput, VelocityModel};

struct Counting;
static ALLOCS: AtomicUsize = AtomicUsize::new(0);
thread_local! {
    // Count only on the test's own thread (the harness may allocate on others).
    static COUNTING: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

fn count() {
    if COUNTING.with(|c| c.get()) {
        ALLOCS.fetch_add(1, Ordering::Relaxed);
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        count();
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, n: usize) -> *mut u8 {
        count();
        unsafe { System.realloc(p, l, n) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn mlp_batch1_velocity_does_not_allocate_after_warmup() {
    let cfg = mlp_config(8);
    let mut m =
        CandleModel::new(cfg.clone(), pir2_backends::Stats::identity(&cfg.spec), 0).unwrap();
    let x = vec![0.1f32; 8 * A];
    let tau = [-1.0, 1.0, 0.9, 0.7, 0.5, 0.3, 0.1, 0.0];
    let o = obs(0.2);
    let input = ModelInput {
        batch: 1,
        horizon: 8,
        action_dim: A,
        x: &x,
        tau: &tau,
        obs_fast: &o,
        n_obs: 2,
        fast_dim: F,
        slow: SlowInput::Vector {
            data: &[0.5],
            dim: 1,
        },
        d_vis: &[1],
    };
    let mut out = vec![0.0; 8 * A];
    m.velocity(&input, &mut out).unwrap();
    let before = ALLOCS.load(Ordering::Relaxed);
    COUNTING.with(|c| c.set(true));
    for _ in 0..50 {
        m.velocity(&input, &mut out).unwrap();
    }
    COUNTING.with(|c| c.set(false));
    let n = ALLOCS.load(Ordering::Relaxed) - before;
    assert_eq!(n, 0, "{n} allocations in 50 warm batch-1 MLP calls");
    assert!(out.iter().all(|v| v.is_finite()));
}
