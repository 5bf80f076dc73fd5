//! A run interrupted after a step checkpoint and resumed continues bit-identically to an
//! uninterrupted run (weights, loss history, checkpoint pick), for the fused U-Net path and
//! the candle-graph path.

mod common;

use common::*;
use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, FilmMode, ModelConfig, UNetConfig};
use pir2_backends::train::{compute_stats, SelfRollout, TrainConfig, TrainReport, Trainer};
use pir2_schedule::train::TrainSchedule;

fn unet() -> Config {
    Config {
        spec: spec(8),
        model: ModelConfig::UNet(UNetConfig {
            widths: vec![8, 16],
            kernel: 3,
            groups: 4,
            tau_dim: 8,
            dvis_dim: 2,
            film: FilmMode::PerPositionHeads,
        }),
    }
}

fn tc() -> TrainConfig {
    TrainConfig {
        steps: 8,
        batch_size: 16,
        lr: 3e-3,
        warmup: 2,
        ema: Some(0.9),
        checkpoint_every: Some(2),
        self_rollout: Some(SelfRollout {
            prob: 0.5,
            step: 0.25,
        }),
        schedule: TrainSchedule::StandardFlow,
        log_every: 1,
        ..TrainConfig::default()
    }
}

/// Validation score that peaks mid-run, so the best pick is not the last checkpoint.
fn score(step: usize) -> f64 {
    -((step as f64) - 4.0).abs()
}

fn bits(m: &CandleModel) -> Vec<Vec<u32>> {
    m.vars()
        .iter()
        .map(|(_, v)| {
            v.flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
                .iter()
                .map(|x| x.to_bits())
                .collect()
        })
        .collect()
}

fn run(
    cfg: &Config,
    fused: bool,
    dir: &std::path::Path,
    stop: Option<usize>,
    resume: bool,
) -> (CandleModel, TrainReport) {
    let data = dataset(8, 12, 3);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    // A resumed run starts from a differently seeded model: the checkpoint must override it.
    let seed = if resume { 99 } else { 1 };
    let mut m = CandleModel::new(cfg.clone(), stats, seed).unwrap();
    let mut t = Trainer::new(tc())
        .fused(fused)
        .out_dir(dir)
        .resume(resume)
        .validate(|_, step| score(step));
    if let Some(s) = stop {
        t = t.stop_after(s);
    }
    let r = t.run(&mut m, data.as_slice()).unwrap();
    (m, r)
}

fn check(cfg: Config, fused: bool) {
    let root = std::env::temp_dir().join(format!("pir2-resume-{fused}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let (straight, r1) = run(&cfg, fused, &root.join("a"), None, false);
    // Interrupted after step 5: the last step checkpoint is step 4.
    let (_, partial) = run(&cfg, fused, &root.join("b"), Some(5), false);
    assert_eq!(partial.losses.len(), 5);
    let (resumed, r2) = run(&cfg, fused, &root.join("b"), None, true);
    assert_eq!(
        bits(&straight),
        bits(&resumed),
        "final weights differ after resume"
    );
    assert_eq!(r1, {
        // Directories differ by the run's root; compare everything else.
        let mut r = r2.clone();
        for c in r.checkpoints.iter_mut().chain(r.best.iter_mut()) {
            c.dir = c
                .dir
                .as_ref()
                .map(|d| root.join("a").join(d.file_name().unwrap()));
        }
        r
    });
    assert_eq!(r1.best.as_ref().map(|b| b.step), Some(4));
    assert_eq!(r2.losses.len(), 8);
    // A changed configuration is refused.
    let data = dataset(8, 12, 3);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let mut m = CandleModel::new(cfg.clone(), stats, 1).unwrap();
    let other = TrainConfig { lr: 1e-3, ..tc() };
    let err = Trainer::new(other)
        .out_dir(root.join("b"))
        .resume(true)
        .run(&mut m, data.as_slice())
        .unwrap_err();
    assert!(err.to_string().contains("training configuration"), "{err}");
    let _ = std::fs::remove_dir_all(&root);
}

/// The study trains side-by-side jobs with their kernels on pools of their own
/// (`with_kernel_pool`, the global pool's thread count): a job's bits are those of the same
/// run on the global pool, also while another job runs at the same time.
#[test]
fn fused_unet_bits_on_a_pool_of_its_own_are_those_of_the_global_pool() {
    use pir2_backends::candle::with_kernel_pool;
    let mut wide = unet();
    if let ModelConfig::UNet(u) = &mut wide.model {
        u.widths = vec![32, 64];
    }
    let root = std::env::temp_dir().join(format!("pir2-pools-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let result = |(m, r): (CandleModel, TrainReport)| (bits(&m), r.losses);
    let global = result(run(&wide, true, &root.join("global"), None, false));
    let (a, b) = std::thread::scope(|s| {
        let job = |name: &'static str| {
            let (cfg, dir) = (&wide, root.join(name));
            s.spawn(move || with_kernel_pool(|| result(run(cfg, true, &dir, None, false))).unwrap())
        };
        let (a, b) = (job("a"), job("b"));
        (a.join().unwrap(), b.join().unwrap())
    });
    assert!(
        global == a,
        "a job on its own pool differs from the global pool's run"
    );
    assert!(global == b, "the second concurrent job differs");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn fused_unet_resume_is_bit_identical() {
    check(unet(), true);
}

#[test]
fn candle_graph_resume_is_bit_identical() {
    check(mlp_config(4), false);
}

/// A run stopped by its stop flag between two step checkpoints (here: after step 5, the
/// checkpoints being every 2 steps) writes its training state as `interrupted-000005/` and
/// returns `Error::Interrupted`; resumed, it continues from step 5 (not from the step-4
/// checkpoint) bit-identically to an uninterrupted run, and the interrupted state is
/// removed when the run finishes. It is never a step checkpoint.
#[test]
fn a_stop_flag_saves_the_exact_step_and_resume_continues_from_it() {
    use pir2_backends::Error;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;

    let cfg = unet();
    let root = std::env::temp_dir().join(format!("pir2-stop-flag-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let (straight, r1) = run(&cfg, true, &root.join("a"), None, false);

    let dir = root.join("b");
    let data = dataset(8, 12, 3);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let mut m = CandleModel::new(cfg.clone(), stats.clone(), 1).unwrap();
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    let err = Trainer::new(tc())
        .out_dir(&dir)
        .validate(|_, step| score(step))
        .on_progress(move |p| {
            if p.step == 5 {
                f.store(true, Ordering::SeqCst);
            }
        })
        .stop_on(flag)
        .run(&mut m, data.as_slice())
        .unwrap_err();
    match &err {
        Error::Interrupted {
            step: 5,
            resume_point: Some(p),
        } => assert!(p.ends_with("interrupted-000005"), "{err}"),
        other => panic!("{other:?}"),
    }
    assert!(dir.join("interrupted-000005").is_dir());
    assert!(!dir.join("step-000006").exists());
    // A fresh run into that directory is refused; a resumed one continues from step 5.
    let mut m = CandleModel::new(cfg.clone(), stats.clone(), 1).unwrap();
    assert!(Trainer::new(tc())
        .out_dir(&dir)
        .run(&mut m, data.as_slice())
        .is_err());
    let mut losses_after = Vec::new();
    let mut m = CandleModel::new(cfg.clone(), stats.clone(), 99).unwrap();
    let r2 = Trainer::new(tc())
        .out_dir(&dir)
        .resume(true)
        .validate(|_, step| score(step))
        .on_progress(|p| losses_after.push(p.step))
        .run(&mut m, data.as_slice())
        .unwrap();
    assert_eq!(losses_after, vec![6, 7, 8], "continued from step 5");
    assert_eq!(
        bits(&straight),
        bits(&m),
        "final weights differ after the stop"
    );
    assert_eq!(r1.losses, r2.losses);
    assert_eq!(
        r1.best.as_ref().map(|b| b.step),
        r2.best.as_ref().map(|b| b.step)
    );
    assert!(
        !dir.join("interrupted-000005").exists(),
        "removed at the end"
    );
    let _ = std::fs::remove_dir_all(&root);
}
