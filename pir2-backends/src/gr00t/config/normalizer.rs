//! GR00T's per-group normalisation of the state and the action (maps in the parent module's
//! docs), read from the checkpoint's `statistics.json`.

use std::collections::BTreeMap;
use std::path::Path;

use super::super::error::{Gr00tError, Result};
use super::{EmbodimentConfig, Group, Norm};

/// Per-dimension affine normalisation of the state and the action (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Normalizer {
    /// `norm(x) = (x − state_offset) · state_inv_scale`, per state dimension.
    state_offset: Vec<f32>,
    state_inv_scale: Vec<f32>,
    /// Clip the normalised state to `[-1, 1]` (min/max and percentile groups).
    state_clip: Vec<bool>,
    /// `raw = scale · x + offset`, per action dimension.
    action_scale: Vec<f32>,
    action_offset: Vec<f32>,
}

type StatsFile = BTreeMap<String, BTreeMap<String, BTreeMap<String, BTreeMap<String, Vec<f64>>>>>;

impl Normalizer {
    /// The identity (no statistics).
    pub fn identity(state_dim: usize, action_dim: usize) -> Self {
        Normalizer {
            state_offset: vec![0.0; state_dim],
            state_inv_scale: vec![1.0; state_dim],
            state_clip: vec![false; state_dim],
            action_scale: vec![1.0; action_dim],
            action_offset: vec![0.0; action_dim],
        }
    }

    /// Load GR00T's `statistics.json` for `cfg` (every group and statistic its norm needs
    /// must be present with the group's width; the error names the missing key).
    pub fn load(path: &Path, cfg: &EmbodimentConfig) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Gr00tError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let stats: StatsFile = serde_json::from_str(&text).map_err(|e| Gr00tError::Parse {
            path: path.to_path_buf(),
            message: format!(
                "expected {{embodiment: {{modality: {{group: {{stat: [numbers]}}}}}}}}: {e}"
            ),
        })?;
        Self::from_stats(&stats, path, cfg)
    }

    fn from_stats(stats: &StatsFile, path: &Path, cfg: &EmbodimentConfig) -> Result<Self> {
        let err =
            |modality: &str, group: &str, stat: &str, problem: String| Gr00tError::Statistics {
                path: path.to_path_buf(),
                key: format!("{}.{modality}.{group}.{stat}", cfg.embodiment_tag),
                problem,
            };
        let emb = stats.get(&cfg.embodiment_tag).ok_or_else(|| {
            err(
                "*",
                "*",
                "*",
                format!(
                    "is missing: no embodiment `{}` (found {:?})",
                    cfg.embodiment_tag,
                    stats.keys().collect::<Vec<_>>()
                ),
            )
        })?;
        // (offset, scale) per dim: norm = (x − offset)/scale; raw = scale·norm + offset.
        let affine = |modality: &str,
                      groups: &[Group]|
         -> Result<(Vec<f32>, Vec<f32>, Vec<bool>)> {
            let (mut off, mut scale, mut clip) = (Vec::new(), Vec::new(), Vec::new());
            for g in groups {
                let get = |stat: &str| -> Result<Vec<f64>> {
                    let v = emb
                        .get(modality)
                        .and_then(|m| m.get(&g.name))
                        .and_then(|s| s.get(stat))
                        .ok_or_else(|| err(modality, &g.name, stat, "is missing".to_string()))?;
                    if v.len() != g.dim {
                        return Err(err(
                            modality,
                            &g.name,
                            stat,
                            format!("has {} values, the group has dim {}", v.len(), g.dim),
                        ));
                    }
                    if v.iter().any(|x| !x.is_finite()) {
                        return Err(err(modality, &g.name, stat, "is not finite".to_string()));
                    }
                    Ok(v.clone())
                };
                match g.norm {
                    Norm::MinMax | Norm::Q01Q99 => {
                        let (lo, hi) = if g.norm == Norm::MinMax {
                            ("min", "max")
                        } else {
                            ("q01", "q99")
                        };
                        let (lo, hi) = (get(lo)?, get(hi)?);
                        for (l, h) in lo.iter().zip(&hi) {
                            let range = (h - l).max(1e-8);
                            off.push((l + range / 2.0) as f32);
                            scale.push((range / 2.0) as f32);
                            clip.push(true);
                        }
                    }
                    Norm::MeanStd => {
                        let (mean, std) = (get("mean")?, get("std")?);
                        for (m, s) in mean.iter().zip(&std) {
                            off.push(*m as f32);
                            scale.push(s.max(1e-8) as f32);
                            clip.push(false);
                        }
                    }
                    Norm::None => {
                        for _ in 0..g.dim {
                            off.push(0.0);
                            scale.push(1.0);
                            clip.push(false);
                        }
                    }
                }
            }
            Ok((off, scale, clip))
        };
        let (so, ss, sc) = affine("state", &cfg.state)?;
        let (ao, ascale, _) = affine("action", &cfg.action)?;
        Ok(Normalizer {
            state_offset: so,
            state_inv_scale: ss.iter().map(|s| 1.0 / s).collect(),
            state_clip: sc,
            action_scale: ascale,
            action_offset: ao,
        })
    }

    /// State width.
    pub fn state_dim(&self) -> usize {
        self.state_offset.len()
    }

    /// Normalise one raw state vector into `out` (same length).
    pub fn normalize_state(&self, raw: &[f32], out: &mut [f32]) {
        for i in 0..raw.len().min(out.len()).min(self.state_offset.len()) {
            let v = (raw[i] - self.state_offset[i]) * self.state_inv_scale[i];
            out[i] = if self.state_clip[i] {
                v.clamp(-1.0, 1.0)
            } else {
                v
            };
        }
    }

    /// Denormalise one action vector in place.
    pub fn denormalize_action(&self, a: &mut [f32]) {
        for (i, x) in a.iter_mut().enumerate() {
            *x = self.action_scale[i] * *x + self.action_offset[i];
        }
    }

    /// The runtime's output map that turns model actions into absolute joint targets.
    pub fn action_output_map(&self) -> pir2_runtime::OutputMap {
        pir2_runtime::OutputMap {
            scale: self.action_scale.clone(),
            offset: self.action_offset.clone(),
        }
    }
}
