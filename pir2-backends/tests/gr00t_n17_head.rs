//! The candle GR00T N1.7 action head against NVIDIA's reference implementation.
//!
//! One file on purpose: every test reads the same reference fixtures and helpers.
//!
//! The fixtures in `tests/fixtures/gr00t_n17_head/` were written by `make_fixture.py` there,
//! which runs Isaac-GR00T's own `Gr00tN1d7ActionHead` (tiny random configurations, fixed
//! seed) and saves its weights under their real tensor names, its inputs and its outputs.
//! `alt` is N1.7's layout (alternating text/image DiT, vlln, position embedding) plus a
//! VL self-attention layer; `plain` is the plain DiT with sinusoidal positions.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use pir2_backends::gr00t::n17::{Gr00tN17Config, Gr00tN17Head, Timesteps, VlTokens};
use pir2_backends::Error;

const CASES: [&str; 2] = ["alt", "plain"];
const TOL: f32 = 1e-4;

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/gr00t_n17_head")
}

struct Case {
    head: Gr00tN17Head,
    io: HashMap<String, Tensor>,
}

impl Case {
    fn load(name: &str) -> Case {
        let dir = fixtures();
        let cfg = Gr00tN17Config::from_json_file(&dir.join(format!("{name}.config.json"))).unwrap();
        let head = Gr00tN17Head::load_weights(
            &dir.join(format!("{name}.weights.safetensors")),
            cfg,
            &Device::Cpu,
        )
        .unwrap();
        let io = candle_core::safetensors::load(
            dir.join(format!("{name}.io.safetensors")),
            &Device::Cpu,
        )
        .unwrap();
        Case { head, io }
    }

    fn get(&self, k: &str) -> &Tensor {
        self.io
            .get(k)
            .unwrap_or_else(|| panic!("fixture lacks {k}"))
    }

    /// The processed VL tokens and the state features, computed by the candle head.
    fn prefix(&self) -> (Tensor, Tensor) {
        let vl = self
            .head
            .process_backbone(self.get("in.backbone_features"))
            .unwrap();
        let s = self
            .head
            .encode_state(self.get("in.state"), self.get("in.embodiment_id"))
            .unwrap();
        (vl, s)
    }

    fn vl<'a>(&'a self, emb: &'a Tensor) -> VlTokens<'a> {
        VlTokens {
            embeddings: emb,
            attention_mask: Some(self.get("in.backbone_attention_mask")),
            image_mask: Some(self.get("in.image_mask")),
            d_vis: None,
        }
    }
}

/// `max |a − b| / max |b|`.
fn rel_err(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims(), "shapes differ");
    let a = a.to_dtype(DType::F32).unwrap().flatten_all().unwrap();
    let b = b.to_dtype(DType::F32).unwrap().flatten_all().unwrap();
    let d = (&a - &b).unwrap().abs().unwrap().max(0).unwrap();
    let m = b.abs().unwrap().max(0).unwrap();
    d.to_scalar::<f32>().unwrap() / m.to_scalar::<f32>().unwrap()
}

fn check(case: &str, what: &str, got: &Tensor, want: &Tensor) {
    let e = rel_err(got, want);
    println!("{case:>5} {what:<16} relative error {e:.2e}");
    assert!(
        e <= TOL,
        "{case}: {what} differs from the reference by {e:.2e} (> {TOL:.0e})"
    );
}

#[test]
fn matches_reference_implementation() {
    for name in CASES {
        let c = Case::load(name);
        let emb = c.get("in.embodiment_id");
        let (vl, s) = c.prefix();
        check(name, "vl_embs", &vl, c.get("out.vl_embs"));
        check(name, "state_features", &s, c.get("out.state_features"));
        let (b, h, _) = c.get("in.actions").dims3().unwrap();
        let t = c.get("in.timesteps");
        let t_bh = t.reshape((b, 1)).unwrap().broadcast_as((b, h)).unwrap();
        let a = c
            .head
            .encode_actions(c.get("in.actions"), &t_bh, emb)
            .unwrap();
        check(name, "action_features", &a, c.get("out.action_features"));
        let sa = Tensor::cat(&[&s, &a], 1).unwrap();
        let out = c.head.dit(&sa, &c.vl(&vl), t).unwrap();
        check(name, "dit_output", &out, c.get("out.dit_output"));
        let v = c
            .head
            .velocity(
                &s,
                c.get("in.actions"),
                Timesteps::Shared(t),
                &c.vl(&vl),
                emb,
            )
            .unwrap();
        check(name, "velocity", &v, c.get("out.velocity"));
        let x = c
            .head
            .sample(&s, c.get("in.noise"), &c.vl(&vl), emb)
            .unwrap();
        check(name, "get_action", &x, c.get("out.action_pred"));
    }
}

#[test]
fn per_position_timesteps_all_equal_reproduce_the_shared_case() {
    for name in CASES {
        let c = Case::load(name);
        let emb = c.get("in.embodiment_id");
        let (vl, s) = c.prefix();
        let x = c.get("in.actions");
        let (b, h, _) = x.dims3().unwrap();
        let t = c.get("in.timesteps");
        let shared = c
            .head
            .velocity(&s, x, Timesteps::Shared(t), &c.vl(&vl), emb)
            .unwrap();
        let t2 = t.reshape((b, 1)).unwrap();
        let actions = t2.broadcast_as((b, h)).unwrap().contiguous().unwrap();
        let tokens = t2.broadcast_as((b, 1 + h)).unwrap().contiguous().unwrap();
        let per = c
            .head
            .velocity(
                &s,
                x,
                Timesteps::PerPosition {
                    actions: &actions,
                    tokens: &tokens,
                },
                &c.vl(&vl),
                emb,
            )
            .unwrap();
        let e = rel_err(&per, &shared);
        println!("{name}: per-position (all equal) vs shared: {e:.2e}");
        assert!(e <= 1e-6, "{name}: {e:.2e}");
        check(name, "per-position", &per, c.get("out.velocity"));

        // Different timesteps per position do reach the per-token path: moving only the last
        // position's timestep changes the velocity.
        let mut tv = tokens
            .to_dtype(DType::F32)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        tv[0][h] = 999.0;
        let tokens2 = Tensor::new(tv, &Device::Cpu).unwrap();
        let mut av = actions
            .to_dtype(DType::F32)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        av[0][h - 1] = 999.0;
        let actions2 = Tensor::new(av, &Device::Cpu).unwrap();
        let moved = c
            .head
            .velocity(
                &s,
                x,
                Timesteps::PerPosition {
                    actions: &actions2,
                    tokens: &tokens2,
                },
                &c.vl(&vl),
                emb,
            )
            .unwrap();
        assert!(
            rel_err(&moved, &shared) > 1e-3,
            "{name}: per-position timestep ignored"
        );
    }
}

/// A scratch directory removed on drop.
struct Scratch(PathBuf);

impl Scratch {
    fn new(tag: &str) -> Scratch {
        let p = std::env::temp_dir().join(format!("pir2-gr00t-n17-{tag}-{}", std::process::id()));
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

fn weights(name: &str) -> HashMap<String, Tensor> {
    candle_core::safetensors::load(
        fixtures().join(format!("{name}.weights.safetensors")),
        &Device::Cpu,
    )
    .unwrap()
}

fn alt_config() -> Gr00tN17Config {
    Gr00tN17Config::from_json_file(&fixtures().join("alt.config.json")).unwrap()
}

fn save(map: &HashMap<String, Tensor>, path: &Path) {
    candle_core::safetensors::save(map, path).unwrap();
}

#[test]
fn loads_a_sharded_checkpoint_with_a_backbone() {
    let dir = Scratch::new("sharded");
    let all = weights("alt");
    // Two shards; the first also holds a backbone tensor (never read by the head).
    let mut shards: [HashMap<String, Tensor>; 2] = Default::default();
    let mut index = serde_json::Map::new();
    for (i, (k, v)) in all.iter().enumerate() {
        let s = i % 2;
        let file = format!("model-0000{}-of-00002.safetensors", s + 1);
        index.insert(k.clone(), file.into());
        shards[s].insert(k.clone(), v.clone());
    }
    shards[0].insert(
        "backbone.model.embed_tokens.weight".into(),
        Tensor::zeros((5, 3), DType::F32, &Device::Cpu).unwrap(),
    );
    index.insert(
        "backbone.model.embed_tokens.weight".into(),
        "model-00001-of-00002.safetensors".into(),
    );
    save(&shards[0], &dir.0.join("model-00001-of-00002.safetensors"));
    save(&shards[1], &dir.0.join("model-00002-of-00002.safetensors"));
    let idx = serde_json::json!({ "metadata": {}, "weight_map": index });
    std::fs::write(dir.0.join("model.safetensors.index.json"), idx.to_string()).unwrap();
    std::fs::copy(
        fixtures().join("alt.config.json"),
        dir.0.join("config.json"),
    )
    .unwrap();

    let sharded = Gr00tN17Head::load(&dir.0, &Device::Cpu).unwrap();
    let c = Case::load("alt");
    let emb = c.get("in.embodiment_id");
    let vl = sharded
        .process_backbone(c.get("in.backbone_features"))
        .unwrap();
    let s = sharded.encode_state(c.get("in.state"), emb).unwrap();
    let v = sharded
        .velocity(
            &s,
            c.get("in.actions"),
            Timesteps::Shared(c.get("in.timesteps")),
            &c.vl(&vl),
            emb,
        )
        .unwrap();
    check("alt", "sharded velocity", &v, c.get("out.velocity"));
}

#[test]
fn bf16_weights_are_widened_to_f32() {
    let dir = Scratch::new("bf16");
    let w = weights("alt");
    let bf16: HashMap<String, Tensor> = w
        .iter()
        .map(|(k, v)| (k.clone(), v.to_dtype(DType::BF16).unwrap()))
        .collect();
    let rounded: HashMap<String, Tensor> = bf16
        .iter()
        .map(|(k, v)| (k.clone(), v.to_dtype(DType::F32).unwrap()))
        .collect();
    save(&bf16, &dir.0.join("bf16.safetensors"));
    save(&rounded, &dir.0.join("f32.safetensors"));
    let c = Case::load("alt");
    let emb = c.get("in.embodiment_id");
    let run = |file: &str| {
        let head =
            Gr00tN17Head::load_weights(&dir.0.join(file), alt_config(), &Device::Cpu).unwrap();
        let vl = head
            .process_backbone(c.get("in.backbone_features"))
            .unwrap();
        let s = head.encode_state(c.get("in.state"), emb).unwrap();
        head.velocity(
            &s,
            c.get("in.actions"),
            Timesteps::Shared(c.get("in.timesteps")),
            &c.vl(&vl),
            emb,
        )
        .unwrap()
    };
    let (a, b) = (run("bf16.safetensors"), run("f32.safetensors"));
    assert_eq!(rel_err(&a, &b), 0.0);
    // and the rounding did change the weights (the comparison above is not vacuous)
    assert!(rel_err(&b, c.get("out.velocity")) > 1e-4);
}

#[test]
fn missing_misshaped_and_unexpected_tensors_are_named() {
    let dir = Scratch::new("bad");
    let path = dir.0.join("model.safetensors");

    let mut w = weights("alt");
    w.remove("action_head.model.proj_out_2.weight");
    save(&w, &path);
    match Gr00tN17Head::load_weights(&path, alt_config(), &Device::Cpu) {
        Err(Error::MissingTensor { name, path: p }) => {
            assert_eq!(name, "action_head.model.proj_out_2.weight");
            assert_eq!(p, path);
        }
        other => panic!("expected MissingTensor, got {other:?}"),
    }

    let mut w = weights("alt");
    w.insert(
        "action_head.action_encoder.W2.W".into(),
        Tensor::zeros((3, 24, 24), DType::F32, &Device::Cpu).unwrap(),
    );
    save(&w, &path);
    let err = Gr00tN17Head::load_weights(&path, alt_config(), &Device::Cpu).unwrap_err();
    match &err {
        Error::TensorShape {
            name,
            expected,
            got,
            ..
        } => {
            assert_eq!(name, "action_head.action_encoder.W2.W");
            assert_eq!(expected, &[3, 48, 24]);
            assert_eq!(got, &[3, 24, 24]);
        }
        other => panic!("expected TensorShape, got {other:?}"),
    }
    assert!(
        err.to_string().contains("action_head.action_encoder.W2.W"),
        "{err}"
    );

    // A configuration without the VL self-attention does not silently drop its weights.
    let mut cfg = alt_config();
    cfg.vl_self_attention = None;
    save(&weights("alt"), &path);
    match Gr00tN17Head::load_weights(&path, cfg, &Device::Cpu) {
        Err(Error::UnexpectedTensor { name, .. }) => {
            assert!(name.starts_with("action_head.vl_self_attention."), "{name}")
        }
        other => panic!("expected UnexpectedTensor, got {other:?}"),
    }
}

/// πR² fine-tuning starts from the checkpoint's head exactly: loaded trainable (its trained
/// tensors as `Var`s, a zero delay table), the head computes the base head's velocity bit for
/// bit, for shared and for per-position timesteps that are all equal, at every `d_vis`; a
/// gradient step then reaches the delay table and the shared AdaLN weights, and the saved
/// weights load back as a head with the trained delay table.
#[test]
fn trainable_head_starts_as_the_base_head() {
    let dir = Scratch::new("trainable");
    let mut all = weights("alt");
    all.insert(
        "backbone.some.weight".into(),
        Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
    );
    save(&all, &dir.0.join("model.safetensors"));
    std::fs::copy(
        fixtures().join("alt.config.json"),
        dir.0.join("config.json"),
    )
    .unwrap();
    let base = Case::load("alt");
    let d_vis_max = 5;
    let train = Gr00tN17Head::load_trainable(&dir.0, d_vis_max, &Device::Cpu).unwrap();
    let table = train.delay_embedding().expect("a delay table");
    assert_eq!(table.dims(), [d_vis_max + 1, 24]);
    let names: Vec<&str> = train
        .trainable_vars()
        .iter()
        .map(|(n, _)| n.as_str())
        .collect();
    assert!(names.contains(&"action_head.delay_embedding.weight"));
    assert!(names.contains(&"action_head.model.transformer_blocks.0.norm1.linear.weight"));
    assert!(names.contains(&"action_head.position_embedding.weight"));
    assert!(!names
        .iter()
        .any(|n| n.contains("vlln") || n.contains("vl_self_attention")));

    let emb = base.get("in.embodiment_id");
    let (vl, s) = base.prefix();
    let x = base.get("in.actions");
    let (b, h, _) = x.dims3().unwrap();
    let t = base.get("in.timesteps");
    let t2 = t.reshape((b, 1)).unwrap();
    let actions = t2.broadcast_as((b, h)).unwrap().contiguous().unwrap();
    let tokens = t2.broadcast_as((b, 1 + h)).unwrap().contiguous().unwrap();
    let per = Timesteps::PerPosition {
        actions: &actions,
        tokens: &tokens,
    };
    let vl_t = train
        .process_backbone(base.get("in.backbone_features"))
        .unwrap();
    let s_t = train.encode_state(base.get("in.state"), emb).unwrap();
    let bits = |t: &Tensor| -> Vec<u32> {
        let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        v.iter().map(|x| x.to_bits()).collect()
    };
    for d in [0u32, 3, 9] {
        let d_vis = Tensor::new(&[d, d], &Device::Cpu).unwrap();
        let vl_train = VlTokens {
            d_vis: Some(&d_vis),
            ..base.vl(&vl_t)
        };
        for ts in [Timesteps::Shared(t), per] {
            let want = base.head.velocity(&s, x, ts, &base.vl(&vl), emb).unwrap();
            let got = train.velocity(&s_t, x, ts, &vl_train, emb).unwrap();
            assert_eq!(bits(&got), bits(&want), "d_vis = {d}");
        }
    }
    // The shared/per-position equivalence of the base head carries over (not bit for bit:
    // the GEMMs differ in shape).
    let d0 = Tensor::new(&[0u32, 0], &Device::Cpu).unwrap();
    let vl_train = VlTokens {
        d_vis: Some(&d0),
        ..base.vl(&vl_t)
    };
    let got = train.velocity(&s_t, x, per, &vl_train, emb).unwrap();
    check(
        "alt",
        "trainable, per-position",
        &got,
        base.get("out.velocity"),
    );
    // A head with a delay table refuses a call without d_vis.
    assert!(train.velocity(&s_t, x, per, &base.vl(&vl_t), emb).is_err());

    // One gradient step on a per-position loss reaches the delay table (row 2 only) and the
    // shared AdaLN weights, and changes the velocity.
    let d2 = Tensor::new(&[2u32, 2], &Device::Cpu).unwrap();
    let vl2 = VlTokens {
        d_vis: Some(&d2),
        ..base.vl(&vl_t)
    };
    let v = train.velocity(&s_t, x, per, &vl2, emb).unwrap();
    let loss = v.sqr().unwrap().mean_all().unwrap();
    let grads = loss.backward().unwrap();
    let var = |name: &str| {
        train
            .trainable_vars()
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.clone())
            .unwrap()
    };
    let delay = var("action_head.delay_embedding.weight");
    let g = grads.get(delay.as_tensor()).expect("delay table gradient");
    let rows = g.abs().unwrap().sum(1).unwrap().to_vec1::<f32>().unwrap();
    assert!(rows[2] > 0.0, "{rows:?}");
    assert!(
        rows.iter().enumerate().all(|(i, &r)| i == 2 || r == 0.0),
        "{rows:?}"
    );
    let ada = var("action_head.model.transformer_blocks.1.norm1.linear.weight");
    assert!(grads.get(ada.as_tensor()).is_some());
    let new = (delay.as_tensor() - (g * 10.0).unwrap()).unwrap();
    delay.set(&new).unwrap();
    let moved = train.velocity(&s_t, x, per, &vl2, emb).unwrap();
    assert!(
        rel_err(&moved, &v) > 1e-3,
        "the step did not change the velocity"
    );
    let same_d0 = train.velocity(&s_t, x, per, &vl_train, emb).unwrap();
    assert_eq!(bits(&same_d0), bits(&got), "row 0 must be untouched");

    // Saved weights (+ config.json) load back as an inference head with the trained table.
    let out = Scratch::new("trainable-out");
    train
        .save_weights(&out.0.join("model.safetensors"))
        .unwrap();
    std::fs::copy(
        fixtures().join("alt.config.json"),
        out.0.join("config.json"),
    )
    .unwrap();
    let back = Gr00tN17Head::load(&out.0, &Device::Cpu).unwrap();
    assert!(back.trainable_vars().is_empty());
    let again = back.velocity(&s_t, x, per, &vl2, emb).unwrap();
    assert_eq!(bits(&again), bits(&moved));
}

/// πR²'s per-position AdaLN heads: a trainable head turned into the per-position form starts
/// as the base head (each head a copy of the shared pair, so any timesteps give the base's
/// velocity), its heads are the trainable tensors in place of the shared ones, one gradient
/// step makes them differ by position, and saved weights load back with the heads.
#[test]
fn per_position_adaln_heads_start_as_the_base_head_and_specialise() {
    let dir = Scratch::new("heads");
    save(&weights("alt"), &dir.0.join("model.safetensors"));
    std::fs::copy(
        fixtures().join("alt.config.json"),
        dir.0.join("config.json"),
    )
    .unwrap();
    let base = Case::load("alt");
    let emb = base.get("in.embodiment_id");
    let x = base.get("in.actions");
    let (b, h, _) = x.dims3().unwrap();
    let shared = Gr00tN17Head::load_trainable(&dir.0, 0, &Device::Cpu).unwrap();
    let heads = Gr00tN17Head::load_trainable(&dir.0, 0, &Device::Cpu)
        .unwrap()
        .with_position_heads(h)
        .unwrap();
    assert_eq!(shared.position_heads(), None);
    assert_eq!(heads.position_heads(), Some(1 + h));
    let names: Vec<&str> = heads
        .trainable_vars()
        .iter()
        .map(|(n, _)| n.as_str())
        .collect();
    assert!(names.contains(&"action_head.model.transformer_blocks.0.norm1.linear_heads.weight"));
    assert!(names.contains(&"action_head.model.proj_out_1_heads.bias"));
    assert!(!names.iter().any(|n| n.ends_with("norm1.linear.weight")));
    assert!(!names.contains(&"action_head.model.proj_out_1.weight"));
    // A wrong count is refused by name.
    let e = heads.clone().with_position_heads(h + 1).unwrap_err();
    assert!(e.to_string().contains("per-position AdaLN heads"), "{e}");

    // Per-position timesteps that differ along the chunk (a staircase).
    let ta: Vec<u32> = (0..b * h).map(|i| (999 - 60 * (i % h)) as u32).collect();
    let tt: Vec<u32> = (0..b * (1 + h))
        .map(|i| {
            if i % (1 + h) == 0 {
                999
            } else {
                (999 - 60 * (i % (1 + h) - 1)) as u32
            }
        })
        .collect();
    let actions = Tensor::from_vec(ta, (b, h), &Device::Cpu).unwrap();
    let tokens = Tensor::from_vec(tt, (b, 1 + h), &Device::Cpu).unwrap();
    let per = Timesteps::PerPosition {
        actions: &actions,
        tokens: &tokens,
    };
    let d0 = Tensor::new(&[0u32, 0], &Device::Cpu).unwrap();
    let run = |m: &Gr00tN17Head, ts: Timesteps<'_>| -> Tensor {
        let vl = m
            .process_backbone(base.get("in.backbone_features"))
            .unwrap();
        let s = m.encode_state(base.get("in.state"), emb).unwrap();
        let vlt = VlTokens {
            d_vis: Some(&d0),
            ..base.vl(&vl)
        };
        m.velocity(&s, x, ts, &vlt, emb).unwrap()
    };
    for ts in [Timesteps::Shared(base.get("in.timesteps")), per] {
        let (a, c) = (run(&shared, ts), run(&heads, ts));
        assert!(
            rel_err(&c, &a) < 1e-6,
            "first forward differs: {}",
            rel_err(&c, &a)
        );
    }
    // One step on a per-position loss: the heads of one layer no longer agree.
    let v = run(&heads, per);
    let grads = v.sqr().unwrap().mean_all().unwrap().backward().unwrap();
    let (_, w) = heads
        .trainable_vars()
        .iter()
        .find(|(n, _)| n == "action_head.model.proj_out_1_heads.weight")
        .unwrap();
    let g = grads.get(w.as_tensor()).expect("a gradient for the heads");
    w.set(&(w.as_tensor() - (g * 1e3).unwrap()).unwrap())
        .unwrap();
    let wv = w.as_tensor();
    let spread = (wv.narrow(0, 1, 1).unwrap() - wv.narrow(0, 2, 1).unwrap())
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert!(spread > 0.0, "heads 1 and 2 did not specialise");
    let moved = run(&heads, per);
    // Saved and loaded back as an inference head, with its heads.
    let out = Scratch::new("heads-out");
    heads
        .save_weights(&out.0.join("model.safetensors"))
        .unwrap();
    std::fs::copy(
        fixtures().join("alt.config.json"),
        out.0.join("config.json"),
    )
    .unwrap();
    let back = Gr00tN17Head::load(&out.0, &Device::Cpu).unwrap();
    assert_eq!(back.position_heads(), Some(1 + h));
    assert!(rel_err(&run(&back, per), &moved) < 1e-6);
}

#[test]
fn dropout_applies_in_the_training_forward_only_and_is_keyed_by_seed_step_and_site() {
    use pir2_backends::gr00t::n17::{DitDropout, DropoutSite};
    let c = Case::load("alt");
    let cfg = c.head.config().dit.clone();
    // The fixture's config is N1.7's: `dropout` 0.2 with `final_dropout`.
    assert_eq!((cfg.dropout, cfg.final_dropout), (0.2, true));
    let emb = c.get("in.embodiment_id");
    let (vl, s) = c.prefix();
    let x = c.get("in.actions");
    let t = c.get("in.timesteps");
    let ts = Timesteps::Shared(t);
    let bits = |t: &Tensor| -> Vec<u32> {
        let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        v.iter().map(|x| x.to_bits()).collect()
    };
    let eval = c.head.velocity(&s, x, ts, &c.vl(&vl), emb).unwrap();
    let train = |d: &DitDropout| {
        c.head
            .velocity_train(&s, x, ts, &c.vl(&vl), emb, d)
            .unwrap()
    };
    let loss = |v: &Tensor| {
        v.sqr()
            .unwrap()
            .mean_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };

    // Rate 0: the training forward is the inference forward, bit for bit.
    let off = DitDropout {
        rate: 0.0,
        ..DitDropout::from_config(&cfg, 7, 3)
    };
    assert_eq!(bits(&train(&off)), bits(&eval));

    // The checkpoint's rate: the same (seed, step) gives the same bits; another step or
    // seed other masks, hence another loss; fewer sites without `final_dropout`.
    let d = DitDropout::from_config(&cfg, 7, 3);
    let v = train(&d);
    assert_ne!(bits(&v), bits(&eval));
    assert_eq!(bits(&train(&d)), bits(&v), "same seed and step, other bits");
    let next = train(&DitDropout { step: 4, ..d });
    assert_ne!(loss(&next), loss(&v), "step 4 drew step 3's masks");
    let seed = train(&DitDropout { seed: 8, ..d });
    assert_ne!(loss(&seed), loss(&v), "seed 8 drew seed 7's masks");
    let no_final = train(&DitDropout {
        final_dropout: false,
        ..d
    });
    assert_ne!(bits(&no_final), bits(&v));
    println!(
        "loss: eval {:.5}, step 3 {:.5}, step 4 {:.5}, seed 8 {:.5}",
        loss(&eval),
        loss(&v),
        loss(&next),
        loss(&seed)
    );
    // No hidden state: the inference forward is unchanged after training forwards.
    let again = c.head.velocity(&s, x, ts, &c.vl(&vl), emb).unwrap();
    assert_eq!(bits(&again), bits(&eval));
    // The sampler (GR00T's get_action) never drops: still the reference's output.
    let a = c
        .head
        .sample(&s, c.get("in.noise"), &c.vl(&vl), emb)
        .unwrap();
    check("alt", "get_action", &a, c.get("out.action_pred"));

    // The masks: 0 or 1/(1 − p), dropped at rate p, element i a function of
    // (seed, step, site, i) only, distinct per site.
    let n = 200_000;
    for p in [0.2, 0.5] {
        let dp = DitDropout { rate: p, ..d };
        let m = dp.mask(DropoutSite::FeedForwardInner(1), n).unwrap();
        let scale = (1.0 / (1.0 - p)) as f32;
        assert!(m.iter().all(|&v| v == 0.0 || v == scale), "p = {p}");
        let dropped = m.iter().filter(|&&v| v == 0.0).count() as f64 / n as f64;
        assert!((dropped - p).abs() < 0.005, "p = {p}: dropped {dropped}");
        let mean = m.iter().map(|&v| f64::from(v)).sum::<f64>() / n as f64;
        assert!((mean - 1.0).abs() < 0.01, "p = {p}: mean {mean}");
        let head = dp.mask(DropoutSite::FeedForwardInner(1), 100).unwrap();
        assert_eq!(head[..], m[..100]);
    }
    let site = |s: DropoutSite| d.mask(s, 1000).unwrap();
    let a = site(DropoutSite::Attention(0));
    for other in [
        DropoutSite::AttentionFinal(0),
        DropoutSite::FeedForwardInner(0),
        DropoutSite::FeedForwardOutput(0),
        DropoutSite::Attention(1),
    ] {
        assert_ne!(a, site(other), "{other:?}");
    }
    assert!(DitDropout { rate: 1.0, ..d }
        .mask(DropoutSite::Attention(0), 4)
        .is_err());

    // The rate comes from `diffusion_model_cfg` (the DiT class's 0.1 when absent) and must
    // be in [0, 1).
    let text = std::fs::read_to_string(fixtures().join("alt.config.json")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    json["diffusion_model_cfg"]
        .as_object_mut()
        .unwrap()
        .remove("dropout");
    let c1 = Gr00tN17Config::from_json_str(&json.to_string(), Path::new("c.json")).unwrap();
    assert_eq!(c1.dit.dropout, 0.1);
    json["diffusion_model_cfg"]["dropout"] = serde_json::json!(1.0);
    let e = Gr00tN17Config::from_json_str(&json.to_string(), Path::new("c.json")).unwrap_err();
    assert!(e.to_string().contains("dropout"), "{e}");
}

#[test]
fn device_built_dropout_masks_are_a_pure_function_of_seed_step_and_site() {
    use pir2_backends::gr00t::n17::{DitConfig, DitDropout, DropoutSite, MaskSource};
    let dev = Device::Cpu;
    let cfg = alt_config().dit;
    let d = DitDropout::from_config(&cfg, 7, 3);
    let shape = (4, 50, 512); // 102 400 values: rows of 512 columns.
    let n = 4 * 50 * 512;
    let get = |d: &DitDropout, site: DropoutSite, src: MaskSource| -> Vec<f32> {
        let m = d.mask_tensor(site, shape, &dev, src).unwrap();
        assert_eq!(m.dims(), [4, 50, 512]);
        assert_eq!(m.dtype(), DType::F32);
        m.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let site = DropoutSite::FeedForwardInner(1);

    // The CPU's masks are unchanged: the host source is `mask` itself, and the training
    // forward on the CPU uses it.
    assert_eq!(MaskSource::for_device(&dev), MaskSource::Host);
    let host = get(&d, site, MaskSource::Host);
    assert_eq!(bits(&host), bits(&d.mask(site, n).unwrap()));

    for p in [0.2, 0.5] {
        let dp = DitDropout { rate: p, ..d };
        let m = get(&dp, site, MaskSource::Device);
        // A fresh object with the same (seed, step, site) gives the same bits.
        let fresh = DitDropout::from_config(
            &DitConfig {
                dropout: p,
                ..cfg.clone()
            },
            7,
            3,
        );
        assert_eq!(bits(&m), bits(&get(&fresh, site, MaskSource::Device)));
        // 0 or exactly 1/(1 − p); dropped at rate p within 5 binomial σ.
        let scale = (1.0 / (1.0 - p)) as f32;
        assert!(m.iter().all(|&v| v == 0.0 || v == scale), "p = {p}");
        let sigma = (p * (1.0 - p) / n as f64).sqrt();
        let rate = |k: usize, of: usize| k as f64 / of as f64;
        let dropped = rate(m.iter().filter(|&&v| v == 0.0).count(), n);
        assert!(
            (dropped - p).abs() < 5.0 * sigma,
            "p = {p}: dropped {dropped}"
        );
        // Neighbours are independent: both dropped at rate p² (row and column neighbours).
        let (rows, cols) = (n / 512, 512);
        let both = |di: usize, dj: usize| {
            let mut k = 0;
            let mut of = 0;
            for i in 0..rows - di {
                for j in 0..cols - dj {
                    of += 1;
                    k += usize::from(m[i * cols + j] == 0.0 && m[(i + di) * cols + j + dj] == 0.0);
                }
            }
            (rate(k, of), of)
        };
        for (di, dj) in [(0, 1), (1, 0), (1, 1)] {
            let (r, of) = both(di, dj);
            let q = p * p;
            let s = (q * (1.0 - q) / of as f64).sqrt();
            assert!((r - q).abs() < 5.0 * s, "p = {p}, ({di}, {dj}): both {r}");
        }
        // Not the host's bits.
        assert_ne!(bits(&m), bits(&get(&dp, site, MaskSource::Host)));
    }

    // Other sites, steps and seeds draw other masks.
    let m = get(&d, site, MaskSource::Device);
    for (other, s) in [
        (d, DropoutSite::FeedForwardInner(0)),
        (d, DropoutSite::FeedForwardOutput(1)),
        (d, DropoutSite::Attention(1)),
        (DitDropout { step: 4, ..d }, site),
        (DitDropout { seed: 8, ..d }, site),
    ] {
        assert_ne!(bits(&m), bits(&get(&other, s, MaskSource::Device)), "{s:?}");
    }
    // Rate 0 keeps everything; an invalid rate is an error, as on the host.
    let ones = get(&DitDropout { rate: 0.0, ..d }, site, MaskSource::Device);
    assert!(ones.iter().all(|&v| v == 1.0));
    assert!(DitDropout { rate: 1.0, ..d }
        .mask_tensor(site, 4, &dev, MaskSource::Device)
        .is_err());
}
