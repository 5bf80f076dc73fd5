//! Diagnosis: are the MPC expert's demonstration labels learnable from the policy's observation?
//!
//! Rolls the sampling-MPC expert on fresh episodes of the paper's Leap-cube variant and
//! measures, on the recorded frames:
//! * **repeats**: the fraction of steps whose action equals the previous one (bit for bit, and
//!   within 1e-4: a linear spline segment gives equal motor-target increments);
//! * **ridge fits** (held-out R², episodes split 3:1) of `a_t` on `a_{t−1}` alone, on the
//!   41-d observation alone, on both, and on `[obs_t, fast_{t−1}]` (what a policy with
//!   `n_obs = 2` sees: `fast_{t−1}` reveals the previous motor target, hence `a_{t−1}`);
//! * **repeatability**: at every `--alt-every`-th step the episode is branched (environment
//!   and plan state saved) and the expert acts from the same state with another sampling seed
//!   for two steps (`a′`, not executed; with the pinned first knot a replan's sample shows in
//!   the *next* action). `Var(a − a′) / (2·Var(a))` is the share of the label variance that
//!   is sampling noise (1 − it bounds the R² of *any* predictor of the label from the state);
//! * **open-loop replay**: each episode's actions replayed from the same initial state
//!   (a determinism check, must equal the closed-loop outcome) and with the cube moved 1 mm
//!   (how much the success depends on feedback).
//!
//! ```text
//! source .native/env.sh
//! cargo run --release -p pir2-sim --features mujoco --example leap_diagnose -- --episodes 24 --fast --pin
//! ```
//! Options: `--episodes N` (24), `--seed S` (1000: not a demonstration seed), `--fast`, `--pin`,
//! `--replan-every K`, `--threads T` (2), `--alt-every K` (1), `--lambda L` (1e-3).

use anyhow::{bail, Context, Result};
use pir2_runtime::Environment;
use pir2_sim::leap::{episode_seeds, LeapConfig, LeapCubeEnv, LeapModel, MpcConfig, MpcExpert, NU};

const F: usize = 32;
const S: usize = 9;

struct Step {
    fast: [f32; F],
    slow: [f32; S],
    a: [f32; NU],
    alt: Option<[f32; NU]>,
    /// The branch's action one step later (same state as the main branch's next step).
    alt_next: Option<[f32; NU]>,
}

struct Ep {
    env_seed: u64,
    steps: Vec<Step>,
    success: bool,
}

fn main() -> Result<()> {
    let mut episodes = 24usize;
    let mut seed = 1000u64;
    let mut mpc = MpcConfig::default();
    let (mut fast, mut pin, mut threads, mut alt_every, mut lambda) = (false, false, 2, 1, 1e-3);
    let mut replan = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = |n: &str| args.next().with_context(|| format!("{n} needs a value"));
        match a.as_str() {
            "--episodes" => episodes = val("--episodes")?.parse()?,
            "--seed" => seed = val("--seed")?.parse()?,
            "--fast" => fast = true,
            "--pin" => pin = true,
            "--threads" => threads = val("--threads")?.parse()?,
            "--alt-every" => alt_every = val("--alt-every")?.parse()?,
            "--lambda" => lambda = val("--lambda")?.parse()?,
            "--replan-every" => replan = Some(val("--replan-every")?.parse()?),
            other => bail!("unknown argument {other}"),
        }
    }
    if fast {
        mpc = MpcConfig::fast();
    }
    mpc.pin_first_knot = pin;
    mpc.threads = threads;
    if let Some(r) = replan {
        mpc.replan_every = r;
    }
    let alt_every = alt_every.max(1);
    println!("expert: {mpc:?}\nepisodes {episodes}, seed {seed}, alternative plan every {alt_every} steps");

    let model = LeapModel::load(None)?;
    let cfg = LeapConfig::paper();
    let mut env = LeapCubeEnv::new(&model, cfg)?;
    let mut expert = MpcExpert::new(&model, mpc, 0)?;
    let mut eps = Vec::new();
    let t0 = std::time::Instant::now();
    for index in 0..episodes {
        let (env_seed, expert_seed) = episode_seeds(seed, index);
        env.reset(env_seed);
        expert.reset(&env, expert_seed);
        let mut steps = Vec::new();
        let mut success = false;
        for t in 0..cfg.max_steps {
            let (mut f, mut s) = ([0.0f32; F], [0.0f32; S]);
            env.observe(&mut f, &mut s);
            let before = expert.snapshot();
            let a = expert.act(&env);
            let (mut alt, mut alt_next) = (None, None);
            if t % alt_every == 0 {
                // Branch: the same environment state and plan state, another sampling seed,
                // two steps (the sampled plan of a replan shows in the *next* action when
                // the first knot is pinned).
                let (env_saved, after) = (env.save(), expert.snapshot());
                expert.restore(&before);
                expert.reseed(expert_seed ^ 0x9e37_79b9_7f4a_7c15u64.wrapping_mul(t as u64 + 1));
                let b = expert.act(&env);
                if !env.step(&b).done && b == a {
                    alt_next = Some(expert.act(&env));
                }
                alt = Some(b);
                env.restore(&env_saved)?;
                expert.restore(&after);
            }
            steps.push(Step {
                fast: f,
                slow: s,
                a,
                alt,
                alt_next,
            });
            let st = env.step(&a);
            if st.done {
                success = st.success;
                break;
            }
        }
        println!(
            "episode {index:3}: {} in {:3} steps ({:.0} s)",
            if success { "success" } else { "FAIL   " },
            steps.len(),
            t0.elapsed().as_secs_f64()
        );
        eps.push(Ep {
            env_seed,
            steps,
            success,
        });
    }
    let wins = eps.iter().filter(|e| e.success).count();
    let frames: usize = eps.iter().map(|e| e.steps.len()).sum();
    println!("\nexpert success {wins}/{} on {frames} frames", eps.len());

    // Exact repeats.
    let (mut rep, mut near, mut pairs) = (0usize, 0usize, 0usize);
    for e in &eps {
        for w in e.steps.windows(2) {
            pairs += 1;
            rep += (w[0].a == w[1].a) as usize;
            let dmax = (0..NU)
                .map(|i| (w[0].a[i] - w[1].a[i]).abs())
                .fold(0.0f32, f32::max);
            near += (dmax < 1e-4) as usize;
        }
    }
    println!(
        "repeats of the previous action: bit-exact {rep}/{pairs} = {:.3}; within 1e-4 {near}/{pairs} = {:.3}",
        rep as f64 / pairs.max(1) as f64,
        near as f64 / pairs.max(1) as f64
    );

    // Label statistics.
    let all: Vec<&Step> = eps.iter().flat_map(|e| e.steps.iter()).collect();
    let mean: Vec<f64> = (0..NU)
        .map(|i| all.iter().map(|s| s.a[i] as f64).sum::<f64>() / all.len() as f64)
        .collect();
    let var_a: f64 = all
        .iter()
        .map(|s| {
            (0..NU)
                .map(|i| (s.a[i] as f64 - mean[i]).powi(2))
                .sum::<f64>()
        })
        .sum::<f64>()
        / all.len() as f64;
    println!(
        "label std (RMS over the 16 dims): {:.4}",
        (var_a / NU as f64).sqrt()
    );

    // Repeatability: pairs of actions at one state from two sampling seeds.
    let (mut dd0, mut n0, mut dd1, mut n1) = (0.0, 0usize, 0.0, 0usize);
    let sq = |x: &[f32; NU], y: &[f32; NU]| {
        (0..NU)
            .map(|i| (x[i] as f64 - y[i] as f64).powi(2))
            .sum::<f64>()
    };
    for e in &eps {
        for (t, s) in e.steps.iter().enumerate() {
            if let Some(b) = &s.alt {
                dd0 += sq(&s.a, b);
                n0 += 1;
            }
            if let (Some(b), Some(next)) = (&s.alt_next, e.steps.get(t + 1)) {
                dd1 += sq(&next.a, b);
                n1 += 1;
            }
        }
    }
    let r0 = dd0 / n0.max(1) as f64 / (2.0 * var_a);
    let r1 = dd1 / n1.max(1) as f64 / (2.0 * var_a);
    let pooled = (dd0 + dd1) / (n0 + n1).max(1) as f64 / (2.0 * var_a);
    println!(
        "repeatability Var(a - a')/(2 Var(a)): at the branching step {r0:.3} ({n0} states), \
         one step later {r1:.3} ({n1} states), pooled {pooled:.3} \
         (so at most {:.3} of the label variance is a function of the state)",
        1.0 - pooled
    );

    // Ridge fits, held out by episode.
    type Feat = fn(&[Step], usize, &mut Vec<f64>);
    let fits: [(&str, Feat); 4] = [
        ("a_(t-1) alone", |st, t, x| {
            let p = t.saturating_sub(1);
            x.extend(st[p].a.iter().map(|&v| if t == 0 { 0.0 } else { v as f64 }));
        }),
        ("obs_t alone (41)", |st, t, x| {
            x.extend(
                st[t]
                    .fast
                    .iter()
                    .chain(st[t].slow.iter())
                    .map(|&v| v as f64),
            );
        }),
        ("obs_t + a_(t-1)", |st, t, x| {
            x.extend(
                st[t]
                    .fast
                    .iter()
                    .chain(st[t].slow.iter())
                    .map(|&v| v as f64),
            );
            let p = t.saturating_sub(1);
            x.extend(st[p].a.iter().map(|&v| if t == 0 { 0.0 } else { v as f64 }));
        }),
        ("obs_t + fast_(t-1) (n_obs=2)", |st, t, x| {
            x.extend(
                st[t]
                    .fast
                    .iter()
                    .chain(st[t].slow.iter())
                    .map(|&v| v as f64),
            );
            let p = t.saturating_sub(1);
            x.extend(st[p].fast.iter().map(|&v| v as f64));
        }),
    ];
    println!(
        "ridge fits of a_t (lambda {lambda}), R² train / held-out (every 4th episode held out):"
    );
    for (name, feat) in fits {
        let (tr, te) = ridge_r2(&eps, feat, lambda);
        println!("  {name:30} {tr:.3} / {te:.3}");
    }

    // Open-loop replay.
    let (mut same, mut moved) = (0usize, 0usize);
    for e in &eps {
        for shift in [0.0, 0.001] {
            env.reset(e.env_seed);
            if shift > 0.0 {
                let (mut p, q) = env.cube_pose();
                p[0] += shift;
                env.set_cube_pose(p, q);
            }
            let mut ok = false;
            for s in &e.steps {
                let st = env.step(&s.a);
                if st.done {
                    ok = st.success;
                    break;
                }
            }
            if shift == 0.0 {
                same += ok as usize;
                if ok != e.success {
                    println!(
                        "  replay of episode seed {} differs from closed loop",
                        e.env_seed
                    );
                }
            } else {
                moved += ok as usize;
            }
        }
    }
    println!(
        "open-loop replay: same initial state {same}/{n} (closed loop {wins}/{n}); cube moved 1 mm {moved}/{n}",
        n = eps.len()
    );
    Ok(())
}

/// Ridge regression of the 16-d action on `feat` (+ a bias), R² (variance explained summed
/// over the action dims) on the training and the held-out episodes.
fn ridge_r2(eps: &[Ep], feat: fn(&[Step], usize, &mut Vec<f64>), lambda: f64) -> (f64, f64) {
    let mut x = Vec::new();
    feat(&eps[0].steps, 0, &mut x);
    let d = x.len() + 1;
    let rows = |held: bool| {
        eps.iter()
            .enumerate()
            .filter(move |(i, _)| (i % 4 == 3) == held)
            .flat_map(|(_, e)| (0..e.steps.len()).map(move |t| (e, t)))
    };
    let mut xtx = vec![0.0; d * d];
    let mut xty = vec![0.0; d * NU];
    let mut buf = Vec::with_capacity(d);
    for (e, t) in rows(false) {
        buf.clear();
        feat(&e.steps, t, &mut buf);
        buf.push(1.0);
        for i in 0..d {
            for j in 0..d {
                xtx[i * d + j] += buf[i] * buf[j];
            }
            for k in 0..NU {
                xty[i * NU + k] += buf[i] * e.steps[t].a[k] as f64;
            }
        }
    }
    for i in 0..d - 1 {
        xtx[i * d + i] += lambda * (1.0 + xtx[i * d + i]);
    }
    let w = solve_spd(&xtx, &xty, d, NU);
    let r2 = |held: bool| {
        let mut pts: Vec<([f64; NU], [f64; NU])> = Vec::new();
        let mut buf = Vec::with_capacity(d);
        for (e, t) in rows(held) {
            buf.clear();
            feat(&e.steps, t, &mut buf);
            buf.push(1.0);
            let mut y = [0.0; NU];
            for k in 0..NU {
                y[k] = (0..d).map(|i| buf[i] * w[i * NU + k]).sum();
            }
            pts.push((y, e.steps[t].a.map(|v| v as f64)));
        }
        let n = pts.len().max(1) as f64;
        let mean: Vec<f64> = (0..NU)
            .map(|k| pts.iter().map(|p| p.1[k]).sum::<f64>() / n)
            .collect();
        let (mut sse, mut sst) = (0.0, 0.0);
        for (y, a) in &pts {
            for k in 0..NU {
                sse += (a[k] - y[k]).powi(2);
                sst += (a[k] - mean[k]).powi(2);
            }
        }
        1.0 - sse / sst.max(1e-30)
    };
    (r2(false), r2(true))
}

/// Solve `A X = B` for a symmetric positive-definite `A` (`d×d`) and `B` (`d×m`) by Cholesky.
fn solve_spd(a: &[f64], b: &[f64], d: usize, m: usize) -> Vec<f64> {
    let mut l = a.to_vec();
    for j in 0..d {
        let s = l[j * d + j] - (0..j).map(|k| l[j * d + k].powi(2)).sum::<f64>();
        let dj = s.max(1e-12).sqrt();
        l[j * d + j] = dj;
        for i in j + 1..d {
            let s = l[i * d + j] - (0..j).map(|k| l[i * d + k] * l[j * d + k]).sum::<f64>();
            l[i * d + j] = s / dj;
        }
    }
    let mut x = b.to_vec();
    for c in 0..m {
        for i in 0..d {
            let s = x[i * m + c] - (0..i).map(|k| l[i * d + k] * x[k * m + c]).sum::<f64>();
            x[i * m + c] = s / l[i * d + i];
        }
        for i in (0..d).rev() {
            let s = x[i * m + c] - (i + 1..d).map(|k| l[k * d + i] * x[k * m + c]).sum::<f64>();
            x[i * m + c] = s / l[i * d + i];
        }
    }
    x
}
