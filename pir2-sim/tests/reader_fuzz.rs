//! The dataset reader never panics: arbitrary and mutated `meta/info.json`, data,
//! episodes and tasks parquet bytes end in `Ok` or in an error, never a panic (proptest
//! reports a panic as a failure). Case counts are small to keep CI fast.

use std::fs;
use std::path::{Path, PathBuf};

use pir2_sim::dataset::{read_dataset, DatasetSpec, DatasetWriter, Episode, WriteMode};
use proptest::prelude::*;

use pir2_tests::fuzz_cases;

/// Removes the directory when the test thread ends.
struct Dir(PathBuf);
impl Drop for Dir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// A small valid dataset (two episodes, widths 2 / 1 / 1), written once per test.
fn dataset(name: &str) -> PathBuf {
    let root = std::env::temp_dir().join(format!("pir2-reader-fuzz-{}-{name}", std::process::id()));
    let _ = fs::remove_dir_all(&root);
    let spec = DatasetSpec {
        fps: 10,
        robot_type: Some("fuzz".into()),
        tasks: vec!["t".into()],
        fast_names: vec!["a".into(), "b".into()],
        slow_names: vec!["s".into()],
        action_names: vec!["u".into()],
        keys: Default::default(),
    };
    let mut w = DatasetWriter::open(&root, spec, WriteMode::New).unwrap();
    for n in [3, 5] {
        let mut e = Episode::new(2, 1, 1);
        for t in 0..n {
            let t = t as f32;
            e.push(&[t, -t], &[0.5 * t], &[0.1 * t]);
        }
        e.done = true;
        w.append(&e).unwrap();
    }
    w.finish().unwrap();
    assert_eq!(read_dataset(&root).unwrap().episodes.len(), 2);
    root
}

/// One edit of a byte string.
#[derive(Debug, Clone)]
enum Edit {
    /// Set the byte at (position mod len) to the value.
    Set(usize, u8),
    /// XOR the byte at (position mod len) with a bit.
    Flip(usize, u8),
    /// Cut the bytes at (position mod len) and after.
    Truncate(usize),
    /// Insert bytes at (position mod len).
    Insert(usize, Vec<u8>),
    /// Delete up to `n` bytes at (position mod len).
    Delete(usize, usize),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        4 => (any::<usize>(), any::<u8>()).prop_map(|(p, v)| Edit::Set(p, v)),
        4 => (any::<usize>(), 0u8..8).prop_map(|(p, b)| Edit::Flip(p, 1 << b)),
        1 => any::<usize>().prop_map(Edit::Truncate),
        1 => (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(p, v)| Edit::Insert(p, v)),
        1 => (any::<usize>(), 1usize..64).prop_map(|(p, n)| Edit::Delete(p, n)),
    ]
}

fn apply(bytes: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut b = bytes.to_vec();
    for e in edits {
        let at = |p: usize, len: usize| if len == 0 { 0 } else { p % len };
        match e {
            Edit::Set(p, v) if !b.is_empty() => {
                let i = at(*p, b.len());
                b[i] = *v;
            }
            Edit::Flip(p, m) if !b.is_empty() => {
                let i = at(*p, b.len());
                b[i] ^= m;
            }
            Edit::Truncate(p) => {
                let i = at(*p, b.len());
                b.truncate(i);
            }
            Edit::Insert(p, v) => {
                let i = at(*p, b.len() + 1);
                b.splice(i..i, v.iter().copied());
            }
            Edit::Delete(p, n) if !b.is_empty() => {
                let i = at(*p, b.len());
                let j = (i + n).min(b.len());
                b.drain(i..j);
            }
            _ => {}
        }
    }
    b
}

/// Puts a file's original bytes back when dropped (also when the case panicked, so the
/// next case and the shrinking start from the valid dataset).
struct Restore(PathBuf, Vec<u8>);
impl Drop for Restore {
    fn drop(&mut self) {
        let _ = fs::write(&self.0, &self.1);
    }
}

/// Write `bytes` to `rel` under `root`, read the dataset (must not panic), restore the file.
fn read_with(root: &Path, rel: &str, original: &[u8], bytes: &[u8]) {
    let path = root.join(rel);
    let _restore = Restore(path.clone(), original.to_vec());
    fs::write(&path, bytes).unwrap();
    let _ = read_dataset(root);
}

const FILES: [&str; 4] = [
    "meta/info.json",
    "data/chunk-000/file-000.parquet",
    "meta/episodes/chunk-000/file-000.parquet",
    "meta/tasks.parquet",
];

proptest! {
    #![proptest_config(fuzz_cases(48, "proptest-regressions/reader_fuzz.txt"))]

    /// Up to 8 byte edits of one file of a valid dataset.
    #[test]
    fn mutated_files_never_panic(
        file in 0..FILES.len(),
        edits in prop::collection::vec(edit(), 1..8),
    ) {
        thread_local!(static ROOT: Dir = Dir(dataset("mutated")));
        ROOT.with(|Dir(root)| {
            let original = fs::read(root.join(FILES[file])).unwrap();
            read_with(root, FILES[file], &original, &apply(&original, &edits));
        });
    }

    /// Arbitrary bytes in place of one file.
    #[test]
    fn arbitrary_files_never_panic(
        file in 0..FILES.len(),
        bytes in prop::collection::vec(any::<u8>(), 0..512),
    ) {
        thread_local!(static ROOT: Dir = Dir(dataset("arbitrary")));
        ROOT.with(|Dir(root)| {
            let original = fs::read(root.join(FILES[file])).unwrap();
            read_with(root, FILES[file], &original, &bytes);
        });
    }

    /// `info.json` fields set to arbitrary JSON-ish values: path templates built from the
    /// characters that matter (`{`, `}`, `:`, digits, `.`, `/`), numbers and strings.
    #[test]
    fn arbitrary_info_fields_never_panic(
        field in prop::sample::select(vec!["data_path", "video_path", "fps", "codebase_version", "features"]),
        template in "[{}:0-9d./a-z_]{0,40}",
        number in any::<f64>(),
        kind in 0..3u8,
    ) {
        thread_local!(static ROOT: Dir = Dir(dataset("info")));
        ROOT.with(|Dir(root)| {
            let path = root.join("meta/info.json");
            let original = fs::read(&path).unwrap();
            let mut info: serde_json::Value = serde_json::from_slice(&original).unwrap();
            info[field] = match kind {
                0 => serde_json::Value::String(template.clone()),
                1 => serde_json::json!(number),
                _ => serde_json::json!([template.clone(), number]),
            };
            read_with(root, "meta/info.json", &original, info.to_string().as_bytes());
        });
    }
}

/// The first panic the mutation search found (parquet 59 / arrow-ipc 59): four bit edits of
/// the data file give its embedded arrow schema an integer 6720 bits wide, and arrow-ipc
/// panics decoding it. Now one error naming the file.
#[test]
fn an_impossible_embedded_arrow_schema_is_an_error_naming_the_file() {
    let root = dataset("arrow-schema");
    let rel = FILES[1];
    let original = fs::read(root.join(rel)).unwrap();
    let edits = [
        Edit::Flip(7800775580451890393, 8),
        Edit::Flip(6196915008747990511, 32),
        Edit::Flip(16049994521141839313, 4),
        Edit::Set(8732187637746650073, 224),
    ];
    fs::write(root.join(rel), apply(&original, &edits)).unwrap();
    let err = read_dataset(&root).unwrap_err();
    assert!(
        matches!(&err, pir2_sim::Error::Malformed { path, .. } if path.ends_with(rel)),
        "{err}"
    );
    fs::remove_dir_all(&root).unwrap();
}
