//! The command line through the binary: each `--help` lists only the flags that apply (the
//! candle servers and the GR00T ones apart), and the old spellings of the GR00T run and
//! servers still reach them, naming the new spelling on stderr.

use std::process::{Command, Output};

fn pir2(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .output()
        .unwrap()
}

fn help(args: &[&str]) -> String {
    let mut a = args.to_vec();
    a.push("--help");
    let out = pir2(&a);
    assert!(
        out.status.success(),
        "{a:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// Before: `pir2 serve policy --help` listed `--gr00t-checkpoint`, `--task` and `--ep` beside
/// the candle flags, and `pir2 run` stood beside `pir2 gr00t`.
#[test]
fn each_help_lists_only_the_flags_that_apply() {
    let top = help(&[]);
    assert!(!top.contains("\n  run "), "{top}");
    let gr00t = help(&["gr00t"]);
    assert!(
        gr00t.contains("\n  run ") && gr00t.contains("\n  serve "),
        "{gr00t}"
    );

    let candle = help(&["serve", "policy"]);
    assert!(
        candle.contains("--checkpoint") && candle.contains("--policy"),
        "{candle}"
    );
    for gr00t_only in ["--gr00t-checkpoint", "--task", "--ep"] {
        assert!(!candle.contains(gr00t_only), "{gr00t_only} in {candle}");
    }
    let stub = help(&["serve", "slow"]);
    assert!(stub.contains("--stub"), "{stub}");
    for gr00t_only in ["--checkpoint", "--task", "--ep"] {
        assert!(!stub.contains(gr00t_only), "{gr00t_only} in {stub}");
    }

    let head = help(&["gr00t", "serve", "policy"]);
    assert!(
        head.contains("--checkpoint") && head.contains("--task"),
        "{head}"
    );
    assert!(head.contains("--ep "), "{head}");
    for candle_only in ["--policy", "--gr00t-checkpoint"] {
        assert!(!head.contains(candle_only), "{candle_only} in {head}");
    }
    let backbone = help(&["gr00t", "serve", "slow"]);
    assert!(
        backbone.contains("--checkpoint") && backbone.contains("--task"),
        "{backbone}"
    );
    assert!(!backbone.contains("--stub"), "{backbone}");

    let run = help(&["gr00t", "run"]);
    assert!(
        run.contains("gr00t-xarm-xhand") && run.contains("--remote-policy"),
        "{run}"
    );
}

/// The only test that uses the old spellings: `pir2 run gr00t-xarm-xhand …` and
/// `pir2 serve policy|slow --gr00t-checkpoint …` are parsed as `pir2 gr00t run|serve …` (no
/// usage error: they fail on the missing checkpoint, or on the build's missing features, as
/// the new spelling does) and say the new spelling on stderr.
#[test]
fn the_old_spellings_still_work_and_name_the_new_ones() {
    let dir = std::env::temp_dir().join(format!("pir2-cli-help-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let missing = dir.join("no-such-checkpoint");
    let ck = missing.to_str().unwrap();
    let json = dir.join("run.json");
    let run = [
        "gr00t-xarm-xhand",
        "--checkpoint",
        ck,
        "--task",
        "catch_book",
    ];
    let run_rest = [
        "--emulate",
        "--ticks",
        "1",
        "--json",
        json.to_str().unwrap(),
    ];

    let old = pir2(&[&["run"][..], &run, &run_rest].concat());
    let err = String::from_utf8_lossy(&old.stderr);
    assert_eq!(old.status.code(), Some(1), "{err}");
    assert!(err.contains("`pir2 gr00t run`"), "{err}");
    assert!(
        json.exists(),
        "the old spelling writes its --json failure report too"
    );
    std::fs::remove_file(&json).unwrap();
    let new = pir2(&[&["gr00t", "run"][..], &run, &run_rest].concat());
    let new_err = String::from_utf8_lossy(&new.stderr);
    assert_eq!(
        err.lines().last(),
        new_err.lines().last(),
        "same error as the new spelling"
    );
    assert!(!new_err.contains("note:"), "{new_err}");

    for verb in ["policy", "slow"] {
        let out = pir2(&[
            "serve",
            verb,
            "--gr00t-checkpoint",
            ck,
            "--task",
            "catch_book",
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(
            err.contains(&format!("`pir2 gr00t serve {verb} --checkpoint`")),
            "{err}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
