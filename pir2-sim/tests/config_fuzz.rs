//! The ball-plate task's TOML configuration loader never panics: byte-mutated files and
//! fields set to extreme values end in a config or an error naming the field. Small case
//! counts (CI).

use pir2_sim::ballplate::{BallPlate, BallPlateConfig};
use proptest::prelude::*;

use pir2_tests::fuzz_cases;

fn default_toml() -> String {
    toml::to_string(&BallPlateConfig::default()).unwrap()
}

fn check(text: &str) {
    if let Ok(cfg) = BallPlateConfig::from_toml_str(text) {
        // A config that validates must also build the task.
        BallPlate::new(cfg).unwrap();
    }
}

proptest! {
    #![proptest_config(fuzz_cases(64, "proptest-regressions/config_fuzz.txt"))]

    /// Up to 8 single-byte replacements of the default file.
    #[test]
    fn mutated_task_configs_never_panic(
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
    ) {
        let mut b = default_toml().into_bytes();
        for (i, v) in &edits {
            let at = i.index(b.len());
            b[at] = *v;
        }
        check(&String::from_utf8_lossy(&b));
    }

    /// One field set to an extreme value.
    #[test]
    fn extreme_task_config_values_never_panic(
        key in any::<prop::sample::Index>(),
        value in prop::sample::select(vec![
            "0", "-1", "1e308", "-1e308", "inf", "-inf", "nan", "18446744073709551615",
            "9223372036854775807", "-9223372036854775808", "1e-320", "\"x\"", "[]", "{}", "true",
        ]),
    ) {
        let text = default_toml();
        let lines: Vec<&str> = text.lines().filter(|l| l.contains(" = ")).collect();
        let line = lines[key.index(lines.len())];
        let name = line.split(" = ").next().unwrap();
        check(&text.replace(line, &format!("{name} = {value}")));
    }
}

/// Sizes that would never end or never fit are refused by name. Before: `push_rate = 1e308`
/// drew pushes until memory ran out, a NaN `push_start` looped forever.
#[test]
fn unbounded_task_configs_are_refused_by_name() {
    for (line, field) in [
        ("push_rate = 1e308", "push_rate"),
        ("push_start = nan", "push_start"),
        ("push_end = 1e308", "push_rate"),
        ("episode_s = 1e300", "episode_s"),
        ("substeps = 18446744073709551615", "substeps"),
    ] {
        let err = BallPlateConfig::from_toml_str(line).unwrap_err();
        assert!(err.to_string().contains(field), "{line}: {err}");
    }
}
