//! The embodiment loader (`embodiment.toml` of a GR00T export) never panics: byte-mutated
//! files and fields set to extreme values end in a config or an error, and a config that
//! loads can be used (widths, limits, period) without overflow. Small case counts (CI).

use std::path::PathBuf;

use pir2_backends::gr00t::EmbodimentConfig;
use pir2_tests::fuzz_cases;
use proptest::prelude::*;

struct File(PathBuf);
impl Drop for File {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn default_toml() -> String {
    EmbodimentConfig::xarm6_xhand().to_toml().unwrap()
}

/// Load `text` as `embodiment.toml`; on success use it as `pir2 gr00t run` does.
fn check(file: &File, text: &[u8]) {
    std::fs::write(&file.0, text).unwrap();
    if let Ok(cfg) = EmbodimentConfig::load(&file.0) {
        let _ = (
            cfg.state_dim(),
            cfg.action_dim(),
            cfg.period_ns(),
            cfg.state_timestep(),
        );
        let l = cfg.action_limits();
        assert_eq!(l.lower.len(), cfg.action_dim());
        let _ = cfg.check_action_groups(&[("arm_joints", 6), ("hand_joints", 12)]);
    }
}

fn file(name: &str) -> File {
    File(std::env::temp_dir().join(format!(
        "pir2-embodiment-fuzz-{}-{name}.toml",
        std::process::id()
    )))
}

proptest! {
    #![proptest_config(fuzz_cases(64, "proptest-regressions/embodiment_fuzz.txt"))]

    /// Up to 8 single-byte replacements of the default file.
    #[test]
    fn mutated_embodiment_files_never_panic(
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
    ) {
        thread_local!(static F: File = file("mutated"));
        let mut b = default_toml().into_bytes();
        for (i, v) in &edits {
            let at = i.index(b.len());
            b[at] = *v;
        }
        F.with(|f| check(f, &b));
    }

    /// One `key = value` line set to an extreme value.
    #[test]
    fn extreme_embodiment_values_never_panic(
        key in any::<prop::sample::Index>(),
        value in prop::sample::select(vec![
            "0", "-1", "1e308", "-1e308", "inf", "nan", "18446744073709551615",
            "9223372036854775807", "-9223372036854775808", "1e-320", "\"x\"", "[]",
            "[1e308, -1e308]", "{}", "true",
        ]),
    ) {
        thread_local!(static F: File = file("extreme"));
        let text = default_toml();
        let lines: Vec<&str> = text.lines().filter(|l| l.contains(" = ")).collect();
        let line = lines[key.index(lines.len())];
        let name = line.split(" = ").next().unwrap();
        let text = text.replace(line, &format!("{name} = {value}"));
        F.with(|f| check(f, text.as_bytes()));
    }
}

/// A group of 2^40 values is refused by name (it would be allocated by `action_limits`).
#[test]
fn huge_group_widths_are_refused() {
    let f = file("huge");
    let text = default_toml();
    let line = text
        .lines()
        .find(|l| l.trim_start().starts_with("dim = "))
        .expect("a group dim");
    std::fs::write(&f.0, text.replacen(line, "dim = 1099511627776", 1)).unwrap();
    let err = EmbodimentConfig::load(&f.0).unwrap_err().to_string();
    assert!(err.contains("at most 8192"), "{err}");
}
