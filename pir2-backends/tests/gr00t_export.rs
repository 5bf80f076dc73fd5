//! The GR00T N1.7 ONNX export (`pir2_backends::gr00t::n17::export`) against the candle head it
//! was exported from: NVIDIA's reference fixtures `alt` (N1.7's layout) and `plain` (plain
//! DiT with sinusoidal positions), real tensor names and tiny sizes, each with a nonzero delay
//! table, exported, loaded by the ONNX GR00T stack (`Gr00tActionHead`: the contract checks,
//! the side weights, the per-position timesteps) and run with ONNX Runtime on the inputs
//! candle's `velocity` gets; and the backbone post-processing (`vlln` from the side weights +
//! `vl_self_attention.onnx`) against candle's `process_backbone`. Needs `ORT_DYLIB_PATH`
//! (`source .native/env.sh`).
#![cfg(feature = "gr00t")]

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use pir2_backends::gr00t::contract::{feed, Bindings, Graph, VL_SELF_ATTENTION};
use pir2_backends::gr00t::n17::export::{export_gr00t_n17, WeightStorage};
use pir2_backends::gr00t::n17::{
    timestep_bucket, Gr00tN17Config, Gr00tN17Head, Timesteps, VlTokens, DELAY_EMBEDDING, PREFIX,
};
use pir2_backends::gr00t::testing::statistics_json;
use pir2_backends::gr00t::weights::SideWeights;
use pir2_backends::gr00t::{
    CheckpointFiles, EmbodimentConfig, Gr00tActionHead, Gr00tCandleHead, Norm, Normalizer, VlLayout,
};
use pir2_backends::ort::OrtOptions;
use pir2_runtime::{ModelInput, SlowInput};

const TOL: f32 = 1e-4;
const H: usize = 8;
const D_VIS_MAX: usize = 2;
const SLOT: i64 = 1;
const T: usize = 6;

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/gr00t_n17_head")
}

/// A scratch directory removed on drop.
struct Scratch(PathBuf);

impl Scratch {
    fn new(tag: &str) -> Scratch {
        let p =
            std::env::temp_dir().join(format!("pir2-gr00t-export-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        Scratch(p)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Deterministic values in `[-s, s]`.
fn noise(n: usize, seed: u64, s: f32) -> Vec<f32> {
    let mut rng = pir2_schedule::Rng::new(seed);
    (0..n).map(|_| rng.uniform_range(-s, s)).collect()
}

fn config(case: &str) -> Gr00tN17Config {
    Gr00tN17Config::from_json_file(&fixtures().join(format!("{case}.config.json"))).unwrap()
}

/// A fixture (`alt`, `plain`) as a fine-tuned step directory: its weights plus a random
/// (nonzero) delay table of `D_VIS_MAX + 1` rows; with `heads`, πR²'s per-position AdaLN
/// heads (`<layer>_heads`, one per DiT token) in place of each shared modulation, every head
/// the shared pair plus noise of its own, so that a graph reading one head for all tokens
/// fails the comparison.
fn step_dir(case: &str, dir: &Path, heads: bool) {
    let dev = Device::Cpu;
    let mut all: HashMap<String, Tensor> = candle_core::safetensors::load(
        fixtures().join(format!("{case}.weights.safetensors")),
        &dev,
    )
    .unwrap();
    let (rows, d_in) = (D_VIS_MAX + 1, config(case).input_embedding_dim);
    all.insert(
        format!("{PREFIX}{DELAY_EMBEDDING}"),
        Tensor::from_vec(noise(rows * d_in, 5, 0.5), (rows, d_in), &dev).unwrap(),
    );
    if heads {
        let n = H + 1;
        let layers: Vec<String> = all
            .keys()
            .filter_map(|k| {
                k.strip_suffix(".weight")
                    .filter(|l| l.ends_with("norm1.linear") || l.ends_with("model.proj_out_1"))
                    .filter(|l| l.contains("model."))
                    .map(str::to_string)
            })
            .collect();
        assert!(!layers.is_empty());
        for (li, layer) in layers.iter().enumerate() {
            for (k, seed) in [("weight", 100), ("bias", 200)] {
                let t = all.remove(&format!("{layer}.{k}")).unwrap();
                let mut dims = vec![n];
                dims.extend(t.dims());
                let tiled = t
                    .unsqueeze(0)
                    .unwrap()
                    .broadcast_as(dims.as_slice())
                    .unwrap();
                let m = tiled.elem_count();
                let scale = t
                    .abs()
                    .unwrap()
                    .max_all()
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap();
                let jitter = Tensor::from_vec(
                    noise(m, seed + li as u64, 0.3 * scale),
                    dims.as_slice(),
                    &dev,
                )
                .unwrap();
                all.insert(format!("{layer}_heads.{k}"), (tiled + jitter).unwrap());
            }
        }
    }
    candle_core::safetensors::save(&all, dir.join("model.safetensors")).unwrap();
    std::fs::copy(
        fixtures().join(format!("{case}.config.json")),
        dir.join("config.json"),
    )
    .unwrap();
}

/// 4 state values, `min(3, A_max − 1) + 1` actions, the fixture's history length, H = 8,
/// slot 1.
fn embodiment(case: &str) -> EmbodimentConfig {
    let c = config(case);
    let mut e = EmbodimentConfig::xarm6_xhand();
    e.name = "tiny".into();
    e.horizon = H;
    e.d_max = 2;
    e.d_vis_max = D_VIS_MAX;
    e.n_obs = c.state_history_length;
    e.embodiment_id = SLOT;
    let g = |name: &str, dim: usize, norm: Norm| {
        let mut x = e.state[0].clone();
        x.name = name.into();
        x.dim = dim;
        x.norm = norm;
        x
    };
    let state = vec![g("arm", 3, Norm::MinMax), g("grip", 1, Norm::MeanStd)];
    let arm = 3.min(c.max_action_dim - 1);
    let action = vec![g("arm", arm, Norm::MinMax), g("grip", 1, Norm::MeanStd)];
    e.state = state;
    e.action = action;
    e.validate().unwrap();
    e
}

fn rel_err(got: &[f32], want: &[f32]) -> f32 {
    assert_eq!(got.len(), want.len());
    let scale = want.iter().fold(0f32, |m, x| m.max(x.abs())).max(1e-6);
    let diff = got
        .iter()
        .zip(want)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    diff / scale
}

/// The graphs and the side file written, loaded by the ONNX stack.
fn exported(
    case: &str,
    dir: &Path,
    cfg: &EmbodimentConfig,
    storage: WeightStorage,
    heads: bool,
) -> (Gr00tN17Head, Gr00tActionHead, Normalizer) {
    let step = dir.join("step");
    let out = dir.join("export");
    std::fs::create_dir_all(&step).unwrap();
    std::fs::create_dir_all(&out).unwrap();
    step_dir(case, &step, heads);
    let head = Gr00tN17Head::load(&step, &Device::Cpu).unwrap();
    let files = export_gr00t_n17(&head, H)
        .unwrap()
        .write(&out, storage)
        .unwrap();
    let external = files.iter().any(|f| f.ends_with(".onnx.data"));
    assert_eq!(external, storage == WeightStorage::External, "{files:?}");
    std::fs::write(out.join("statistics.json"), statistics_json(cfg, None)).unwrap();
    let norm = Normalizer::load(&out.join("statistics.json"), cfg).unwrap();
    let files = CheckpointFiles::in_dir(&out);
    let onnx = Gr00tActionHead::load(&files, cfg, norm.clone(), SLOT, &OrtOptions::default())
        .unwrap_or_else(|e| panic!("the ONNX stack refuses the export: {e}"));
    (head, onnx, norm)
}

/// Inputs for B = 2: per-position τ (a hidden front, a partly denoised middle, a clean
/// end), d_vis 1 and 9 (clamped to `D_VIS_MAX`), 6 tokens (2 text, 3 image, 1 padding).
struct Inputs {
    x: Vec<f32>,
    tau: Vec<f32>,
    obs: Vec<f32>,
    vl: Vec<f32>,
    d_vis: Vec<u32>,
    layout: VlLayout,
}

fn inputs(a: usize, n_obs: usize, d_vl: usize) -> Inputs {
    let b = 2;
    let mut tau = Vec::new();
    for bi in 0..b {
        for p in 0..H {
            tau.push(match p {
                0 if bi == 0 => -1.0,
                p => ((p as f32 + 0.37 * bi as f32) / H as f32).min(1.0),
            });
        }
    }
    Inputs {
        x: noise(b * H * a, 1, 1.0),
        tau,
        obs: noise(b * n_obs * 4, 2, 2.5),
        vl: noise(b * T * d_vl, 3, 1.5),
        d_vis: vec![1, 9],
        layout: VlLayout {
            image_mask: vec![false, false, true, true, true, false],
            attention_mask: vec![true, true, true, true, true, false],
        },
    }
}

/// candle's velocity `[B, H, A]` on the same inputs the ONNX stack gets: normalised padded
/// state, per-position timesteps with the state token at the embodiment's state timestep.
fn candle_velocity(
    head: &Gr00tN17Head,
    norm: &Normalizer,
    cfg: &EmbodimentConfig,
    i: &Inputs,
) -> Vec<f32> {
    let dev = Device::Cpu;
    let c = head.config();
    let (b, a, msd, a_max) = (2, cfg.action_dim(), c.max_state_dim, c.max_action_dim);
    let n_obs = cfg.n_obs;
    let mut state = vec![0f32; b * n_obs * msd];
    for k in 0..b * n_obs {
        norm.normalize_state(&i.obs[k * 4..(k + 1) * 4], &mut state[k * msd..k * msd + 4]);
    }
    let state = Tensor::from_vec(state, (b, n_obs, msd), &dev).unwrap();
    let mut x = vec![0f32; b * H * a_max];
    for r in 0..b * H {
        x[r * a_max..r * a_max + a].copy_from_slice(&i.x[r * a..(r + 1) * a]);
    }
    let x = Tensor::from_vec(x, (b, H, a_max), &dev).unwrap();
    let buckets = c.num_timestep_buckets;
    let t_act: Vec<u32> = i.tau.iter().map(|&t| timestep_bucket(t, buckets)).collect();
    let mut t_tok = Vec::new();
    for bi in 0..b {
        t_tok.push(cfg.state_timestep() as u32);
        t_tok.extend_from_slice(&t_act[bi * H..(bi + 1) * H]);
    }
    let t_act = Tensor::from_vec(t_act, (b, H), &dev).unwrap();
    let t_tok = Tensor::from_vec(t_tok, (b, 1 + H), &dev).unwrap();
    let emb = Tensor::new(&[SLOT as u32, SLOT as u32], &dev).unwrap();
    let d_vl = c.backbone_embedding_dim;
    let vl = Tensor::from_vec(i.vl.clone(), (b, T, d_vl), &dev).unwrap();
    let mask = |m: &[bool]| {
        let v: Vec<u8> = (0..b).flat_map(|_| m.iter().map(|&x| x as u8)).collect();
        Tensor::from_vec(v, (b, T), &dev).unwrap()
    };
    let (img, att) = (mask(&i.layout.image_mask), mask(&i.layout.attention_mask));
    let d_vis = Tensor::new(i.d_vis.as_slice(), &dev).unwrap();
    let tokens = VlTokens {
        embeddings: &vl,
        attention_mask: Some(&att),
        image_mask: Some(&img),
        d_vis: Some(&d_vis),
    };
    let s = head.encode_state(&state, &emb).unwrap();
    let per = Timesteps::PerPosition {
        actions: &t_act,
        tokens: &t_tok,
    };
    let v = head.velocity(&s, &x, per, &tokens, &emb).unwrap();
    v.narrow(2, 0, a)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

fn onnx_velocity(
    onnx: &mut Gr00tActionHead,
    i: &Inputs,
    a: usize,
    n_obs: usize,
    d_vl: usize,
) -> Vec<f32> {
    onnx.set_vl_layout(i.layout.clone());
    let input = ModelInput {
        batch: 2,
        horizon: H,
        action_dim: a,
        x: &i.x,
        tau: &i.tau,
        obs_fast: &i.obs,
        n_obs,
        fast_dim: 4,
        slow: SlowInput::Tokens {
            data: &i.vl,
            tokens: T,
            dim: d_vl,
        },
        d_vis: &i.d_vis,
    };
    let mut out = vec![0f32; 2 * H * a];
    onnx.forward(&input, &mut out).unwrap();
    out
}

/// One fixture through export + the ONNX stack against candle; the comparison must see the
/// delay table and the per-position timesteps.
fn parity(case: &str, storage: WeightStorage) {
    parity_with(case, storage, false);
}

fn parity_with(case: &str, storage: WeightStorage, heads: bool) {
    let dir = Scratch::new(&format!("{case}-{storage:?}-{heads}"));
    let cfg = embodiment(case);
    let (head, mut onnx, norm) = exported(case, &dir.0, &cfg, storage, heads);
    assert_eq!(head.position_heads(), heads.then_some(H + 1));
    let c = head.config().clone();
    let (d_vl, d_in, n_obs) = (c.backbone_embedding_dim, c.input_embedding_dim, cfg.n_obs);
    let a = cfg.action_dim();
    let i = inputs(a, n_obs, d_vl);
    let want = candle_velocity(&head, &norm, &cfg, &i);
    let got = onnx_velocity(&mut onnx, &i, a, n_obs, d_vl);
    let err = rel_err(&got, &want);
    eprintln!("{case}: velocity, ONNX Runtime vs candle, relative error {err:.3e}");
    assert!(err <= TOL, "{case}: relative error {err:.3e} > {TOL:e}");
    // The comparison sees the delay table: another d_vis changes candle's answer by far more
    // than the tolerance (so a graph or side file that dropped it would fail above).
    let mut other = inputs(a, n_obs, d_vl);
    other.d_vis = vec![0, 0];
    let moved = candle_velocity(&head, &norm, &cfg, &other);
    let sens = rel_err(&moved, &want);
    assert!(
        sens > 100.0 * TOL,
        "{case}: d_vis moved the velocity by only {sens:.3e}"
    );
    // ... and so does one τ (per-position timesteps reach both graphs).
    let mut other = inputs(a, n_obs, d_vl);
    other.tau[3] = 0.9;
    let got_t = onnx_velocity(&mut onnx, &other, a, n_obs, d_vl);
    let want_t = candle_velocity(&head, &norm, &cfg, &other);
    assert!(rel_err(&got_t, &want_t) <= TOL, "{case}");
    assert!(rel_err(&got_t, &got) > 100.0 * TOL, "{case}");

    // The candle head behind the ONNX head's interface (`pir2 gr00t run --candle-head`): the same
    // glue, so the same velocity.
    let mut direct = Gr00tCandleHead::load(&dir.0.join("step"), &cfg, norm.clone(), SLOT).unwrap();
    direct.set_vl_layout(i.layout.clone());
    let mut got_c = vec![0f32; got.len()];
    direct
        .forward(
            &ModelInput {
                batch: 2,
                horizon: H,
                action_dim: a,
                x: &i.x,
                tau: &i.tau,
                obs_fast: &i.obs,
                n_obs,
                fast_dim: 4,
                slow: SlowInput::Tokens {
                    data: &i.vl,
                    tokens: T,
                    dim: d_vl,
                },
                d_vis: &i.d_vis,
            },
            &mut got_c,
        )
        .unwrap();
    let err_c = rel_err(&got_c, &got);
    eprintln!("{case}: velocity, Gr00tCandleHead vs the ONNX stack, relative error {err_c:.3e}");
    assert!(err_c <= TOL, "{case}: candle head vs ONNX {err_c:.3e}");
    assert_eq!(direct.d_vis_counts(), &[0, 1, 1]);

    // The side file holds the fine-tuned delay table, bit for bit.
    let side = SideWeights::load(&dir.0.join("export/pir2_gr00t.safetensors")).unwrap();
    let table = side.delay_embedding(D_VIS_MAX, d_in).unwrap();
    let want_table = head
        .delay_embedding()
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    assert_eq!(table, want_table);
}

/// N1.7's layout: alternating text/image cross-attention with both masks, vlln, position
/// embedding, 2 history steps, a VL self-attention layer.
#[test]
fn exported_alt_head_matches_candle_through_the_onnx_stack() {
    parity("alt", WeightStorage::Auto);
}

/// The same with every weight in ONNX external data (`onnx/*.onnx.data`), the layout the
/// full-size DiT (over protobuf's 2 GiB) is written in.
#[test]
fn exported_head_with_external_weights_matches_candle() {
    parity("alt", WeightStorage::External);
}

/// The plain DiT: every block cross-attends to all tokens (no masks in the graph),
/// sinusoidal positions in the blocks, no position embedding, no vlln.
#[test]
fn exported_plain_head_matches_candle_through_the_onnx_stack() {
    parity("plain", WeightStorage::Auto);
}

/// πR²'s per-position AdaLN heads (one per DiT token, each different) through the export:
/// ONNX Runtime's velocity equals candle's.
#[test]
fn exported_head_with_per_position_adaln_heads_matches_candle() {
    parity_with("alt", WeightStorage::Auto, true);
}

#[test]
fn exported_backbone_post_processing_matches_candle() {
    let dir = Scratch::new("vlsa");
    let cfg = embodiment("alt");
    let (head, _, _) = exported("alt", &dir.0, &cfg, WeightStorage::Auto, false);
    let d = head.config().backbone_embedding_dim;
    let raw = noise(T * d, 9, 2.0);
    let want = head
        .process_backbone(&Tensor::from_vec(raw.clone(), (1, T, d), &Device::Cpu).unwrap())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    // vlln from the side file (LayerNorm, ε = 1e-5), then the exported graph.
    let side = SideWeights::load(&dir.0.join("export/pir2_gr00t.safetensors")).unwrap();
    let (w, b) = side.vlln(d).unwrap().expect("vlln in the side file");
    let mut x = raw;
    for row in x.chunks_mut(d) {
        let mean = row.iter().sum::<f32>() / d as f32;
        let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / d as f32;
        let inv = 1.0 / (var + 1e-5).sqrt();
        for (j, v) in row.iter_mut().enumerate() {
            *v = (*v - mean) * inv * w[j] + b[j];
        }
    }
    let path = dir.0.join("export/onnx/vl_self_attention.onnx");
    let mut g = Graph::load(
        &path,
        VL_SELF_ATTENTION,
        &OrtOptions::default(),
        &mut Bindings::default(),
    )
    .unwrap();
    let mut got = Vec::new();
    g.run_into(
        vec![feed("hidden_states", &[1, T, d], &x).unwrap()],
        "output",
        &mut got,
    )
    .unwrap();
    let err = rel_err(&got, &want);
    eprintln!("vlln + VL self-attention: ONNX Runtime vs candle, relative error {err:.3e}");
    assert!(err <= TOL, "relative error {err:.3e} > {TOL:e}");
}
