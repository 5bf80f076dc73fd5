//! A dataset task's output through `pir2 export` and ONNX Runtime: the exported model samples
//! the same chunks through the runtime's action head as the candle checkpoint it came from,
//! and scores the same open-loop error on the held-out episodes (feature `ort`; needs
//! ORT_DYLIB_PATH, see scripts/setup-native.sh).
#![cfg(feature = "ort")]

use std::path::Path;
use std::process::Command;

use pir2_backends::candle::CandleModel;
use pir2_backends::ort::OrtModel;
use pir2_cli::study::dataset::{self, DatasetTaskConfig};
use pir2_cli::study::open_loop::{open_loop_error, sample_chunk, snapshot, OpenLoop};
use pir2_cli::study::pipeline::output_map;
use pir2_runtime::HeadSpec;
use pir2_sim::dataset::read_selected;

mod common;
use common::Scratch;

const TASK: &str = r#"
fast_keys = ["observation.state", "observation.goal"]
slow_keys = ["observation.speed"]
horizon = 8
n_obs = 2
policy = "pi_r2"
seed = 3

[recipe]
pir2_d_max = 2

[model]
kind = "mlp"
width = 32
depth = 2

[train]
steps = 60
batch_size = 32
warmup = 10

[validation]
held_out_episodes = [2]
checkpoints = 2
windows = 8
"#;

#[test]
fn an_exported_dataset_policy_runs_through_the_runtime_like_its_checkpoint() {
    let dir = Scratch::new("dataset-onnx");
    let data =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-sim/tests/fixtures/lerobot-reach");
    for policy in ["pi_r2", "rtc", "flow"] {
        let cfg =
            DatasetTaskConfig::from_toml(&TASK.replace("\"pi_r2\"", &format!("\"{policy}\"")))
                .unwrap();
        let out = dir.path().join(policy);
        dataset::train(&data, &cfg, &out, false).unwrap();
        let onnx = dir.path().join(format!("{policy}.onnx"));
        let status = Command::new(env!("CARGO_BIN_EXE_pir2"))
            .args(["export", out.join("best").to_str().unwrap(), "--onnx"])
            .arg(&onnx)
            .status()
            .unwrap();
        assert!(status.success());
        let mut candle = CandleModel::load(&out.join("best")).unwrap();
        let mut ort = OrtModel::load(&onnx).unwrap();
        let ds = read_selected(&data, &cfg.selection()).unwrap();
        let held = vec![ds.episodes[2].clone()];
        let spec = *candle.spec();
        let head = HeadSpec {
            horizon: spec.horizon,
            action_dim: spec.action_dim,
            n_obs: spec.n_obs,
            fast_dim: spec.fast_dim,
            slow_dim: spec.slow.len(),
            period: 100_000_000,
            d_max: cfg.policy.d_max(&cfg.recipe),
            d_vis_max: spec.d_vis_max,
        };
        let mode = cfg.policy.deployments(&cfg.recipe)[0].mode;
        for t in [0, 7, 20] {
            let snap = snapshot(&held[0], t, &head);
            let a = sample_chunk(&mut candle, head, &mode, 1, &snap, 11).unwrap();
            let b = sample_chunk(&mut ort, head, &mode, 1, &snap, 11).unwrap();
            for (x, y) in a.x.iter().zip(&b.x) {
                assert!(
                    (x - y).abs() < 1e-3,
                    "{policy} t={t}: {:?} vs {:?}",
                    a.x,
                    b.x
                );
            }
        }
        let ol = OpenLoop {
            spec: head,
            mode,
            delay: 1,
            output: output_map(&candle),
            windows: 8,
            seed: 5,
        };
        let ec = open_loop_error(&mut candle, &held, &ol).unwrap();
        let eo = open_loop_error(&mut ort, &held, &ol).unwrap();
        assert!(
            (ec.rmse - eo.rmse).abs() < 1e-3,
            "{policy}: {ec:?} vs {eo:?}"
        );
    }
}
