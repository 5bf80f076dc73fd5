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
use pir2_backends::gr00t::Normalizer;
use pir2_backends::gr00t::{EmbodimentConfig, Group, GroupFormat, Norm};
use pir2_backends::train::gr00t::ActionTargets;
use pir2_cli::study::gr00t::{train, Gr00tTargets, Gr00tTrainOptions};
use pir2_sim::dataset::{
    read_selected, DatasetSpec, DatasetWriter, Episode, FeatureKeys, FeatureSelection, WriteMode,
};

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
        format: GroupFormat::Default,
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
        let run = pir2(&[
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
            out.as_os_str(),
            "--device".as_ref(),
            d.as_ref(),
        ]);
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

/// Replays one episode's raw states (the fast row is the raw state, as on the robot) and
/// records the commands it is sent.
struct Replay {
    states: Vec<Vec<f32>>,
    t: usize,
    sent: Vec<Vec<f32>>,
}

impl pir2_runtime::Environment for Replay {
    fn spec(&self) -> pir2_runtime::EnvSpec {
        pir2_runtime::EnvSpec {
            fast_dim: 4,
            slow_dim: 0,
            action_dim: 4,
            control_period: 40_000_000,
            max_steps: self.states.len(),
        }
    }
    fn reset(&mut self, _seed: u64) {
        self.t = 0;
        self.sent.clear();
    }
    fn observe(&mut self, fast: &mut [f32], _slow: &mut [f32]) {
        fast.copy_from_slice(&self.states[self.t]);
    }
    fn step(&mut self, action: &[f32]) -> pir2_runtime::EnvStep {
        self.sent.push(action.to_vec());
        self.t += 1;
        pir2_runtime::EnvStep {
            done: self.t >= self.states.len(),
            success: true,
            reward: 0.0,
        }
    }
}

/// A head that outputs the training target exactly: it finds the dataset frame of the
/// snapshot's newest raw state and steers every slot to what the trainer's own encoder
/// ([`Gr00tTargets`]) makes of that frame's chunk.
struct TargetOracle {
    targets: Gr00tTargets,
    episode: usize,
    states: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    chunk: Vec<f32>,
}

impl pir2_runtime::VelocityModel for TargetOracle {
    fn backend(&self) -> &'static str {
        "training-target oracle"
    }
    fn velocity(
        &mut self,
        inp: &pir2_runtime::ModelInput<'_>,
        out: &mut [f32],
    ) -> pir2_runtime::Result<()> {
        let (h, a, f) = (inp.horizon, inp.action_dim, inp.fast_dim);
        let newest = &inp.obs_fast[(inp.n_obs - 1) * f..inp.n_obs * f];
        let t = self
            .states
            .iter()
            .position(|s| s.as_slice() == newest)
            .expect("the snapshot's state is a dataset frame");
        let len = self.actions.len();
        for p in 0..h {
            self.chunk[p * a..(p + 1) * a].copy_from_slice(&self.actions[(t + p).min(len - 1)]);
        }
        self.targets
            .encode(self.episode, t, &mut self.chunk)
            .map_err(|e| pir2_runtime::Error::Config(e.to_string()))?;
        for p in 0..h {
            let tau = inp.tau[p];
            for j in 0..a {
                let i = p * a + j;
                out[i] = if (0.0..1.0).contains(&tau) {
                    (self.chunk[i] - inp.x[i]) / (1.0 - tau)
                } else {
                    0.0
                };
            }
        }
        Ok(())
    }
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
    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(o.out.join("statistics.json")).unwrap())
            .unwrap();
    let tag = emb.embodiment_tag.as_str();
    let rel = &stats[tag]["relative_action"]["arm"]["min"];
    assert_eq!(rel.as_array().map(Vec::len), Some(h), "{rel}");
    assert_eq!(rel[0].as_array().map(Vec::len), Some(3), "{rel}");
    assert!(stats[tag]["relative_action"].get("grip").is_none());
    let norm = Normalizer::load(&o.out.join("statistics.json"), &emb).unwrap();
    assert!(norm.per_slot());
    let map = norm.action_output_map();
    assert_eq!(map.reference, [Some(0), Some(1), Some(2), None]);

    let sel = FeatureSelection {
        fast: vec!["observation.state".into()],
        slow: Vec::new(),
        action: "action".into(),
    };
    let ds = read_selected(&i.data, &sel).unwrap();

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
    let (mut chunk, mut reference, mut u) = (vec![0f32; h * 4], [0f32; 4], [0f32; 4]);
    let mut moved = 0.0f32;
    for (e, ep) in ds.episodes.iter().enumerate() {
        let len = ep.len();
        for t in 0..=len - h {
            for p in 0..h {
                chunk[p * 4..(p + 1) * 4].copy_from_slice(ep.action((t + p).min(len - 1)));
            }
            targets.encode(e, t, &mut chunk).unwrap();
            assert!(chunk.iter().all(|z| z.abs() <= 1.0), "{chunk:?}");
            map.fill_reference(ep.fast(t), &mut reference);
            for p in 0..h {
                map.decode(&chunk[p * 4..(p + 1) * 4], p, &reference, &mut u);
                let want = ep.action((t + p).min(len - 1));
                for (j, (x, w)) in u.iter().zip(want).enumerate() {
                    assert!(
                        (x - w).abs() < 1e-5,
                        "episode {e} frame {t} slot {p} dim {j}: decoded {x}, dataset {w}"
                    );
                }
            }
            moved = moved.max((ep.fast(t)[0] - ep.fast(0)[0]).abs());
        }
    }
    assert!(moved > 0.5, "the reference state must move ({moved})");

    // Deployed: the lock-step runtime with the run's output map.
    use pir2_runtime::{ActionHead, HeadSpec, LatencyWindow, LockstepDriver, LockstepTiming, Mode};
    use pir2_schedule::{Alignment, FrontMode};
    let pir2_async = |nfe| Mode::PiR2Async {
        nfe,
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
    };
    let pir2_sync = Mode::PiR2Sync {
        nfe: None,
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
    };
    for (mode, call_ticks) in [
        (pir2_async(None), 1),
        (pir2_async(Some(2)), 2),
        (pir2_sync, 2),
    ] {
        for (e, ep) in ds.episodes.iter().enumerate() {
            let states: Vec<Vec<f32>> = (0..ep.len()).map(|t| ep.fast(t).to_vec()).collect();
            let actions: Vec<Vec<f32>> = (0..ep.len()).map(|t| ep.action(t).to_vec()).collect();
            let sp = HeadSpec {
                horizon: h,
                action_dim: 4,
                n_obs: emb.n_obs,
                fast_dim: 4,
                slow_dim: 0,
                period: 40_000_000,
                d_max: emb.d_max,
                d_vis_max: 0,
            };
            let oracle = TargetOracle {
                targets: targets.clone(),
                episode: e,
                states: states.clone(),
                actions: actions.clone(),
                chunk: vec![0.0; h * 4],
            };
            let mut head = ActionHead::new(
                oracle,
                sp,
                mode.head_mode(4),
                LatencyWindow::new(20, 0, sp.period, sp.d_max),
                5,
            )
            .unwrap();
            let mut env = Replay {
                states,
                t: 0,
                sent: Vec::new(),
            };
            let timing = LockstepTiming {
                call_ticks,
                slow_delay: 0,
                overrun_ticks: 0,
                overrun_every: 0,
                pin_delay: true,
            };
            let mut drv = LockstepDriver::new(&head).with_output(map.clone());
            let res = drv
                .run_episode(&mut env, &mut head, &mode, timing, 1, |_, _| {})
                .unwrap();
            assert_eq!(res.steps, ep.len());
            // Ticks up to len − H: every command there comes from chunks made (and rebased)
            // at frames the trainer draws. Later ones may decode a clipped slot: GR00T
            // neither trains on nor takes statistics from chunks that run past the end.
            for (t, sent) in env.sent.iter().enumerate().take(ep.len() + 1 - h) {
                for (j, (x, w)) in sent.iter().zip(&actions[t]).enumerate() {
                    assert!(
                        (x - w).abs() < 1e-4,
                        "{} episode {e} tick {t} dim {j}: sent {x}, dataset {w}",
                        mode.describe()
                    );
                }
            }
        }
    }
}
