//! The Leap study's defaults are the paper's simulation protocol (feature `mujoco`: the task
//! loads the scene; nothing is trained).
#![cfg(feature = "mujoco")]

use pir2_backends::config::FilmMode;
use pir2_cli::study::leap_cube::{LeapCubeTask, LeapStudyConfig};
use pir2_cli::study::{Sweep, Task};
use pir2_runtime::{DelayLaw, LockstepTiming, Mode, Policy};
use pir2_schedule::train::{DelayDist, TrainSchedule};

fn task(cfg: LeapStudyConfig) -> LeapCubeTask {
    LeapCubeTask::new(cfg).expect("Leap-cube scene: source .native/env.sh")
}

#[test]
fn defaults_are_the_papers_simulation_protocol() {
    let t = task(LeapStudyConfig::default());
    let settings = t.settings();
    // Validation success rates tie often: the later checkpoint wins a tie.
    assert!(settings.later_ties);
    let r = settings.recipe;
    assert_eq!(r.flow_steps, 15);
    assert_eq!(r.delays, DelayLaw::Exponential { rate: 1.0 });
    let TrainSchedule::PiR2(draws) = Policy::PiR2.schedule(&r) else {
        panic!("πR² draws a staircase");
    };
    assert_eq!(draws.delay, DelayDist::Exponential { max: 5, rate: 1.0 });
    assert_eq!(
        Policy::Rtc.schedule(&r),
        TrainSchedule::TrainTimeRtc {
            delay: DelayDist::Exponential { max: 10, rate: 1.0 }
        }
    );
    // No staleness training, no delay embedding; two observation frames.
    let spec = t.spec();
    assert_eq!((spec.d_vis_max, spec.n_obs), (0, 2));
    // Two frames on the slow (cube) channel too: 2 × 9 values.
    assert_eq!(spec.slow, pir2_runtime::SlowSpec::Vector { dim: 18 });
    // The deployment study starts with sync flow acting h = d (the paper: "h = d for all
    // methods"), then the rows.
    let study = t.deployment_study();
    assert_eq!(study.rows[0].sweep, Sweep::UnitDelaySync);
    assert!(matches!(
        study.rows[0].row.mode,
        Mode::SyncFlow { steps: 15, .. }
    ));
    assert_eq!(study.rows.len(), t.rows().len() + 1);
    // Naive async is the plain swap; temporal ensembling is a separate, labelled row.
    let rows = t.rows();
    let labels: Vec<&str> = rows.iter().map(|r| r.label.as_str()).collect();
    let plain = rows
        .iter()
        .find(|r| r.label == "naive async")
        .unwrap_or_else(|| panic!("no plain naive async row in {labels:?}"));
    assert!(matches!(
        plain.mode,
        Mode::NaiveAsync {
            steps: 15,
            ensemble: None
        }
    ));
    let te: Vec<_> = rows
        .iter()
        .filter(|r| {
            matches!(
                r.mode,
                Mode::NaiveAsync {
                    ensemble: Some(_),
                    ..
                }
            )
        })
        .collect();
    assert_eq!(te.len(), 1);
    assert!(te[0].label.contains("not in the paper"), "{}", te[0].label);
    assert!(rows.iter().any(|r| r.label == "train-time RTC"));
    let no_te = task(LeapStudyConfig {
        te_row: false,
        ..LeapStudyConfig::default()
    });
    assert!(!no_te.rows().iter().any(|r| matches!(
        r.mode,
        Mode::NaiveAsync {
            ensemble: Some(_),
            ..
        }
    )));
}

#[test]
fn the_zero_delay_policy_is_the_horizon_studys_and_validates_at_zero_latency() {
    let t = task(LeapStudyConfig {
        policies: vec![
            Policy::Flow,
            Policy::PiR2,
            Policy::PiR2ZeroDelay,
            Policy::PiR2ZeroDelayFull,
        ],
        ..LeapStudyConfig::default()
    });
    for zp in [Policy::PiR2ZeroDelay, Policy::PiR2ZeroDelayFull] {
        // Not a deployment-study row (it cannot run with a delay) ...
        assert!(!t.rows().iter().any(|r| r.policy == zp));
        // ... but a horizon-study row, at zero latency.
        let h = t.horizon_study();
        let zd = h
            .rows
            .iter()
            .find(|r| r.row.policy == zp)
            .expect("a zero-delay row");
        assert_eq!(zd.sweep, Sweep::Once(LockstepTiming::zero_latency()));
        assert!(h.policies().contains(&zp));
        let (mode, timing) = t.validation(zp);
        assert!(matches!(mode, Mode::PiR2Async { .. }));
        assert_eq!(timing, LockstepTiming::zero_latency());
    }
    // The paper's variant runs the full streaming ramp (n = H), the extra n = `nfe`.
    let (full, _) = t.validation(Policy::PiR2ZeroDelayFull);
    assert!(matches!(full, Mode::PiR2Async { nfe: None, .. }));
    // Others validate at the settings' unit delay.
    let (mode, timing) = t.validation(Policy::PiR2);
    assert_eq!(mode, t.validation_mode(Policy::PiR2));
    assert_eq!(timing, LockstepTiming::for_mode(&mode, t.settings().val_d0));
    assert_ne!(timing, LockstepTiming::zero_latency());
}

/// The evaluation environment stacks the slow frames exactly as training stacks the recorded
/// ones: same seed, same actions, same values (sensing noise included).
#[test]
fn evaluation_stacks_slow_frames_as_training_does() {
    use pir2_runtime::Environment;
    use pir2_sim::dataset::Episode;
    use pir2_sim::leap::{LeapConfig, LeapCubeEnv, LeapModel, NU};

    let t = task(LeapStudyConfig {
        max_steps: 40,
        ..LeapStudyConfig::default()
    });
    let scene = LeapModel::load(None).expect("scene");
    let mut bare = LeapCubeEnv::new(
        &scene,
        LeapConfig {
            max_steps: 40,
            ..LeapConfig::paper()
        },
    )
    .expect("env");
    let mut stacked = t.make_env().expect("env");
    let (f, s) = (bare.spec().fast_dim, bare.spec().slow_dim);
    assert_eq!(stacked.spec().slow_dim, 2 * s);
    let mut recorded = Episode::new(f, s, NU);
    let mut seen = Vec::new();
    let (mut fast, mut slow, mut slow2) = (vec![0.0; f], vec![0.0; s], vec![0.0; 2 * s]);
    let mut fast2 = vec![0.0; f];
    bare.reset(7);
    stacked.reset(7);
    for k in 0..12 {
        bare.observe(&mut fast, &mut slow);
        stacked.observe(&mut fast2, &mut slow2);
        assert_eq!(fast, fast2, "tick {k}");
        let action: Vec<f32> = (0..NU)
            .map(|i| 0.05 * ((i + k) % 3) as f32 - 0.05)
            .collect();
        recorded.push(&fast, &slow, &action);
        seen.push(slow2.clone());
        bare.step(&action);
        stacked.step(&action);
    }
    let two = recorded.with_slow_frames(2);
    for (k, s2) in seen.iter().enumerate() {
        assert_eq!(two.slow(k), &s2[..], "tick {k}");
    }
    // The frames differ from tick to tick (the test would pass vacuously on a frozen cube).
    assert_ne!(two.slow(11)[..s], two.slow(11)[s..]);
}

#[test]
fn zero_slow_frames_is_refused_by_name() {
    let e = LeapCubeTask::new(LeapStudyConfig {
        slow_frames: 0,
        ..LeapStudyConfig::default()
    })
    .unwrap_err();
    assert!(e.to_string().contains("slow_frames"), "{e}");
}

/// The committed study config parses and is the paper's protocol at the stated scale.
#[test]
fn the_committed_study_config_is_the_papers_protocol() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../studies/leap-cube/study.toml"
    );
    let text = std::fs::read_to_string(path).expect("studies/leap-cube/study.toml");
    let cfg: LeapStudyConfig = toml::from_str(&text).expect("a valid study config");
    let paper = LeapStudyConfig::default();
    assert_eq!(
        (cfg.episodes, cfg.seeds.len(), cfg.d0s.clone()),
        (100, 3, vec![1, 2, 3])
    );
    assert_eq!((cfg.hs.clone(), cfg.max_steps), (vec![1, 2, 4, 8], 600));
    assert_eq!((cfg.batch_size, cfg.lr, cfg.warmup), (256, 1e-4, 500));
    assert!(cfg.val_episodes >= 20);
    assert_eq!(
        (cfg.delays, cfg.pir2_d_max, cfg.rtc_d_max, cfg.flow_steps),
        (paper.delays, 5, 10, 15)
    );
    assert_eq!((cfg.d_vis_max, cfg.slow_frames), (0, 2));
    for p in [
        Policy::Flow,
        Policy::Rtc,
        Policy::PiR2,
        Policy::PiR2Hidden,
        Policy::PiR2Full,
        Policy::PiR2ZeroDelay,
        Policy::PiR2ZeroDelayFull,
    ] {
        assert!(cfg.policies.contains(&p), "{p:?}");
    }
    // The paper's architecture: one FiLM head per chunk position for the πR² policies.
    assert_eq!(cfg.pir2_film, FilmMode::PerPositionHeads);
}

/// The ablation configs (a shared FiLM projection of per-position τ) keep the fingerprint their
/// committed cells were logged under, and differ from the heads study only in the FiLM and in
/// the paper's zero-delay policy.
#[test]
fn the_ablation_configs_keep_the_fingerprint_of_their_committed_cells() {
    use pir2_cli::study::evaluate::config_fingerprint;
    let read = |name: &str| -> LeapStudyConfig {
        let path = format!("{}/../studies/leap-cube/{name}", env!("CARGO_MANIFEST_DIR"));
        let text = std::fs::read_to_string(&path).expect("a committed study config");
        toml::from_str(&text).expect("a valid study config")
    };
    for name in [
        "ablation-per-position-tau.toml",
        "ablation-per-position-tau-horizon.toml",
    ] {
        let cfg = read(name);
        assert_eq!(cfg.pir2_film, FilmMode::PerPositionTau, "{name}");
        assert_eq!(
            config_fingerprint(&cfg).unwrap(),
            "668fe64c89fa9b53",
            "{name}"
        );
    }
    let (heads, ablation) = (read("study.toml"), read("ablation-per-position-tau.toml"));
    assert_ne!(
        config_fingerprint(&heads).unwrap(),
        config_fingerprint(&ablation).unwrap()
    );
    assert_eq!(
        LeapStudyConfig {
            pir2_film: heads.pir2_film,
            policies: heads.policies.clone(),
            ..ablation
        },
        heads
    );
}

/// The heads study takes its baselines' cells from the ablation's committed logs: flow and
/// train-time RTC train the same shared-FiLM U-Net under both configs, so their cells count
/// under the ablation's fingerprint too; πR²'s (another network) do not.
#[test]
fn the_heads_study_reports_its_baselines_from_the_ablations_cells() {
    use pir2_cli::study::report::report;
    let dir = format!("{}/../studies/leap-cube", env!("CARGO_MANIFEST_DIR"));
    let read = |name: &str| -> LeapStudyConfig {
        let text = std::fs::read_to_string(format!("{dir}/{name}")).expect("a committed config");
        toml::from_str(&text).expect("a valid study config")
    };
    let heads = task(read("study.toml"));
    for p in [Policy::Flow, Policy::Rtc] {
        let fps = heads.equivalent_fingerprints(p).unwrap();
        assert!(
            fps.iter().any(|f| f == "668fe64c89fa9b53"),
            "{p:?}: {fps:?}"
        );
    }
    for p in [Policy::PiR2Full, Policy::PiR2ZeroDelayFull, Policy::PiR2] {
        assert!(
            heads.equivalent_fingerprints(p).unwrap().is_empty(),
            "{p:?}"
        );
    }
    let log = std::path::PathBuf::from(format!(
        "{dir}/results/ablation-per-position-tau/deployment-cells.jsonl"
    ));
    let study = heads.deployment_study();
    let r = report(&heads, &study, &[log.as_path()], true).unwrap();
    let seeds = heads.settings().seeds.len();
    for row in &study.rows {
        let n = r.cells.iter().filter(|c| c.label == row.row.label).count();
        match row.row.policy {
            Policy::Flow | Policy::Rtc => {
                assert_eq!(n, seeds * study.columns.len(), "{}", row.row.label)
            }
            _ => assert_eq!(
                n, 0,
                "{}: the ablation's πR² is another network",
                row.row.label
            ),
        }
    }
}

/// The horizon study's config is the study config with its batched cells, nothing else.
#[test]
fn the_committed_horizon_config_is_the_study_config_batched() {
    let read = |name: &str| -> LeapStudyConfig {
        let path = format!("{}/../studies/leap-cube/{name}", env!("CARGO_MANIFEST_DIR"));
        let text = std::fs::read_to_string(&path).expect("a committed study config");
        toml::from_str(&text).expect("a valid study config")
    };
    for (s, h) in [
        ("study.toml", "horizon.toml"),
        (
            "ablation-per-position-tau.toml",
            "ablation-per-position-tau-horizon.toml",
        ),
    ] {
        let (study, horizon) = (read(s), read(h));
        assert_eq!(study.batch_episodes, 1);
        assert_eq!(
            horizon,
            LeapStudyConfig {
                batch_episodes: 100,
                ..study
            }
        );
    }
}

#[test]
fn diagnostic_rows_add_the_pir2_checkpoint_as_sync_flow_without_touching_other_cells() {
    use pir2_cli::study::evaluate::config_fingerprint;
    let off = LeapStudyConfig::default();
    let on = LeapStudyConfig {
        diagnostic_rows: true,
        ..LeapStudyConfig::default()
    };
    // Off (the default): no diagnostic row.
    let base = task(off.clone()).deployment_study();
    assert!(!base.rows.iter().any(|r| r.row.label.contains("diagnostic")));
    // On: one more row, the πR² checkpoint acting as sync flow with the flow baselines' K,
    // swept like the sync-flow row; every other row is unchanged.
    let diag = task(on.clone()).deployment_study();
    assert_eq!(diag.rows.len(), base.rows.len() + 1);
    assert_eq!(&diag.rows[..base.rows.len()], &base.rows[..]);
    let extra = diag.rows.last().unwrap();
    assert!(
        extra.row.label.starts_with("diagnostic:"),
        "{}",
        extra.row.label
    );
    assert_eq!(extra.row.policy, Policy::PiR2);
    assert_eq!(extra.row.mode, Mode::SyncFlow { steps: 15, h: 1 });
    assert_eq!(extra.sweep, Sweep::UnitDelaySync);
    // Without the πR² policy there is nothing to diagnose.
    let no_pir2 = task(LeapStudyConfig {
        policies: vec![Policy::Flow],
        ..on.clone()
    });
    assert!(!no_pir2
        .deployment_study()
        .rows
        .iter()
        .any(|r| r.row.label.contains("diagnostic")));
    // The switch only adds rows: logged cells of the other rows stay valid.
    assert_eq!(
        config_fingerprint(&off).unwrap(),
        config_fingerprint(&on).unwrap()
    );
}

#[test]
fn logs_written_before_the_checkpoint_directory_left_the_fingerprint_are_still_read() {
    use pir2_cli::study::evaluate::{config_fingerprint, earlier_config_fingerprints};
    // `studies/leap-cube/ablation-per-position-tau.toml` narrowed to seed 0, evaluated with `--checkpoint
    // runs/leap-study-wide`: the fingerprint its cell logs were written under (sessions
    // 18-21, `studies/leap-cube/results/ablation-per-position-tau/*-cells.jsonl`) is this config's
    // earlier one, whichever directory it is evaluated from now.
    let text = r#"
        dataset = "runs/leap-playground"
        train_steps = 20000
        batch_size = 256
        lr = 1e-4
        warmup = 500
        widths = [64, 128, 256]
        groups = 8
        checkpoints = 10
        val_episodes = 20
        episodes = 100
        seeds = [0]
        d0s = [1, 2, 3]
        hs = [1, 2, 4, 8]
        nfe = 2
        flow_steps = 15
        max_steps = 600
        threads = 2
        policies = ["pi_r2_full"]
        slow_frames = 2
        best_of_last = 3
        pir2_film = "per_position_tau"
    "#;
    let mut cfg: LeapStudyConfig = toml::from_str(text).unwrap();
    cfg.pretrained = Some("runs/leap-study-wide".into());
    assert_eq!(
        earlier_config_fingerprints(&cfg).unwrap(),
        vec!["09281c1188a6d8e5".to_string()]
    );
    let now = config_fingerprint(&cfg).unwrap();
    cfg.pretrained = Some("elsewhere/leap-study-wide".into());
    cfg.train_missing = true;
    assert_eq!(config_fingerprint(&cfg).unwrap(), now);
}

#[test]
fn an_evaluation_refuses_a_policy_missing_from_the_checkpoint_directory_before_any_work() {
    let root = std::env::temp_dir().join(format!("pir2-leap-missing-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let trained = root.join("trained");
    std::fs::create_dir_all(&trained).unwrap();
    let out = root.join("out");
    let cfg = LeapStudyConfig {
        policies: vec![Policy::Flow],
        pretrained: Some(trained.to_string_lossy().into_owned()),
        dataset: root.join("no-such-dataset").to_string_lossy().into_owned(),
        ..LeapStudyConfig::default()
    };
    let e = pir2_cli::study::leap_cube::study_deployment(&cfg, &out, false)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("flow-seed0") && e.contains("--train-missing"),
        "{e}"
    );
    // Refused before the dataset is read or the output directory made.
    assert!(!out.exists());
    std::fs::remove_dir_all(&root).unwrap();
}

/// The committed expert (`studies/leap-cube/expert/`, MuJoCo Playground's published policy)
/// regenerates the study's demonstrations: a short batch of its first seed, collected as
/// `pir2 collect leap-cube` collects, has a fixed fingerprint, equal to that of the same
/// episodes in the full dataset (fingerprint `4882c66b901ef2c7`) where that is present.
#[test]
fn the_committed_expert_regenerates_the_demonstrations() {
    use pir2_cli::study::leap_cube::ExpertChoice;
    use pir2_cli::study::leap_cube::{collect_leap, load_demos};
    use pir2_cli::study::pipeline::DataFingerprint;
    let expert = std::path::PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../studies/leap-cube/expert/leap-playground.safetensors"
    ));
    let out = std::env::temp_dir().join(format!("pir2-leap-expert-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let stop = std::sync::atomic::AtomicBool::new(false);
    collect_leap(
        &out,
        &[0],
        4,
        pir2_sim::dataset::WriteMode::New,
        &ExpertChoice::Weights(vec![expert]),
        &stop,
    )
    .unwrap();
    let demos: Vec<_> = load_demos(&out)
        .unwrap()
        .iter()
        .map(|e| e.with_slow_frames(2))
        .collect();
    let f = DataFingerprint::of(&demos);
    std::fs::remove_dir_all(&out).unwrap();
    // Where the full dataset has been collected (`runs/leap-playground`, seed-major), its first
    // four episodes are this batch: the same successes, frame for frame.
    let full = std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../runs/leap-playground"
    ));
    if full.join("meta/info.json").exists() {
        let ds = pir2_sim::dataset::read_dataset(full).unwrap();
        let first: Vec<_> = ds.episodes[..4]
            .iter()
            .filter(|e| e.success && e.len() >= 2)
            .map(|e| e.with_slow_frames(2))
            .collect();
        let g = DataFingerprint::of(&first);
        assert_eq!(
            (g.episodes, g.frames, g.fingerprint),
            (f.episodes, f.frames, f.fingerprint.clone())
        );
    }
    // Measured with this expert: 3 of the first 4 seed-0 episodes succeed (the full
    // 200-episode collection with it gives 148 used episodes, 37,930 frames,
    // `4882c66b901ef2c7`, the study's demonstrations).
    assert_eq!(
        (f.episodes, f.frames, f.fingerprint.as_str()),
        (3, 792, "cb0f6357c614a008")
    );
}
