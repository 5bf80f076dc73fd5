//! PPO on the paper's Leap-cube variant: train (resumable), evaluate the deterministic
//! expert, or measure throughput. See README.md next to this file.
//!
//! ```text
//! source .native/env.sh
//! cargo build --release -p pir2-sim --features mujoco --example leap_ppo
//! target/release/examples/leap_ppo --out RUN_DIR --steps 100000000          # train
//! target/release/examples/leap_ppo --out RUN_DIR --resume --steps 200000000 # continue
//! target/release/examples/leap_ppo --eval --weights RUN_DIR/expert.safetensors --episodes 200
//! target/release/examples/leap_ppo --eval --weights EXPERT --delays 0,1,2,3   # actions late
//! target/release/examples/leap_ppo --bench
//! ```

use std::fs::OpenOptions;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use pir2_runtime::Environment;
use pir2_schedule::Rng;
use pir2_sim::leap::ppo::{evaluate, evaluate_delayed, IterStats, PpoConfig, PpoExpert, Trainer};
use pir2_sim::leap::{LeapConfig, LeapCubeEnv, LeapModel, NU};
use serde_json::json;

#[derive(Debug)]
struct Args {
    mode: Mode,
    out: Option<PathBuf>,
    resume: bool,
    steps: u64,
    threads: usize,
    checkpoint_secs: f64,
    print_every: u64,
    eval_every_checkpoint: usize,
    weights: Option<PathBuf>,
    episodes: usize,
    eval_seed: u64,
    delays: Vec<usize>,
    cfg: PpoConfig,
    bench_steps: usize,
}

#[derive(Debug, PartialEq)]
enum Mode {
    Train,
    Eval,
    Bench,
}

fn parse_list(s: &str, what: &str) -> anyhow::Result<Vec<usize>> {
    s.split(',')
        .map(|v| {
            v.trim()
                .parse::<usize>()
                .with_context(|| format!("{what}: comma-separated integers"))
        })
        .collect()
}

fn parse() -> anyhow::Result<Args> {
    let mut a = Args {
        mode: Mode::Train,
        out: None,
        resume: false,
        steps: 100_000_000,
        threads: 2,
        checkpoint_secs: 300.0,
        print_every: 10,
        eval_every_checkpoint: 50,
        weights: None,
        episodes: 200,
        eval_seed: 0,
        delays: Vec::new(),
        cfg: PpoConfig::default(),
        bench_steps: 20_000,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut val = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--eval" => a.mode = Mode::Eval,
            "--bench" => a.mode = Mode::Bench,
            "--out" => a.out = Some(val()?.into()),
            "--resume" => a.resume = true,
            "--steps" => a.steps = val()?.parse()?,
            "--threads" => a.threads = val()?.parse()?,
            "--checkpoint-secs" => a.checkpoint_secs = val()?.parse()?,
            "--print-every" => a.print_every = val()?.parse()?,
            "--eval-episodes" => a.eval_every_checkpoint = val()?.parse()?,
            "--weights" => a.weights = Some(val()?.into()),
            "--episodes" => a.episodes = val()?.parse()?,
            "--eval-seed" => a.eval_seed = val()?.parse()?,
            "--delays" => a.delays = parse_list(&val()?, "delays")?,
            "--bench-steps" => a.bench_steps = val()?.parse()?,
            "--seed" => a.cfg.seed = val()?.parse()?,
            "--n-envs" => a.cfg.n_envs = val()?.parse()?,
            "--rollout-len" => a.cfg.rollout_len = val()?.parse()?,
            "--segment-iters" => a.cfg.segment_iters = val()?.parse()?,
            "--epochs" => a.cfg.epochs = val()?.parse()?,
            "--minibatches" => a.cfg.minibatches = val()?.parse()?,
            "--lr" => a.cfg.learning_rate = val()?.parse()?,
            "--entropy" => a.cfg.entropy_coef = val()?.parse()?,
            "--gamma" => a.cfg.gamma = val()?.parse()?,
            "--lambda" => a.cfg.gae_lambda = val()?.parse()?,
            "--init-std" => a.cfg.init_log_std = val()?.parse::<f32>()?.ln(),
            "--hidden" => {
                let h = parse_list(&val()?, "hidden sizes")?;
                a.cfg.actor_hidden = h.clone();
                a.cfg.critic_hidden = h;
            }
            "--prev-action" => a.cfg.prev_action = true,
            other => bail!("unknown argument {other} (see the README next to leap_ppo/main.rs)"),
        }
    }
    Ok(a)
}

fn main() -> anyhow::Result<()> {
    let args = parse()?;
    let model = LeapModel::load(None)?;
    match args.mode {
        Mode::Train => train(&model, &args),
        Mode::Eval => {
            let w = args
                .weights
                .as_deref()
                .context("--eval needs --weights FILE")?;
            let ex = PpoExpert::load(w)?;
            if !args.delays.is_empty() {
                println!("delay (ticks) | success | median steps to success");
                for &d in &args.delays {
                    let r = evaluate_delayed(
                        &model,
                        &ex,
                        0..args.episodes,
                        args.eval_seed,
                        args.threads,
                        d,
                    )?;
                    println!(
                        "{d:>13} | {}/{} = {:.3} | {}",
                        r.successes,
                        r.episodes,
                        r.success_rate(),
                        r.median_steps().map_or("-".into(), |m| m.to_string())
                    );
                }
                return Ok(());
            }
            let t0 = Instant::now();
            let r = evaluate(&model, &ex, 0..args.episodes, args.eval_seed, args.threads)?;
            let (it, steps) = ex.trained();
            println!(
                "EVAL {}: iteration {it}, {steps} env steps; success {}/{} = {:.3}; median steps to success {}; drops {}; {:.1} s",
                w.display(),
                r.successes,
                r.episodes,
                r.success_rate(),
                r.median_steps().map_or("-".into(), |m| m.to_string()),
                r.drops,
                t0.elapsed().as_secs_f64()
            );
            Ok(())
        }
        Mode::Bench => bench(&model, &args),
    }
}

fn cpu_seconds() -> f64 {
    // utime + stime of this process from /proc (Linux); NaN elsewhere.
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            let rest = s.rsplit_once(')')?.1.to_string();
            let f: Vec<&str> = rest.split_whitespace().collect();
            let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
            Some(ticks / 100.0)
        })
        .unwrap_or(f64::NAN)
}

fn bench(model: &LeapModel, args: &Args) -> anyhow::Result<()> {
    let n = args.bench_steps;
    // 1. Physics alone: the bare environment, random actions, one thread.
    let mut env = LeapCubeEnv::new(model, LeapConfig::paper())?;
    let (mut fast, mut slow) = ([0.0f32; 32], [0.0f32; 9]);
    let mut rng = Rng::new(1);
    let mut a = [0.0f32; NU];
    env.reset(0);
    let (t0, c0) = (Instant::now(), cpu_seconds());
    let mut eps = 0;
    for _ in 0..n {
        env.observe(&mut fast, &mut slow);
        a.iter_mut().for_each(|v| *v = rng.uniform_range(-1.0, 1.0));
        if env.step(&a).done {
            eps += 1;
            env.reset(eps);
        }
    }
    let (w, c) = (t0.elapsed().as_secs_f64(), cpu_seconds() - c0);
    println!(
        "physics only (LeapCubeEnv, paper, random actions, 1 thread): {n} control steps in {w:.2} s = {:.0} steps/s wall, {:.0} steps per CPU-s",
        n as f64 / w,
        n as f64 / c
    );
    // 2. Training iterations at 1 and 2 threads, two network sizes.
    for hidden in [vec![256, 128, 64], vec![512, 256, 128]] {
        for threads in [1usize, 2] {
            let cfg = PpoConfig {
                actor_hidden: hidden.clone(),
                critic_hidden: hidden.clone(),
                ..args.cfg.clone()
            };
            let mut tr = Trainer::new(model, cfg.clone(), threads)?;
            let iters = 3;
            let (mut roll, mut learn) = (0.0, 0.0);
            let (t0, c0) = (Instant::now(), cpu_seconds());
            for _ in 0..iters {
                let s = tr.iterate()?;
                roll += s.rollout_secs;
                learn += s.learn_secs;
            }
            let (w, c) = (t0.elapsed().as_secs_f64(), cpu_seconds() - c0);
            let steps = (iters * cfg.n_envs * cfg.rollout_len) as f64;
            println!(
                "PPO {hidden:?}, {} envs × {} steps, {} epochs, {threads} thread(s): {:.0} env steps/s wall ({:.0} per CPU-s); rollout {:.0} steps/s, learning share {:.0} %",
                cfg.n_envs,
                cfg.rollout_len,
                cfg.epochs,
                steps / w,
                steps / c,
                steps / roll,
                100.0 * learn / (roll + learn)
            );
            if threads == 2 {
                let sps = steps / w;
                println!(
                    "  budget at this rate: 10M steps {:.1} h, 50M {:.1} h, 100M {:.1} h",
                    1e7 / sps / 3600.0,
                    5e7 / sps / 3600.0,
                    1e8 / sps / 3600.0
                );
            }
        }
    }
    Ok(())
}

/// Keep only log lines of iterations before `iteration` (after a resume).
fn truncate_log(path: &Path, iteration: u64) -> anyhow::Result<()> {
    if !path.exists() {
        return Ok(());
    }
    let f = std::fs::File::open(path)?;
    let mut keep = Vec::new();
    for line in BufReader::new(f).lines() {
        let line = line?;
        let v: serde_json::Value = match serde_json::from_str(&line) {
            Ok(v) => v,
            Err(_) => continue,
        };
        if v.get("iteration")
            .and_then(|i| i.as_u64())
            .is_some_and(|i| i < iteration)
        {
            keep.push(line);
        }
    }
    let mut out = String::new();
    for l in keep {
        out.push_str(&l);
        out.push('\n');
    }
    std::fs::write(path, out)?;
    Ok(())
}

fn train(model: &LeapModel, args: &Args) -> anyhow::Result<()> {
    let out = args.out.as_deref().context("training needs --out DIR")?;
    std::fs::create_dir_all(out.join("experts"))?;
    let ckpt = out.join("checkpoint.safetensors");
    let log_path = out.join("log.jsonl");
    let mut tr = if args.resume {
        let tr = Trainer::load_checkpoint(model, &ckpt, args.threads)
            .with_context(|| format!("resuming from {}", ckpt.display()))?;
        truncate_log(&log_path, tr.iteration())?;
        println!(
            "resumed from {} at iteration {} ({} env steps); config {}",
            ckpt.display(),
            tr.iteration(),
            tr.env_steps(),
            serde_json::to_string(tr.config())?
        );
        tr
    } else {
        if ckpt.exists() {
            bail!(
                "{} exists: pass --resume to continue it, or choose another --out",
                ckpt.display()
            );
        }
        std::fs::write(
            out.join("config.json"),
            serde_json::to_string_pretty(&args.cfg)?,
        )?;
        std::fs::write(&log_path, "")?;
        println!("config {}", serde_json::to_string(&args.cfg)?);
        Trainer::new(model, args.cfg.clone(), args.threads)?
    };
    let mut log = OpenOptions::new()
        .append(true)
        .create(true)
        .open(&log_path)?;
    let start = Instant::now();
    let mut last_ckpt = Instant::now();
    let mut window: Vec<IterStats> = Vec::new();
    let (mut w_roll, mut w_learn, mut w_wall) = (0.0, 0.0, Instant::now());
    let mut w_steps = 0u64;
    loop {
        let s = tr.iterate()?;
        w_roll += s.rollout_secs;
        w_learn += s.learn_secs;
        w_steps += (tr.config().n_envs * tr.config().rollout_len) as u64;
        let n_ep = s.episodes.len();
        let succ = s.episodes.iter().filter(|e| e.success).count();
        let mean = |f: &dyn Fn(&pir2_sim::leap::ppo::EpisodeRecord) -> f64| {
            if n_ep == 0 {
                f64::NAN
            } else {
                s.episodes.iter().map(f).sum::<f64>() / n_ep as f64
            }
        };
        let rec = json!({
            "iteration": s.iteration,
            "env_steps": s.env_steps,
            "wall_secs": start.elapsed().as_secs_f64(),
            "rollout_secs": s.rollout_secs,
            "learn_secs": s.learn_secs,
            "episodes": n_ep,
            "successes": succ,
            "drops": s.episodes.iter().filter(|e| e.dropped).count(),
            "mean_return": mean(&|e| e.ret),
            "mean_len": mean(&|e| e.len as f64),
            "mean_step_reward": s.mean_step_reward,
            "term_orientation": mean(&|e| e.terms.orientation / e.len as f64),
            "term_position": mean(&|e| e.terms.position / e.len as f64),
            "term_hand_pose": mean(&|e| e.terms.hand_pose / e.len as f64),
            "term_action_rate": mean(&|e| e.terms.action_rate / e.len as f64),
            "term_energy": mean(&|e| e.terms.energy / e.len as f64),
            "policy_loss": s.policy_loss,
            "value_loss": s.value_loss,
            "clip_frac": s.clip_frac,
            "approx_kl": s.approx_kl,
            "mean_std": s.mean_std,
            "explained_variance": s.explained_variance,
        });
        writeln!(log, "{rec}")?;
        window.push(s);
        if tr.iteration() % args.print_every == 0 {
            let eps: Vec<_> = window.iter().flat_map(|s| s.episodes.iter()).collect();
            let n = eps.len().max(1) as f64;
            let last = window.last().expect("window is non-empty");
            println!(
                "it {:6} | {:11} steps | {:6.0} steps/s | learn {:2.0} % | ep {:4} ret {:7.2} succ {:.3} drop {:.3} len {:5.1} | σ {:.3} vloss {:8.3} ev {:5.2} kl {:.4} clip {:.3} | {:.0} s",
                tr.iteration(),
                tr.env_steps(),
                w_steps as f64 / w_wall.elapsed().as_secs_f64(),
                100.0 * w_learn / (w_roll + w_learn),
                eps.len(),
                eps.iter().map(|e| e.ret).sum::<f64>() / n,
                eps.iter().filter(|e| e.success).count() as f64 / n,
                eps.iter().filter(|e| e.dropped).count() as f64 / n,
                eps.iter().map(|e| e.len as f64).sum::<f64>() / n,
                last.mean_std,
                last.value_loss,
                last.explained_variance,
                last.approx_kl,
                last.clip_frac,
                start.elapsed().as_secs_f64(),
            );
            window.clear();
            (w_roll, w_learn, w_steps) = (0.0, 0.0, 0);
            w_wall = Instant::now();
        }
        let finished = tr.env_steps() >= args.steps;
        if tr.at_segment_boundary()
            && (finished || last_ckpt.elapsed().as_secs_f64() >= args.checkpoint_secs)
        {
            tr.save_checkpoint(&ckpt)?;
            let ex = tr.expert();
            ex.save(&out.join("expert.safetensors"))?;
            let snap = out
                .join("experts")
                .join(format!("expert-{:011}.safetensors", tr.env_steps()));
            ex.save(&snap)?;
            last_ckpt = Instant::now();
            let t0 = Instant::now();
            // Quick deterministic check on episodes disjoint from the final evaluation's.
            let r = evaluate(
                model,
                &ex,
                1_000_000..1_000_000 + args.eval_every_checkpoint,
                0,
                args.threads,
            )?;
            let line = json!({
                "iteration": tr.iteration() - 1,
                "env_steps": tr.env_steps(),
                "checkpoint": true,
                "eval_episodes": r.episodes,
                "eval_success": r.success_rate(),
                "eval_median_steps": r.median_steps(),
                "eval_drops": r.drops,
                "eval_secs": t0.elapsed().as_secs_f64(),
            });
            writeln!(log, "{line}")?;
            println!(
                "checkpoint at iteration {} ({} steps): deterministic expert {}/{} = {:.3} (median steps {}), drops {}, eval {:.1} s",
                tr.iteration(),
                tr.env_steps(),
                r.successes,
                r.episodes,
                r.success_rate(),
                r.median_steps().map_or("-".into(), |m| m.to_string()),
                r.drops,
                t0.elapsed().as_secs_f64()
            );
        }
        if finished && tr.at_segment_boundary() {
            println!("reached {} env steps; stopping", tr.env_steps());
            return Ok(());
        }
    }
}
