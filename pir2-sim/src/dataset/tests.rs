//! Collection, writing, resuming and reading back, on the ball-on-plate task.
//!
//! One file on purpose: the collect, write, stats and read modules are tested through the same
//! small episodes and round trips (a dataset written by one module is read back by another).

use arrow_array::cast::AsArray;
use arrow_array::types::Float64Type;
use arrow_array::ArrayRef;
use arrow_array::Float32Array;
use arrow_array::Int64Array;
use arrow_array::ListArray;
use arrow_array::RecordBatch;
use arrow_array::StringArray;
use serde_json::json;
use serde_json::Value;
use std::fs;
use std::path::PathBuf;
use std::sync::Arc;

use super::*;
use crate::ballplate::{BallPlate, BallPlateConfig};
use crate::expert::{LqrConfig, LqrExpert};

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("pir2-sim-test-{}-{name}", std::process::id()));
    let _ = fs::remove_dir_all(&d);
    d
}

fn setup() -> (BallPlate, LqrExpert) {
    let cfg = BallPlateConfig::default();
    (
        BallPlate::new(cfg.clone()).unwrap(),
        LqrExpert::new(&cfg, LqrConfig::default()).unwrap(),
    )
}

fn short(n: usize) -> CollectConfig {
    CollectConfig {
        episodes: n,
        seed: 7,
        ..Default::default()
    }
}

#[test]
fn template_formatting() {
    assert_eq!(
        fill_template(DATA_PATH, 0, 7),
        "data/chunk-000/file-007.parquet"
    );
    assert_eq!(
        fill_template("x/{chunk_index}/{file_index:05d}/{other}", 12, 3),
        "x/12/00003/{other}"
    );
}

#[test]
fn collects_successful_demos_with_clean_labels() {
    let (mut env, mut ex) = setup();
    let mut calls = 0;
    let eps = collect_episodes(&mut env, &mut ex, &short(3), &mut |p| {
        calls += 1;
        assert!(p.kept <= 3);
    })
    .unwrap();
    assert_eq!(eps.len(), 3);
    assert!(calls >= 4);
    for e in &eps {
        assert!(e.success && e.done);
        assert_eq!(e.len(), 500);
        assert_eq!((e.fast_dim, e.slow_dim, e.action_dim), (6, 4, 2));
        // Labels are the expert's clamped actions.
        assert!(e.action.iter().all(|a| a.abs() <= 0.15 + 1e-6));
    }
    // Executed actions carry noise: "θ − last target" differs from the label's effect, so
    // re-running the episode without noise gives other observations.
    let e0 = &eps[0];
    let clean = run_episode(&mut env, &mut ex, e0.seed, 0.0, 0);
    assert_eq!(
        clean.fast(0),
        e0.fast(0),
        "same seed, same first observation"
    );
    assert_ne!(
        clean.fast, e0.fast,
        "action noise must change the trajectory"
    );
    let again = run_episode(&mut env, &mut ex, e0.seed, 0.01, 0);
    assert_eq!(&again, e0, "collection is deterministic");
}

#[test]
fn write_read_roundtrip() {
    let root = tmpdir("roundtrip");
    let (mut env, mut ex) = setup();
    let spec = DatasetSpec::ballplate(50);
    let (stats, summary) = collect_to_dataset(
        &mut env,
        &mut ex,
        &short(3),
        &root,
        &spec,
        WriteMode::New,
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(stats.kept, 3);
    assert_eq!(summary.total_episodes, 3);
    assert!(root.join("data/chunk-000/file-000.parquet").exists());
    assert!(root
        .join("meta/episodes/chunk-000/file-000.parquet")
        .exists());
    assert!(root.join("meta/tasks.parquet").exists());
    let ds = read_dataset(&root).unwrap();
    assert_eq!(ds.fps, 50.0);
    assert_eq!(ds.tasks, spec.tasks);
    assert_eq!(ds.episodes.len(), 3);
    assert_eq!(ds.total_frames(), summary.total_frames);
    let mut env2 = env.clone();
    let direct = collect_episodes(&mut env2, &mut ex, &short(3), &mut |_| {}).unwrap();
    assert_eq!(ds.episodes, direct, "parquet round trip must be lossless");

    let info: Value =
        serde_json::from_str(&fs::read_to_string(root.join(INFO_PATH)).unwrap()).unwrap();
    assert_eq!(info["codebase_version"], "v3.0");
    assert_eq!(info["total_frames"], 1500);
    assert_eq!(info["features"]["observation.state"]["shape"], json!([6]));
    assert_eq!(
        info["features"]["observation.environment_state"]["names"],
        json!(["ball_x", "ball_y", "ball_vx", "ball_vy"])
    );
    assert_eq!(info["splits"]["train"], "0:3");
    let eb = read_parquet(&root.join("meta/episodes/chunk-000/file-000.parquet")).unwrap();
    let col = eb[0]
        .column_by_name("stats/index/max")
        .expect("per-episode index stats");
    let maxes = col.as_list::<i32>().value(2);
    assert_eq!(
        maxes.as_primitive::<Float64Type>().values().to_vec(),
        vec![1499.0]
    );
    assert!(eb[0]
        .column_by_name("stats/observation.state/q99")
        .is_some());
    let st: Value =
        serde_json::from_str(&fs::read_to_string(root.join(STATS_PATH)).unwrap()).unwrap();
    assert_eq!(st["action"]["count"], json!([1500]));
    assert_eq!(st["index"]["max"], json!([1499.0]));
    let m = st["observation.environment_state"]["mean"][0]
        .as_f64()
        .unwrap();
    let direct_mean = direct
        .iter()
        .flat_map(|e| (0..e.len()).map(move |t| e.slow(t)[0] as f64))
        .sum::<f64>()
        / 1500.0;
    assert!((m - direct_mean).abs() < 1e-9);
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn refuses_to_overwrite_and_resumes() {
    let root = tmpdir("resume");
    let (mut env, mut ex) = setup();
    let spec = DatasetSpec::ballplate(50);
    collect_to_dataset(
        &mut env,
        &mut ex,
        &short(2),
        &root,
        &spec,
        WriteMode::New,
        &mut |_| {},
    )
    .unwrap();
    let err = collect_to_dataset(
        &mut env,
        &mut ex,
        &short(3),
        &root,
        &spec,
        WriteMode::New,
        &mut |_| {},
    )
    .unwrap_err();
    assert!(matches!(err, Error::AlreadyExists { .. }), "{err}");
    assert!(err.to_string().contains("Resume"));
    // Resume to 3: only one more episode, in a new file pair.
    let mut seen = Vec::new();
    let (stats, summary) = collect_to_dataset(
        &mut env,
        &mut ex,
        &short(3),
        &root,
        &spec,
        WriteMode::Resume,
        &mut |p| seen.push(p.kept),
    )
    .unwrap();
    assert_eq!(stats.kept, 1);
    assert_eq!(seen.first(), Some(&2));
    assert_eq!(summary.total_episodes, 3);
    assert!(root.join("data/chunk-000/file-001.parquet").exists());
    assert!(root
        .join("meta/episodes/chunk-000/file-001.parquet")
        .exists());
    // Same episodes as a one-shot collection (the attempt sequence continues).
    let ds = read_dataset(&root).unwrap();
    let direct = collect_episodes(&mut env, &mut ex, &short(3), &mut |_| {}).unwrap();
    assert_eq!(ds.episodes, direct);
    // Resuming a complete dataset writes nothing new.
    let (stats, _) = collect_to_dataset(
        &mut env,
        &mut ex,
        &short(3),
        &root,
        &spec,
        WriteMode::Resume,
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(stats.kept, 0);
    assert!(!root.join("data/chunk-000/file-002.parquet").exists());
    // Overwrite starts from scratch.
    let (_, summary) = collect_to_dataset(
        &mut env,
        &mut ex,
        &short(1),
        &root,
        &spec,
        WriteMode::Overwrite,
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(summary.total_episodes, 1);
    assert!(!root.join("data/chunk-000/file-001.parquet").exists());
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn resume_moves_aside_an_interrupted_write_and_refuses_other_orphans() {
    let root = tmpdir("orphan");
    let (mut env, mut ex) = setup();
    let spec = DatasetSpec::ballplate(50);
    let upto = |n, root: &std::path::Path, mode, env: &mut _, ex: &mut _| {
        collect_to_dataset(env, ex, &short(n), root, &spec, mode, &mut |_| {}).unwrap()
    };
    upto(1, &root, WriteMode::New, &mut env, &mut ex);
    // The tail of a write killed between its data file and its episodes file.
    fs::copy(
        root.join("data/chunk-000/file-000.parquet"),
        root.join("data/chunk-000/file-001.parquet"),
    )
    .unwrap();
    let w = DatasetWriter::open(&root, spec.clone(), WriteMode::Resume).unwrap();
    let aside = root.join(".pir2-interrupted/data/chunk-000/file-001.parquet");
    assert_eq!(w.set_aside(), std::slice::from_ref(&aside));
    assert!(aside.exists() && !root.join("data/chunk-000/file-001.parquet").exists());
    assert_eq!(w.file_no, 1);
    drop(w);
    assert_eq!(read_dataset(&root).unwrap().episodes.len(), 1);
    // A temporary leftover is harmless and its number is not reused.
    fs::write(root.join("data/chunk-000/file-001.parquet.tmp"), b"partial").unwrap();
    let w = DatasetWriter::open(&root, spec.clone(), WriteMode::Resume).unwrap();
    assert_eq!(w.file_no, 2);
    drop(w);
    // A data file below the last referenced one that no episode references is not an
    // interrupted write: refused by name. (The leftover makes the next session write 002.)
    upto(2, &root, WriteMode::Resume, &mut env, &mut ex);
    assert!(root.join("data/chunk-000/file-002.parquet").exists());
    fs::remove_file(root.join("data/chunk-000/file-001.parquet.tmp")).unwrap();
    fs::copy(
        root.join("data/chunk-000/file-000.parquet"),
        root.join("data/chunk-000/file-001.parquet"),
    )
    .unwrap();
    let err = DatasetWriter::open(&root, spec, WriteMode::Resume).unwrap_err();
    assert!(
        matches!(&err, Error::Inconsistent { path, .. } if path.ends_with("data/chunk-000/file-001.parquet")),
        "{err}"
    );
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn resume_refuses_other_features() {
    let root = tmpdir("features");
    let (mut env, mut ex) = setup();
    let spec = DatasetSpec::ballplate(50);
    collect_to_dataset(
        &mut env,
        &mut ex,
        &short(1),
        &root,
        &spec,
        WriteMode::New,
        &mut |_| {},
    )
    .unwrap();
    let other = DatasetSpec {
        fps: 25,
        ..spec.clone()
    };
    let err = DatasetWriter::open(&root, other, WriteMode::Resume).unwrap_err();
    assert!(matches!(err, Error::Inconsistent { .. }), "{err}");
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn refuses_non_dataset_directory() {
    let root = tmpdir("nondataset");
    fs::create_dir_all(&root).unwrap();
    fs::write(root.join("notes.txt"), "mine").unwrap();
    for mode in [WriteMode::New, WriteMode::Resume] {
        let err = DatasetWriter::open(&root, DatasetSpec::ballplate(50), mode).unwrap_err();
        assert!(matches!(err, Error::AlreadyExists { .. }), "{err}");
    }
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn missing_file_and_column_errors_name_them() {
    let root = tmpdir("errors");
    let err = read_dataset(&root).unwrap_err();
    assert!(
        matches!(&err, Error::MissingFile { path } if path.ends_with("meta/info.json")),
        "{err}"
    );
    let (mut env, mut ex) = setup();
    let spec = DatasetSpec::ballplate(50);
    collect_to_dataset(
        &mut env,
        &mut ex,
        &short(1),
        &root,
        &spec,
        WriteMode::New,
        &mut |_| {},
    )
    .unwrap();
    let opts = ReadOptions {
        action_key: "action.absent".into(),
        ..Default::default()
    };
    let err = read_dataset_with(&root, &opts).unwrap_err();
    match &err {
        Error::MissingColumn { path, column } => {
            assert_eq!(column, "action.absent");
            assert!(path.ends_with("data/chunk-000/file-000.parquet"));
        }
        e => panic!("unexpected {e}"),
    }
    assert!(
        err.to_string().contains("file-000.parquet") && err.to_string().contains("action.absent")
    );
    // A column of the wrong type.
    let opts = ReadOptions {
        action_key: "next.done".into(),
        ..Default::default()
    };
    let err = read_dataset_with(&root, &opts).unwrap_err();
    assert!(
        matches!(&err, Error::ColumnType { column, .. } if column == "next.done"),
        "{err}"
    );
    // A missing data file.
    fs::remove_file(root.join("data/chunk-000/file-000.parquet")).unwrap();
    let err = read_dataset(&root).unwrap_err();
    assert!(
        matches!(&err, Error::MissingFile { path } if path.ends_with("file-000.parquet")),
        "{err}"
    );
    fs::remove_dir_all(&root).unwrap();
}

/// A dataset laid out like LeRobot writes it through HF `datasets`/pandas: variable-size
/// float64 lists, int32 indices, no pir2 columns, task as an unnamed pandas index.
#[test]
fn reads_foreign_layout() {
    let root = tmpdir("foreign");
    let data = root.join("data/chunk-000/file-000.parquet");
    let n = 5usize;
    let state = ListArray::from_iter_primitive::<Float64Type, _, _>(
        (0..n).map(|t| Some(vec![Some(t as f64), Some(-(t as f64))])),
    );
    let action = ListArray::from_iter_primitive::<Float64Type, _, _>(
        (0..n).map(|t| Some(vec![Some(0.5 * t as f64)])),
    );
    let batch = RecordBatch::try_from_iter(vec![
        ("observation.state", Arc::new(state) as ArrayRef),
        ("action", Arc::new(action) as ArrayRef),
        (
            "episode_index",
            Arc::new(arrow_array::Int32Array::from(vec![0, 0, 1, 1, 1])) as ArrayRef,
        ),
        (
            "frame_index",
            Arc::new(Int64Array::from(vec![0, 1, 0, 1, 2])) as ArrayRef,
        ),
        (
            "timestamp",
            Arc::new(Float32Array::from(vec![0.0, 0.1, 0.0, 0.1, 0.2])) as ArrayRef,
        ),
    ])
    .unwrap();
    write_batch_file(&data, &batch).unwrap();
    let eps = RecordBatch::try_from_iter(vec![
        (
            "episode_index",
            Arc::new(Int64Array::from(vec![0, 1])) as ArrayRef,
        ),
        ("length", Arc::new(Int64Array::from(vec![2, 3])) as ArrayRef),
        (
            "data/chunk_index",
            Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
        ),
        (
            "data/file_index",
            Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
        ),
    ])
    .unwrap();
    write_batch_file(&root.join("meta/episodes/chunk-000/file-000.parquet"), &eps).unwrap();
    let tasks = RecordBatch::try_from_iter(vec![
        (
            "task_index",
            Arc::new(Int64Array::from(vec![0])) as ArrayRef,
        ),
        (
            "__index_level_0__",
            Arc::new(StringArray::from(vec!["push the T"])) as ArrayRef,
        ),
    ])
    .unwrap();
    write_batch_file(&root.join(TASKS_PATH), &tasks).unwrap();
    write_json_file(
        &root.join(INFO_PATH),
        &json!({"codebase_version": "v3.0", "fps": 10, "data_path": DATA_PATH, "features": {}}),
    )
    .unwrap();
    let ds = read_dataset(&root).unwrap();
    assert_eq!(ds.tasks, vec!["push the T".to_string()]);
    assert_eq!(ds.episodes.len(), 2);
    let e1 = &ds.episodes[1];
    assert_eq!(
        (e1.fast_dim, e1.slow_dim, e1.action_dim, e1.len()),
        (2, 0, 1, 3)
    );
    assert_eq!(e1.fast(2), &[4.0, -4.0]);
    assert_eq!(e1.action(0), &[1.0]);
    // Length mismatch is reported against the data file.
    let bad = RecordBatch::try_from_iter(vec![
        (
            "episode_index",
            Arc::new(Int64Array::from(vec![0, 1])) as ArrayRef,
        ),
        ("length", Arc::new(Int64Array::from(vec![2, 4])) as ArrayRef),
        (
            "data/chunk_index",
            Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
        ),
        (
            "data/file_index",
            Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
        ),
    ])
    .unwrap();
    write_batch_file(&root.join("meta/episodes/chunk-000/file-000.parquet"), &bad).unwrap();
    let err = read_dataset(&root).unwrap_err();
    assert!(
        matches!(&err, Error::Inconsistent { reason, .. } if reason.contains("3 frames")),
        "{err}"
    );
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn stats_match_numpy_conventions() {
    let s = FeatureStats::compute(&[1.0, 10.0, 2.0, 20.0, 3.0, 30.0, 4.0, 40.0], 2);
    assert_eq!(s.count, 4);
    assert_eq!(s.min, vec![1.0, 10.0]);
    assert_eq!(s.max, vec![4.0, 40.0]);
    assert_eq!(s.mean, vec![2.5, 25.0]);
    assert!((s.std[0] - 1.25f64.sqrt()).abs() < 1e-12, "population std");
    // numpy.quantile([1,2,3,4], 0.5) = 2.5, 0.1 → 1.3
    assert!((s.quantiles[2][0] - 2.5).abs() < 1e-12);
    assert!((s.quantiles[1][0] - 1.3).abs() < 1e-12);
}

#[test]
fn rejects_misshapen_episodes() {
    let root = tmpdir("shape");
    let mut w = DatasetWriter::open(&root, DatasetSpec::ballplate(50), WriteMode::New).unwrap();
    let mut e = Episode::new(5, 2, 2);
    e.push(&[0.0; 5], &[0.0; 2], &[0.0; 2]);
    assert!(matches!(w.append(&e), Err(Error::EpisodeShape { .. })));
    assert!(matches!(
        w.append(&Episode::new(6, 2, 2)),
        Err(Error::EpisodeShape { .. })
    ));
    let _ = fs::remove_dir_all(&root);
}

#[test]
fn slow_frames_stack_oldest_first_padded_with_the_first_frame() {
    let mut e = Episode::new(1, 2, 1);
    for t in 0..4 {
        let t = t as f32;
        e.push(&[t], &[t, -t], &[0.5 * t]);
    }
    let two = e.with_slow_frames(2);
    assert_eq!(two.slow_dim, 4);
    assert_eq!(two.slow(0), [0.0, -0.0, 0.0, -0.0]);
    assert_eq!(two.slow(1), [0.0, -0.0, 1.0, -1.0]);
    assert_eq!(two.slow(3), [2.0, -2.0, 3.0, -3.0]);
    // Everything else is kept.
    assert_eq!((two.fast, two.action), (e.fast.clone(), e.action.clone()));
    assert_eq!(e.with_slow_frames(1), e);
}

/// A two-episode dataset of widths (2, 1, 1) written by our writer (no simulation).
fn tiny_dataset(name: &str) -> PathBuf {
    let root = tmpdir(name);
    let spec = DatasetSpec {
        fps: 10,
        robot_type: None,
        tasks: vec!["t".into()],
        fast_names: vec!["a".into(), "b".into()],
        slow_names: vec!["s".into()],
        action_names: vec!["u".into()],
        keys: FeatureKeys::default(),
    };
    let mut w = DatasetWriter::open(&root, spec, WriteMode::New).unwrap();
    for n in [3, 4] {
        let mut e = Episode::new(2, 1, 1);
        for t in 0..n {
            let t = t as f32;
            e.push(&[t, -t], &[0.5 * t], &[0.1 * t]);
        }
        e.done = true;
        w.append(&e).unwrap();
    }
    w.finish().unwrap();
    root
}

fn set_info(root: &std::path::Path, key: &str, value: Value) {
    let path = root.join(INFO_PATH);
    let mut info: Value = serde_json::from_str(&fs::read_to_string(&path).unwrap()).unwrap();
    info[key] = value;
    write_json_file(&path, &info).unwrap();
}

#[test]
fn bad_path_templates_are_one_error_naming_the_field() {
    let root = tiny_dataset("templates");
    assert_eq!(read_dataset(&root).unwrap().episodes.len(), 2);
    let cases: &[(&str, Value, &str)] = &[
        // Width 2^40: formatting it would try to allocate a terabyte.
        (
            "data_path",
            json!("data/chunk-{chunk_index:01099511627776d}/file-{file_index:03d}.parquet"),
            "width above",
        ),
        (
            "data_path",
            json!("data/{chunk_index:33d}/file-{file_index:03d}.parquet"),
            "width above",
        ),
        (
            "data_path",
            json!("../outside/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"),
            "`..`",
        ),
        (
            "data_path",
            json!("data/../../file-{file_index:03d}.parquet"),
            "`..`",
        ),
        (
            "data_path",
            json!("/etc/chunk-{chunk_index}/file-{file_index}.parquet"),
            "absolute",
        ),
        (
            "data_path",
            json!("data/{episode_index}.parquet"),
            "unknown",
        ),
        ("data_path", json!("data/{chunk_index"), "unclosed"),
        ("data_path", json!("data/{chunk_index:3x}"), "format"),
        ("data_path", json!(""), "empty"),
        ("data_path", json!(7), "not a string"),
        (
            "video_path",
            json!("../videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"),
            "`..`",
        ),
        (
            "video_path",
            json!("v/{file_index:99999999999d}.mp4"),
            "width",
        ),
    ];
    for (field, value, why) in cases {
        let dir = tiny_dataset(&format!("templates-{field}-{why}"));
        set_info(&dir, field, value.clone());
        let err = read_dataset(&dir).unwrap_err();
        match &err {
            Error::PathTemplate {
                field: f, reason, ..
            } => {
                assert_eq!(f, field, "{err}");
                assert!(reason.contains(why), "{value}: {err}");
            }
            e => panic!("{field} = {value}: expected a PathTemplate error, got {e}"),
        }
        assert!(err.to_string().contains(field), "{err}");
        fs::remove_dir_all(&dir).unwrap();
    }
    // LeRobot's own templates pass.
    set_info(
        &root,
        "video_path",
        json!("videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"),
    );
    set_info(&root, "data_path", json!(DATA_PATH));
    assert_eq!(read_dataset(&root).unwrap().episodes.len(), 2);
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn episode_rows_out_of_range_are_an_error() {
    let root = tiny_dataset("rows");
    let eps = RecordBatch::try_from_iter(vec![
        (
            "episode_index",
            Arc::new(Int64Array::from(vec![0, 1])) as ArrayRef,
        ),
        (
            "length",
            Arc::new(Int64Array::from(vec![3, i64::MAX])) as ArrayRef,
        ),
        (
            "data/chunk_index",
            Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
        ),
        (
            "data/file_index",
            Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
        ),
    ])
    .unwrap();
    write_batch_file(&root.join("meta/episodes/chunk-000/file-000.parquet"), &eps).unwrap();
    let err = read_dataset(&root).unwrap_err();
    assert!(
        matches!(&err, Error::Inconsistent { reason, .. } if reason.contains("`length`")),
        "{err}"
    );
    fs::remove_dir_all(&root).unwrap();
}

/// One episode whose `observation.state` rows are 2 wide for the first 1024 rows (the
/// reader's first batch) and 3 wide after: each batch is uniform, the episode is not.
#[test]
fn mixed_list_widths_across_row_groups_are_an_error_naming_the_column() {
    let root = tmpdir("mixed-widths");
    let n = 1100usize;
    let width = |t: usize| if t < 1024 { 2 } else { 3 };
    let state = ListArray::from_iter_primitive::<Float64Type, _, _>(
        (0..n).map(|t| Some(vec![Some(t as f64); width(t)])),
    );
    let action = ListArray::from_iter_primitive::<Float64Type, _, _>(
        (0..n).map(|t| Some(vec![Some(0.5 * t as f64)])),
    );
    let batch = RecordBatch::try_from_iter(vec![
        ("observation.state", Arc::new(state) as ArrayRef),
        ("action", Arc::new(action) as ArrayRef),
        (
            "episode_index",
            Arc::new(Int64Array::from(vec![0; n])) as ArrayRef,
        ),
        (
            "frame_index",
            Arc::new(Int64Array::from_iter_values(0..n as i64)) as ArrayRef,
        ),
    ])
    .unwrap();
    // Two row groups (1024 + 76 rows), each of one width.
    let data = root.join("data/chunk-000/file-000.parquet");
    fs::create_dir_all(data.parent().unwrap()).unwrap();
    let props = parquet::file::properties::WriterProperties::builder()
        .set_max_row_group_row_count(Some(1024))
        .build();
    let mut w = parquet::arrow::ArrowWriter::try_new(
        fs::File::create(&data).unwrap(),
        batch.schema(),
        Some(props),
    )
    .unwrap();
    w.write(&batch).unwrap();
    w.close().unwrap();
    let eps = RecordBatch::try_from_iter(vec![
        (
            "episode_index",
            Arc::new(Int64Array::from(vec![0])) as ArrayRef,
        ),
        (
            "length",
            Arc::new(Int64Array::from(vec![n as i64])) as ArrayRef,
        ),
        (
            "data/chunk_index",
            Arc::new(Int64Array::from(vec![0])) as ArrayRef,
        ),
        (
            "data/file_index",
            Arc::new(Int64Array::from(vec![0])) as ArrayRef,
        ),
    ])
    .unwrap();
    write_batch_file(&root.join("meta/episodes/chunk-000/file-000.parquet"), &eps).unwrap();
    write_json_file(
        &root.join(INFO_PATH),
        &json!({"codebase_version": "v3.0", "fps": 10, "data_path": DATA_PATH, "features": {}}),
    )
    .unwrap();
    let err = read_dataset(&root).unwrap_err();
    assert!(
        matches!(&err, Error::ColumnType { column, found, .. }
            if column == "observation.state" && found.contains("width 3")),
        "{err}"
    );
    fs::remove_dir_all(&root).unwrap();
}

/// `WriteMode::Overwrite` keeps the old dataset until the new one has an episode: a session
/// dropped (crashed, failed) or finished before its first episode leaves it readable and
/// unchanged; a finished one replaces it, leaving no staging directory behind.
#[test]
fn overwrite_swaps_only_when_the_first_episode_is_written() {
    let root = tiny_dataset("overwrite-swap");
    let before = read_dataset(&root).unwrap();
    let spec = || DatasetSpec {
        fps: 10,
        robot_type: None,
        tasks: vec!["t".into()],
        fast_names: vec!["a".into(), "b".into()],
        slow_names: vec!["s".into()],
        action_names: vec!["u".into()],
        keys: FeatureKeys::default(),
    };
    let entries = |root: &std::path::Path| {
        let mut v: Vec<String> = fs::read_dir(root)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };
    // Opened, an episode buffered, then dropped (an error or a crash before `finish`).
    let mut w = DatasetWriter::open(&root, spec(), WriteMode::Overwrite).unwrap();
    let mut e = Episode::new(2, 1, 1);
    e.push(&[9.0, 9.0], &[9.0], &[9.0]);
    w.append(&e).unwrap();
    assert_eq!(
        read_dataset(&root).unwrap(),
        before,
        "old dataset intact while writing"
    );
    drop(w);
    assert_eq!(read_dataset(&root).unwrap(), before);
    assert_eq!(entries(&root), ["data", "meta"], "staging removed");
    // Finished without an episode (e.g. Ctrl-C before the first one ended): unchanged.
    let w = DatasetWriter::open(&root, spec(), WriteMode::Overwrite).unwrap();
    let s = w.finish().unwrap();
    assert_eq!((s.total_episodes, s.written_episodes), (2, 0));
    assert_eq!(read_dataset(&root).unwrap(), before);
    // Finished with one episode: replaced.
    let mut w = DatasetWriter::open(&root, spec(), WriteMode::Overwrite).unwrap();
    w.append(&e).unwrap();
    let s = w.finish().unwrap();
    assert_eq!((s.total_episodes, s.written_episodes), (1, 1));
    assert_eq!(
        s.data_file.as_deref(),
        Some(root.join("data/chunk-000/file-000.parquet").as_path())
    );
    let after = read_dataset(&root).unwrap();
    assert_eq!(after.episodes.len(), 1);
    assert_eq!(after.episodes[0].fast, vec![9.0, 9.0]);
    assert_eq!(entries(&root), ["data", "meta"]);
    fs::remove_dir_all(&root).unwrap();
}

/// A set stop flag ends a collection after the episode in progress, and what was kept is
/// written.
#[test]
fn a_stopped_collection_writes_the_episodes_it_finished() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let root = tmpdir("stop");
    let (mut env, mut ex) = setup();
    let spec = DatasetSpec::ballplate(50);
    let stop = AtomicBool::new(false);
    let (stats, summary) = collect_to_dataset_until(
        &mut env,
        &mut ex,
        &short(10),
        &root,
        &spec,
        WriteMode::New,
        &stop,
        &mut |p| {
            if p.kept == 2 {
                stop.store(true, Ordering::SeqCst);
            }
        },
    )
    .unwrap();
    assert!(stats.stopped);
    assert_eq!((stats.kept, summary.total_episodes), (2, 2));
    assert_eq!(read_dataset(&root).unwrap().episodes.len(), 2);
    // Resume adds the rest, continuing the attempt sequence.
    let (stats, summary) = collect_to_dataset(
        &mut env,
        &mut ex,
        &short(3),
        &root,
        &spec,
        WriteMode::Resume,
        &mut |_| {},
    )
    .unwrap();
    assert!(!stats.stopped);
    assert_eq!((stats.kept, summary.total_episodes), (1, 3));
    fs::remove_dir_all(&root).unwrap();
}

/// A collection writes its dataset every `flush_every` kept episodes: while it runs, the
/// dataset on disk is whole and holds every flushed episode (before: everything stayed in
/// memory until the end, and a killed process lost it all); an overwrite replaces the old
/// dataset at its first flush.
#[test]
fn a_collection_writes_as_it_goes() {
    let root = tmpdir("flush");
    let (mut env, mut ex) = setup();
    let spec = DatasetSpec::ballplate(50);
    let cfg = CollectConfig {
        flush_every: 2,
        ..short(5)
    };
    let mut on_disk = Vec::new();
    let (_, summary) = collect_to_dataset(
        &mut env,
        &mut ex,
        &cfg,
        &root,
        &spec,
        WriteMode::New,
        &mut |p| on_disk.push((p.kept, read_dataset(&root).map_or(0, |d| d.episodes.len()))),
    )
    .unwrap();
    // Progress is reported after the sink ran: every second kept episode flushed the
    // pending ones; the fifth is written by `finish`.
    assert!(
        on_disk.iter().all(|&(kept, disk)| disk == kept - kept % 2),
        "{on_disk:?}"
    );
    assert!(on_disk.contains(&(4, 4)), "{on_disk:?}");
    assert_eq!((summary.total_episodes, summary.written_episodes), (5, 5));
    let first = read_dataset(&root).unwrap();
    // Three flushes: three data files, read back as one dataset.
    assert_eq!(first.episodes.len(), 5);

    // Overwrite: the old dataset stays until the first flush, then the new one grows.
    let mut seen = Vec::new();
    let cfg = CollectConfig {
        flush_every: 2,
        seed: 99,
        ..short(3)
    };
    collect_to_dataset(
        &mut env,
        &mut ex,
        &cfg,
        &root,
        &spec,
        WriteMode::Overwrite,
        &mut |p| seen.push((p.kept, read_dataset(&root).unwrap().episodes.len())),
    )
    .unwrap();
    assert_eq!(seen, [(0, 5), (1, 5), (2, 2), (3, 2)], "{seen:?}");
    assert_eq!(read_dataset(&root).unwrap().episodes.len(), 3);
    let mut names: Vec<String> = fs::read_dir(&root)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["data", "meta"], "staging removed");
    fs::remove_dir_all(&root).unwrap();
}
