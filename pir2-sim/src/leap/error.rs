//! Errors of the Leap-cube environment (kept inside `leap` until the crate-wide error enum
//! lands; the variants map one-to-one onto a `Leap(..)` section there).

use std::path::PathBuf;

/// Errors raised while loading or running the Leap-cube scene.
#[derive(Debug, thiserror::Error)]
pub enum LeapError {
    // --- scene files ---
    /// `PIR2_LEAP_CUBE_DIR` is unset and no explicit path was given.
    #[error(
        "the Leap-cube scene directory is unknown: set PIR2_LEAP_CUBE_DIR (run \
         `scripts/setup-native.sh` and `source .native/env.sh`) or pass a path"
    )]
    SceneDirUnset,
    /// A scene file (or the directory) does not exist or cannot be read.
    #[error(
        "cannot read the Leap-cube scene file {path}: {source} (run `scripts/setup-native.sh`, \
         which installs the playground scene into .native/leap_cube)"
    )]
    SceneFile {
        /// The file that could not be read.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A mesh whose file is missing is used by a geom that takes part in the physics, so it
    /// cannot be stripped without changing the dynamics.
    #[error(
        "mesh `{mesh}` (file {file}) is missing and used by a colliding or massive geom in {xml}; \
         only visual-only meshes may be stripped"
    )]
    PhysicalMeshMissing {
        /// Mesh asset name.
        mesh: String,
        /// The missing file.
        file: PathBuf,
        /// The XML that uses it.
        xml: PathBuf,
    },
    /// MuJoCo rejected the scene.
    #[error("MuJoCo could not load {path}: {message}")]
    Load {
        /// The top-level scene file.
        path: PathBuf,
        /// MuJoCo's message.
        message: String,
    },
    /// The loaded model lacks an element the task needs (wrong scene file).
    #[error("the scene has no {kind} named `{name}` (is this the LeapCubeReorient scene?)")]
    MissingElement {
        /// Element kind (body, site, sensor, joint).
        kind: &'static str,
        /// Element name.
        name: String,
    },
    // --- use ---
    /// A buffer had the wrong length.
    #[error("{what}: expected length {expected}, got {got}")]
    Shape {
        /// Which buffer.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Actual length.
        got: usize,
    },
    /// A configuration value is out of range.
    #[error("invalid configuration: {0}")]
    Config(String),
}

/// Result alias of the `leap` module.
pub type Result<T> = std::result::Result<T, LeapError>;
