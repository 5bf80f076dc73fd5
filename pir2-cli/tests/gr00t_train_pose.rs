//! A relative end-effector pose group through `pir2 gr00t train`, end to end: a synthetic
//! N1.7-shaped checkpoint wide enough for a 9-value `xyz_rot6d` pose (the tiny `alt` fixture
//! of `gr00t_train.rs` with its action encoder/decoder and state encoder widened to
//! `max_action_dim = max_state_dim = 10`, under GR00T's tensor names), a dataset whose state
//! and action are an end-effector pose plus a gripper, and the checks:
//! - the run trains and writes `relative_action.eef` `[H, 9]` tables;
//! - the relative poses are GR00T's `T_ref⁻¹·T` (reference = the state of the sample's
//!   frame, rot6d = the first two rows of `R`), checked against scipy's `Rotation` on the
//!   same poses, in both layouts (`xyz_rot6d`, `xyz_rotvec`), and the written tables are
//!   their per-slot minimum and maximum over the chunks the statistics take;
//! - the trainer's targets decode back to the dataset's absolute poses through the runtime's
//!   output map, and the lock-step runtime driven by a head that outputs exactly those targets
//!   sends the dataset's pose at every tick up to `len − H` (πR² async with one- and
//!   two-tick calls, πR² sync).
//!
//! The same run with an `xyz_rotvec` pose (6 values) is the second test.
//!
//! Needs `$PIR2_PYTHON` with numpy and scipy (scripts/setup-native.sh; `source
//! .native/env.sh`).
#![cfg(feature = "gr00t")]

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};
use pir2_backends::gr00t::testing::python_from_env;
use pir2_backends::gr00t::{EmbodimentConfig, Group, GroupFormat, Norm, Normalizer};
use pir2_cli::study::gr00t::{train, Gr00tTargets, Gr00tTrainOptions};
use pir2_runtime::pose::{relative, PoseFormat};
use pir2_runtime::PoseGroup;
use pir2_sim::dataset::{
    read_selected, DatasetSpec, DatasetWriter, Episode, FeatureKeys, WriteMode,
};

mod common;
use common::gr00t::{
    encode_decode_every_chunk, group, lockstep_sends_the_datasets_actions, padding, read_json,
    run_python, small_embodiment, state_and_action, wide_alt_checkpoint, write_alt_features,
    ALT_D_VL, TOKENS,
};
use common::Scratch;

const FRAMES_PER_EPISODE: usize = 14;
const EPISODES: usize = 3;
/// The widened checkpoint's `max_action_dim` and `max_state_dim`.
const WIDE: usize = 10;

/// End-effector pose + gripper (1), for the state and the action.
fn width(format: PoseFormat) -> usize {
    format.width() + 1
}

/// State `eef` (9 or 6) + `grip` 1; action `eef` (relative pose in `format` to the state's
/// `eef`) + `grip`; H = 8, d_max = 2, n_obs = 2, slot 1.
fn embodiment(path: &Path, format: PoseFormat) {
    let pw = format.width();
    let mut e = small_embodiment("tiny-eef", 8);
    e.state = vec![
        group("eef", pw, Norm::MinMax),
        group("grip", 1, Norm::MinMax),
    ];
    e.action = vec![
        Group {
            relative: true,
            format: match format {
                PoseFormat::XyzRot6d => GroupFormat::XyzRot6d,
                PoseFormat::XyzRotvec => GroupFormat::XyzRotvec,
            },
            ..group("eef", pw, Norm::MinMax)
        },
        group("grip", 1, Norm::MinMax),
    ];
    std::fs::write(path, e.to_toml().unwrap()).unwrap();
}

/// The rotation matrix of the rotation vector `w` (Rodrigues), row-major.
fn rotation(w: [f64; 3]) -> [[f64; 3]; 3] {
    let th = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    let k = w.map(|x| x / th);
    let kx = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let k2: f64 = (0..3).map(|m| kx[i][m] * kx[m][j]).sum();
            r[i][j] = f64::from(u8::from(i == j)) + th.sin() * kx[i][j] + (1.0 - th.cos()) * k2;
        }
    }
    r
}

/// A pose along a smooth path at phase `ph` (rotations up to about 1.2 rad about varying
/// axes), in GR00T's `xyz_rot6d` (rows 0 and 1 of `R`) or `xyz_rotvec`.
fn pose(ph: f64, format: PoseFormat) -> Vec<f32> {
    let w = [
        0.6 * ph.sin(),
        0.5 * (1.3 * ph).cos(),
        0.9 * (0.7 * ph).sin() + 0.2,
    ];
    let t = [0.3 * ph.sin(), 0.2 * ph.cos(), 0.05 * ph];
    let r = rotation(w);
    let rot: Vec<f64> = match format {
        PoseFormat::XyzRot6d => r[0].iter().chain(r[1].iter()).copied().collect(),
        PoseFormat::XyzRotvec => w.to_vec(),
    };
    t.iter().chain(&rot).map(|&v| v as f32).collect()
}

/// Episodes whose state is a pose and a gripper, and whose action is the pose a little ahead
/// on the same path (so a relative action is not the identity) and a gripper command.
fn dataset(root: &Path, format: PoseFormat) {
    let wd = width(format);
    let names = |p: &str| (0..wd).map(|i| format!("{p}{i}")).collect::<Vec<_>>();
    let spec = DatasetSpec {
        fps: 25,
        robot_type: Some("tiny-eef".into()),
        tasks: vec!["pick the cube".into()],
        fast_names: names("s"),
        slow_names: Vec::new(),
        action_names: names("a"),
        keys: FeatureKeys::default(),
    };
    let mut w = DatasetWriter::open(root, spec, WriteMode::New).unwrap();
    for e in 0..EPISODES {
        let mut ep = Episode::new(wd, 0, wd);
        for t in 0..FRAMES_PER_EPISODE {
            let ph = 0.3 * t as f64 + 1.7 * e as f64;
            let mut s = pose(ph, format);
            s.push(ph.sin() as f32);
            let mut a = pose(ph + 0.35, format);
            a.push((0.8 * (ph + 0.2).sin()) as f32);
            ep.push(&s, &[], &a);
        }
        w.append(&ep).unwrap();
    }
    w.finish().unwrap();
}

/// Backbone outputs: N frames of 6 tokens of width 20; tokens 0-1 text, 2-4 image, 5 padding.
fn features(path: &Path, frames: usize) {
    let mut seed = 7u64;
    let emb = Tensor::from_vec(
        padding(&mut seed, frames * TOKENS * ALT_D_VL),
        (frames, TOKENS, ALT_D_VL),
        &Device::Cpu,
    )
    .unwrap();
    write_alt_features(path, emb);
}

/// GR00T's relative pose with scipy's `Rotation` (Isaac-GR00T's `pose.py` builds on it):
/// for each `[reference, pose]` pair in `xyz_rot6d`, the rotation is read from the first
/// two rows (the third is their cross product), `T_ref⁻¹·T` is
/// `(R_ref⁻¹·R, R_ref⁻¹·(t − t_ref))`, written back as `xyz_rot6d` (first two rows) and as
/// `xyz_rotvec`; the inputs are also written as `xyz_rotvec`.
const SCIPY_REF: &str = r#"
import json, sys
import numpy as np
from scipy.spatial.transform import Rotation

def read6d(v):
    v = np.asarray(v, dtype=np.float64)
    r0 = v[3:6] / np.linalg.norm(v[3:6])
    r1 = v[6:9] - r0 * (r0 @ v[6:9]); r1 /= np.linalg.norm(r1)
    return v[:3], Rotation.from_matrix(np.stack([r0, r1, np.cross(r0, r1)]))

pairs = json.load(open(sys.argv[1]))
out = []
for ref, pose in pairs:
    t0, r0 = read6d(ref); t, r = read6d(pose)
    rel_r = r0.inv() * r
    rel_t = r0.inv().apply(t - t0)
    m = rel_r.as_matrix()
    out.append({
        "rot6d": list(rel_t) + list(m[0]) + list(m[1]),
        "rotvec": list(rel_t) + list(rel_r.as_rotvec()),
        "ref_rotvec": list(t0) + list(r0.as_rotvec()),
        "pose_rotvec": list(t) + list(r.as_rotvec()),
    })
json.dump(out, open(sys.argv[2], "w"))
"#;

fn max_diff(a: &[f32], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn a_relative_pose_group_trains_and_deploys_back_to_the_datasets_poses() {
    trains_and_deploys(PoseFormat::XyzRot6d);
}

/// The same with an `xyz_rotvec` pose (6 values); the scipy check is the `xyz_rot6d` test's
/// (it compares both layouts).
#[test]
fn a_relative_rotvec_pose_group_trains_and_deploys_back_to_the_datasets_poses() {
    trains_and_deploys(PoseFormat::XyzRotvec);
}

fn trains_and_deploys(format: PoseFormat) {
    let (pw, wd) = (format.width(), width(format));
    let dir = Scratch::new(&format!("gr00t-train-pose-{pw}"));
    let root = dir.path();
    let (ck, data, emb_path, feats) = (
        root.join("ck"),
        root.join("data"),
        root.join("embodiment.toml"),
        root.join("features.safetensors"),
    );
    wide_alt_checkpoint(&ck, WIDE);
    dataset(&data, format);
    embodiment(&emb_path, format);
    features(&feats, EPISODES * FRAMES_PER_EPISODE);
    let mut o = Gr00tTrainOptions::new(&ck, &data, &emb_path, &feats, &root.join("run"));
    o.steps = 2;
    o.batch_size = 8;
    o.lr = 1e-3;
    o.seed = 3;
    let r = train(&o, |_| {}).unwrap();
    assert_eq!(r.report.losses.len(), 2);
    assert!(
        r.report.losses.iter().all(|(_, l)| l.is_finite()),
        "{:?}",
        r.report.losses
    );

    // The statistics the deployment reads: `[H, pw]` relative tables for the pose only.
    let emb = EmbodimentConfig::load(&o.out.join("embodiment.toml")).unwrap();
    let h = emb.horizon;
    let stats = read_json(&o.out.join("statistics.json"));
    let tag = emb.embodiment_tag.as_str();
    let table = |stat: &str| -> Vec<Vec<f64>> {
        serde_json::from_value(stats[tag]["relative_action"]["eef"][stat].clone()).unwrap()
    };
    let (rel_min, rel_max) = (table("min"), table("max"));
    assert_eq!(rel_min.len(), h);
    assert!(rel_min.iter().chain(&rel_max).all(|r| r.len() == pw));
    assert!(stats[tag]["relative_action"].get("grip").is_none());
    let norm = Normalizer::load(&o.out.join("statistics.json"), &emb).unwrap();
    assert!(norm.per_slot());
    let map = norm.action_output_map();
    let want_ref: Vec<Option<usize>> = (0..pw).map(Some).chain([None]).collect();
    assert_eq!(map.reference, want_ref);
    assert_eq!(map.poses, [PoseGroup { first: 0, format }]);

    let ds = read_selected(&data, &state_and_action()).unwrap();

    // GR00T's convention, independently: scipy's T_ref⁻¹·T on every (state of frame t,
    // action of frame t + p) pair the statistics are taken over.
    if format == PoseFormat::XyzRot6d {
        check_against_scipy(root, &ds, h, &rel_min, &rel_max);
    }

    // Encode (trainer) → decode (runtime), every chunk inside its episode (t ≤ len − H, the
    // chunks every statistics rule covers) and every slot.
    let targets = Gr00tTargets::new(norm, h, &ds.episodes);
    let worst = encode_decode_every_chunk(&ds, &targets, &map, h, wd);
    println!("encode → decode: max |decoded − dataset| = {worst:.2e}");

    // Deployed: the lock-step runtime with the run's output map; every command up to
    // len − H comes from chunks made (and rebased) at frames inside the episode, which every
    // statistics rule covers.
    let worst = lockstep_sends_the_datasets_actions(&ds, &targets, &map, &emb, wd);
    println!("deployed: max |sent − dataset| = {worst:.2e}");
}

/// GR00T's `T_ref⁻¹·T` with scipy's `Rotation` on every (state of frame `t`, action of frame
/// `t + p`) pose pair of `ds` (`xyz_rot6d`) against pir2's `pose::relative`, in both layouts;
/// the run's `relative_action` tables must be the per-slot extremes of scipy's values over
/// the chunks the statistics take: GR00T's rule (the chunks inside their episode,
/// `t ≤ len − H`). The data is chosen so that the other plausible rule (every frame, the last
/// action repeated past the end, which pir2 used before) gives other tables, so a regression
/// to it fails here.
fn check_against_scipy(
    root: &Path,
    ds: &pir2_sim::dataset::Dataset,
    h: usize,
    rel_min: &[Vec<f64>],
    rel_max: &[Vec<f64>],
) {
    let mut pairs = Vec::new();
    for ep in &ds.episodes {
        let len = ep.len();
        for t in 0..len {
            for p in 0..h {
                let a = ep.action((t + p).min(len - 1));
                let inside = t + h <= len;
                pairs.push((p, inside, ep.fast(t)[..9].to_vec(), a[..9].to_vec()));
            }
        }
    }
    let python = python_from_env().unwrap();
    let (script, qpath, rpath) = (
        root.join("scipy_ref.py"),
        root.join("pairs.json"),
        root.join("scipy.json"),
    );
    let q: Vec<[&Vec<f32>; 2]> = pairs.iter().map(|(_, _, s, a)| [s, a]).collect();
    std::fs::write(&qpath, serde_json::to_string(&q).unwrap()).unwrap();
    run_python(
        &python,
        &script,
        SCIPY_REF,
        &[qpath.as_os_str(), rpath.as_os_str()],
        "scipy reference",
    );
    let theirs: Vec<HashMap<String, Vec<f64>>> =
        serde_json::from_str(&std::fs::read_to_string(&rpath).unwrap()).unwrap();
    assert_eq!(theirs.len(), pairs.len());
    let (mut worst6, mut worst_v) = (0f64, 0f64);
    // Per rule (0: every frame, padded; 1: inside the episode): per-slot min and max.
    let mut lo = [vec![vec![f64::MAX; 9]; h], vec![vec![f64::MAX; 9]; h]];
    let mut hi = [vec![vec![f64::MIN; 9]; h], vec![vec![f64::MIN; 9]; h]];
    for ((p, inside, s, a), sc) in pairs.iter().zip(&theirs) {
        let mut rel = [0f32; 9];
        relative(PoseFormat::XyzRot6d, s, a, &mut rel);
        worst6 = worst6.max(max_diff(&rel, &sc["rot6d"]));
        for rule in 0..2 {
            if rule == 1 && !inside {
                continue;
            }
            for (j, v) in sc["rot6d"].iter().enumerate() {
                lo[rule][*p][j] = lo[rule][*p][j].min(*v);
                hi[rule][*p][j] = hi[rule][*p][j].max(*v);
            }
        }
        let to32 = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let mut rel_v = [0f32; 6];
        relative(
            PoseFormat::XyzRotvec,
            &to32(&sc["ref_rotvec"]),
            &to32(&sc["pose_rotvec"]),
            &mut rel_v,
        );
        worst_v = worst_v.max(max_diff(&rel_v, &sc["rotvec"]));
    }
    println!(
        "pir2 vs scipy, {} relative poses: max |diff| rot6d {worst6:.2e}, rotvec {worst_v:.2e}",
        pairs.len()
    );
    assert!(worst6 < 1e-5, "xyz_rot6d: max |pir2 − scipy| = {worst6}");
    assert!(worst_v < 1e-5, "xyz_rotvec: max |pir2 − scipy| = {worst_v}");
    // The written tables are the per-slot extremes of those relative poses under one rule.
    let worst_under = |rule: usize| -> f64 {
        let mut w = 0f64;
        for p in 0..h {
            for j in 0..9 {
                w = w
                    .max((rel_min[p][j] - lo[rule][p][j]).abs())
                    .max((rel_max[p][j] - hi[rule][p][j]).abs());
            }
        }
        w
    };
    let (padded, inside) = (worst_under(0), worst_under(1));
    println!(
        "relative_action.eef vs scipy's extremes: max |diff| {padded:.2e} (every frame, padded), \
         {inside:.2e} (chunks inside the episode)"
    );
    let rules_differ = (0..h).any(|p| {
        (0..9).any(|j| {
            (lo[0][p][j] - lo[1][p][j]).abs() > 1e-3 || (hi[0][p][j] - hi[1][p][j]).abs() > 1e-3
        })
    });
    assert!(
        rules_differ,
        "the data cannot tell the two chunk rules apart"
    );
    assert!(
        inside < 1e-5,
        "the relative_action.eef tables are not scipy's extremes over the chunks inside the \
         episode (max |diff| {inside}; {padded} against every frame, padded)"
    );
}
