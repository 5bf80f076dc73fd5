//! The batch-1 U-Net path (hand-written kernels) allocates nothing after warm-up, on the
//! shipped Leap-cube configuration.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, Stats};
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
fn unet_batch1_velocity_does_not_allocate_after_warmup() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/leap_cube_unet.toml");
    let cfg = Config::from_file(&path).unwrap();
    let spec = cfg.spec;
    let mut m = CandleModel::new(cfg, Stats::identity(&spec), 0).unwrap();
    assert!(m.fused());
    let (h, a) = (spec.horizon, spec.action_dim);
    let x: Vec<f32> = (0..h * a).map(|i| (i as f32 * 0.37).sin()).collect();
    let mut tau: Vec<f32> = (0..h).map(|p| 1.0 - p as f32 / h as f32).collect();
    tau[0] = -1.0;
    let obs: Vec<f32> = (0..spec.n_obs * spec.fast_dim)
        .map(|i| (i as f32 * 0.1).cos())
        .collect();
    let slow = vec![0.2f32; spec.slow.len()];
    let input = ModelInput {
        batch: 1,
        horizon: h,
        action_dim: a,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: spec.n_obs,
        fast_dim: spec.fast_dim,
        slow: SlowInput::Vector {
            data: &slow,
            dim: spec.slow.len(),
        },
        d_vis: &[2],
    };
    let mut out = vec![0.0; h * a];
    m.velocity(&input, &mut out).unwrap();
    let first = out.clone();
    let before = ALLOCS.load(Ordering::Relaxed);
    COUNTING.with(|c| c.set(true));
    for _ in 0..20 {
        m.velocity(&input, &mut out).unwrap();
    }
    COUNTING.with(|c| c.set(false));
    let n = ALLOCS.load(Ordering::Relaxed) - before;
    assert_eq!(n, 0, "{n} allocations in 20 warm batch-1 U-Net calls");
    assert_eq!(out, first, "repeated calls must be bit-identical");
    assert!(out.iter().all(|v| v.is_finite()));
    // The counter works: a call after a weight change rebuilds the host copy.
    m.weights_changed();
    COUNTING.with(|c| c.set(true));
    m.velocity(&input, &mut out).unwrap();
    COUNTING.with(|c| c.set(false));
    assert!(
        ALLOCS.load(Ordering::Relaxed) > before,
        "the counting allocator saw nothing"
    );
}
