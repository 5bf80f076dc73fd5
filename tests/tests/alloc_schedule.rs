//! One inference call (plan + step + slide + remap, with a d change) allocates nothing.

use pir2_schedule::{Alignment, FrontMode, StreamBuffer, StreamConfig};
use pir2_tests::{count_allocations, CountingAlloc};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

#[test]
fn inference_call_allocates_nothing() {
    for front in [FrontMode::Visible, FrontMode::Hidden] {
        for alignment in [Alignment::Fresh, Alignment::Paper] {
            let cfg = StreamConfig {
                horizon: 16,
                action_dim: 16,
                nfe: if alignment == Alignment::Fresh {
                    Some(2)
                } else {
                    None
                },
                alignment,
                front,
                max_delay: 3,
            };
            let mut buf = StreamBuffer::new(cfg, 0).unwrap();
            buf.warm_start(1, &vec![0.0; 256]).unwrap();
            let v = vec![0.01f32; 256];
            // Warm the code paths once.
            buf.plan(1).unwrap();
            buf.step(&v).unwrap();
            buf.slide(1).unwrap();
            let (n, _) = count_allocations(|| {
                for d in [1usize, 3, 2, 2, 1] {
                    buf.plan(d).unwrap();
                    let x = buf.model_x()[0] + buf.model_tau()[0];
                    std::hint::black_box(x);
                    buf.step(&v).unwrap();
                    buf.slide(d).unwrap();
                    // A relative policy's rebase onto the next call's reference.
                    buf.remap(|p, z, out| out[0] = z[0] + 0.01 * p as f32);
                }
            });
            assert_eq!(
                n, 0,
                "{front:?}/{alignment:?}: an inference call allocated {n} times"
            );
            // The counter works: an allocation is seen.
            let (m, _) = count_allocations(|| std::hint::black_box(vec![1u8; 10]));
            assert_eq!(m, 1);
        }
    }
}
