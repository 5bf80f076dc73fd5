//! Checkpoint directories whose velocity model is an ONNX graph: `model.onnx` (pir2's ONNX
//! contract, see `pir2_backends::ort`) next to `stats.json` and `identity.json`, in place of
//! a candle checkpoint's `config.json` + `model.safetensors`. Written by a trainer outside
//! pir2 (e.g. `examples/lerobot-flow/train.py`), run by `pir2 eval ballplate --checkpoint DIR`
//! through ONNX Runtime (feature `ort`).
//!
//! ```text
//! DIR/model.onnx     inputs x [B,H,A], tau [B,H], obs_fast [B,n_obs,F] (raw; the graph
//!                    normalises), obs_slow, d_vis; output v [B,H,A] (normalised action space)
//! DIR/stats.json     the normalisation statistics (`pir2_backends::config::Stats`); the
//!                    runtime denormalises the actions with `action`
//! DIR/identity.json  the policy the graph was trained as and the SHA-256 of model.onnx
//! ```
//!
//! The graph's sizes must be those of the task's spec; `identity.json` is required and its
//! hash must be that of `model.onnx` (a graph replaced after the identity was written is
//! refused).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use pir2_backends::checkpoint::{Identity, IDENTITY_FILE, STATS_FILE, WEIGHTS_FILE};
use pir2_backends::config::{Spec, Stats};
use pir2_runtime::Policy;

/// File name of the ONNX graph in an ONNX checkpoint.
pub const ONNX_FILE: &str = "model.onnx";

/// What a checkpoint directory holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CheckpointKind {
    /// `model.safetensors`: a candle checkpoint.
    Candle,
    /// `model.onnx`: an ONNX checkpoint ([`OnnxCheckpoint`]).
    Onnx,
}

/// Which kind of checkpoint `dir` is; a directory with neither or both weight files is
/// refused by name.
pub fn kind(dir: &Path) -> Result<CheckpointKind> {
    if !dir.is_dir() {
        bail!("checkpoint {} is not a directory", dir.display());
    }
    let (candle, onnx) = (dir.join(WEIGHTS_FILE), dir.join(ONNX_FILE));
    match (candle.is_file(), onnx.is_file()) {
        (true, false) => Ok(CheckpointKind::Candle),
        (false, true) => Ok(CheckpointKind::Onnx),
        (true, true) => bail!(
            "checkpoint {} holds both {WEIGHTS_FILE} (a candle checkpoint) and {ONNX_FILE} (an \
             ONNX checkpoint); keep one of them",
            dir.display()
        ),
        (false, false) => bail!(
            "checkpoint {} holds neither {WEIGHTS_FILE} (a candle checkpoint) nor {ONNX_FILE} \
             (an ONNX checkpoint with {STATS_FILE} and {IDENTITY_FILE})",
            dir.display()
        ),
    }
}

/// An ONNX checkpoint's files, read and checked (the graph itself is loaded by
/// [`OnnxCheckpoint::models`]).
#[derive(Debug, Clone)]
pub struct OnnxCheckpoint {
    /// The directory.
    pub dir: PathBuf,
    /// `model.onnx`.
    pub onnx: PathBuf,
    /// `stats.json`, checked against the spec.
    pub stats: Stats,
    /// `identity.json`, its hash checked against `model.onnx`.
    pub identity: Identity,
}

impl OnnxCheckpoint {
    /// Read `dir`'s `stats.json` and `identity.json` and check them against `spec` and the
    /// bytes of `model.onnx`.
    pub fn read(dir: &Path, spec: &Spec) -> Result<Self> {
        let onnx = dir.join(ONNX_FILE);
        let stats_path = dir.join(STATS_FILE);
        let text = std::fs::read_to_string(&stats_path)
            .with_context(|| format!("reading {}", stats_path.display()))?;
        let stats: Stats = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", stats_path.display()))?;
        stats
            .validate(spec)
            .with_context(|| format!("{} does not fit the task", stats_path.display()))?;
        let id_path = dir.join(IDENTITY_FILE);
        let text = std::fs::read_to_string(&id_path).with_context(|| {
            format!(
                "reading {} (an ONNX checkpoint must record the policy it was trained as and \
                 the SHA-256 of {ONNX_FILE})",
                id_path.display()
            )
        })?;
        let identity: Identity = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", id_path.display()))?;
        let bytes = std::fs::read(&onnx).with_context(|| format!("reading {}", onnx.display()))?;
        let sha = pir2_backends::checkpoint::weights_sha256(&bytes);
        if sha != identity.weights_sha256 {
            bail!(
                "{} has SHA-256 {sha}, but {} records {}: the graph was replaced after its \
                 identity was written",
                onnx.display(),
                id_path.display(),
                identity.weights_sha256
            );
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            onnx,
            stats,
            identity,
        })
    }

    /// The policy the graph was trained as (`None`: unrecorded).
    pub fn policy(&self) -> Option<Policy> {
        self.identity.policy
    }

    /// The action head's models: one ONNX Runtime session per evaluation thread, their
    /// actions denormalised with `stats.json`. The graph is loaded once here and checked
    /// against `spec` (horizon, action width, history, fast width, slow input).
    #[cfg(feature = "ort")]
    pub fn models(&self, spec: &Spec) -> Result<crate::study::pipeline::Models<'static>> {
        use pir2_backends::ort::OrtModel;
        use pir2_runtime::{OutputMap, VelocityModel};

        let first = OrtModel::load(&self.onnx)
            .with_context(|| format!("loading {}", self.onnx.display()))?;
        let d = *first.dims();
        let found = (d.horizon, d.action_dim, d.n_obs, d.fast_dim, d.slow);
        let want = (
            spec.horizon,
            spec.action_dim,
            spec.n_obs,
            spec.fast_dim,
            spec.slow,
        );
        if found != want {
            bail!(
                "{}: the graph's (horizon, action_dim, n_obs, fast_dim, slow) = {found:?}, the \
                 task's = {want:?}",
                self.onnx.display()
            );
        }
        if spec.d_vis_max > 0 && !d.has_d_vis {
            eprintln!(
                "note: {} declares no d_vis input: the slow features' age is not fed to it",
                self.onnx.display()
            );
        }
        let n = &self.stats.action;
        let output = OutputMap {
            scale: n.std.clone(),
            offset: n.mean.clone(),
            clip: Vec::new(),
            reference: Vec::new(),
            poses: Vec::new(),
        };
        let path = self.onnx.clone();
        let first = std::sync::Mutex::new(Some(first));
        Ok(crate::study::pipeline::Models::new(output, move || {
            let reuse = first.lock().unwrap_or_else(|p| p.into_inner()).take();
            let model = match reuse {
                Some(m) => m,
                // The same file loaded and checked above; a failure now is a changed file.
                None => OrtModel::load(&path)
                    .unwrap_or_else(|e| panic!("reloading {} failed: {e}", path.display())),
            };
            Box::new(model) as Box<dyn VelocityModel>
        }))
    }

    /// Without the `ort` feature an ONNX checkpoint cannot run: an error saying so.
    #[cfg(not(feature = "ort"))]
    pub fn models(&self, _spec: &Spec) -> Result<crate::study::pipeline::Models<'static>> {
        bail!(
            "checkpoint {} is an ONNX checkpoint ({ONNX_FILE}): running it needs a pir2 built \
             with `--features ort` (ONNX Runtime 1.31, ORT_DYLIB_PATH; see \
             scripts/setup-native.sh)",
            self.dir.display()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_directory_with_neither_or_both_weight_files_is_refused_by_name() {
        let dir = std::env::temp_dir().join(format!("pir2-onnx-kind-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let err = format!("{:#}", kind(&dir).unwrap_err());
        assert!(err.contains("neither") && err.contains(ONNX_FILE), "{err}");
        std::fs::write(dir.join(ONNX_FILE), b"x").unwrap();
        assert_eq!(kind(&dir).unwrap(), CheckpointKind::Onnx);
        std::fs::write(dir.join(WEIGHTS_FILE), b"x").unwrap();
        let err = format!("{:#}", kind(&dir).unwrap_err());
        assert!(err.contains("both"), "{err}");
        std::fs::remove_file(dir.join(ONNX_FILE)).unwrap();
        assert_eq!(kind(&dir).unwrap(), CheckpointKind::Candle);
        std::fs::remove_dir_all(&dir).unwrap();
        let err = format!("{:#}", kind(&dir).unwrap_err());
        assert!(err.contains("not a directory"), "{err}");
    }
}
