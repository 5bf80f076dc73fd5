//! Reading features by name: a dataset written by LeRobot's own writer (lerobot 0.4.4,
//! `tests/fixtures/make_lerobot_fixture.py`), one written by our writer under custom keys, and
//! the errors for features that cannot be read.

use std::path::{Path, PathBuf};

use pir2_sim::dataset::{
    float_features, read_dataset, read_selected, DatasetSpec, DatasetWriter, Episode, FeatureKeys,
    FeatureSelection, WriteMode,
};
use pir2_sim::Error;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/lerobot-reach")
}

fn sel(fast: &[&str], slow: &[&str], action: &str) -> FeatureSelection {
    FeatureSelection {
        fast: fast.iter().map(|s| s.to_string()).collect(),
        slow: slow.iter().map(|s| s.to_string()).collect(),
        action: action.into(),
    }
}

/// A copy of the fixture whose `meta/info.json` is changed by `edit`.
fn patched(name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("pir2-lerobot-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    copy_dir(&fixture(), &dir);
    let p = dir.join("meta/info.json");
    let mut info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    edit(&mut info);
    std::fs::write(&p, serde_json::to_string_pretty(&info).unwrap()).unwrap();
    dir
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

#[test]
fn reads_the_lerobot_written_fixture_by_feature_name() {
    let ds = read_selected(
        &fixture(),
        &sel(
            &["observation.state", "observation.goal"],
            &["observation.speed"],
            "action",
        ),
    )
    .unwrap();
    assert_eq!(ds.fps, 10.0);
    assert_eq!(ds.tasks, ["reach the goal"]);
    assert_eq!(ds.episodes.len(), 6);
    assert_eq!(ds.total_frames(), 180);
    let e0 = &ds.episodes[0];
    assert_eq!((e0.fast_dim, e0.slow_dim, e0.action_dim), (5, 1, 2));
    // Frame 0 of episode 0: position (0.8, 0), phase 0; goal (0, -0.2) (float64 in the file);
    // the action is 0.4 · (goal − position) clipped to ±0.3.
    assert_eq!(e0.fast(0), [0.8, 0.0, 0.0, 0.0, -0.2]);
    assert_eq!(e0.slow(0), [0.0]);
    assert_eq!(e0.action(0), [-0.3, -0.08]);
    // The script's rule holds on every frame: action = clip(0.4 · (goal − pos)), and the
    // next position is the position plus the action.
    for e in &ds.episodes {
        for t in 0..e.len() {
            let f = e.fast(t);
            for j in 0..2 {
                let want = (0.4 * (f[3 + j] - f[j])).clamp(-0.3, 0.3);
                assert!((e.action(t)[j] - want).abs() < 1e-5, "{t} {j}");
                if t + 1 < e.len() {
                    let next = e.fast(t + 1)[j];
                    assert!((next - (f[j] + e.action(t)[j])).abs() < 1e-5);
                }
            }
        }
    }
    // The float features LeRobot declared, by key (timestamp is a float scalar too).
    let keys: Vec<String> = float_features(&ds.info)
        .into_iter()
        .map(|f| format!("{}:{}:{}", f.key, f.dtype, f.width))
        .collect();
    assert_eq!(
        keys,
        [
            "action:float32:2",
            "observation.goal:float64:2",
            "observation.speed:float32:1",
            "observation.state:float32:3",
            "timestamp:float32:1"
        ]
    );
}

fn feature_error(root: &Path, s: &FeatureSelection) -> (String, String) {
    match read_selected(root, s) {
        Err(Error::Feature { key, reason, .. }) => (key, reason),
        other => panic!("expected a feature error, got {other:?}"),
    }
}

#[test]
fn a_missing_key_is_one_error_naming_it_and_the_float_features_there() {
    let (key, reason) = feature_error(&fixture(), &sel(&["observation.pos"], &[], "action"));
    assert_eq!(key, "observation.pos");
    assert!(reason.contains("not in meta/info.json"), "{reason}");
    assert!(reason.contains("observation.state"), "{reason}");
    let (key, _) = feature_error(&fixture(), &sel(&["observation.state"], &[], "act"));
    assert_eq!(key, "act");
}

#[test]
fn non_float_duplicate_video_and_matrix_features_are_refused_by_name() {
    let (key, reason) = feature_error(&fixture(), &sel(&["frame_index"], &[], "action"));
    assert_eq!(key, "frame_index");
    assert!(reason.contains("\"int64\""), "{reason}");
    let (key, reason) = feature_error(
        &fixture(),
        &sel(&["observation.state"], &["observation.state"], "action"),
    );
    assert_eq!(key, "observation.state");
    assert!(reason.contains("more than once"), "{reason}");

    let root = patched("video", |info| {
        info["features"]["observation.images.top"] = serde_json::json!({"dtype": "video", "shape": [48, 64, 3], "names": ["height", "width", "channels"]});
        info["features"]["observation.matrix"] =
            serde_json::json!({"dtype": "float32", "shape": [2, 2], "names": null});
    });
    let (key, reason) = feature_error(
        &root,
        &sel(
            &["observation.state", "observation.images.top"],
            &[],
            "action",
        ),
    );
    assert_eq!(key, "observation.images.top");
    assert!(reason.contains("video feature"), "{reason}");
    let (key, reason) = feature_error(&root, &sel(&["observation.matrix"], &[], "action"));
    assert_eq!(key, "observation.matrix");
    assert!(reason.contains("[2,2]"), "{reason}");
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn a_width_that_differs_from_info_json_is_an_error_naming_the_column() {
    let root = patched("width", |info| {
        info["features"]["observation.goal"]["shape"] = serde_json::json!([3]);
    });
    match read_selected(&root, &sel(&["observation.goal"], &[], "action")) {
        Err(Error::ColumnType {
            column, expected, ..
        }) => {
            assert_eq!(column, "observation.goal");
            assert!(expected.contains("width 3"), "{expected}");
        }
        other => panic!("expected a column type error, got {other:?}"),
    }
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn our_writer_with_custom_keys_round_trips_and_resumes() {
    let root = std::env::temp_dir().join(format!("pir2-custom-keys-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let spec = DatasetSpec {
        fps: 20,
        robot_type: Some("custom".into()),
        tasks: vec!["t".into()],
        fast_names: vec!["q0".into(), "q1".into()],
        slow_names: vec!["target".into()],
        action_names: vec!["dq".into()],
        keys: FeatureKeys {
            fast: "observation.joints".into(),
            slow: "observation.target".into(),
            action: "action.joint_velocity".into(),
        },
    };
    let episode = |n: usize, k: f32| {
        let mut e = Episode::new(2, 1, 1);
        for t in 0..n {
            let t = t as f32;
            e.push(&[t, k * t], &[k], &[k - t]);
        }
        e
    };
    let mut w = DatasetWriter::open(&root, spec.clone(), WriteMode::New).unwrap();
    w.append(&episode(4, 1.0)).unwrap();
    w.finish().unwrap();
    // A second session appends (the writer reads its own custom columns back for the stats).
    let mut w = DatasetWriter::open(&root, spec, WriteMode::Resume).unwrap();
    w.append(&episode(3, 2.0)).unwrap();
    w.finish().unwrap();
    let ds = read_selected(
        &root,
        &sel(
            &["observation.target", "observation.joints"],
            &[],
            "action.joint_velocity",
        ),
    )
    .unwrap();
    assert_eq!(ds.episodes.len(), 2);
    let e1 = &ds.episodes[1];
    assert_eq!((e1.fast_dim, e1.slow_dim, e1.action_dim), (3, 0, 1));
    assert_eq!(e1.fast(2), [2.0, 2.0, 4.0], "target first, then the joints");
    assert_eq!(e1.action(2), [0.0]);
    // The default reader looks for `observation.state` and says so.
    let err = read_dataset(&root).unwrap_err();
    assert!(
        matches!(&err, Error::MissingColumn { column, .. } if column == "observation.state"),
        "{err}"
    );
    std::fs::remove_dir_all(&root).unwrap();
}
