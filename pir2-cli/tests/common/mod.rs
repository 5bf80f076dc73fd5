//! Shared helpers of the `pir2-cli` integration tests.

use std::path::{Path, PathBuf};

/// The GR00T tests' fixtures; each GR00T test binary uses a part of them.
#[cfg(feature = "gr00t")]
#[allow(dead_code)]
pub mod gr00t;

/// A fresh scratch directory under the system temp dir, removed when dropped.
pub struct Scratch(PathBuf);

impl Scratch {
    /// `pir2-cli-<name>-<pid>`, emptied first.
    pub fn new(name: &str) -> Self {
        let p = std::env::temp_dir().join(format!("pir2-cli-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        Self(p)
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
