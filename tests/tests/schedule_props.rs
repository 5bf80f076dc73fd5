//! Property tests for the invariants of `docs/method.md` §1 (numbered as there).

use pir2_schedule::train::{DelayDist, Draw, FrontVisibility, PiR2Draws, TrainSchedule};
use pir2_schedule::{Alignment, FrontMode, Rng, Staircase, StreamBuffer, StreamConfig};
use proptest::prelude::*;

/// A valid `(H, d, n, alignment)`; `n = None` for the paper alignment.
fn staircase_params() -> impl Strategy<Value = (usize, usize, Option<usize>, Alignment)> {
    (4usize..=64, any::<bool>(), 0usize..1000, 0usize..1000).prop_map(|(h, paper, dr, nr)| {
        if paper {
            let dmax = (h - 1) / 2;
            let d = 1 + dr % dmax;
            (h, d, None, Alignment::Paper)
        } else {
            let dmax = (h + 1) / 3; // H >= 3d - 1
            let d = 1 + dr % dmax;
            let n = 1 + nr % Staircase::n_max(h, d);
            (h, d, Some(n), Alignment::Fresh)
        }
    })
}

/// A buffer configuration with a max delay valid for its `H`, plus a delay sequence.
fn buffer_case() -> impl Strategy<Value = (StreamConfig, Vec<usize>, u64)> {
    (
        4usize..=64,
        any::<bool>(),
        1usize..=4,
        0usize..1000,
        1usize..1000,
        any::<u64>(),
        any::<bool>(),
    )
        .prop_flat_map(|(h, paper, a, mr, nr, seed, hidden)| {
            let max_by_h = if paper { (h - 1) / 2 } else { (h + 1) / 3 };
            let max_delay = 1 + mr % max_by_h.min(6);
            let nfe = if paper {
                None
            } else {
                Some(1 + nr % Staircase::n_max(h, max_delay).max(1) * 2)
            };
            let cfg = StreamConfig {
                horizon: h,
                action_dim: a,
                nfe,
                alignment: if paper {
                    Alignment::Paper
                } else {
                    Alignment::Fresh
                },
                front: if hidden {
                    FrontMode::Hidden
                } else {
                    FrontMode::Visible
                },
                max_delay,
            };
            (
                Just(cfg),
                prop::collection::vec(1usize..=max_delay, 1..40),
                Just(seed),
            )
        })
}

fn oracle_action(t: u64, j: usize) -> f32 {
    (0.37 * t as f32 + 1.3 * j as f32).sin()
}

/// Exact velocity `v = a − ε = (a − x)/(1 − τ)` for slots with `τ < 1`; random elsewhere.
fn oracle_velocity(buf: &StreamBuffer, rng: &mut Rng, v: &mut [f32]) {
    let a = buf.config().action_dim;
    for p in 0..buf.config().horizon {
        let t = buf.tau()[p];
        for j in 0..a {
            let i = p * a + j;
            v[i] = if t < 1.0 {
                (oracle_action(buf.index() + p as u64, j) - buf.x()[i]) / (1.0 - t)
            } else {
                rng.normal() * 10.0
            };
        }
    }
}

fn oracle_chunk(h: usize, a: usize, base: u64) -> Vec<f32> {
    (0..h * a)
        .map(|i| oracle_action(base + (i / a) as u64, i % a))
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Invariant 1: τ* is non-increasing, in [0,1], front = 1, tail = 0.
    #[test]
    fn inv1_staircase_shape((h, d, n, al) in staircase_params()) {
        let s = Staircase::new(h, d, n, al).unwrap();
        let t = s.to_vec();
        for p in 0..h {
            prop_assert!((0.0..=1.0).contains(&t[p]));
            if p > 0 { prop_assert!(t[p] <= t[p - 1], "not non-increasing at {p}: {t:?}"); }
            if p < d { prop_assert_eq!(t[p], 1.0); }
            if p >= h - d { prop_assert_eq!(t[p], 0.0, "tail at {} of {:?}", p, t); }
        }
        // Fresh: every ramp slot advances by exactly 1/n per call.
        if al == Alignment::Fresh {
            let n = s.nfe() as f32;
            for p in 2 * d..h {
                let adv = s.tau_after(p) - s.tau(p);
                if s.tau(p) > 0.0 && s.tau_after(p) < 1.0 {
                    prop_assert!((adv - 1.0 / n).abs() < 1e-6, "p {p} adv {adv} n {n}");
                }
            }
        }
    }

    /// Invariants 2, 3, 4: Δτ ≥ 0, τ + Δτ ≤ 1, front bit-identical, steady cycle exact.
    #[test]
    fn inv234_steady_delay((h, d, n, al) in staircase_params(), a in 1usize..=4, seed in any::<u64>(), hidden in any::<bool>()) {
        let cfg = StreamConfig { horizon: h, action_dim: a, nfe: n, alignment: al,
            front: if hidden { FrontMode::Hidden } else { FrontMode::Visible }, max_delay: d };
        let mut buf = StreamBuffer::new(cfg, seed).unwrap();
        let mut rng = Rng::new(seed ^ 1);
        let clean: Vec<f32> = (0..h * a).map(|_| rng.normal()).collect();
        buf.warm_start(d, &clean).unwrap();
        let want = buf.staircase(d).unwrap().to_vec();
        let mut v = vec![0.0; h * a];
        for _ in 0..3 * h {
            buf.plan(d).unwrap();
            for p in 0..h {
                prop_assert!(buf.delta()[p] >= 0.0);
                prop_assert!(buf.tau()[p] + buf.delta()[p] <= 1.0 + 1e-7);
            }
            let front: Vec<u32> = buf.x()[..d * a].iter().map(|x| x.to_bits()).collect();
            if hidden {
                prop_assert!(buf.model_x()[..d * a].iter().all(|&x| x == 0.0));
                prop_assert!(buf.model_tau()[..d].iter().all(|&t| t == pir2_schedule::HIDDEN_FRONT_TAU));
            }
            rng.fill_normal(&mut v);
            buf.step(&v).unwrap();
            let after: Vec<u32> = buf.x()[..d * a].iter().map(|x| x.to_bits()).collect();
            prop_assert_eq!(front, after, "front modified by a step");
            buf.slide(d).unwrap();
            for p in 0..h {
                prop_assert!((buf.tau()[p] - want[p]).abs() <= 1e-6, "τ {:?} != τ* {:?}", buf.tau(), want);
            }
        }
    }

    /// Invariants 2, 3, 5, 7: random delay sequences (changing every call), exact-velocity
    /// oracle: every call valid, emitted slots clean and exact, convergence to τ*,d' within
    /// ⌈H/d'⌉ calls at constant d'.
    #[test]
    fn inv2357_changing_delay((cfg, delays, seed) in buffer_case()) {
        let (h, a) = (cfg.horizon, cfg.action_dim);
        let mut buf = StreamBuffer::new(cfg, seed).unwrap();
        let mut rng = Rng::new(seed ^ 2);
        buf.warm_start(delays[0], &oracle_chunk(h, a, 0)).unwrap();
        let mut v = vec![0.0; h * a];
        let run = |buf: &mut StreamBuffer, d: usize, rng: &mut Rng, v: &mut Vec<f32>| -> Result<(), TestCaseError> {
            buf.plan(d).unwrap();
            for p in 0..h {
                prop_assert!(buf.delta()[p] >= 0.0, "Δτ < 0");
                prop_assert!(buf.tau()[p] + buf.delta()[p] <= 1.0 + 1e-7);
            }
            let front: Vec<u32> = buf.x()[..d * a].iter().map(|x| x.to_bits()).collect();
            oracle_velocity(buf, rng, v);
            let e = buf.step(v).unwrap();
            let after: Vec<u32> = buf.x()[..d * a].iter().map(|x| x.to_bits()).collect();
            prop_assert_eq!(front, after);
            for p in e.start..e.start + e.len {
                prop_assert_eq!(buf.tau()[p], 1.0, "emitted slot {} not clean", p);
            }
            // Every clean slot (front and emitted) is exactly the oracle's action.
            for p in 0..h {
                if buf.tau()[p] >= 1.0 {
                    for j in 0..a {
                        let want = oracle_action(buf.index() + p as u64, j);
                        prop_assert!((buf.x()[p * a + j] - want).abs() < 1e-5, "slot {p}: {} vs {want}", buf.x()[p * a + j]);
                    }
                }
            }
            // Staircase validity (invariant 1 shape) of the live buffer.
            for p in 1..h { prop_assert!(buf.tau()[p] <= buf.tau()[p - 1] + 1e-7); }
            buf.slide(d).unwrap();
            Ok(())
        };
        for &d in &delays {
            run(&mut buf, d, &mut rng, &mut v)?;
        }
        // Invariant 5: constant d' afterwards: exactly τ*,d' within ⌈H/d'⌉ calls.
        let d_last = *delays.last().unwrap();
        let d_new = 1 + (d_last % cfg.max_delay);
        let want = buf.staircase(d_new).unwrap().to_vec();
        let bound = h.div_ceil(d_new);
        for _ in 0..bound {
            run(&mut buf, d_new, &mut rng, &mut v)?;
        }
        for p in 0..h {
            prop_assert!((buf.tau()[p] - want[p]).abs() <= 1e-6, "not converged after {} calls: {:?} vs {:?}", bound, buf.tau(), want);
        }
    }

    /// Invariant 6: slide by k keeps clean slots bit-identical and appends k slots at τ = 0.
    #[test]
    fn inv6_slide((h, d, n, al) in staircase_params(), a in 1usize..=3, k in 0usize..=64, seed in any::<u64>()) {
        let k = k % (h + 1);
        let cfg = StreamConfig { horizon: h, action_dim: a, nfe: n, alignment: al, front: FrontMode::Visible, max_delay: d };
        let mut buf = StreamBuffer::new(cfg, seed).unwrap();
        let clean: Vec<f32> = (0..h * a).map(|i| i as f32 * 0.01).collect();
        buf.warm_start(d, &clean).unwrap();
        let x0 = buf.x().to_vec();
        let t0 = buf.tau().to_vec();
        buf.slide(k).unwrap();
        for p in 0..h - k {
            prop_assert_eq!(buf.tau()[p].to_bits(), t0[p + k].to_bits());
            for j in 0..a {
                prop_assert_eq!(buf.x()[p * a + j].to_bits(), x0[(p + k) * a + j].to_bits());
            }
        }
        for p in h - k..h { prop_assert_eq!(buf.tau()[p], 0.0); }
        prop_assert_eq!(buf.index(), k as u64);
    }

    /// Invariant 8: training draws.
    #[test]
    fn inv8_training_draws(h in 8usize..=64, dmax in 1usize..=3, jitter in 0.0f32..0.3, alpha in 0.0f32..1.0,
                           seed in any::<u64>(), exp in any::<bool>(), paper in any::<bool>(), a in 1usize..=3) {
        let delay = if exp { DelayDist::Exponential { max: dmax, rate: 0.5 } } else { DelayDist::Uniform { max: dmax } };
        let alignment = if paper { Alignment::Paper } else { Alignment::Fresh };
        let sched = TrainSchedule::PiR2(PiR2Draws { alpha, delay, n: if paper { None } else { Some(2) }, alignment, jitter,
            front: FrontVisibility::Visible });
        prop_assume!(sched.validate(h).is_ok());
        let mut rng = Rng::new(seed);
        let mut draw = Draw::new(h);
        let actions: Vec<f32> = (0..h * a).map(|i| (i as f32).cos()).collect();
        let eps: Vec<f32> = (0..h * a).map(|i| (i as f32 * 0.7).sin()).collect();
        let (mut x, mut tin, mut tgt) = (vec![0.0; h * a], vec![0.0; h], vec![0.0; h * a]);
        for _ in 0..50 {
            sched.draw(&mut rng, &mut draw).unwrap();
            draw.build(&actions, &eps, a, &mut x, &mut tin, &mut tgt).unwrap();
            prop_assert!(draw.tau.iter().all(|t| (0.0..=1.0).contains(t)));
            let all_masked = draw.mask.iter().all(|&m| m == 1.0);
            let shared = draw.tau.iter().all(|&t| t == draw.tau[0]);
            if draw.delay == 0 && all_masked && shared && h > 1 {
                continue; // warm-up branch: one shared τ, no mask
            }
            // Staircase branch: mask exactly p < d, front = ground truth.
            let d = draw.delay;
            for p in 0..h {
                prop_assert_eq!(draw.mask[p], if p < d { 0.0 } else { 1.0 });
                if p < d {
                    prop_assert_eq!(draw.tau[p], 1.0, "jitter touched the front");
                    for j in 0..a { prop_assert_eq!(x[p * a + j], actions[p * a + j]); }
                }
            }
            if jitter == 0.0 {
                let n = if paper { None } else { Some(2usize.min(Staircase::n_max(h, d)).max(1)) };
                let want = Staircase::new(h, d, n, alignment).unwrap().to_vec();
                prop_assert_eq!(&draw.tau, &want);
            }
        }
    }
}

/// Chi-square goodness of fit of the delay distributions (invariant 8).
#[test]
fn delay_distributions_chi_square() {
    let cases = [
        DelayDist::Uniform { max: 5 },
        DelayDist::Uniform { max: 10 },
        DelayDist::Exponential { max: 5, rate: 0.5 },
        DelayDist::Exponential { max: 8, rate: 1.2 },
    ];
    for (ci, dist) in cases.iter().enumerate() {
        let mut rng = Rng::new(100 + ci as u64);
        let n = 200_000usize;
        let mut counts = vec![0usize; dist.max() + 1];
        for _ in 0..n {
            counts[dist.sample(&mut rng)] += 1;
        }
        let mut chi2 = 0.0;
        let mut dof = 0usize;
        for (k, &c) in counts.iter().enumerate() {
            let e = dist.pmf(k) * n as f64;
            if e == 0.0 {
                assert_eq!(c, 0, "{dist:?} produced impossible delay {k}");
                continue;
            }
            chi2 += (c as f64 - e).powi(2) / e;
            dof += 1;
        }
        dof -= 1;
        // 99.9% quantile of chi-square ≈ dof + 3.1·sqrt(2·dof) + 10 (conservative for dof ≤ 10).
        let crit = dof as f64 + 3.1 * (2.0 * dof as f64).sqrt() + 10.0;
        assert!(
            chi2 < crit,
            "{dist:?}: chi2 {chi2:.2} >= {crit:.2} (dof {dof}), counts {counts:?}"
        );
        // And a wrong distribution is rejected by the same test (the test can fail).
        let wrong = DelayDist::Uniform {
            max: dist.max().max(1),
        };
        if wrong != *dist {
            let chi2_wrong: f64 = counts
                .iter()
                .enumerate()
                .filter(|(k, _)| wrong.pmf(*k) > 0.0)
                .map(|(k, &c)| {
                    (c as f64 - wrong.pmf(k) * n as f64).powi(2) / (wrong.pmf(k) * n as f64)
                })
                .sum();
            assert!(
                chi2_wrong > crit,
                "chi-square cannot tell {dist:?} from {wrong:?}"
            );
        }
    }
}

/// Warm-up branch frequency matches α and uses one shared τ with no mask.
#[test]
fn warmup_branch_frequency() {
    let h = 16;
    let sched = TrainSchedule::PiR2(PiR2Draws {
        alpha: 0.2,
        delay: DelayDist::Uniform { max: 3 },
        n: Some(2),
        ..Default::default()
    });
    let mut rng = Rng::new(3);
    let mut draw = Draw::new(h);
    let n = 50_000;
    let mut warm = 0;
    for _ in 0..n {
        sched.draw(&mut rng, &mut draw).unwrap();
        if draw.delay == 0 {
            assert!(draw.mask.iter().all(|&m| m == 1.0));
            assert!(draw.tau.iter().all(|&t| t == draw.tau[0]));
            warm += 1;
        }
    }
    let f = warm as f64 / n as f64;
    assert!((f - 0.2).abs() < 0.01, "warm-up fraction {f}");
}

/// Hidden front in training: zeroed x and the indicator τ.
#[test]
fn hidden_front_in_training() {
    let (h, a) = (16, 2);
    let sched = TrainSchedule::PiR2(PiR2Draws {
        alpha: 0.0,
        n: Some(2),
        front: FrontVisibility::Hidden,
        ..Default::default()
    });
    let mut rng = Rng::new(4);
    let mut draw = Draw::new(h);
    let ones = vec![1.0f32; h * a];
    let (mut x, mut tin, mut tgt) = (vec![0.0; h * a], vec![0.0; h], vec![0.0; h * a]);
    for _ in 0..100 {
        sched.draw(&mut rng, &mut draw).unwrap();
        draw.build(&ones, &ones, a, &mut x, &mut tin, &mut tgt)
            .unwrap();
        assert!(draw.hidden && draw.delay >= 1);
        for p in 0..draw.delay {
            assert_eq!(tin[p], pir2_schedule::HIDDEN_FRONT_TAU);
            assert_eq!(&x[p * a..(p + 1) * a], &[0.0, 0.0]);
        }
        assert_eq!(tin[draw.delay], draw.tau[draw.delay]);
    }
}
