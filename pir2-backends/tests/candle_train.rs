//! Training, sampling, checkpoints and determinism of the candle backend.
//!
//! One file on purpose: the tests share the datasets and model configs of `common` and one call
//! helper.

mod common;

use common::*;
use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, FilmMode, ModelConfig, UNetConfig};
use pir2_backends::train::{compute_stats, TrainConfig, Trainer};
use pir2_backends::Error;
use pir2_runtime::model::{ModelInput, SlowInput, VelocityModel};
use pir2_schedule::train::{DelayDist, PiR2Draws, TrainSchedule};
use pir2_schedule::Rng;

fn quick(steps: usize, lr: f64, schedule: TrainSchedule) -> TrainConfig {
    TrainConfig {
        steps,
        batch_size: 64,
        lr,
        warmup: 20,
        betas: (0.9, 0.999),
        weight_decay: 1e-5,
        schedule,
        log_every: 1000,
        ..TrainConfig::default()
    }
}

fn mean(xs: &[(usize, f32)]) -> f32 {
    xs.iter().map(|x| x.1).sum::<f32>() / xs.len() as f32
}

/// Train, then check the loss fell and K-step Euler samples match the function.
fn learns_function(cfg: Config, steps: usize, lr: f64, tol: f32) {
    let data = dataset(256, 24, 1);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let h = cfg.spec.horizon;
    let mut model = CandleModel::new(cfg, stats, 3).unwrap();
    let report = Trainer::new(quick(steps, lr, TrainSchedule::StandardFlow))
        .run(&mut model, data.as_slice())
        .unwrap();
    let l = &report.losses;
    let (first, last) = (mean(&l[..10]), mean(&l[l.len() - 20..]));
    assert!(
        last < 0.3 * first,
        "loss did not fall enough: {first} -> {last}"
    );
    let mut rng = Rng::new(9);
    let mut worst = 0.0f32;
    for &(c0, c1) in &[(-0.7f32, 0.2f32), (0.0, -0.5), (0.4, 0.8), (0.9, -0.9)] {
        // The target is deterministic, so the mean of a few sampled chunks must match it
        // (one sample alone also carries the flow's residual sampling noise).
        const SAMPLES: usize = 4;
        let mut chunk = vec![0.0f32; h * A];
        for _ in 0..SAMPLES {
            let c = model
                .sample_euler(
                    &obs(c0),
                    SlowInput::Vector {
                        data: &[c1],
                        dim: 1,
                    },
                    1,
                    10,
                    &mut rng,
                )
                .unwrap();
            for (m, v) in chunk.iter_mut().zip(&c) {
                *m += v / SAMPLES as f32;
            }
        }
        let want = target(c0, c1);
        eprintln!("({c0}, {c1}): want {want:?}, got {:?}", &chunk[..A]);
        for p in 0..h {
            for j in 0..A {
                worst = worst.max((chunk[p * A + j] - want[j]).abs());
            }
        }
    }
    eprintln!("loss {first} -> {last}, worst sample error {worst}");
    assert!(
        worst < tol,
        "sampled actions off by {worst} (tolerance {tol})"
    );
}

#[test]
fn mlp_learns_a_known_function() {
    learns_function(mlp_config(8), 1500, 3e-3, 0.25);
}

#[test]
fn unet_learns_a_known_function() {
    let cfg = Config {
        spec: spec(8),
        model: ModelConfig::UNet(UNetConfig {
            widths: vec![16, 32],
            kernel: 3,
            groups: 4,
            tau_dim: 16,
            dvis_dim: 4,
            film: FilmMode::PerPositionHeads,
        }),
    };
    learns_function(cfg, 300, 6e-3, 0.2);
}

fn train_weights(seed: u64, schedule: TrainSchedule) -> Vec<Vec<f32>> {
    let cfg = mlp_config(8);
    let data = dataset(8, 12, 2);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let mut model = CandleModel::new(cfg, stats, 5).unwrap();
    let tc = TrainConfig {
        seed,
        ema: Some(0.9),
        batch_size: 16,
        ..quick(15, 1e-3, schedule)
    };
    Trainer::new(tc).run(&mut model, data.as_slice()).unwrap();
    model
        .vars()
        .iter()
        .map(|(_, v)| v.flatten_all().unwrap().to_vec1::<f32>().unwrap())
        .collect()
}

#[test]
fn same_seed_same_weights() {
    let s = TrainSchedule::PiR2(PiR2Draws {
        n: Some(2),
        delay: DelayDist::Uniform { max: 2 },
        ..PiR2Draws::default()
    });
    let a = train_weights(11, s);
    let b = train_weights(11, s);
    let bits = |w: &Vec<Vec<f32>>| w.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a), bits(&b));
    assert_ne!(bits(&a), bits(&train_weights(12, s)));
}

fn one_call(m: &mut CandleModel) -> Vec<f32> {
    let h = m.spec().horizon;
    let tau: Vec<f32> = (0..h)
        .map(|p| if p == 0 { -1.0 } else { p as f32 / h as f32 })
        .collect();
    call_at(m, &tau)
}

fn call_at(m: &mut CandleModel, tau: &[f32]) -> Vec<f32> {
    let h = m.spec().horizon;
    let x: Vec<f32> = (0..h * A).map(|i| (i as f32 * 0.37).sin()).collect();
    let o = obs(0.3);
    let input = ModelInput {
        batch: 1,
        horizon: h,
        action_dim: A,
        x: &x,
        tau,
        obs_fast: &o,
        n_obs: 2,
        fast_dim: F,
        slow: SlowInput::Vector {
            data: &[0.1],
            dim: 1,
        },
        d_vis: &[1],
    };
    let mut v = vec![0.0; h * A];
    m.velocity(&input, &mut v).unwrap();
    v
}

#[test]
fn checkpoint_round_trip_and_no_overwrite() {
    let dir = std::env::temp_dir().join(format!("pir2-ck-rt-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let cfg = mlp_config(8);
    let data = dataset(4, 10, 3);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let mut m = CandleModel::new(cfg.clone(), stats, 1).unwrap();
    m.save(&dir).unwrap();
    let mut back = CandleModel::load_expect(&dir, &cfg.spec).unwrap();
    assert_eq!(back.stats(), m.stats());
    assert_eq!(one_call(&mut m), one_call(&mut back));
    assert!(matches!(m.save(&dir), Err(Error::CheckpointExists(_))));
    let other = pir2_backends::config::Spec {
        fast_dim: 3,
        ..cfg.spec
    };
    assert!(matches!(
        CandleModel::load_expect(&dir, &other),
        Err(Error::SpecMismatch {
            field: "fast_dim",
            ..
        })
    ));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn missing_or_misshapen_tensor_is_named() {
    use pir2_backends::checkpoint;
    let base = std::env::temp_dir().join(format!("pir2-ck-bad-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&base);
    let cfg = mlp_config(8);
    let m = CandleModel::new(cfg.clone(), pir2_backends::Stats::identity(&cfg.spec), 1).unwrap();
    let tensors: Vec<(String, Vec<usize>, Vec<f32>)> = m
        .vars()
        .iter()
        .map(|(n, v)| {
            (
                n.clone(),
                v.dims().to_vec(),
                v.flatten_all().unwrap().to_vec1().unwrap(),
            )
        })
        .collect();
    // Missing.
    let dir = base.join("missing");
    checkpoint::save(
        &dir,
        &cfg,
        m.stats(),
        tensors
            .iter()
            .filter(|t| t.0 != "mlp.1.weight")
            .map(|(n, s, d)| (n.clone(), s.clone(), d.as_slice())),
    )
    .unwrap();
    let e = CandleModel::load(&dir).unwrap_err();
    assert!(
        matches!(&e, Error::MissingTensor { name, .. } if name == "mlp.1.weight"),
        "{e}"
    );
    assert!(e.to_string().contains("mlp.1.weight"));
    // Wrong shape.
    let dir = base.join("shape");
    checkpoint::save(
        &dir,
        &cfg,
        m.stats(),
        tensors.iter().map(|(n, s, d)| {
            if n == "mlp.out.bias" {
                (n.clone(), vec![1, s[0]], d.as_slice())
            } else {
                (n.clone(), s.clone(), d.as_slice())
            }
        }),
    )
    .unwrap();
    let e = CandleModel::load(&dir).unwrap_err();
    assert!(
        matches!(&e, Error::TensorShape { name, .. } if name == "mlp.out.bias"),
        "{e}"
    );
    // Extra tensor (weights of another architecture).
    let dir = base.join("extra");
    let extra = [0.0f32; 2];
    checkpoint::save(
        &dir,
        &cfg,
        m.stats(),
        tensors
            .iter()
            .map(|(n, s, d)| (n.clone(), s.clone(), d.as_slice()))
            .chain(std::iter::once(("stray".to_string(), vec![2], &extra[..]))),
    )
    .unwrap();
    let e = CandleModel::load(&dir).unwrap_err();
    assert!(
        matches!(&e, Error::UnexpectedTensor { name, .. } if name == "stray"),
        "{e}"
    );
    std::fs::remove_dir_all(&base).unwrap();
}

#[test]
fn validation_callback_picks_the_best_checkpoint() {
    let dir = std::env::temp_dir().join(format!("pir2-val-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let cfg = mlp_config(8);
    let data = dataset(8, 12, 4);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let mut m = CandleModel::new(cfg, stats, 0).unwrap();
    let scores = [0.2, 0.9, 0.4];
    let mut seen = Vec::new();
    let mut calls = 0;
    let tc = TrainConfig {
        checkpoint_every: Some(5),
        batch_size: 8,
        ..quick(15, 1e-3, TrainSchedule::StandardFlow)
    };
    let report = Trainer::new(tc)
        .out_dir(&dir)
        .validate(|_m: &mut CandleModel, step| {
            seen.push(step);
            calls += 1;
            scores[calls - 1]
        })
        .run(&mut m, data.as_slice())
        .unwrap();
    assert_eq!(seen, vec![5, 10, 15]);
    let best = report.best.clone().unwrap();
    assert_eq!(best.step, 10);
    // The model holds the best weights, identical to the saved step-10 checkpoint.
    let mut saved = CandleModel::load(best.dir.as_ref().unwrap()).unwrap();
    assert_eq!(one_call(&mut m), one_call(&mut saved));
    assert!(dir.join("loss.jsonl").exists() && dir.join("best.json").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn tied_validation_scores_go_to_the_earlier_step_by_default_and_the_later_on_request() {
    let cfg = mlp_config(8);
    let data = dataset(8, 12, 4);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let tc = TrainConfig {
        checkpoint_every: Some(5),
        batch_size: 8,
        ..quick(20, 1e-3, TrainSchedule::StandardFlow)
    };
    // Steps 5, 10, 15, 20: the best score 0.5 is reached at 10 and tied at 15.
    let scores = [0.1, 0.5, 0.5, 0.3];
    let best_step = |later: bool| {
        let mut m = CandleModel::new(cfg.clone(), stats.clone(), 0).unwrap();
        let mut calls = 0;
        let report = Trainer::new(tc.clone())
            .later_ties(later)
            .validate(|_m: &mut CandleModel, _step| {
                calls += 1;
                scores[calls - 1]
            })
            .run(&mut m, data.as_slice())
            .unwrap();
        let best = report.best.unwrap();
        assert_eq!(best.score, Some(0.5));
        best.step
    };
    assert_eq!(best_step(false), 10);
    assert_eq!(best_step(true), 15);
}

#[test]
fn self_rollout_training_runs_and_stays_finite() {
    use pir2_backends::train::SelfRollout;
    let cfg = mlp_config(8);
    let data = dataset(8, 12, 5);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let mut m = CandleModel::new(cfg, stats, 0).unwrap();
    let s = TrainSchedule::PiR2(PiR2Draws {
        n: Some(2),
        delay: DelayDist::Uniform { max: 2 },
        ..PiR2Draws::default()
    });
    let tc = TrainConfig {
        self_rollout: Some(SelfRollout {
            prob: 0.5,
            step: 0.5,
        }),
        batch_size: 16,
        ..quick(20, 1e-3, s)
    };
    let r = Trainer::new(tc).run(&mut m, data.as_slice()).unwrap();
    assert_eq!(r.losses.len(), 20);
    assert!(r.losses.iter().all(|l| l.1.is_finite()));
}

#[test]
fn dit_trains_and_its_delay_embedding_starts_at_zero() {
    use pir2_backends::config::DitConfig;
    let cfg = Config {
        spec: spec(8),
        model: ModelConfig::Dit(DitConfig {
            width: 32,
            depth: 2,
            heads: 4,
            mlp_ratio: 2,
            tau_dim: 16,
            ada: FilmMode::PerPositionHeads,
        }),
    };
    let data = dataset(32, 16, 6);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let mut m = CandleModel::new(cfg.clone(), stats, 0).unwrap();
    let (_, delay) = m
        .vars()
        .iter()
        .find(|(n, _)| n == "delay_embed")
        .expect("delay embedding");
    assert_eq!(delay.dims(), &[cfg.spec.d_vis_max + 1, 32]);
    assert!(delay
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .iter()
        .all(|&v| v == 0.0));
    let r = Trainer::new(quick(100, 3e-3, TrainSchedule::StandardFlow))
        .run(&mut m, data.as_slice())
        .unwrap();
    let l = &r.losses;
    let (first, last) = (mean(&l[..10]), mean(&l[l.len() - 20..]));
    assert!(
        last < 0.5 * first,
        "DiT loss did not fall: {first} -> {last}"
    );
    // The delay embedding received gradient (it is part of the model, not a constant).
    let (_, delay) = m.vars().iter().find(|(n, _)| n == "delay_embed").unwrap();
    assert!(delay
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .iter()
        .any(|&v| v != 0.0));
}

#[test]
fn finetune_from_shared_film_starts_position_uniform() {
    let dir = std::env::temp_dir().join(format!("pir2-ft-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let unet = |film| Config {
        spec: spec(8),
        model: ModelConfig::UNet(UNetConfig {
            widths: vec![8, 16],
            kernel: 3,
            groups: 4,
            tau_dim: 8,
            dvis_dim: 2,
            film,
        }),
    };
    let shared = CandleModel::new(
        unet(FilmMode::Shared),
        pir2_backends::Stats::identity(&spec(8)),
        2,
    )
    .unwrap();
    shared.save(&dir).unwrap();
    let mut shared = CandleModel::load(&dir).unwrap();
    // The ablation (a zero-initialised shared projection of τ_p): equal at any τ.
    let mut pp = CandleModel::init_from(&dir, unet(FilmMode::PerPositionTau)).unwrap();
    assert!(pp.vars().iter().any(|(n, _)| n.contains("film_pos")));
    assert_eq!(one_call(&mut shared), one_call(&mut pp));
    // The paper's heads: every head a copy of the shared head, so the first forward equals the
    // base's at a position-uniform τ (the base's own regime), to 1e-6.
    let mut heads = CandleModel::init_from(&dir, unet(FilmMode::PerPositionHeads)).unwrap();
    assert!(heads.vars().iter().any(|(n, _)| n.contains("film_heads")));
    assert!(!heads
        .vars()
        .iter()
        .any(|(n, _)| n.ends_with(".film.weight")));
    for t in [0.0, 0.4, 1.0] {
        let tau = vec![t; 8];
        let (a, b) = (call_at(&mut shared, &tau), call_at(&mut heads, &tau));
        for (x, y) in a.iter().zip(&b) {
            assert!(
                (x - y).abs() <= 1e-6 * x.abs().max(1.0),
                "τ = {t}: {x} vs {y}"
            );
        }
    }
    // At a staircase τ the heads see each position's own τ, the shared head only the mean.
    assert_ne!(one_call(&mut shared), one_call(&mut heads));
    // A plain load with the wrong architecture still fails, naming a tensor.
    assert!(matches!(
        CandleModel::init_from(&dir, mlp_config(8)),
        Err(Error::MissingTensor { .. } | Error::TensorShape { .. })
    ));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn shipped_configs_parse_and_build() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        let cfg = Config::from_file(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        let m =
            CandleModel::new(cfg.clone(), pir2_backends::Stats::identity(&cfg.spec), 0).unwrap();
        assert!(m.num_params() > 0);
        n += 1;
    }
    assert!(n >= 2, "expected the shipped configs in {}", dir.display());
}

#[test]
fn trainer_refuses_a_dir_with_old_checkpoints_before_training() {
    let dir = std::env::temp_dir().join(format!("pir2-old-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("step-000005")).unwrap();
    let cfg = mlp_config(8);
    let data = dataset(4, 10, 7);
    let mut m = CandleModel::new(
        cfg.clone(),
        compute_stats(data.as_slice(), &cfg.spec).unwrap(),
        0,
    )
    .unwrap();
    let mut steps = 0;
    let r = Trainer::new(quick(5, 1e-3, TrainSchedule::StandardFlow))
        .out_dir(&dir)
        .on_progress(|_| steps += 1)
        .run(&mut m, data.as_slice());
    assert!(matches!(r, Err(Error::CheckpointExists(_))));
    assert_eq!(steps, 0);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn hidden_front_draws_train_every_architecture() {
    use pir2_backends::config::DitConfig;
    use pir2_schedule::train::FrontVisibility;
    let s = TrainSchedule::PiR2(PiR2Draws {
        n: Some(2),
        delay: DelayDist::Uniform { max: 2 },
        front: FrontVisibility::Hidden,
        ..PiR2Draws::default()
    });
    let data = dataset(8, 12, 8);
    for model in [
        mlp_config(8).model,
        ModelConfig::UNet(UNetConfig {
            widths: vec![8, 16],
            kernel: 3,
            groups: 4,
            tau_dim: 8,
            dvis_dim: 2,
            film: FilmMode::PerPositionHeads,
        }),
        ModelConfig::Dit(DitConfig {
            width: 16,
            depth: 2,
            heads: 2,
            mlp_ratio: 2,
            tau_dim: 8,
            ada: FilmMode::PerPositionHeads,
        }),
    ] {
        let cfg = Config {
            spec: spec(8),
            model,
        };
        let mut m = CandleModel::new(
            cfg.clone(),
            compute_stats(data.as_slice(), &cfg.spec).unwrap(),
            0,
        )
        .unwrap();
        let r = Trainer::new(TrainConfig {
            batch_size: 8,
            ..quick(5, 1e-3, s)
        })
        .run(&mut m, data.as_slice())
        .unwrap();
        assert!(r.losses.iter().all(|l| l.1.is_finite()), "{:?}", cfg.model);
        assert!(one_call(&mut m).iter().all(|v| v.is_finite()));
    }
}

/// `held_out_loss` draws its batches as the trainer does: with the trainer's seed, batch
/// size and schedule, its one-batch loss is the trainer's step-1 loss (computed before the
/// first update); it is deterministic, and it falls once the model has trained.
#[test]
fn held_out_loss_matches_the_trainers_first_step_and_falls_with_training() {
    use pir2_backends::train::held_out_loss;
    let cfg = mlp_config(8);
    let data = dataset(32, 16, 2);
    let stats = compute_stats(data.as_slice(), &cfg.spec).unwrap();
    let schedule = TrainSchedule::PiR2(PiR2Draws {
        n: Some(2),
        delay: DelayDist::Uniform { max: 2 },
        ..PiR2Draws::default()
    });
    let tc = TrainConfig {
        seed: 5,
        ..quick(150, 3e-3, schedule)
    };
    let mut model = CandleModel::new(cfg, stats, 1).unwrap();
    let before = held_out_loss(&mut model, data.as_slice(), schedule, 64, 1, 5).unwrap();
    assert_eq!(
        before,
        held_out_loss(&mut model, data.as_slice(), schedule, 64, 1, 5).unwrap()
    );
    let report = Trainer::new(tc).run(&mut model, data.as_slice()).unwrap();
    let first = report.losses[0].1 as f64;
    assert!(
        (before - first).abs() < 1e-4 * first.max(1.0),
        "{before} vs the trainer's {first}"
    );
    let after = held_out_loss(&mut model, data.as_slice(), schedule, 64, 4, 6).unwrap();
    assert!(after < 0.5 * before, "{before} -> {after}");
}

/// The per-position heads specialise in training: they start as copies of one head and, after a
/// few πR² steps (per-position τ), the heads of one block differ from each other.
#[test]
fn per_position_heads_specialise_in_training() {
    let cfg = Config {
        spec: spec(8),
        model: ModelConfig::UNet(UNetConfig {
            widths: vec![8, 16],
            kernel: 3,
            groups: 4,
            tau_dim: 8,
            dvis_dim: 2,
            film: FilmMode::PerPositionHeads,
        }),
    };
    let data = dataset(8, 12, 8);
    let mut m = CandleModel::new(
        cfg.clone(),
        compute_stats(data.as_slice(), &cfg.spec).unwrap(),
        0,
    )
    .unwrap();
    let heads = |m: &CandleModel| -> Vec<f32> {
        let (_, v) = m
            .vars()
            .iter()
            .find(|(n, _)| n == "down.0.res0.film_heads.weight")
            .unwrap();
        v.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    let spread = |w: &[f32]| -> f32 {
        let per = w.len() / 8;
        (1..8)
            .flat_map(|p| (0..per).map(move |i| (p, i)))
            .map(|(p, i)| (w[p * per + i] - w[i]).abs())
            .fold(0.0, f32::max)
    };
    assert_eq!(spread(&heads(&m)), 0.0, "heads start as copies");
    let s = TrainSchedule::PiR2(PiR2Draws {
        n: Some(2),
        delay: DelayDist::Uniform { max: 2 },
        ..PiR2Draws::default()
    });
    Trainer::new(TrainConfig {
        batch_size: 8,
        ..quick(20, 1e-3, s)
    })
    .run(&mut m, data.as_slice())
    .unwrap();
    let after = spread(&heads(&m));
    assert!(after > 1e-4, "heads did not specialise: spread {after}");
}

/// A DiT finetuned with per-position AdaLN heads from a shared-head checkpoint starts as that
/// checkpoint: every head is a copy of the shared head, and the shared head already read each
/// token's own τ, so the first forward is equal at any τ.
#[test]
fn dit_finetuned_with_heads_starts_as_its_shared_checkpoint() {
    use pir2_backends::config::DitConfig;
    let dir = std::env::temp_dir().join(format!("pir2-ft-dit-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let dit = |ada| Config {
        spec: spec(8),
        model: ModelConfig::Dit(DitConfig {
            width: 16,
            depth: 2,
            heads: 2,
            mlp_ratio: 2,
            tau_dim: 8,
            ada,
        }),
    };
    let shared = CandleModel::new(
        dit(FilmMode::PerPositionTau),
        pir2_backends::Stats::identity(&spec(8)),
        4,
    )
    .unwrap();
    // adaLN-zero starts at zero: perturb every weight so the modulation carries signal.
    let mut rng = Rng::new(9);
    for (_, v) in shared.vars() {
        let t = v.as_tensor();
        let noise: Vec<f32> = (0..t.elem_count())
            .map(|_| rng.uniform_range(-0.2, 0.2))
            .collect();
        let noise = candle_core::Tensor::from_vec(noise, t.dims(), t.device()).unwrap();
        v.set(&(t + noise).unwrap()).unwrap();
    }
    shared.save(&dir).unwrap();
    let mut shared = CandleModel::load(&dir).unwrap();
    let mut heads = CandleModel::init_from(&dir, dit(FilmMode::PerPositionHeads)).unwrap();
    assert!(heads
        .vars()
        .iter()
        .any(|(n, _)| n == "blocks.0.ada_heads.weight"));
    assert!(heads
        .vars()
        .iter()
        .any(|(n, _)| n == "final.ada_heads.bias"));
    let (a, b) = (one_call(&mut shared), one_call(&mut heads));
    assert!(
        a.iter().any(|v| v.abs() > 1e-3),
        "the head must compute something"
    );
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() <= 1e-5 * x.abs().max(1.0), "{x} vs {y}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
