//! `pir2 train gr00t` end to end on a synthetic N1.7-shaped checkpoint (the tiny `alt`
//! configuration of the reference fixtures: GR00T's real tensor names), a synthetic
//! LeRobotDataset v3.0 and synthetic backbone features: the run trains, its step checkpoint
//! loads back as a GR00T head with the delay table, an interrupted run resumes
//! bit-identically, the VL-token cache is reused only for the same inputs, and bad inputs
//! are one error naming what is wrong.
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use candle_core::{DType, Device, Tensor};
use pir2_backends::candle::gr00t_n17::Gr00tN17Head;
use pir2_backends::gr00t::{EmbodimentConfig, Group, Norm};
use pir2_cli::study::gr00t::{train, Gr00tTrainOptions};
use pir2_sim::dataset::{DatasetSpec, DatasetWriter, Episode, FeatureKeys, WriteMode};

mod common;
use common::Scratch;

const FRAMES_PER_EPISODE: usize = 14;
const EPISODES: usize = 3;
const TOKENS: usize = 6;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-backends/tests/fixtures/gr00t_n17_head")
}

/// The `alt` fixture as a checkpoint directory (max_state_dim 6, state history 2,
/// max_action_dim 5, 8 positions, D_vl 20, 3 embodiment slots).
fn checkpoint(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::copy(fixtures().join("alt.config.json"), dir.join("config.json")).unwrap();
    std::fs::copy(
        fixtures().join("alt.weights.safetensors"),
        dir.join("model.safetensors"),
    )
    .unwrap();
}

fn group(name: &str, dim: usize, norm: Norm) -> Group {
    Group {
        name: name.into(),
        dim,
        norm,
        relative: false,
        state_key: None,
        format: Default::default(),
    }
}

/// 4 state values (3 joints min/max + 1 mean/std), 4 action values, H = 8, d_max = 2,
/// d_vis_max = 2, n_obs = 2, slot 1.
fn embodiment(path: &Path, state_dim: usize) {
    let mut e = EmbodimentConfig::xarm6_xhand();
    e.name = "tiny".into();
    e.horizon = 8;
    e.d_max = 2;
    e.d_vis_max = 2;
    e.n_obs = 2;
    e.embodiment_id = 1;
    e.state = vec![
        group("arm", state_dim - 1, Norm::MinMax),
        group("grip", 1, Norm::MeanStd),
    ];
    e.action = vec![
        group("arm", 3, Norm::MinMax),
        group("grip", 1, Norm::Q01Q99),
    ];
    std::fs::write(path, e.to_toml().unwrap()).unwrap();
}

/// Episodes whose action is a smooth function of the state.
fn dataset(root: &Path, state_dim: usize) {
    let names = |p: &str, n: usize| (0..n).map(|i| format!("{p}{i}")).collect::<Vec<_>>();
    let spec = DatasetSpec {
        fps: 25,
        robot_type: Some("tiny".into()),
        tasks: vec!["pick the cube".into()],
        fast_names: names("q", state_dim),
        slow_names: Vec::new(),
        action_names: names("a", 4),
        keys: FeatureKeys::default(),
    };
    let mut w = DatasetWriter::open(root, spec, WriteMode::New).unwrap();
    for e in 0..EPISODES {
        let mut ep = Episode::new(state_dim, 0, 4);
        for t in 0..FRAMES_PER_EPISODE {
            let ph = 0.3 * t as f32 + e as f32;
            let q: Vec<f32> = (0..state_dim).map(|i| (ph + i as f32).sin()).collect();
            let a: Vec<f32> = (0..4).map(|i| 0.8 * (ph + 0.2 + i as f32).sin()).collect();
            ep.push(&q, &[], &a);
        }
        w.append(&ep).unwrap();
    }
    w.finish().unwrap();
}

/// Backbone outputs: N frames of 6 tokens of width 20; tokens 0-1 text, 2-4 image, 5 padding.
fn features(path: &Path, frames: usize, seed: u64) {
    let dev = Device::Cpu;
    let emb = Tensor::randn(0f32, 1.0, (frames, TOKENS, 20), &dev).unwrap();
    // A fixed per-seed offset so two seeds give different files.
    let emb = (emb + seed as f64).unwrap();
    let row = [0u8, 0, 1, 1, 1, 0];
    let image: Vec<u8> = (0..frames).flat_map(|_| row).collect();
    let attn: Vec<u8> = (0..frames).flat_map(|_| [1u8, 1, 1, 1, 1, 0]).collect();
    let map = std::collections::HashMap::from([
        ("embeddings".to_string(), emb),
        (
            "image_mask".to_string(),
            Tensor::from_vec(image, (frames, TOKENS), &dev).unwrap(),
        ),
        (
            "attention_mask".to_string(),
            Tensor::from_vec(attn, (frames, TOKENS), &dev).unwrap(),
        ),
    ]);
    candle_core::safetensors::save(&map, path).unwrap();
}

struct Inputs {
    _dir: Scratch,
    ck: PathBuf,
    data: PathBuf,
    emb: PathBuf,
    feats: PathBuf,
    root: PathBuf,
}

fn inputs(name: &str) -> Inputs {
    let dir = Scratch::new(name);
    let root = dir.path().to_path_buf();
    let i = Inputs {
        ck: root.join("ck"),
        data: root.join("data"),
        emb: root.join("embodiment.toml"),
        feats: root.join("features.safetensors"),
        root,
        _dir: dir,
    };
    checkpoint(&i.ck);
    dataset(&i.data, 4);
    embodiment(&i.emb, 4);
    features(&i.feats, EPISODES * FRAMES_PER_EPISODE, 0);
    i
}

fn options(i: &Inputs, out: &str) -> Gr00tTrainOptions {
    let mut o = Gr00tTrainOptions::new(&i.ck, &i.data, &i.emb, &i.feats, &i.root.join(out));
    o.steps = 6;
    o.batch_size = 8;
    o.lr = 1e-3;
    o.checkpoint_every = Some(3);
    o.seed = 11;
    o
}

fn pir2(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .output()
        .expect("runs pir2")
}

fn bytes(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn trains_resumes_bit_identically_and_loads_back() {
    let i = inputs("gr00t-train");
    // The binary, the whole run.
    let out_full = i.root.join("full");
    let args: Vec<&std::ffi::OsStr> = vec![
        "train".as_ref(),
        "gr00t".as_ref(),
        "--checkpoint".as_ref(),
        i.ck.as_os_str(),
        "--data".as_ref(),
        i.data.as_os_str(),
        "--embodiment".as_ref(),
        i.emb.as_os_str(),
        "--features".as_ref(),
        i.feats.as_os_str(),
        "--out".as_ref(),
        out_full.as_os_str(),
        "--steps".as_ref(),
        "6".as_ref(),
        "--batch-size".as_ref(),
        "8".as_ref(),
        "--lr".as_ref(),
        "0.001".as_ref(),
        "--checkpoint-every".as_ref(),
        "3".as_ref(),
        "--seed".as_ref(),
        "11".as_ref(),
    ];
    let run = pir2(&args);
    let text =
        String::from_utf8_lossy(&run.stdout).to_string() + &String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{text}");
    assert!(text.contains("(built)"), "{text}");
    let losses: Vec<f64> = std::fs::read_to_string(out_full.join("loss.jsonl"))
        .unwrap()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| v["loss"].as_f64())
        .collect();
    assert!(
        !losses.is_empty() && losses.iter().all(|l| l.is_finite()),
        "{losses:?}"
    );

    // The library, interrupted after 4 steps (step-000003 written), then resumed: the same
    // bits as the uninterrupted run, and the VL cache of the same inputs is reused.
    let mut o = options(&i, "resumed");
    o.stop_after = Some(4);
    let first = train(&o, |_| {}).unwrap();
    assert!(first.cache.1, "a new output directory builds its cache");
    assert!(!o.out.join("step-000006").exists());
    o.stop_after = None;
    o.resume = true;
    let second = train(&o, |_| {}).unwrap();
    assert!(!second.cache.1, "the same inputs reuse the cache");
    for f in [
        "model.safetensors",
        "train_state.safetensors",
        "config.json",
    ] {
        let (a, b) = (
            out_full.join("step-000006").join(f),
            o.out.join("step-000006").join(f),
        );
        assert!(bytes(&a) == bytes(&b), "{f} differs after resume");
    }
    let state_losses = |dir: &Path| -> serde_json::Value {
        let text = std::fs::read_to_string(dir.join("step-000006/train_state.json")).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        v["report"]["losses"].clone()
    };
    let full = state_losses(&out_full);
    assert_eq!(full.as_array().map(Vec::len), Some(6), "{full}");
    assert_eq!(
        full,
        state_losses(&o.out),
        "per-step losses differ after resume"
    );
    assert_eq!(second.report.losses.len(), 6);

    // Ctrl-C after step 2 (no step checkpoint there): the exact state is saved as
    // `interrupted-000002`, the run continues from it bit-identically and removes it.
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut o = options(&i, "stopped");
    o.stop = Some(flag.clone());
    let e = train(&o, |p| {
        if p.step == 2 {
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
        }
    })
    .unwrap_err();
    assert!(format!("{e:#}").contains("interrupted"), "{e:#}");
    assert!(o.out.join("interrupted-000002").is_dir());
    o.stop = None;
    o.resume = true;
    train(&o, |_| {}).unwrap();
    assert!(!o.out.join("interrupted-000002").exists());
    assert!(
        bytes(&out_full.join("step-000006/model.safetensors"))
            == bytes(&o.out.join("step-000006/model.safetensors")),
        "resume from an interrupted state differs"
    );
    assert_eq!(full, state_losses(&o.out));

    // The step checkpoint is a GR00T head with a trained delay table.
    let head = Gr00tN17Head::load(&out_full.join("step-000006"), &Device::Cpu).unwrap();
    let table = head.delay_embedding().expect("delay table");
    assert_eq!(table.dims(), [3, 24]);
    let trained = table.abs().unwrap().sum_all().unwrap();
    assert!(
        trained
            .to_dtype(DType::F32)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
            > 0.0
    );
    let stats = std::fs::read_to_string(out_full.join("statistics.json")).unwrap();
    assert!(
        stats.contains("\"q99\"") && stats.contains("\"arm\""),
        "{stats}"
    );

    // Other features: another cache file, never the old one.
    features(&i.feats, EPISODES * FRAMES_PER_EPISODE, 1);
    let mut o = options(&i, "other-features");
    o.steps = 1;
    let third = train(&o, |_| {}).unwrap();
    assert!(third.cache.1);
    assert_ne!(third.cache.0.file_name(), second.cache.0.file_name());

    // Resuming with changed inputs is refused by name.
    let mut o = options(&i, "resumed");
    o.resume = true;
    o.steps = 6;
    let e = format!("{:#}", train(&o, |_| {}).unwrap_err());
    assert!(e.contains("gr00t_run.json"), "{e}");
}

#[test]
fn bad_inputs_are_one_error_naming_what_is_wrong() {
    let i = inputs("gr00t-train-errors");
    let err = |o: &Gr00tTrainOptions| {
        let e = format!("{:#}", train(o, |_| {}).unwrap_err());
        println!("{e}");
        e
    };

    // A checkpoint without the action head's tensors.
    let no_head = i.root.join("no-head");
    std::fs::create_dir_all(&no_head).unwrap();
    std::fs::copy(i.ck.join("config.json"), no_head.join("config.json")).unwrap();
    let bb = std::collections::HashMap::from([(
        "backbone.embed.weight".to_string(),
        Tensor::zeros((2, 2), DType::F32, &Device::Cpu).unwrap(),
    )]);
    candle_core::safetensors::save(&bb, no_head.join("model.safetensors")).unwrap();
    let mut o = options(&i, "e1");
    o.checkpoint = no_head;
    let e = err(&o);
    assert!(
        e.contains("action_head.") && e.contains("model.safetensors"),
        "{e}"
    );

    // A dataset whose state width disagrees with the embodiment.
    let wide = i.root.join("wide");
    dataset(&wide, 5);
    let mut o = options(&i, "e2");
    o.data = wide;
    let e = err(&o);
    assert!(
        e.contains("observation.state") && e.contains('5') && e.contains('4'),
        "{e}"
    );

    // An embodiment whose state does not fit the checkpoint's max_state_dim (6).
    let big = i.root.join("big.toml");
    embodiment(&big, 7);
    let mut o = options(&i, "e3");
    o.embodiment = big;
    let e = err(&o);
    assert!(e.contains("max_state_dim"), "{e}");

    // Features for another number of frames.
    let short = i.root.join("short.safetensors");
    features(&short, 10, 0);
    let mut o = options(&i, "e4");
    o.features = short;
    let e = err(&o);
    assert!(e.contains("10 frames") && e.contains("42"), "{e}");

    // Features without an image mask.
    let no_mask = i.root.join("no-mask.safetensors");
    let m = std::collections::HashMap::from([(
        "embeddings".to_string(),
        Tensor::zeros((42, TOKENS, 20), DType::F32, &Device::Cpu).unwrap(),
    )]);
    candle_core::safetensors::save(&m, &no_mask).unwrap();
    let mut o = options(&i, "e5");
    o.features = no_mask;
    let e = err(&o);
    assert!(e.contains("image_mask"), "{e}");
}
