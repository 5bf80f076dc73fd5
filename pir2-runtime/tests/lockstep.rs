//! Deterministic lock-step tests with the exact-velocity oracle.

use pir2_runtime::*;
use pir2_schedule::{Alignment, FrontMode};

const PERIOD: Nanos = 20_000_000; // 50 Hz
const A: usize = 2;
const H: usize = 16;

fn target(t: u64, j: usize) -> f32 {
    (0.21 * t as f32 + 0.9 * j as f32).sin()
}

/// Fast obs = [tick, 0], slow obs = [tick]: the oracle reads the snapshot tick from the
/// newest fast frame; tests read the slow frame's tick to check its delay.
#[derive(Debug, Default)]
struct TrackEnv {
    t: u64,
    max_steps: usize,
    sent: Vec<Vec<f32>>,
}

impl Environment for TrackEnv {
    fn spec(&self) -> EnvSpec {
        EnvSpec {
            fast_dim: 2,
            slow_dim: 1,
            action_dim: A,
            control_period: PERIOD,
            max_steps: self.max_steps,
        }
    }
    fn reset(&mut self, _seed: u64) {
        self.t = 0;
        self.sent.clear();
    }
    fn observe(&mut self, fast: &mut [f32], slow: &mut [f32]) {
        fast[0] = self.t as f32;
        fast[1] = 0.0;
        slow[0] = self.t as f32;
    }
    fn step(&mut self, action: &[f32]) -> EnvStep {
        self.sent.push(action.to_vec());
        self.t += 1;
        EnvStep {
            done: self.t as usize >= self.max_steps,
            success: true,
            reward: 0.0,
        }
    }
}

/// Exact velocity for the target trajectory; logs (snapshot tick, slow tick, d_vis).
#[derive(Debug, Default)]
struct Oracle {
    log: Vec<(u64, u64, u32)>,
}

impl VelocityModel for Oracle {
    fn backend(&self) -> &'static str {
        "oracle"
    }
    fn velocity(&mut self, inp: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        inp.validate()?;
        let f = inp.fast_dim;
        let t_s = inp.obs_fast[(inp.n_obs - 1) * f] as u64;
        let slow_tick = match inp.slow {
            SlowInput::Vector { data, .. } => data[0] as u64,
            _ => u64::MAX,
        };
        self.log.push((t_s, slow_tick, inp.d_vis[0]));
        for p in 0..inp.horizon {
            let tau = inp.tau[p];
            for j in 0..inp.action_dim {
                let i = p * inp.action_dim + j;
                out[i] = if (0.0..1.0).contains(&tau) {
                    (target(t_s + p as u64, j) - inp.x[i]) / (1.0 - tau)
                } else {
                    0.0
                };
            }
        }
        Ok(())
    }
}

fn spec(mode: &Mode) -> HeadSpec {
    // πR² at H = 16 supports d ≤ 5; the K-step baselines need ⌈1.75·3⌉ = 6.
    let d_max = if matches!(mode, Mode::PiR2Async { .. } | Mode::PiR2Sync { .. }) {
        5
    } else {
        6
    };
    HeadSpec {
        horizon: H,
        action_dim: A,
        n_obs: 2,
        fast_dim: 2,
        slow_dim: 1,
        period: PERIOD,
        d_max,
        d_vis_max: 5,
    }
}

fn pir2(front: FrontMode, nfe: Option<usize>, alignment: Alignment) -> Mode {
    Mode::PiR2Async {
        nfe,
        alignment,
        front,
    }
}

fn run(mode: Mode, timing: LockstepTiming, steps: usize) -> (EpisodeResult, TrackEnv, Oracle) {
    let sp = spec(&mode);
    let mut head = ActionHead::new(
        Oracle::default(),
        sp,
        mode.head_mode(4),
        LatencyWindow::new(20, 0, PERIOD, sp.d_max),
        7,
    )
    .unwrap();
    let mut env = TrackEnv {
        max_steps: steps,
        ..Default::default()
    };
    let mut drv = LockstepDriver::new(&head);
    let r = drv
        .run_episode(&mut env, &mut head, &mode, timing, 1, |_, _| {})
        .unwrap();
    let log = head.model().log.clone();
    (r, env, Oracle { log })
}

fn assert_tracks(env: &TrackEnv, tol: f32, what: &str) {
    for (t, a) in env.sent.iter().enumerate() {
        for (j, &v) in a.iter().enumerate() {
            assert!(
                (v - target(t as u64, j)).abs() < tol,
                "{what}: tick {t} dim {j}: sent {v}, target {}",
                target(t as u64, j)
            );
        }
    }
}

#[test]
fn pir2_oracle_executes_the_target_exactly_across_swaps() {
    for d in 1..=4 {
        for front in [FrontMode::Visible, FrontMode::Hidden] {
            for (nfe, al) in [
                (Some(2), Alignment::Fresh),
                (None, Alignment::Fresh),
                (None, Alignment::Paper),
            ] {
                let timing = LockstepTiming {
                    call_ticks: d,
                    slow_delay: 0,
                    overrun_ticks: 0,
                    overrun_every: 0,
                    pin_delay: true,
                };
                let (r, env, _) = run(pir2(front, nfe, al), timing, 120);
                assert_eq!(r.steps, 120);
                assert_eq!(r.metrics.overruns, 0, "d={d}");
                assert!(
                    r.metrics.swaps >= (120 / d) as u64,
                    "swaps {}",
                    r.metrics.swaps
                );
                assert_tracks(&env, 1e-4, &format!("d={d} {front:?} {nfe:?} {al:?}"));
            }
        }
    }
}

#[test]
fn baselines_with_the_oracle_track_the_target() {
    for mode in [
        Mode::NaiveAsync {
            steps: 5,
            ensemble: None,
        },
        Mode::NaiveAsync {
            steps: 5,
            ensemble: Some(0.1),
        },
        Mode::TrainTimeRtc { steps: 5 },
        Mode::InferenceRtc {
            steps: 5,
            overlap: None,
            ramp_rate: 5.0,
        },
    ] {
        let (r, env, _) = run(mode, LockstepTiming::for_mode(&mode, 2), 100);
        assert_eq!(r.metrics.overruns, 0);
        assert_tracks(&env, 1e-4, mode.name());
    }
}

#[test]
fn sync_flow_holds_while_the_call_runs() {
    let mode = Mode::SyncFlow { steps: 4, h: 4 };
    let (r, env, _) = run(mode, LockstepTiming::for_mode(&mode, 2), 60);
    // d = ⌈1.75·2⌉ = 4 ticks of hold after every 4 executed actions (the first chunk comes
    // from the warm start, so the robot starts moving at once).
    assert!(r.metrics.holds > 0);
    let held = r.metrics.holds as usize;
    assert!((24..=32).contains(&held), "holds {held}");
    // Holds repeat the previous action exactly.
    let mut repeats = 0;
    for w in env.sent.windows(2) {
        if w[0] == w[1] {
            repeats += 1;
        }
    }
    assert!(repeats >= held - 1);
}

#[test]
fn overruns_send_the_clean_estimate_and_are_counted() {
    let timing = LockstepTiming {
        call_ticks: 1,
        slow_delay: 0,
        overrun_ticks: 2,
        overrun_every: 3,
        pin_delay: true,
    };
    let (r, env, _) = run(
        pir2(FrontMode::Visible, Some(2), Alignment::Fresh),
        timing,
        90,
    );
    assert!(r.metrics.overruns > 0, "no overrun counted");
    // With the oracle, x̂ is exact: even overrun ticks execute the target.
    assert_tracks(&env, 1e-4, "overrun");
    // Swaps happened at the elapsed index (> d for overrun calls).
    assert!(r.metrics.calls.iter().any(|c| c.elapsed == 3));
}

#[test]
fn d_adapts_to_measured_latency() {
    // Every 2nd call takes 3 extra ticks: mean latency 2.5 ticks → d = 3 (round half away).
    let timing = LockstepTiming {
        call_ticks: 1,
        slow_delay: 0,
        overrun_ticks: 3,
        overrun_every: 2,
        pin_delay: false,
    };
    let (r, env, _) = run(
        pir2(FrontMode::Visible, Some(2), Alignment::Fresh),
        timing,
        200,
    );
    let ds: Vec<usize> = r.metrics.calls.iter().map(|c| c.d).collect();
    assert_eq!(
        ds[1], 1,
        "the initial delay is used before the window fills: {ds:?}"
    );
    assert!(
        ds.iter().skip(22).all(|&d| d == 3),
        "d did not adapt: {ds:?}"
    );
    assert_tracks(&env, 1e-4, "adaptive d");
}

#[test]
fn slow_features_arrive_d_vis_ticks_late() {
    for d_vis in 0..=3 {
        let timing = LockstepTiming {
            call_ticks: 1,
            slow_delay: d_vis,
            overrun_ticks: 0,
            overrun_every: 0,
            pin_delay: true,
        };
        let (_, _, oracle) = run(
            pir2(FrontMode::Visible, Some(2), Alignment::Fresh),
            timing,
            40,
        );
        for &(t_s, slow_tick, dv) in oracle.log.iter().filter(|l| l.0 >= 5) {
            assert_eq!(slow_tick, t_s - d_vis as u64, "slow frame age");
            assert_eq!(dv as usize, d_vis, "d_vis fed to the model");
        }
    }
}

#[test]
fn paper_effective_delays_reach_the_head() {
    for d0 in 1..=3 {
        for mode in [
            Mode::NaiveAsync {
                steps: 3,
                ensemble: None,
            },
            Mode::TrainTimeRtc { steps: 3 },
            Mode::PiR2Sync {
                nfe: Some(2),
                alignment: Alignment::Fresh,
                front: FrontMode::Visible,
            },
            Mode::PiR2Async {
                nfe: Some(2),
                alignment: Alignment::Fresh,
                front: FrontMode::Visible,
            },
        ] {
            let want = mode.effective_delays(d0);
            let (r, _, oracle) = run(mode, LockstepTiming::for_mode(&mode, d0), 60);
            let c = &r.metrics.calls[3];
            assert_eq!(c.elapsed, want.d, "{} d0={d0}", mode.name());
            if matches!(mode, Mode::PiR2Async { .. } | Mode::PiR2Sync { .. }) {
                assert_eq!(c.d, want.d);
            }
            assert!(oracle
                .log
                .iter()
                .skip(10)
                .all(|l| l.2 as usize == want.d_vis));
        }
    }
}

#[test]
fn zero_latency_calls_swap_within_the_tick() {
    // Sync flow with h = 2 and zero-latency calls: no holds, a new chunk every 2 ticks.
    let mode = Mode::SyncFlow { steps: 3, h: 2 };
    let timing = LockstepTiming {
        call_ticks: 0,
        slow_delay: 0,
        overrun_ticks: 0,
        overrun_every: 0,
        pin_delay: true,
    };
    let (r, env, _) = run(mode, timing, 40);
    assert_eq!(r.metrics.holds, 0);
    assert!(r.metrics.calls.iter().all(|c| c.elapsed == 0));
    assert_eq!(r.metrics.swaps, 1 + 19); // warm start + one call every 2 ticks from t = 2
                                         // Each chunk is planned from its own snapshot: the oracle's target holds.
    assert_tracks(&env, 1e-4, "zero-latency sync");
    let (r, env, _) = run(
        pir2(FrontMode::Visible, Some(2), Alignment::Fresh),
        timing,
        40,
    );
    assert_eq!(r.metrics.overruns, 0);
    assert_tracks(&env, 1e-4, "zero-latency πR²");
}

#[test]
fn zero_delay_policy_acts_on_the_newest_observation_within_the_tick() {
    // A policy trained with d_max = 0 (the paper's zero-delay variant for the horizon study):
    // every call uses the d = 0 ramp, sees the observation of its own tick, and the slot it
    // finishes is executed in that same tick.
    let mode = pir2(FrontMode::Visible, Some(2), Alignment::Fresh);
    let mut sp = spec(&mode);
    sp.d_max = 0;
    let new_head = || {
        ActionHead::new(
            Oracle::default(),
            sp,
            mode.head_mode(4),
            LatencyWindow::new(20, 0, PERIOD, 1),
            7,
        )
        .unwrap()
    };
    let timing = LockstepTiming {
        call_ticks: 0,
        slow_delay: 0,
        overrun_ticks: 0,
        overrun_every: 0,
        pin_delay: true,
    };
    let steps = 40;
    let mut head = new_head();
    let mut env = TrackEnv {
        max_steps: steps,
        ..Default::default()
    };
    let mut drv = LockstepDriver::new(&head);
    let r = drv
        .run_episode(&mut env, &mut head, &mode, timing, 1, |_, _| {})
        .unwrap();
    assert_eq!(
        r.metrics.calls.len(),
        1 + steps,
        "the warm start, then one call per tick"
    );
    assert!(r.metrics.calls.iter().all(|c| c.d == 0 && c.elapsed == 0));
    assert_eq!(r.metrics.overruns, 0);
    // After the 4 warm-start evaluations (tick 0), call t evaluates on tick t's observation.
    let ticks: Vec<u64> = head.model().log[4..].iter().map(|l| l.0).collect();
    assert_eq!(ticks, (0..steps as u64).collect::<Vec<_>>());
    assert_tracks(&env, 1e-4, "zero-delay πR²");

    // The same policy refuses timing it was not trained for.
    let mut head = new_head();
    let late = LockstepTiming {
        call_ticks: 1,
        ..timing
    };
    let err = drv
        .run_episode(&mut env, &mut head, &mode, late, 1, |_, _| {})
        .unwrap_err();
    assert!(err.to_string().contains("d_max = 0"), "{err}");
}
