//! One control tick (read, publish, swap, send) allocates nothing.

use std::sync::Arc;

use pir2_runtime::realtime::{ControlLoop, Shared};
use pir2_runtime::testing::FakeRobot;
use pir2_runtime::*;
use pir2_tests::{count_allocations, CountingAlloc};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

#[test]
fn control_tick_allocates_nothing() {
    let (h, a, f, n_obs) = (16, 3, 6, 2);
    // Absolute, and relative with per-slot statistics (decoded per chunk).
    let relative = OutputMap {
        scale: vec![0.5; h * a],
        offset: vec![0.1; h * a],
        clip: vec![true; a],
        reference: vec![Some(0), None, Some(2)],
        poses: Vec::new(),
    };
    let cases = [None, Some(0.1)]
        .into_iter()
        .flat_map(|e| [(e, OutputMap::default()), (e, relative.clone())]);
    for (ensemble, output) in cases {
        let clock: Arc<dyn Clock> = Arc::new(MockClock::new());
        let mut robot = FakeRobot::new(a, clock);
        let shared = Shared::new(n_obs, f, h, a);
        let cfg = ControlConfig {
            horizon: h,
            action_dim: a,
            policy: CallPolicy::Async,
            ensemble,
            output,
        };
        let mut lp = ControlLoop::new(ControlState::new(cfg).unwrap(), n_obs, f);
        let mut first = Chunk::new(h, a);
        first.clean.fill(true);
        lp.control.deliver(&mut first);
        let mut spare = Chunk::new(h, a);
        let mut act = robot.clone();
        // Warm the paths.
        lp.tick(&shared, &mut robot, &mut act).unwrap();
        let (n, _) = count_allocations(|| {
            for t in 0..40u64 {
                if t % 2 == 0 {
                    spare.base = lp.control.tick();
                    spare.snapshot_tick = lp.control.tick().saturating_sub(1);
                    spare.clean.fill(t % 4 == 0); // half the chunks force the x̂ path
                    lp.control.deliver(&mut spare);
                }
                lp.tick(&shared, &mut robot, &mut act).unwrap();
            }
        });
        assert_eq!(
            n, 0,
            "ensemble {ensemble:?}: control ticks allocated {n} times"
        );
        assert!(lp.control.metrics.overruns > 0 || ensemble.is_some());
    }
}
