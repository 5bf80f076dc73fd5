//! Batched lock-step evaluation: with a model whose rows do not depend on the batch, a
//! batched cell equals the batch-1 cell exactly; it is repeatable; and an error or a panic in
//! one episode, or a failing batched call, ends the cell in an error instead of a hang.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::Duration;

use pir2_runtime::*;
use pir2_schedule::{Alignment, FrontMode};

const PERIOD: Nanos = 20_000_000;
const A: usize = 2;
const H: usize = 16;

/// A point that must reach a target drawn from the episode seed before a horizon that also
/// depends on the seed: episodes end at different ticks, and success depends on the actions.
#[derive(Debug, Default)]
struct Reach {
    s: [f32; 2],
    goal: [f32; 2],
    t: usize,
    max_steps: usize,
    /// Panic at this tick (a broken environment).
    panic_at: Option<usize>,
}

impl Environment for Reach {
    fn spec(&self) -> EnvSpec {
        EnvSpec {
            fast_dim: 3,
            slow_dim: 2,
            action_dim: A,
            control_period: PERIOD,
            max_steps: 200,
        }
    }
    fn reset(&mut self, seed: u64) {
        let mut rng = pir2_schedule::Rng::new(seed);
        let mut u = || (rng.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
        self.goal = [2.0 * u() - 1.0, 2.0 * u() - 1.0];
        self.s = [0.0; 2];
        self.t = 0;
        self.max_steps = 12 + (seed % 40) as usize;
    }
    fn observe(&mut self, fast: &mut [f32], slow: &mut [f32]) {
        fast[..2].copy_from_slice(&self.s);
        fast[2] = self.t as f32 / 100.0;
        slow.copy_from_slice(&self.goal);
    }
    fn step(&mut self, action: &[f32]) -> EnvStep {
        if self.panic_at == Some(self.t) {
            panic!("broken environment at tick {}", self.t);
        }
        for j in 0..2 {
            self.s[j] += 0.06 * action[j].clamp(-1.0, 1.0);
        }
        self.t += 1;
        let dist = ((self.s[0] - self.goal[0]).powi(2) + (self.s[1] - self.goal[1]).powi(2)).sqrt();
        let success = dist < 0.08;
        EnvStep {
            done: success || self.t >= self.max_steps,
            success,
            reward: -dist,
        }
    }
}

/// A nonlinear velocity computed row by row (so exactly independent of the batch): flows
/// towards a noisy steering command; records the largest batch it saw; fails on call
/// `fail_at` (counted over rows) if set. With `coupled`, each row also depends on its place
/// in the batch and the batch size (as a backend's batched arithmetic may), and `digest`
/// hashes every answer in call order.
#[derive(Debug, Default)]
struct Steer {
    max_batch: usize,
    rows: usize,
    fail_at: Option<usize>,
    /// Panic instead of returning the error at `fail_at`.
    panic: bool,
    coupled: bool,
    digest: u64,
}

impl VelocityModel for Steer {
    fn backend(&self) -> &'static str {
        "steer"
    }
    fn velocity(&mut self, inp: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        inp.validate()?;
        self.max_batch = self.max_batch.max(inp.batch);
        self.rows += inp.batch;
        if self.fail_at.is_some_and(|n| self.rows >= n) {
            assert!(!self.panic, "steer: injected panic");
            return Err(Error::Model("steer: injected failure".into()));
        }
        let SlowInput::Vector { data: slow, dim } = inp.slow else {
            return Err(Error::Model("steer: expects a slow vector".into()));
        };
        let (f, n) = (inp.fast_dim, inp.n_obs);
        for b in 0..inp.batch {
            let newest = &inp.obs_fast[(b * n + n - 1) * f..(b * n + n) * f];
            let goal = &slow[b * dim..(b + 1) * dim];
            for p in 0..inp.horizon {
                let tau = inp.tau[b * inp.horizon + p];
                for j in 0..inp.action_dim {
                    let i = (b * inp.horizon + p) * inp.action_dim + j;
                    let x = inp.x[i];
                    let mut cmd = (3.0 * (goal[j] - newest[j])).tanh() + 0.4 * (5.0 * x).sin();
                    if self.coupled {
                        cmd += 0.3 * (b as f32 + 0.7 * inp.batch as f32).sin();
                    }
                    out[i] = if (0.0..1.0).contains(&tau) {
                        (cmd - x) / (1.0 - tau).max(0.05)
                    } else {
                        0.0
                    };
                }
            }
        }
        for v in out.iter() {
            self.digest = self.digest.wrapping_mul(0x100_0000_01B3) ^ u64::from(v.to_bits());
        }
        Ok(())
    }
}

fn spec(mode: &Mode) -> HeadSpec {
    let d_max = if matches!(mode, Mode::PiR2Async { .. } | Mode::PiR2Sync { .. }) {
        5
    } else {
        6
    };
    HeadSpec {
        horizon: H,
        action_dim: A,
        n_obs: 2,
        fast_dim: 3,
        slow_dim: 2,
        period: PERIOD,
        d_max,
        d_vis_max: 5,
    }
}

fn modes() -> [Mode; 3] {
    [
        Mode::PiR2Async {
            nfe: None,
            alignment: Alignment::Fresh,
            front: FrontMode::Visible,
        },
        Mode::NaiveAsync {
            steps: 4,
            ensemble: None,
        },
        Mode::SyncFlow { steps: 3, h: 4 },
    ]
}

/// Run `f` on a thread and fail (instead of hanging the suite) if it takes over a minute; a
/// panic in `f` (a failed assertion) is passed on as it is.
fn within_a_minute<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    let handle = std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    match rx.recv_timeout(Duration::from_secs(60)) {
        Ok(v) => v,
        Err(mpsc::RecvTimeoutError::Disconnected) => match handle.join() {
            Err(panic) => std::panic::resume_unwind(panic),
            Ok(()) => unreachable!("the thread sent nothing and did not panic"),
        },
        Err(mpsc::RecvTimeoutError::Timeout) => panic!("the batched evaluation hung"),
    }
}

/// `episodes` episodes of `mode` from seed 11 (the head from [`spec`], the lock-step timing
/// of a call taking 2 ticks, no output map).
fn cell(mode: Mode, episodes: usize, output: &OutputMap) -> StudyCell<'_> {
    StudyCell {
        head: spec(&mode),
        mode,
        timing: LockstepTiming::for_mode(&mode, 2),
        output,
        episodes,
        seed: 11,
    }
}

fn batched(mode: Mode, episodes: usize, group: usize, model: &mut Steer) -> Result<(usize, u64)> {
    let output = OutputMap::default();
    eval_cell_batched(
        &Reach::default,
        model,
        &cell(mode, episodes, &output),
        group,
        &|| {},
    )
}

#[test]
fn batched_cells_equal_batch_one_cells_for_a_row_independent_model() {
    within_a_minute(|| {
        for mode in modes() {
            let output = OutputMap::default();
            let single = eval_cell(
                &Reach::default,
                &Steer::default,
                &cell(mode, 23, &output),
                2,
                &|| {},
            )
            .unwrap();
            assert!(
                single.0 > 0 && single.0 < 23,
                "{}: the test needs both outcomes, got {}/23",
                mode.name(),
                single.0
            );
            for group in [1, 5, 23, 64] {
                let mut model = Steer::default();
                let got = batched(mode, 23, group, &mut model).unwrap();
                assert_eq!(got, single, "{} with groups of {group}", mode.name());
                assert_eq!(model.max_batch, group.min(23), "{} batch size", mode.name());
            }
        }
    });
}

#[test]
fn batched_cells_repeat_exactly_when_rows_depend_on_the_batch() {
    // The batch's composition must follow from the episodes alone: with a model whose rows
    // depend on their place in the batch, three runs give the same answers, bit for bit.
    within_a_minute(|| {
        for mode in modes() {
            let mut runs = Vec::new();
            for _ in 0..3 {
                let mut model = Steer {
                    coupled: true,
                    ..Default::default()
                };
                let r = batched(mode, 17, 8, &mut model).unwrap();
                runs.push((r, model.rows, model.digest));
            }
            assert_eq!(runs[0], runs[1], "{}", mode.name());
            assert_eq!(runs[1], runs[2], "{}", mode.name());
        }
    });
}

#[test]
fn a_failing_batched_call_ends_the_cell_in_its_error() {
    let err = within_a_minute(|| {
        let mut model = Steer {
            fail_at: Some(200),
            ..Default::default()
        };
        batched(modes()[1], 12, 12, &mut model).unwrap_err()
    });
    assert!(
        err.to_string().contains("injected failure"),
        "unexpected error: {err}"
    );
}

#[test]
fn a_panicking_batched_call_ends_the_cell_in_one_error_without_a_hang() {
    let err = within_a_minute(|| {
        let mut model = Steer {
            fail_at: Some(200),
            panic: true,
            ..Default::default()
        };
        batched(modes()[1], 12, 12, &mut model).unwrap_err()
    });
    assert!(
        matches!(&err, Error::Panicked { message, .. } if message.contains("injected panic")),
        "unexpected error: {err}"
    );
}

#[test]
fn an_episode_panic_ends_the_cell_in_one_error_without_stalling_the_others() {
    let err = within_a_minute(|| {
        let made = AtomicUsize::new(0);
        let make_env = || Reach {
            panic_at: (made.fetch_add(1, Ordering::SeqCst) == 3).then_some(4),
            ..Default::default()
        };
        let output = OutputMap::default();
        let mut model = Steer::default();
        eval_cell_batched(
            &make_env,
            &mut model,
            &cell(modes()[0], 9, &output),
            9,
            &|| {},
        )
        .unwrap_err()
    });
    assert!(
        matches!(&err, Error::Panicked { message, .. } if message.contains("broken environment")),
        "unexpected error: {err}"
    );
}

#[test]
fn an_episode_error_ends_the_cell_without_stalling_the_others() {
    // A head spec the mode cannot run (d_max too small for the flow baseline's delay) fails
    // in every episode before the first call; the cell must return that error.
    let err = within_a_minute(|| {
        let mode = Mode::NaiveAsync {
            steps: 4,
            ensemble: None,
        };
        let output = OutputMap::default();
        let mut bad = cell(mode, 6, &output);
        bad.head.horizon = 0;
        let mut model = Steer::default();
        eval_cell_batched(&Reach::default, &mut model, &bad, 3, &|| {}).unwrap_err()
    });
    assert!(!err.to_string().is_empty());
}
