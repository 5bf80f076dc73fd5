//! Relative actions (GR00T N1.7's `use_relative_action`): each chunk is decoded against the
//! state at its snapshot with per-slot statistics, and what the head carries from call to
//! call is rebased onto every new reference, so a committed action never moves.

use pir2_runtime::*;
use pir2_schedule::{Alignment, FrontMode};

const PERIOD: Nanos = 20_000_000;
const A: usize = 2;
const H: usize = 16;
/// Fast observation: `[tick, s₀, s₁]`; action `j` is relative to `s_j`.
const F: usize = 3;

/// The absolute command the policy should send at tick `t`.
fn target(t: u64, j: usize) -> f32 {
    (0.21 * t as f32 + 0.9 * j as f32).sin()
}

/// The state: moves every tick, whatever the robot is sent (a drifting reference).
fn state(t: u64, j: usize) -> f32 {
    0.3 * (0.7 * t as f32 + j as f32).sin() + 0.05 * t as f32
}

/// Per-slot statistics: `u = x·scale[p, j] + offset[p, j] + s_j`.
fn scale(p: usize, j: usize) -> f32 {
    0.5 + 0.05 * p as f32 + 0.1 * j as f32
}
fn offset(p: usize, j: usize) -> f32 {
    0.1 * j as f32 - 0.02 * p as f32
}

fn relative_map() -> OutputMap {
    let mut m = OutputMap {
        reference: vec![Some(1), Some(2)],
        ..Default::default()
    };
    for p in 0..H {
        for j in 0..A {
            m.scale.push(scale(p, j));
            m.offset.push(offset(p, j));
        }
    }
    m
}

#[derive(Debug, Default)]
struct DriftEnv {
    t: u64,
    max_steps: usize,
    sent: Vec<Vec<f32>>,
}

impl Environment for DriftEnv {
    fn spec(&self) -> EnvSpec {
        EnvSpec {
            fast_dim: F,
            slow_dim: 0,
            action_dim: A,
            control_period: PERIOD,
            max_steps: self.max_steps,
        }
    }
    fn reset(&mut self, _seed: u64) {
        self.t = 0;
        self.sent.clear();
    }
    fn observe(&mut self, fast: &mut [f32], _slow: &mut [f32]) {
        fast[0] = self.t as f32;
        for j in 0..A {
            fast[1 + j] = state(self.t, j);
        }
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

/// Exact velocity towards the target written in the call's relative coordinates:
/// slot `p` of a call at tick `t_s` with state `s` is `(target(t_s + p) − s − offset_p)/scale_p`.
#[derive(Debug, Default)]
struct RelativeOracle;

impl VelocityModel for RelativeOracle {
    fn backend(&self) -> &'static str {
        "relative oracle"
    }
    fn velocity(&mut self, inp: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        inp.validate()?;
        let newest = &inp.obs_fast[(inp.n_obs - 1) * F..];
        let t_s = newest[0] as u64;
        for p in 0..inp.horizon {
            let tau = inp.tau[p];
            for j in 0..A {
                let i = p * A + j;
                let z = (target(t_s + p as u64, j) - newest[1 + j] - offset(p, j)) / scale(p, j);
                out[i] = if (0.0..1.0).contains(&tau) {
                    (z - inp.x[i]) / (1.0 - tau)
                } else {
                    0.0
                };
            }
        }
        Ok(())
    }
}

fn spec(d_max: usize) -> HeadSpec {
    HeadSpec {
        horizon: H,
        action_dim: A,
        n_obs: 2,
        fast_dim: F,
        slow_dim: 0,
        period: PERIOD,
        d_max,
        d_vis_max: 0,
    }
}

/// With an exact model in relative coordinates every command sent is the absolute target,
/// in every mode, while the state (the reference) moves every tick: πR²'s committed front
/// and its partly denoised slots are rebased at each call, train-time RTC's committed front
/// too, and temporal ensembling averages decoded commands. Without the rebase, the front
/// would be decoded against a newer state than the one it was made for and miss the target
/// by the state's motion.
#[test]
fn relative_actions_reach_the_absolute_target_in_every_mode_while_the_state_moves() {
    let pir2 = |front, nfe, alignment| Mode::PiR2Async {
        nfe,
        alignment,
        front,
    };
    let cases = [
        (pir2(FrontMode::Visible, Some(2), Alignment::Fresh), 1, 0),
        (pir2(FrontMode::Visible, Some(2), Alignment::Fresh), 3, 4),
        (pir2(FrontMode::Hidden, None, Alignment::Paper), 2, 0),
        (
            Mode::PiR2Sync {
                nfe: None,
                alignment: Alignment::Fresh,
                front: FrontMode::Visible,
            },
            2,
            0,
        ),
        (Mode::TrainTimeRtc { steps: 4 }, 3, 0),
        (
            Mode::InferenceRtc {
                steps: 4,
                overlap: None,
                ramp_rate: 5.0,
            },
            3,
            0,
        ),
        (
            Mode::NaiveAsync {
                steps: 4,
                ensemble: Some(0.1),
            },
            2,
            0,
        ),
        (
            Mode::NaiveAsync {
                steps: 4,
                ensemble: None,
            },
            3,
            0,
        ),
        (Mode::SyncFlow { steps: 4, h: 4 }, 0, 0),
    ];
    for (mode, call_ticks, overrun_every) in cases {
        let sp = spec(5);
        let mut head = ActionHead::new(
            RelativeOracle,
            sp,
            mode.head_mode(4),
            LatencyWindow::new(20, 0, PERIOD, sp.d_max),
            7,
        )
        .unwrap();
        let mut env = DriftEnv {
            max_steps: 80,
            ..Default::default()
        };
        let timing = LockstepTiming {
            call_ticks,
            slow_delay: 0,
            overrun_ticks: 1,
            overrun_every,
            pin_delay: true,
        };
        let mut drv = LockstepDriver::new(&head).with_output(relative_map());
        let r = drv
            .run_episode(&mut env, &mut head, &mode, timing, 1, |_, _| {})
            .unwrap();
        assert_eq!(r.steps, 80);
        assert!(
            r.metrics.swaps > 15,
            "{}: {} swaps",
            mode.describe(),
            r.metrics.swaps
        );
        if overrun_every > 0 {
            assert!(r.metrics.overruns > 0, "{}: no overrun", mode.describe());
        }
        for (t, u) in env.sent.iter().enumerate() {
            for (j, &v) in u.iter().enumerate() {
                let want = target(t as u64, j);
                assert!(
                    (v - want).abs() < 1e-4,
                    "{} (call ticks {call_ticks}): tick {t} dim {j}: sent {v}, target {want}",
                    mode.describe()
                );
            }
        }
    }
}

/// One πR² call after another on a state that moved: every slot that was clean in the first
/// chunk decodes, in the second, to the same command (it moved one slot left and onto the
/// new reference); with the state unchanged and no tick elapsed the buffer is untouched.
#[test]
fn a_committed_action_does_not_move_when_the_state_moves() {
    let mode = Mode::PiR2Async {
        nfe: Some(2),
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
    };
    let sp = spec(3);
    let mut head = ActionHead::new(
        Wobbly,
        sp,
        mode.head_mode(4),
        LatencyWindow::new(20, 0, PERIOD, sp.d_max),
        3,
    )
    .unwrap();
    head.set_output(&relative_map()).unwrap();
    head.force_delay(Some(2));
    let mut snap = Snapshot::new(&sp);
    let set = |snap: &mut Snapshot, tick: u64, s: [f32; 2]| {
        snap.tick = tick;
        for k in 0..sp.n_obs {
            snap.fast[k * F..(k + 1) * F].copy_from_slice(&[tick as f32, s[0], s[1]]);
        }
    };
    let decode = |c: &Chunk, slot: usize| {
        let mut u = [0.0; A];
        relative_map().decode(&c.x[slot * A..(slot + 1) * A], slot, &c.reference, &mut u);
        u
    };
    let (mut c0, mut c1, mut c2) = (Chunk::new(H, A), Chunk::new(H, A), Chunk::new(H, A));
    set(&mut snap, 10, [0.2, -0.4]);
    head.warm_start(&snap, 2, &mut c0).unwrap();
    assert_eq!(c0.reference, [0.2, -0.4]);
    head.call(&snap, &mut c1).unwrap();
    // Same tick, same state: the carried buffer's front is bit-identical.
    assert_eq!(&c1.x[..2 * A], &c0.x[..2 * A]);
    // One tick later the state has moved.
    set(&mut snap, 11, [0.9, 0.35]);
    head.call(&snap, &mut c2).unwrap();
    assert_eq!(c2.reference, [0.9, 0.35]);
    let clean = c1.clean.iter().take_while(|c| **c).count();
    assert!(
        clean >= 3,
        "the first call emits slots [2, 4): {clean} clean"
    );
    for slot in 1..clean {
        assert!(c2.clean[slot - 1]);
        let (before, after) = (decode(&c1, slot), decode(&c2, slot - 1));
        for j in 0..A {
            assert!(
                (before[j] - after[j]).abs() < 1e-5,
                "slot {slot} dim {j}: {} became {}",
                before[j],
                after[j]
            );
        }
        // The model-space value did change (the test would see a missing rebase).
        assert_ne!(c1.x[slot * A], c2.x[(slot - 1) * A]);
    }
}

/// GR00T N1.7's inference-time RTC: the `d` slots the robot executes while a call runs are
/// the chunk in flight's, exactly (rebased onto the new reference when actions are
/// relative); the slot after them is denoised; an overlap shorter than `d` freezes only the
/// overlap.
#[test]
fn inference_rtc_keeps_what_the_robot_executes_during_the_call() {
    let sp = spec(4);
    for relative in [false, true] {
        for (overlap, frozen) in [(None, 3), (Some(2), 2), (Some(8), 3)] {
            let mode = Mode::InferenceRtc {
                steps: 4,
                overlap,
                ramp_rate: 5.0,
            };
            let mut head = ActionHead::new(
                Wobbly,
                sp,
                mode.head_mode(4),
                LatencyWindow::new(20, 0, PERIOD, sp.d_max),
                5,
            )
            .unwrap();
            let map = if relative {
                relative_map()
            } else {
                OutputMap::default()
            };
            if relative {
                head.set_output(&map).unwrap();
            }
            head.force_delay(Some(3));
            let mut snap = Snapshot::new(&sp);
            let set = |snap: &mut Snapshot, tick: u64, s: [f32; 2]| {
                snap.tick = tick;
                for k in 0..sp.n_obs {
                    snap.fast[k * F..(k + 1) * F].copy_from_slice(&[tick as f32, s[0], s[1]]);
                }
            };
            let decode = |c: &Chunk, slot: usize| -> Vec<f32> {
                let x = &c.x[slot * A..(slot + 1) * A];
                if !relative {
                    return x.to_vec();
                }
                let mut u = [0.0; A];
                map.decode(x, slot, &c.reference, &mut u);
                u.to_vec()
            };
            let (mut c0, mut c1) = (Chunk::new(H, A), Chunk::new(H, A));
            set(&mut snap, 10, [0.2, -0.4]);
            head.warm_start(&snap, 3, &mut c0).unwrap();
            // Two ticks later, the state has moved.
            set(&mut snap, 12, [0.9, 0.35]);
            head.call(&snap, &mut c1).unwrap();
            assert_eq!(c1.base, 12);
            let what = format!("relative {relative}, overlap {overlap:?}");
            for p in 0..frozen {
                let (before, after) = (decode(&c0, p + 2), decode(&c1, p));
                for j in 0..A {
                    assert!(
                        (before[j] - after[j]).abs() < 1e-5,
                        "{what}: frozen slot {p} dim {j}: {} became {}",
                        before[j],
                        after[j]
                    );
                }
            }
            // The slot after the frozen ones is denoised (the strengths themselves are
            // tested in pir2-schedule).
            let moved: f32 = {
                let (b, a) = (decode(&c0, frozen + 2), decode(&c1, frozen));
                (0..A).map(|j| (b[j] - a[j]).abs()).sum()
            };
            assert!(moved > 1e-4, "{what}: slot {frozen} never moved");
        }
    }
}

/// A model with a fixed, non-trivial velocity field (no oracle: any output must keep the
/// committed actions where they are).
#[derive(Debug)]
struct Wobbly;

impl VelocityModel for Wobbly {
    fn backend(&self) -> &'static str {
        "wobbly"
    }
    fn velocity(&mut self, inp: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        for (i, o) in out.iter_mut().enumerate() {
            *o = (0.37 * i as f32).cos() - 0.5 * inp.x[i];
        }
        Ok(())
    }
}

/// A reference outside the fast observation, or statistics of the wrong size, are refused
/// by the head before anything runs, naming the field.
#[test]
fn a_relative_map_that_does_not_fit_the_head_is_refused_by_name() {
    let mode = Mode::TrainTimeRtc { steps: 2 };
    let sp = spec(3);
    let mut head = ActionHead::new(
        Wobbly,
        sp,
        mode.head_mode(2),
        LatencyWindow::new(20, 0, PERIOD, sp.d_max),
        1,
    )
    .unwrap();
    let mut m = relative_map();
    m.reference[1] = Some(F);
    let e = head.set_output(&m).unwrap_err().to_string();
    assert!(
        e.contains("output.reference[1] = 3") && e.contains("fast_dim = 3"),
        "{e}"
    );
    let mut m = relative_map();
    m.scale.pop();
    let e = head.set_output(&m).unwrap_err().to_string();
    assert!(e.contains("output.scale has 31 entries"), "{e}");
    head.set_output(&relative_map()).unwrap();
}
