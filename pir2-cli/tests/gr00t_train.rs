//! `pir2 gr00t train` end to end on a synthetic N1.7-shaped checkpoint (the tiny `alt`
//! configuration of the reference fixtures: GR00T's real tensor names), a synthetic
//! LeRobotDataset v3.0 and synthetic backbone features: the run trains, its step checkpoint
//! loads back as a GR00T head with the delay table, an interrupted run resumes
//! bit-identically, the VL-token cache is reused only for the same inputs, and bad inputs
//! are one error naming what is wrong.
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use pir2_backends::gr00t::n17::Gr00tN17Head;
use pir2_backends::gr00t::Normalizer;
use pir2_backends::gr00t::{EmbodimentConfig, Norm};
use pir2_cli::study::gr00t::{train, Gr00tTargets, Gr00tTrainOptions};
use pir2_sim::dataset::{
    read_selected, DatasetSpec, DatasetWriter, Episode, FeatureKeys, WriteMode,
};

mod common;
use common::gr00t::{
    alt_checkpoint, arm_grip_embodiment, encode_decode_every_chunk,
    lockstep_sends_the_datasets_actions, pir2, pir2_text, read_json, state_and_action, train_args,
    write_alt_features, ALT_D_VL, TOKENS,
};
use common::Scratch;

const FRAMES_PER_EPISODE: usize = 14;
const EPISODES: usize = 3;

/// 4 state values (3 joints min/max + 1 mean/std), 4 action values, H = 8, d_max = 2,
/// d_vis_max = 2, n_obs = 2, slot 1.
fn embodiment(path: &Path, state_dim: usize) {
    let e = arm_grip_embodiment(8, state_dim - 1);
    std::fs::write(path, e.to_toml().unwrap()).unwrap();
}

/// [`embodiment`] with the `arm` action group relative to the `arm` state group (and `grip`
/// min/max: the percentiles would clip the extremes of the dataset's actions).
fn relative_embodiment(path: &Path) {
    embodiment(path, 4);
    let mut e = EmbodimentConfig::load(path).unwrap();
    e.action[0].relative = true;
    e.action[1].norm = Norm::MinMax;
    std::fs::write(path, e.to_toml().unwrap()).unwrap();
}

/// Episodes whose action is a smooth function of the state.
fn dataset(root: &Path, state_dim: usize) {
    dataset_of(root, state_dim, FRAMES_PER_EPISODE);
}

/// [`dataset`] with `frames` frames per episode.
fn dataset_of(root: &Path, state_dim: usize, frames: usize) {
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
        for t in 0..frames {
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
    let emb = common::gr00t::seeded_normal((frames, TOKENS, ALT_D_VL), 0x6e01);
    // A fixed per-seed offset so two seeds give different files.
    let emb = (emb + seed as f64).unwrap();
    write_alt_features(path, emb);
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
    alt_checkpoint(&i.ck);
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

/// `pir2 gr00t train` on the inputs `i` into `out`, with `extra` flags.
fn train_cli(i: &Inputs, out: &Path, extra: &[&str]) -> Vec<std::ffi::OsString> {
    let mut args = train_args(&i.ck, &i.data, &i.emb, &i.feats, out);
    args.extend(extra.iter().map(Into::into));
    args
}

fn bytes(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn trains_resumes_bit_identically_and_loads_back() {
    let i = inputs("gr00t-train");
    // The binary, the whole run.
    let out_full = i.root.join("full");
    let (run, text) = pir2_text(&train_cli(
        &i,
        &out_full,
        &[
            "--steps",
            "6",
            "--batch-size",
            "8",
            "--lr",
            "0.001",
            "--checkpoint-every",
            "3",
            "--seed",
            "11",
        ],
    ));
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

    // GR00T's DiT dropout is on by default (the fixture's config: 0.2 with final_dropout,
    // keyed by seed and step, so the resumes above are bit-identical with it). Without it the
    // same first batch gives another loss, and a dropout run does not resume without it.
    let mut o = options(&i, "no-dropout");
    o.dropout = false;
    o.steps = 1;
    let plain = train(&o, |_| {}).unwrap();
    let (with, without) = (second.report.losses[0], plain.report.losses[0]);
    println!("step 1 loss: dropout {:.6}, none {:.6}", with.1, without.1);
    assert_eq!(with.0, without.0);
    assert_ne!(
        with.1, without.1,
        "the dropout run's first loss is the plain one"
    );
    let mut o = options(&i, "full");
    o.dropout = false;
    o.resume = true;
    let e = format!("{:#}", train(&o, |_| {}).unwrap_err());
    assert!(e.contains("gr00t_run.json"), "{e}");

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

    // Devices, through the binary: a GPU this build lacks names the feature to build with
    // (before anything is read or written); an unknown name lists the accepted ones.
    let device = |d: &str| {
        let out = i.root.join(format!("dev-{d}"));
        let run = pir2(&train_cli(&i, &out, &["--device", d]));
        assert!(!run.status.success(), "--device {d} ran");
        assert!(!out.exists(), "--device {d} wrote {}", out.display());
        let e = String::from_utf8_lossy(&run.stderr).to_string();
        println!("{e}");
        e
    };
    if !cfg!(feature = "cuda") {
        let e = device("cuda:1");
        assert!(
            e.contains("`cuda:1`") && e.contains("--features cuda"),
            "{e}"
        );
    }
    if !cfg!(feature = "metal") {
        let e = device("metal");
        assert!(e.contains("--features metal"), "{e}");
    }
    let e = device("tpu");
    assert!(e.contains("`tpu`") && e.contains("cuda:N"), "{e}");

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

    // Episodes shorter than the horizon (8): no whole chunk to train on, as in GR00T.
    let short_eps = i.root.join("short-episodes");
    dataset_of(&short_eps, 4, 7);
    let mut o = options(&i, "e-short");
    o.data = short_eps;
    let e = err(&o);
    assert!(e.contains("H = 8") && e.contains("longest has 7"), "{e}");
    assert!(!o.out.join("statistics.json").exists(), "{e}");

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

/// A relative action group trains (the refusal is gone) and what it trains on deploys back
/// to the dataset: the run writes `relative_action.arm` as `[H, 3]` tables, computed over the
/// chunks inside their episode as GR00T's statistics tool does; the trainer's targets
/// (`Gr00tTargets`, GR00T's `a_{t+p} − s_t` normalised per slot) of every chunk it draws
/// decode with the runtime's output map of the run's `statistics.json` to the dataset's
/// absolute actions; and the lock-step runtime driven by a head that outputs exactly those
/// targets sends, at every tick up to `len − H` of every episode, the dataset's action of
/// that tick (πR² async with one- and two-tick calls, πR² without async): each slot is
/// decoded against the state of the call that made it, the reference training used for it.
#[test]
fn a_relative_group_trains_and_deploys_back_to_the_datasets_actions() {
    let i = inputs("gr00t-train-relative");
    relative_embodiment(&i.emb);
    let mut o = options(&i, "rel");
    o.steps = 2;
    o.checkpoint_every = None;
    let r = train(&o, |_| {}).unwrap();
    assert_eq!(r.report.losses.len(), 2);
    assert!(r.report.losses.iter().all(|(_, l)| l.is_finite()));

    // The statistics the deployment reads.
    let emb = EmbodimentConfig::load(&o.out.join("embodiment.toml")).unwrap();
    let h = emb.horizon;
    let stats = read_json(&o.out.join("statistics.json"));
    let tag = emb.embodiment_tag.as_str();
    let rel = &stats[tag]["relative_action"]["arm"]["min"];
    assert_eq!(rel.as_array().map(Vec::len), Some(h), "{rel}");
    assert_eq!(rel[0].as_array().map(Vec::len), Some(3), "{rel}");
    assert!(stats[tag]["relative_action"].get("grip").is_none());
    let norm = Normalizer::load(&o.out.join("statistics.json"), &emb).unwrap();
    assert!(norm.per_slot());
    let map = norm.action_output_map();
    assert_eq!(map.reference, [Some(0), Some(1), Some(2), None]);

    let ds = read_selected(&i.data, &state_and_action()).unwrap();

    // The tables are GR00T's (`RelativeActionLoader`): slot p over the chunks inside their
    // episode, t ∈ 0..=len − H (the last one ends on the last frame). The old rule (every
    // frame, the last action repeated) gives other tables on this data.
    let table = |stat: &str, p: usize, j: usize| {
        stats[tag]["relative_action"]["arm"][stat][p][j]
            .as_f64()
            .unwrap()
    };
    let rel_values = |p: usize, j: usize, padded: bool| -> Vec<f64> {
        let mut v = Vec::new();
        for ep in &ds.episodes {
            let len = ep.len();
            let frames = if padded { len } else { len + 1 - h };
            for t in 0..frames {
                let a = ep.action((t + p).min(len - 1))[j];
                v.push(f64::from(a) - f64::from(ep.fast(t)[j]));
            }
        }
        v
    };
    let mut old_rule_differs = false;
    for p in 0..h {
        for j in 0..3 {
            let v = rel_values(p, j, false);
            assert_eq!(v.len(), EPISODES * (FRAMES_PER_EPISODE + 1 - h));
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            let min = v.iter().copied().fold(f64::INFINITY, f64::min);
            let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            for (stat, want) in [("mean", mean), ("min", min), ("max", max)] {
                let got = table(stat, p, j);
                assert!(
                    (got - want).abs() <= 1e-9 * (1.0 + want.abs()),
                    "relative_action.arm.{stat}[{p}][{j}] = {got}, GR00T's rule gives {want}"
                );
            }
            let old = rel_values(p, j, true);
            let old_mean = old.iter().sum::<f64>() / old.len() as f64;
            old_rule_differs |= (old_mean - mean).abs() > 1e-6;
        }
    }
    assert!(old_rule_differs, "the data cannot tell the two rules apart");

    let targets = Gr00tTargets::new(norm, h, &ds.episodes);

    // Encode (trainer) → decode (runtime), every chunk the trainer draws (t ≤ len − H) and
    // every slot: inside [-1, 1] (min/max groups are never clipped) and exact.
    encode_decode_every_chunk(&ds, &targets, &map, h, 4);
    let mut moved = 0.0f32;
    for ep in &ds.episodes {
        for t in 0..=ep.len() - h {
            moved = moved.max((ep.fast(t)[0] - ep.fast(0)[0]).abs());
        }
    }
    assert!(moved > 0.5, "the reference state must move ({moved})");

    // Deployed: the lock-step runtime with the run's output map.
    lockstep_sends_the_datasets_actions(&ds, &targets, &map, &emb, 4);
}
