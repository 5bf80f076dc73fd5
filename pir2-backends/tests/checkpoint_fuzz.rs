//! The checkpoint loader never panics: `config.json`, `stats.json` and `model.safetensors`
//! with byte edits, arbitrary bytes, or numbers of `config.json` set to extreme values end in
//! `Ok` or an error from [`CandleModel::load`], never a panic (proptest reports a panic as a
//! failure) and never an allocation the file does not back. Case counts are small (CI).

use std::fs;
use std::path::{Path, PathBuf};

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{
    Config, DitConfig, FilmMode, MlpConfig, ModelConfig, SlowSpec, Spec, Stats, UNetConfig,
};
use pir2_tests::fuzz_cases;
use proptest::prelude::*;
use serde_json::Value;

const FILES: [&str; 3] = ["config.json", "stats.json", "model.safetensors"];

/// Removes the directory when the test thread ends.
struct Dir(PathBuf);
impl Drop for Dir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// Three small checkpoints (MLP, U-Net, DiT), saved once per test thread.
fn checkpoints(name: &str) -> Dir {
    let root = std::env::temp_dir().join(format!("pir2-ckpt-fuzz-{}-{name}", std::process::id()));
    let _ = fs::remove_dir_all(&root);
    let spec = Spec {
        horizon: 4,
        action_dim: 2,
        n_obs: 2,
        fast_dim: 3,
        slow: SlowSpec::Vector { dim: 2 },
        d_vis_max: 2,
    };
    let models = [
        ModelConfig::Mlp(MlpConfig {
            width: 8,
            depth: 2,
            tau_freqs: 2,
            dvis_dim: 2,
        }),
        ModelConfig::UNet(UNetConfig {
            widths: vec![8, 8],
            kernel: 3,
            groups: 4,
            tau_dim: 4,
            dvis_dim: 2,
            ..UNetConfig::default()
        }),
        ModelConfig::Dit(DitConfig {
            width: 8,
            depth: 1,
            heads: 2,
            mlp_ratio: 2,
            tau_dim: 4,
            ada: FilmMode::PerPositionHeads,
        }),
    ];
    for (i, model) in models.into_iter().enumerate() {
        let cfg = Config { spec, model };
        let m = CandleModel::new(cfg, Stats::identity(&spec), 1).unwrap();
        let dir = root.join(format!("m{i}"));
        m.save(&dir).unwrap();
        CandleModel::load(&dir).unwrap();
        // Without identity.json (a checkpoint written before it existed), so that edited
        // weights reach the loader's checks instead of failing the hash comparison.
        fs::remove_file(dir.join("identity.json")).unwrap();
        CandleModel::load(&dir).unwrap();
    }
    Dir(root)
}

#[derive(Debug, Clone)]
enum Edit {
    Set(usize, u8),
    Flip(usize, u8),
    Truncate(usize),
    Insert(usize, Vec<u8>),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        4 => (any::<usize>(), any::<u8>()).prop_map(|(p, v)| Edit::Set(p, v)),
        4 => (any::<usize>(), 0u8..8).prop_map(|(p, b)| Edit::Flip(p, 1 << b)),
        1 => any::<usize>().prop_map(Edit::Truncate),
        1 => (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(p, v)| Edit::Insert(p, v)),
    ]
}

fn apply(bytes: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut b = bytes.to_vec();
    for e in edits {
        let len = b.len();
        match e {
            Edit::Set(p, v) if len > 0 => b[p % len] = *v,
            Edit::Flip(p, m) if len > 0 => b[p % len] ^= m,
            Edit::Truncate(p) if len > 0 => b.truncate(p % len),
            Edit::Insert(p, v) => {
                let i = p % (len + 1);
                b.splice(i..i, v.iter().copied());
            }
            _ => {}
        }
    }
    b
}

/// Puts a file's original bytes back when dropped (also when the case panicked, so the
/// next case and the shrinking start from the valid checkpoint).
struct Restore(PathBuf, Vec<u8>);
impl Drop for Restore {
    fn drop(&mut self) {
        let _ = fs::write(&self.0, &self.1);
    }
}

/// Replace `file` of checkpoint `model` by `bytes`, load (must not panic), restore.
fn load_with(root: &Path, model: usize, file: &str, bytes: &[u8]) {
    let dir = root.join(format!("m{model}"));
    let path = dir.join(file);
    let _restore = Restore(path.clone(), fs::read(&path).unwrap());
    fs::write(&path, bytes).unwrap();
    let _ = CandleModel::load(&dir);
}

/// Every number in a JSON value, as a path of object keys / array indices.
fn number_paths(v: &Value, here: &mut Vec<Value>, out: &mut Vec<Vec<Value>>) {
    match v {
        Value::Number(_) => out.push(here.clone()),
        Value::Object(m) => {
            for (k, x) in m {
                here.push(Value::String(k.clone()));
                number_paths(x, here, out);
                here.pop();
            }
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                here.push(Value::from(i));
                number_paths(x, here, out);
                here.pop();
            }
        }
        _ => {}
    }
}

fn at<'a>(v: &'a mut Value, path: &[Value]) -> &'a mut Value {
    path.iter().fold(v, |v, k| match k {
        Value::String(s) => &mut v[s.as_str()],
        k => &mut v[k.as_u64().unwrap() as usize],
    })
}

proptest! {
    #![proptest_config(fuzz_cases(48, "proptest-regressions/checkpoint_fuzz.txt"))]

    /// Up to 8 byte edits of one file of one checkpoint.
    #[test]
    fn mutated_checkpoint_files_never_panic(
        model in 0..3usize,
        file in 0..FILES.len(),
        edits in prop::collection::vec(edit(), 1..8),
    ) {
        thread_local!(static ROOT: Dir = checkpoints("mutated"));
        ROOT.with(|root| {
            let path = root.0.join(format!("m{model}")).join(FILES[file]);
            let bytes = apply(&fs::read(path).unwrap(), &edits);
            load_with(&root.0, model, FILES[file], &bytes);
        });
    }

    /// Arbitrary bytes in place of one file.
    #[test]
    fn arbitrary_checkpoint_files_never_panic(
        model in 0..3usize,
        file in 0..FILES.len(),
        bytes in prop::collection::vec(any::<u8>(), 0..256),
    ) {
        thread_local!(static ROOT: Dir = checkpoints("arbitrary"));
        ROOT.with(|root| load_with(&root.0, model, FILES[file], &bytes));
    }

    /// One to three numbers of `config.json` set to extreme values (0, huge, negative,
    /// fractional): a size the weights file does not back must be an error, not an
    /// allocation or an overflow.
    #[test]
    fn extreme_config_numbers_never_panic(
        model in 0..3usize,
        picks in prop::collection::vec(
            (any::<prop::sample::Index>(), prop::sample::select(vec![
                serde_json::json!(0), serde_json::json!(1), serde_json::json!(2),
                serde_json::json!(3), serde_json::json!(65), serde_json::json!(4096),
                serde_json::json!(1u64 << 31), serde_json::json!(1u64 << 40),
                serde_json::json!(u64::MAX), serde_json::json!(-1), serde_json::json!(0.5),
            ])),
            1..4,
        ),
    ) {
        thread_local!(static ROOT: Dir = checkpoints("numbers"));
        ROOT.with(|root| {
            let path = root.0.join(format!("m{model}")).join("config.json");
            let mut cfg: Value = serde_json::from_slice(&fs::read(path).unwrap()).unwrap();
            let mut paths = Vec::new();
            number_paths(&cfg, &mut Vec::new(), &mut paths);
            for (i, v) in &picks {
                let p = i.get(&paths).clone();
                *at(&mut cfg, &p) = v.clone();
            }
            load_with(&root.0, model, "config.json", cfg.to_string().as_bytes());
        });
    }

    /// `Config::from_file` on arbitrary TOML-ish text (the `pir2 train --model` file).
    #[test]
    fn arbitrary_model_config_files_never_panic(
        text in "[a-z_=\\[\\]{}0-9.,\" \n-]{0,200}",
    ) {
        thread_local!(static ROOT: Dir = checkpoints("toml"));
        ROOT.with(|root| {
            let path = root.0.join("model.toml");
            fs::write(&path, &text).unwrap();
            if let Ok(cfg) = Config::from_file(&path) {
                let _ = cfg.validate();
            }
        });
    }
}

#[test]
fn a_config_larger_than_its_weights_is_an_error_not_an_allocation() {
    let root = checkpoints("huge");
    let dir = root.0.join("m0");
    let path = dir.join("config.json");
    let original: Value = serde_json::from_slice(&fs::read(&path).unwrap()).unwrap();
    let load_with_width = |w: u64| {
        let mut cfg = original.clone();
        cfg["model"]["width"] = serde_json::json!(w);
        fs::write(&path, cfg.to_string()).unwrap();
        CandleModel::load(&dir).unwrap_err().to_string()
    };
    // 2^40: refused by name (before: n_obs·F-style products overflowed, a 2^40-wide layer
    // was allocated).
    let err = load_with_width(1 << 40);
    assert!(err.contains("mlp.width") && err.contains("limit"), "{err}");
    // 8192: a legal width, but 67 M weights the 8-wide checkpoint does not hold: refused
    // before the layer is allocated.
    let err = load_with_width(8192);
    assert!(
        err.contains("more weight values than the checkpoint holds"),
        "{err}"
    );
    // n_obs · fast_dim overflowed usize (a panic in debug builds).
    let mut cfg = original.clone();
    cfg["spec"]["n_obs"] = serde_json::json!(u64::MAX);
    fs::write(&path, cfg.to_string()).unwrap();
    let err = CandleModel::load(&dir).unwrap_err().to_string();
    assert!(err.contains("spec.n_obs"), "{err}");
}

/// Saves of sibling checkpoints (`ckpt.v1`, `ckpt.v2`) never share or delete a temporary
/// directory: another writer's in-progress `ckpt.partial` is left alone, and nothing but the
/// checkpoints is left behind.
#[test]
fn saves_use_their_own_temporary_directory() {
    let root = checkpoints("save");
    let out = root.0.join("run");
    let theirs = out.join("ckpt.partial");
    fs::create_dir_all(&theirs).unwrap();
    fs::write(theirs.join("config.json"), "another writer's file").unwrap();
    let m = CandleModel::load(&root.0.join("m0")).unwrap();
    m.save(&out.join("ckpt.v1")).unwrap();
    m.save(&out.join("ckpt.v2")).unwrap();
    assert_eq!(
        fs::read_to_string(theirs.join("config.json")).unwrap(),
        "another writer's file"
    );
    let mut names: Vec<String> = fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["ckpt.partial", "ckpt.v1", "ckpt.v2"]);
    CandleModel::load(&out.join("ckpt.v2")).unwrap();
    // An existing checkpoint is never replaced.
    assert!(m.save(&out.join("ckpt.v1")).is_err());
}

/// `identity.json`: the policy set on the model is recorded and read back with the hash of
/// the weights; a checkpoint without it loads with both unrecorded (the hash is still
/// computed); weights replaced after the save, or an unreadable identity, are errors naming
/// `identity.json`.
#[test]
fn the_identity_records_the_policy_and_catches_replaced_weights() {
    use pir2_backends::checkpoint::{weights_sha256, Checkpoint};
    let root = checkpoints("identity");
    let mut m = CandleModel::load(&root.0.join("m0")).unwrap();
    assert_eq!(m.policy(), None);
    let sha = m.weights_sha256().unwrap().to_owned();
    let bytes = fs::read(root.0.join("m0/model.safetensors")).unwrap();
    assert_eq!(sha, weights_sha256(&bytes));
    m.set_policy(Some(pir2_runtime::Policy::Rtc));
    let dir = root.0.join("rtc");
    m.save(&dir).unwrap();
    let back = CandleModel::load(&dir).unwrap();
    assert_eq!(back.policy(), Some(pir2_runtime::Policy::Rtc));
    assert_eq!(back.weights_sha256(), Some(sha.as_str()));
    let ck = Checkpoint::load(&dir).unwrap();
    assert_eq!(ck.identity.unwrap().weights_sha256, sha);

    fs::copy(
        root.0.join("m1/model.safetensors"),
        dir.join("model.safetensors"),
    )
    .unwrap();
    let err = Checkpoint::load(&dir).unwrap_err().to_string();
    assert!(
        err.contains("identity.json") && err.contains("weights were replaced"),
        "{err}"
    );
    fs::write(dir.join("identity.json"), "{\"policy\": \"nope\"}").unwrap();
    let err = Checkpoint::load(&dir).unwrap_err().to_string();
    assert!(err.contains("identity.json"), "{err}");
}
