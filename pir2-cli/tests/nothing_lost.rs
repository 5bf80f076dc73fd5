//! Nothing lost, through the `pir2` binary: a failed `pir2 gr00t run` still writes its `--json`
//! report (with the error) and never replaces an existing one; `pir2 collect` on Ctrl-C
//! finishes the episode in progress and writes what it kept, and a killed one keeps what it
//! wrote as it went; `--overwrite` keeps the old dataset until the new one has an episode.

use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("pir2-nothing-lost-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn pir2(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .output()
        .unwrap()
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// A `pir2 gr00t run` that fails (no checkpoint; in a build without the GR00T stack, no stack)
/// writes `{"error": …}` to `--json`; a second run with the same `--json` refuses to start
/// and leaves the file as it was. Before: nothing was written on failure, and an existing
/// file was overwritten by a run that succeeded.
#[test]
fn run_json_records_a_failure_and_never_replaces_a_file() {
    let dir = tmpdir("run-json");
    let json = dir.join("run.json");
    let missing = dir.join("no-such-checkpoint");
    let args = [
        "gr00t",
        "run",
        "gr00t-xarm-xhand",
        "--checkpoint",
        missing.to_str().unwrap(),
        "--task",
        "catch_book",
        "--emulate",
        "--ticks",
        "5",
        "--json",
        json.to_str().unwrap(),
    ];
    let out = pir2(&args);
    assert!(!out.status.success(), "{}", text(&out.stderr));
    let report = std::fs::read_to_string(&json).expect("the failure report must be written");
    let v: serde_json::Value = serde_json::from_str(&report).unwrap();
    let err = v["error"].as_str().expect("an `error` string");
    assert!(!err.is_empty());
    assert!(
        text(&out.stderr).contains(err.lines().next().unwrap()),
        "the report holds the error the run printed: {err:?} vs {}",
        text(&out.stderr)
    );
    assert_eq!(v["task"], "catch_book");
    // Again with the same --json: refused by name, file untouched.
    let out = pir2(&args);
    assert!(!out.status.success());
    let stderr = text(&out.stderr);
    assert!(
        stderr.contains("already exists") && stderr.contains(json.to_str().unwrap()),
        "{stderr}"
    );
    assert_eq!(std::fs::read_to_string(&json).unwrap(), report);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An error ends the process with status 1 and one report on stderr (message and causes),
/// without a stack backtrace even when `RUST_BACKTRACE` asks for one: an expected error such
/// as an interrupted training or a missing file is not a crash. Before, `main` returned the
/// `anyhow` error and its `Debug` form printed the captured backtrace.
#[test]
fn an_error_is_one_report_without_a_backtrace() {
    let dir = tmpdir("error-report");
    let missing = dir.join("no-such-config.toml");
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["demo", "--config", missing.to_str().unwrap()])
        .args(["--out", dir.join("out").to_str().unwrap()])
        .env("RUST_BACKTRACE", "1")
        .env("RUST_LIB_BACKTRACE", "1")
        .output()
        .unwrap();
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.starts_with("Error: "), "{stderr}");
    assert_eq!(stderr.matches("Error: ").count(), 1, "{stderr}");
    assert!(
        stderr.contains("no-such-config.toml"),
        "names the path: {stderr}"
    );
    assert!(!stderr.to_lowercase().contains("backtrace"), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

fn spawn_collect(out: &Path, extra: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(["collect", "ballplate", "--episodes", "1000000", "--out"])
        .arg(out)
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// SIGINT, then wait (≤ 120 s) for the exit; returns the exit status and stdout + stderr.
fn interrupt(mut child: Child, after: Duration) -> (std::process::ExitStatus, String) {
    std::thread::sleep(after);
    // SAFETY: plain kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
    let t0 = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        if t0.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            panic!("still running 120 s after SIGINT");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    (out.status, text(&out.stdout) + &text(&out.stderr))
}

/// Ctrl-C during `pir2 collect ballplate` ends it cleanly with the finished episodes
/// written (readable, fewer than asked). Before: SIGINT killed the process and every
/// collected episode (held in memory) was lost.
#[test]
fn collect_on_sigint_writes_the_finished_episodes() {
    let dir = tmpdir("collect-sigint");
    let data = dir.join("dataset");
    let (status, log) = interrupt(spawn_collect(&data, &[]), Duration::from_secs(3));
    assert_eq!(status.signal(), None, "killed by the signal: {log}");
    assert!(status.success(), "{status:?}: {log}");
    assert!(log.contains("interrupted"), "{log}");
    let ds = pir2_sim::dataset::read_dataset(&data).unwrap_or_else(|e| panic!("{e}: {log}"));
    assert!(
        !ds.episodes.is_empty() && ds.episodes.len() < 1_000_000,
        "{} episodes: {log}",
        ds.episodes.len()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `pir2 collect --overwrite` interrupted at once: the dataset there is still readable
/// (the old one if no new episode was finished, else the new one). Before: the old `data/`
/// and `meta/` were deleted when the writer opened, and the interruption left nothing.
#[test]
fn an_interrupted_overwrite_never_leaves_no_dataset() {
    let dir = tmpdir("collect-overwrite");
    let data = dir.join("dataset");
    let out = pir2(&[
        "collect",
        "ballplate",
        "--episodes",
        "2",
        "--out",
        data.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let before = pir2_sim::dataset::read_dataset(&data).unwrap();
    assert_eq!(before.episodes.len(), 2);
    let (status, log) = interrupt(
        spawn_collect(&data, &["--overwrite", "--seed", "99"]),
        Duration::from_millis(300),
    );
    let after = pir2_sim::dataset::read_dataset(&data)
        .unwrap_or_else(|e| panic!("no readable dataset after {status:?}: {e}\n{log}"));
    assert!(
        after == before || (!after.episodes.is_empty() && after.episodes != before.episodes),
        "{log}"
    );
    // No staging directory is left behind.
    let names: Vec<String> = std::fs::read_dir(&data)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names.iter().all(|n| n == "data" || n == "meta"),
        "{names:?}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// SIGKILL during `pir2 collect ballplate` (no handler can run): the dataset on disk holds
/// every episode written so far (it is written every 10 kept episodes) and `--resume`
/// continues it. Before: the episodes were held in memory until the end and all lost.
#[test]
fn a_killed_collection_keeps_what_it_wrote_and_resumes() {
    let dir = tmpdir("collect-kill");
    let data = dir.join("dataset");
    let mut child = spawn_collect(&data, &[]);
    let t0 = Instant::now();
    // Until the first flush is on disk (a whole dataset), then a little longer.
    while pir2_sim::dataset::read_dataset(&data).is_err() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "nothing written in 60 s"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(300));
    child.kill().unwrap();
    let out = child.wait_with_output().unwrap();
    let log = text(&out.stdout) + &text(&out.stderr);
    let ds = pir2_sim::dataset::read_dataset(&data).unwrap_or_else(|e| panic!("{e}: {log}"));
    let n = ds.episodes.len();
    assert!(n >= 10 && n % 10 == 0, "{n} episodes: {log}");
    let more = (n + 3).to_string();
    let out = pir2(&[
        "collect",
        "ballplate",
        "--episodes",
        &more,
        "--resume",
        "--out",
        data.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let ds = pir2_sim::dataset::read_dataset(&data).unwrap();
    assert_eq!(ds.episodes.len(), n + 3);
    std::fs::remove_dir_all(&dir).unwrap();
}
