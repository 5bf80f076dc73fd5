//! `pir2 eval ballplate --checkpoint DIR` on an ONNX checkpoint (model.onnx, stats.json,
//! identity.json; what examples/lerobot-flow/train.py writes): it runs through ONNX Runtime
//! and scores what the candle checkpoint it was exported from scores; a directory with
//! neither or both weight files, a replaced graph, a graph of other sizes than the task's and
//! another policy are refused by name
//! (feature `ort`; needs ORT_DYLIB_PATH, see scripts/setup-native.sh).
#![cfg(feature = "ort")]

use std::path::Path;
use std::process::{Command, Output};

use pir2_backends::candle::CandleModel;
use pir2_backends::checkpoint::{weights_sha256, Identity};
use pir2_backends::config::{Config, MlpConfig, ModelConfig, Stats};
use pir2_cli::study::{ballplate, Cell, Policy};

mod common;
use common::Scratch;

fn eval(dir: &Path, policy: &str, json: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["eval", "ballplate", "--checkpoint"])
        .arg(dir)
        .args(["--policy", policy, "--episodes", "2", "--d0", "1", "--json"])
        .arg(json)
        .output()
        .unwrap()
}

fn cells(json: &Path) -> Vec<Cell> {
    serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn an_onnx_checkpoint_is_evaluated_like_the_candle_checkpoint_it_came_from() {
    let dir = Scratch::new("onnx-checkpoint");
    let spec = ballplate::spec();
    let mut stats = Stats::identity(&spec);
    // Not the identity on the actions: the ONNX path must denormalise with stats.json.
    stats.action.mean = vec![0.01, -0.02];
    stats.action.std = vec![0.5, 0.25];
    let mut model = CandleModel::new(
        Config {
            spec,
            model: ModelConfig::Mlp(MlpConfig {
                width: 32,
                depth: 2,
                ..MlpConfig::default()
            }),
        },
        stats,
        7,
    )
    .unwrap();
    model.set_policy(Some(Policy::PiR2));
    let candle = dir.path().join("candle");
    model.save(&candle).unwrap();

    // The ONNX checkpoint: the exported graph, the same stats, its own identity.
    let onnx = dir.path().join("onnx");
    std::fs::create_dir_all(&onnx).unwrap();
    let status = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["export", candle.to_str().unwrap(), "--onnx"])
        .arg(onnx.join("model.onnx"))
        .status()
        .unwrap();
    assert!(status.success());
    std::fs::copy(candle.join("stats.json"), onnx.join("stats.json")).unwrap();
    let identity = |sha: String| {
        serde_json::to_string(&Identity {
            policy: Some(Policy::PiR2),
            weights_sha256: sha,
        })
        .unwrap()
    };
    let sha = weights_sha256(&std::fs::read(onnx.join("model.onnx")).unwrap());
    std::fs::write(onnx.join("identity.json"), identity(sha)).unwrap();

    let (jo, jc) = (dir.path().join("onnx.json"), dir.path().join("candle.json"));
    let o = eval(&onnx, "pir2", &jo);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("ONNX Runtime"), "{}", stderr(&o));
    let c = eval(&candle, "pir2", &jc);
    assert!(c.status.success(), "{}", stderr(&c));
    let (co, cc) = (cells(&jo), cells(&jc));
    assert!(!co.is_empty());
    assert!(co.iter().all(|c| c.episodes == 2 && c.d0 == 1));
    let key = |v: &[Cell]| {
        v.iter()
            .map(|c| (c.label.clone(), c.successes))
            .collect::<Vec<_>>()
    };
    assert_eq!(key(&co), key(&cc));

    // Another policy than the one recorded.
    let o = eval(&onnx, "rtc", &dir.path().join("rtc.json"));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("trained as pir2"), "{}", stderr(&o));

    // A graph replaced after its identity was written.
    let tampered = dir.path().join("tampered");
    std::fs::create_dir_all(&tampered).unwrap();
    for f in ["model.onnx", "stats.json"] {
        std::fs::copy(onnx.join(f), tampered.join(f)).unwrap();
    }
    std::fs::write(tampered.join("identity.json"), identity("00".repeat(32))).unwrap();
    let o = eval(&tampered, "pir2", &dir.path().join("t.json"));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("was replaced"), "{}", stderr(&o));

    // A graph of other sizes than the task's (H = 8 instead of 16).
    let short = dir.path().join("short");
    let mut small = CandleModel::new(
        Config {
            spec: pir2_backends::config::Spec { horizon: 8, ..spec },
            model: ModelConfig::Mlp(MlpConfig {
                width: 8,
                depth: 1,
                ..MlpConfig::default()
            }),
        },
        Stats::identity(&spec),
        1,
    )
    .unwrap();
    small.set_policy(Some(Policy::PiR2));
    small.save(&dir.path().join("short-candle")).unwrap();
    std::fs::create_dir_all(&short).unwrap();
    let status = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["export"])
        .arg(dir.path().join("short-candle"))
        .arg("--onnx")
        .arg(short.join("model.onnx"))
        .status()
        .unwrap();
    assert!(status.success());
    std::fs::copy(onnx.join("stats.json"), short.join("stats.json")).unwrap();
    let sha = weights_sha256(&std::fs::read(short.join("model.onnx")).unwrap());
    std::fs::write(short.join("identity.json"), identity(sha)).unwrap();
    let o = eval(&short, "pir2", &dir.path().join("s.json"));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("the task's = (16"), "{}", stderr(&o));

    // Both weight files, then neither.
    std::fs::copy(
        candle.join("model.safetensors"),
        tampered.join("model.safetensors"),
    )
    .unwrap();
    let o = eval(&tampered, "pir2", &dir.path().join("b.json"));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("holds both"), "{}", stderr(&o));
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let o = eval(&empty, "pir2", &dir.path().join("e.json"));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("holds neither"), "{}", stderr(&o));
}
