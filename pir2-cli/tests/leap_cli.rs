//! `pir2 collect|train|eval leap-cube` through the binary: with the `mujoco` feature the whole
//! chain on a tiny config (2 expert episodes, 3 training steps, 1 episode of 10 steps per cell); without
//! it, one clear error.

use std::path::Path;
use std::process::Command;

fn pir2(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .output()
        .expect("running pir2")
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// `pir2 eval leap-cube --study STUDY` with `config` and `data` over the runs in `trained`
/// into `out`.
#[cfg(feature = "mujoco")]
fn eval_args<'a>(
    study: &'a str,
    config: &'a Path,
    data: &'a Path,
    trained: &'a Path,
    out: &'a Path,
) -> Vec<&'a str> {
    vec![
        "eval",
        "leap-cube",
        "--study",
        study,
        "--config",
        s(config),
        "--data",
        s(data),
        "--checkpoint",
        s(trained),
        "--out",
        s(out),
    ]
}

#[cfg(not(feature = "mujoco"))]
#[test]
fn leap_cube_without_the_feature_says_how_to_build() {
    let dir = std::env::temp_dir().join(format!("pir2-leap-nofeat-{}", std::process::id()));
    for args in [
        vec!["collect", "leap-cube", "--out", s(&dir)],
        vec!["train", "leap-cube", "--data", s(&dir), "--out", s(&dir)],
        vec!["eval", "leap-cube", "--study", "horizon", "--out", s(&dir)],
        vec!["report", "leap-cube", "--cells", s(&dir), "--out", s(&dir)],
    ] {
        let o = pir2(&args);
        assert!(!o.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains("--features mujoco"), "{args:?}: {err}");
    }
    assert!(!dir.exists(), "nothing is written");
}

#[cfg(feature = "mujoco")]
#[test]
fn leap_cube_collect_train_eval_through_the_binary() {
    let dir = std::env::temp_dir().join(format!("pir2-leap-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("tmp dir");
    let data = dir.join("data");
    let ok = |args: &[&str]| {
        let o = pir2(args);
        assert!(
            o.status.success(),
            "{args:?}: {}\n{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let collect = [
        "collect",
        "leap-cube",
        "--out",
        s(&data),
        "--seeds",
        "0",
        "--per-seed",
        "2",
        "--fast",
    ];
    let out = ok(&collect);
    assert!(out.contains("2 episodes"), "{out}");
    // A second run without --resume refuses; with --resume it adds nothing.
    assert!(!pir2(&collect).status.success());
    let mut resume = collect.to_vec();
    resume.push("--resume");
    let out = ok(&resume);
    assert!(
        out.contains("2 episodes") && out.contains("0 written"),
        "{out}"
    );

    let cfg = dir.join("tiny.toml");
    std::fs::write(
        &cfg,
        "train_steps = 3\nbatch_size = 8\nwarmup = 1\nwidths = [8, 16]\ngroups = 4\n\
         checkpoints = 2\nval_episodes = 1\nepisodes = 1\nseeds = [0]\nd0s = [2]\nhs = [1, 8]\n\
         flow_steps = 2\nmax_steps = 10\nthreads = 1\n",
    )
    .expect("config");
    let trained = dir.join("trained");
    ok(&[
        "train",
        "leap-cube",
        "--data",
        s(&data),
        "--config",
        s(&cfg),
        "--out",
        s(&trained),
    ]);
    for p in ["pir2", "pir2full", "rtc", "flow"] {
        assert!(trained.join(format!("{p}-seed0/best")).exists(), "{p}");
    }
    // Training into it again needs --resume; --resume keeps finished policies and continues
    // an unfinished one from its step checkpoints; another config is refused by name.
    let train = [
        "train",
        "leap-cube",
        "--data",
        s(&data),
        "--config",
        s(&cfg),
        "--out",
        s(&trained),
    ];
    let again = pir2(&train);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("not empty"));
    std::fs::remove_dir_all(trained.join("flow-seed0/best")).expect("remove best");
    // A run written before a config field existed (here: `best_of_last`, at its default)
    // still resumes: the configs are compared as values, not as text.
    let written = trained.join("config.toml");
    let text = std::fs::read_to_string(&written).expect("config.toml");
    assert!(text.contains("best_of_last = 0\n"), "{text}");
    std::fs::write(&written, text.replace("best_of_last = 0\n", "")).expect("older config");
    let mut resume = train.to_vec();
    resume.push("--resume");
    // --seeds narrows the config's seeds (one run at a time); a seed it does not list is
    // refused by name, before anything is trained.
    let mut other_seed = resume.clone();
    other_seed.extend(["--policy", "flow", "--seeds", "3"]);
    let o = pir2(&other_seed);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("seed 3 is not one of the config's seeds [0]"),
        "{err}"
    );
    assert!(!trained.join("flow-seed0/best").exists());
    let o = pir2(&resume);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("Rtc seed 0 finished in an earlier run"),
        "{err}"
    );
    assert!(trained.join("flow-seed0/best").exists());
    let other = dir.join("other.toml");
    std::fs::write(
        &other,
        std::fs::read_to_string(&cfg)
            .unwrap()
            .replace("train_steps = 3", "train_steps = 4"),
    )
    .unwrap();
    let mut differs = resume.clone();
    differs[5] = s(&other);
    let o = pir2(&differs);
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("the config differs"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // The evaluation also reports the best checkpoint per cell over one more step checkpoint.
    let eval_cfg = dir.join("eval.toml");
    std::fs::write(
        &eval_cfg,
        std::fs::read_to_string(&cfg).unwrap() + "best_of_last = 1\n",
    )
    .unwrap();
    for (study, row, col) in [
        ("deployment", "| πR² async (n=2) |", "d0=2"),
        ("horizon", "| sync flow |", "h=8"),
    ] {
        let out_dir = dir.join(study);
        let eval = eval_args(study, &eval_cfg, &data, &trained, &out_dir);
        let out = ok(&eval);
        assert!(out.contains(row) && out.contains(col), "{out}");
        for f in [
            "result.json",
            "table.md",
            "success.png",
            "success-best-per-cell.png",
        ] {
            assert!(out_dir.join(f).exists(), "{study}/{f}");
        }
        assert!(out.contains("Best checkpoint per cell"), "{out}");
        // Per cell, the best checkpoint is at least the chosen one.
        let result: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out_dir.join("result.json")).unwrap())
                .unwrap();
        let (cells, best) = (
            result["cells"].as_array().unwrap(),
            result["best_per_cell"].as_array().unwrap(),
        );
        assert_eq!(cells.len(), best.len());
        for (c, b) in cells.iter().zip(best) {
            assert_eq!((&c["label"], &c["d0"]), (&b["label"], &b["d0"]));
            assert!(b["successes"].as_u64() >= c["successes"].as_u64());
        }
        // The trained policies were loaded, not trained again.
        assert!(!out_dir.join("checkpoints").exists(), "{study}");

        // Every measured cell is in the cell log; an interrupted evaluation (here: the log
        // cut in the middle of a line, the outputs gone) continues with --resume, measures
        // only the missing cells and ends with the same results.
        let log_file = out_dir.join("cells.jsonl");
        let log = std::fs::read_to_string(&log_file).unwrap();
        let lines: Vec<&str> = log.lines().collect();
        assert!(lines.len() >= cells.len(), "{study}: {log}");
        let again = pir2(&eval);
        assert!(
            !again.status.success(),
            "{study}: a second run needs --resume"
        );
        let keep = lines.len() / 2;
        let cut = lines[..keep].join("\n") + "\n" + &lines[keep][..lines[keep].len() / 2];
        std::fs::write(&log_file, cut).unwrap();
        for f in ["result.json", "table.md"] {
            std::fs::remove_file(out_dir.join(f)).unwrap();
        }
        let mut resume = eval.to_vec();
        resume.push("--resume");
        let o = pir2(&resume);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{study}: {err}");
        assert!(
            err.contains(&format!("{keep} cells measured earlier are reused")),
            "{study}: {err}"
        );
        assert_eq!(
            std::fs::read_to_string(&log_file).unwrap().lines().count(),
            lines.len(),
            "{study}: one line per cell again"
        );
        let resumed: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out_dir.join("result.json")).unwrap())
                .unwrap();
        assert_eq!(resumed["cells"], result["cells"], "{study}");
        assert_eq!(resumed["best_per_cell"], result["best_per_cell"], "{study}");

        // The same tables from the cell log alone, without the checkpoints or the dataset.
        let report_dir = dir.join(format!("{study}-report"));
        let out = ok(&[
            "report",
            "leap-cube",
            "--study",
            study,
            "--config",
            s(&eval_cfg),
            "--data",
            s(&data),
            "--cells",
            s(&log_file),
            "--out",
            s(&report_dir),
        ]);
        assert!(out.contains(row) && out.contains("Per seed"), "{out}");
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(report_dir.join("report.json")).unwrap())
                .unwrap();
        assert_eq!(report["cells"], result["cells"], "{study}: from the log");
        assert_eq!(
            report["best_per_cell"], result["best_per_cell"],
            "{study}: from the log"
        );
        assert_eq!(
            report["missing"].as_array().map(Vec::len),
            Some(0),
            "{study}"
        );
        // A log without this config's cells (`other`: another step count) is refused.
        let o = pir2(&[
            "report",
            "leap-cube",
            "--study",
            study,
            "--config",
            s(&other),
            "--cells",
            s(&log_file),
        ]);
        assert!(!o.status.success());
        assert!(
            String::from_utf8_lossy(&o.stderr).contains("holds no cell of this config"),
            "{}",
            String::from_utf8_lossy(&o.stderr)
        );
    }

    // A run without the step checkpoints the best-per-cell protocol takes (one restored from
    // its saved state keeps only best/) is refused by name before anything is measured;
    // --best-of-last 0 measures its chosen cells.
    for e in std::fs::read_dir(trained.join("rtc-seed0"))
        .unwrap()
        .flatten()
    {
        if e.file_name().to_string_lossy().starts_with("step-") {
            std::fs::remove_dir_all(e.path()).unwrap();
        }
    }
    let chosen_only = dir.join("chosen-only");
    let mut eval_chosen = eval_args("deployment", &eval_cfg, &data, &trained, &chosen_only);
    eval_chosen.extend(["--policies", "rtc"]);
    let o = pir2(&eval_chosen);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("rtc-seed0") && err.contains("step-00000") && err.contains("--best-of-last 0"),
        "{err}"
    );
    assert!(!chosen_only.exists(), "nothing measured, nothing written");
    eval_chosen.extend(["--best-of-last", "0"]);
    let out = ok(&eval_chosen);
    assert!(out.contains("train-time RTC"), "{out}");
    assert!(!out.contains("Best checkpoint per cell"), "{out}");

    // A listed policy missing from --checkpoint (the zero-delay variant was not trained) is
    // refused by name before anything runs; --train-missing trains it into --out.
    let with_zero = dir.join("with-zero.toml");
    std::fs::write(
        &with_zero,
        std::fs::read_to_string(&cfg).unwrap() + "policies = [\"flow\", \"pi_r2_zero_delay\"]\n",
    )
    .unwrap();
    let zero_out = dir.join("horizon-zero");
    let mut eval_zero = eval_args("horizon", &with_zero, &data, &trained, &zero_out);
    let o = pir2(&eval_zero);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("pir2zerodelay-seed0") && err.contains("--train-missing"),
        "{err}"
    );
    assert!(!err.contains("flow-seed0"), "{err}");
    assert!(!zero_out.exists(), "nothing is written");
    eval_zero.push("--train-missing");
    let o = pir2(&eval_zero);
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{err}");
    assert!(out.contains("zero-delay"), "{out}");
    // It is validated as it runs, without latency (not at the baselines' d0).
    let validations: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("PiR2ZeroDelay seed 0: checkpoint validation"))
        .collect();
    assert!(!validations.is_empty(), "{err}");
    assert!(
        validations.iter().all(|l| l.ends_with("at zero latency")),
        "{err}"
    );
    assert!(zero_out
        .join("checkpoints/pir2zerodelay-seed0/best")
        .exists());
    assert!(!zero_out.join("checkpoints/flow-seed0").exists());

    // Ctrl-C during training saves the exact step reached (not only the last step
    // checkpoint); --resume continues from it.
    let long = dir.join("long.toml");
    std::fs::write(
        &long,
        std::fs::read_to_string(&cfg)
            .unwrap()
            .replace("train_steps = 3", "train_steps = 100000"),
    )
    .unwrap();
    let stopped = dir.join("stopped");
    let train_long = |extra: &[&str]| {
        let mut args = vec![
            "train",
            "leap-cube",
            "--policy",
            "flow",
            "--data",
            s(&data),
            "--config",
            s(&long),
            "--out",
            s(&stopped),
        ];
        args.extend_from_slice(extra);
        interrupt_after_progress(&args)
    };
    let (first, log) = train_long(&[]);
    assert!(log.contains("training interrupted at step"), "{log}");
    let saved = std::fs::read_dir(stopped.join("flow-seed0"))
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .find(|n| n.starts_with("interrupted-"))
        .unwrap_or_else(|| panic!("no interrupted-* state: {log}"));
    let at: usize = saved["interrupted-".len()..].parse().unwrap();
    assert!(at >= first, "saved {at}, progress reached {first}");
    let (resumed_first, log) = train_long(&["--resume"]);
    assert!(
        resumed_first > at,
        "the resumed run's first progress line is step {resumed_first}, the state was at {at}: {log}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// What [`interrupt_when`] saw.
#[cfg(feature = "mujoco")]
struct Interrupted {
    /// The stderr line that triggered the signal.
    line: String,
    /// All of stderr.
    log: String,
    /// All of stdout.
    stdout: String,
    status: std::process::ExitStatus,
}

/// Run `pir2 args`, send it SIGINT once a stderr line satisfies `at`, and wait (at most
/// 120 s) for it to end.
#[cfg(feature = "mujoco")]
fn interrupt_when(args: &[&str], at: impl Fn(&str) -> bool) -> Interrupted {
    use std::io::{BufRead, BufReader, Read};
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let mut child = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .stderr(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("running pir2");
    let mut stdout_pipe = child.stdout.take().expect("stdout");
    let reader = std::thread::spawn(move || {
        let mut text = String::new();
        stdout_pipe.read_to_string(&mut text).expect("stdout");
        text
    });
    let mut log = String::new();
    let mut lines = BufReader::new(child.stderr.take().expect("stderr")).lines();
    let mut hit = None;
    for line in lines.by_ref() {
        let line = line.expect("stderr line");
        log += &line;
        log.push('\n');
        if at(&line) {
            hit = Some(line);
            break;
        }
    }
    let line = hit.unwrap_or_else(|| panic!("the awaited line never came: {log}"));
    // SAFETY: plain kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
    let t0 = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "still running 120 s after SIGINT: {log}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    for l in lines {
        log += &l.expect("stderr line");
        log.push('\n');
    }
    let status = child.wait().expect("wait");
    let stdout = reader.join().expect("stdout reader");
    Interrupted {
        line,
        log,
        stdout,
        status,
    }
}

/// Run `pir2 args`, SIGINT it once its first `step N/` progress line appears; returns N and
/// the whole stderr after the process ended (unsuccessfully).
#[cfg(feature = "mujoco")]
fn interrupt_after_progress(args: &[&str]) -> (usize, String) {
    let step = |line: &str| {
        line.split(": step ")
            .nth(1)
            .and_then(|r| r.split('/').next())
            .and_then(|n| n.parse::<usize>().ok())
    };
    let run = interrupt_when(args, |l| step(l).is_some());
    assert!(
        !run.status.success(),
        "an interrupted training is not a success: {}",
        run.log
    );
    (step(&run.line).expect("a progress line"), run.log)
}

/// Ctrl-C during `pir2 collect leap-cube`: the batch in progress is finished and written, the
/// process exits 0 and says how many episodes the dataset holds; `--resume` continues from
/// there. The expert is an untrained policy (weights written here), so an episode costs
/// physics only. Before: the "written now" count of the summary was the last batch's.
#[cfg(feature = "mujoco")]
#[test]
fn leap_cube_collect_on_sigint_writes_the_batch_in_progress_and_resumes() {
    use std::os::unix::process::ExitStatusExt;

    use pir2_sim::leap::ppo::{PpoConfig, Trainer};
    use pir2_sim::leap::LeapModel;

    let dir = std::env::temp_dir().join(format!("pir2-leap-sigint-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("tmp dir");
    let scene = LeapModel::load(None)
        .expect("Leap-cube scene: run scripts/setup-native.sh and source .native/env.sh");
    let cfg = PpoConfig {
        seed: 3,
        n_envs: 2,
        rollout_len: 1,
        env_chunk: 1,
        minibatches: 1,
        grad_chunks: 1,
        actor_hidden: vec![8],
        critic_hidden: vec![8],
        ..PpoConfig::default()
    };
    let expert = dir.join("expert.safetensors");
    Trainer::new(&scene, cfg, 1)
        .expect("untrained expert")
        .expert()
        .save(&expert)
        .expect("save expert");
    let data = dir.join("data");
    let collect = |per_seed: usize, extra: &[&str]| {
        let mut args: Vec<String> = ["collect", "leap-cube", "--seeds", "0", "--out", s(&data)]
            .iter()
            .map(|a| a.to_string())
            .collect();
        args.extend(["--per-seed".into(), per_seed.to_string()]);
        args.extend(["--expert".into(), s(&expert).to_string()]);
        args.extend(extra.iter().map(|a| a.to_string()));
        args
    };
    // Signal once two batches are written, so the summary must add up several batches.
    let args = collect(1000, &[]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let run = interrupt_when(&args, |l| l.starts_with("collected 10/"));
    let (log, stdout) = (run.log, run.stdout);
    assert!(log.contains("collected 10/1000"), "{log}");
    assert_eq!(run.status.signal(), None, "killed by the signal: {log}");
    assert!(run.status.success(), "{:?}: {log}", run.status);
    let held: usize = log
        .split("interrupted: ")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no `interrupted: N/1000` line: {log}"));
    assert!((10..1000).contains(&held) && held % 5 == 0, "{held}: {log}");
    assert!(
        stdout.contains(&format!("{held} episodes"))
            && stdout.contains(&format!("({held} written now")),
        "{stdout}"
    );
    let ds = pir2_sim::dataset::read_dataset(&data).expect("readable after SIGINT");
    assert_eq!(ds.episodes.len(), held);

    // Resume to three more episodes than were written: only those three are collected.
    let out = Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(collect(held + 3, &["--resume"]))
        .output()
        .expect("resume");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}");
    assert!(
        stdout.contains(&format!("{} episodes", held + 3)) && stdout.contains("(3 written now"),
        "{stdout}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
