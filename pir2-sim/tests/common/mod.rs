//! Shared set-up of the fuzz tests.

use proptest::test_runner::{Config as ProptestConfig, FileFailurePersistence};

/// Cases per property: `n` in CI; `PIR2_FUZZ_CASES` runs more (a longer local search).
/// Shrunk failures are kept in `regressions` (under `proptest-regressions/`, committed) and
/// replayed first on every run.
pub fn cases(n: u32, regressions: &'static str) -> ProptestConfig {
    let n = std::env::var("PIR2_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(n);
    ProptestConfig {
        cases: n,
        failure_persistence: Some(Box::new(FileFailurePersistence::Direct(regressions))),
        ..ProptestConfig::default()
    }
}
