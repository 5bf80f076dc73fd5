//! The one error type of `pir2-sim`, sectioned by origin: configuration, experts, datasets
//! (files, content, camera videos) and, with feature `mujoco`, the Leap-cube scene and
//! environment and the PPO trainer and expert. Only errors of the libraries below convert
//! into it (TOML's); it converts into nothing, so no conversion runs back up.

use std::path::PathBuf;

/// Result alias of `pir2-sim`.
pub type Result<T> = std::result::Result<T, Error>;

/// Everything that can go wrong in `pir2-sim`.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    // ---- configuration -------------------------------------------------------------
    /// A configuration file or string could not be parsed.
    #[error("invalid configuration: {0}")]
    Config(#[from] toml::de::Error),
    /// A configuration value is out of its valid range.
    #[error("invalid configuration value `{field}`: {reason}")]
    ConfigValue {
        /// The offending field.
        field: &'static str,
        /// Why it is invalid.
        reason: String,
    },

    // ---- experts -----------------------------------------------------------------------
    /// The discrete Riccati iteration did not converge.
    #[error("discrete Riccati equation did not converge after {iterations} iterations (last change {change:e})")]
    Riccati {
        /// Iterations performed.
        iterations: usize,
        /// Relative change of `P` in the last iteration.
        change: f64,
    },

    // ---- datasets: file system -----------------------------------------------------
    /// A file or directory could not be read or written.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file or directory concerned.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A dataset exists where a new one was to be written.
    #[error("a dataset already exists at {path} ({what}); pass WriteMode::Resume to add episodes to it or WriteMode::Overwrite to replace it")]
    AlreadyExists {
        /// Root of the existing dataset.
        path: PathBuf,
        /// What was found there.
        what: String,
    },
    /// A file the dataset layout requires is missing.
    #[error("dataset file missing: {path}")]
    MissingFile {
        /// The missing file.
        path: PathBuf,
    },

    // ---- datasets: content ---------------------------------------------------------
    /// A parquet file could not be read or written.
    #[error("parquet error in {path}: {source}")]
    Parquet {
        /// The parquet file.
        path: PathBuf,
        /// The underlying error.
        source: parquet::errors::ParquetError,
    },
    /// Arrow data could not be assembled.
    #[error("arrow error for {path}: {source}")]
    Arrow {
        /// The file being written or read.
        path: PathBuf,
        /// The underlying error.
        source: arrow_schema::ArrowError,
    },
    /// A JSON metadata file is malformed.
    #[error("JSON error in {path}: {source}")]
    Json {
        /// The JSON file.
        path: PathBuf,
        /// The underlying error.
        source: serde_json::Error,
    },
    /// A required column is absent from a parquet file.
    #[error("{path}: missing column `{column}`")]
    MissingColumn {
        /// The parquet file.
        path: PathBuf,
        /// The missing column.
        column: String,
    },
    /// A column has an unexpected type or width.
    #[error("{path}: column `{column}` has type {found}, expected {expected}")]
    ColumnType {
        /// The parquet file.
        path: PathBuf,
        /// The column.
        column: String,
        /// What the reader accepts.
        expected: String,
        /// What the file holds.
        found: String,
    },
    /// The dataset contradicts itself (e.g. episode lengths vs. frames).
    #[error("inconsistent dataset at {path}: {reason}")]
    Inconsistent {
        /// The file where the contradiction was found.
        path: PathBuf,
        /// What does not match.
        reason: String,
    },
    /// The parquet/arrow decoder gave up on malformed bytes by panicking; the panic was
    /// caught at the reader's boundary and is reported here instead.
    #[error("{path}: malformed parquet file (the decoder failed: {message})")]
    Malformed {
        /// The parquet file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// A path template of `meta/info.json` (`data_path`, `video_path`) is unusable: it is
    /// absolute or climbs out of the dataset root (`..`), asks for a zero-padding width above
    /// [`MAX_TEMPLATE_WIDTH`](crate::dataset::MAX_TEMPLATE_WIDTH), or has a malformed or
    /// unknown placeholder.
    #[error("{path}: `{field}` = {template:?} is not a usable path template: {reason}")]
    PathTemplate {
        /// The `info.json` file.
        path: PathBuf,
        /// The field (`data_path` or `video_path`).
        field: String,
        /// The template as found (cut to 200 characters).
        template: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A feature asked for by name (a training task's fast, slow or action key) cannot be
    /// read: absent from `meta/info.json`, not a float feature (an image or video, an
    /// integer, a string), not a fixed-width vector, or asked for twice.
    #[error("{path}: feature `{key}` {reason}")]
    Feature {
        /// The dataset's `meta/info.json`.
        path: PathBuf,
        /// The feature key.
        key: String,
        /// What is wrong with it.
        reason: String,
    },
    // ---- datasets: camera videos ----------------------------------------------------
    /// The video decoder program (`ffmpeg`) could not be started.
    #[error("cannot run the video decoder `{program}` ({source}): install FFmpeg (Debian/Ubuntu: `apt-get install ffmpeg`; scripts/setup-native.sh does) or point PIR2_FFMPEG at the program")]
    FfmpegMissing {
        /// The program that was run.
        program: PathBuf,
        /// Why it could not be started.
        source: std::io::Error,
    },
    /// A video file could not be decoded.
    #[error("video {path}: {reason}")]
    Video {
        /// The video file.
        path: PathBuf,
        /// What went wrong (the decoder's last messages included).
        reason: String,
    },
    /// A camera frame stored as an image (an image feature in the data files) cannot be
    /// read: no row, no bytes, bytes that do not decode, or an image that is not 8-bit grey,
    /// RGB or RGBA.
    #[error("{path}: camera `{key}`, episode {episode}, frame {frame}: {reason}")]
    ImageFrame {
        /// The data file.
        path: PathBuf,
        /// The image feature.
        key: String,
        /// `episode_index`.
        episode: i64,
        /// `frame_index` within the episode.
        frame: usize,
        /// What is wrong.
        reason: String,
    },
    /// A camera frame the dataset's timestamps ask for is not in its video (LeRobot's rule:
    /// the decoded frame nearest to `from_timestamp + timestamp` must lie within the
    /// tolerance).
    #[error("video {path}: no frame for episode {episode}, frame {frame} at {timestamp:.6} s (the nearest decoded frame is {nearest}; tolerance {tolerance} s)")]
    VideoFrame {
        /// The video file.
        path: PathBuf,
        /// `episode_index`.
        episode: i64,
        /// `frame_index` within the episode.
        frame: usize,
        /// The timestamp asked for, in the video file's time.
        timestamp: f64,
        /// The nearest decoded frame (its time and distance), or that none was decoded.
        nearest: String,
        /// The tolerance, s.
        tolerance: f64,
    },

    /// Episodes handed to the writer do not fit the dataset's features.
    #[error("episode {episode} does not fit the dataset: {reason}")]
    EpisodeShape {
        /// Index of the episode in the dataset.
        episode: usize,
        /// What does not match.
        reason: String,
    },

    // ---- the Leap-cube scene and environment (`leap`, feature `mujoco`) ---------------
    // -- scene files --
    /// `PIR2_LEAP_CUBE_DIR` is unset and no explicit path was given.
    #[cfg(feature = "mujoco")]
    #[error(
        "the Leap-cube scene directory is unknown: set PIR2_LEAP_CUBE_DIR (run \
         `scripts/setup-native.sh` and `source .native/env.sh`) or pass a path"
    )]
    SceneDirUnset,
    /// A scene file (or the directory) does not exist or cannot be read.
    #[cfg(feature = "mujoco")]
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
    #[cfg(feature = "mujoco")]
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
    #[cfg(feature = "mujoco")]
    #[error("MuJoCo could not load {path}: {message}")]
    SceneLoad {
        /// The top-level scene file.
        path: PathBuf,
        /// MuJoCo's message.
        message: String,
    },
    /// The loaded model lacks an element the task needs (wrong scene file).
    #[cfg(feature = "mujoco")]
    #[error("the scene has no {kind} named `{name}` (is this the LeapCubeReorient scene?)")]
    MissingElement {
        /// Element kind (body, site, sensor, joint).
        kind: &'static str,
        /// Element name.
        name: String,
    },
    // -- use --
    /// A buffer had the wrong length.
    #[cfg(feature = "mujoco")]
    #[error("{what}: expected length {expected}, got {got}")]
    LeapShape {
        /// Which buffer.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Actual length.
        got: usize,
    },
    /// A configuration value of the Leap-cube environment or its MPC expert is out of range
    /// (or a saved state does not fit the model).
    #[cfg(feature = "mujoco")]
    #[error("invalid configuration: {0}")]
    LeapInvalid(String),

    // ---- the PPO trainer and expert (`leap::ppo`, feature `mujoco`) -------------------
    /// A configuration value is out of range.
    #[cfg(feature = "mujoco")]
    #[error("invalid PPO configuration: {0}")]
    PpoInvalid(String),
    /// Reading or writing a file failed.
    #[cfg(feature = "mujoco")]
    #[error("{action} {path}: {source}")]
    PpoIo {
        /// What was being done ("cannot write", ...).
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A weights or checkpoint file is malformed or does not match the configuration.
    #[cfg(feature = "mujoco")]
    #[error("{path}: {message}")]
    PpoFormat {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// Training produced a non-finite loss, gradient or parameter (fail closed: the
    /// checkpoint on disk is the last good state).
    #[cfg(feature = "mujoco")]
    #[error("training diverged at iteration {iteration}: {what} is not finite")]
    PpoDiverged {
        /// The PPO iteration.
        iteration: u64,
        /// Which quantity.
        what: &'static str,
    },
}

impl Error {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            source,
        }
    }
    pub(crate) fn parquet(path: impl Into<PathBuf>, source: parquet::errors::ParquetError) -> Self {
        Self::Parquet {
            path: path.into(),
            source,
        }
    }
    pub(crate) fn json(path: impl Into<PathBuf>, source: serde_json::Error) -> Self {
        Self::Json {
            path: path.into(),
            source,
        }
    }
}
