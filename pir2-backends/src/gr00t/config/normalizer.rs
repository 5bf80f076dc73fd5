//! GR00T's per-group normalisation of the state and the action (maps in the parent module's
//! docs), read from the checkpoint's `statistics.json`.

use std::collections::BTreeMap;
use std::path::Path;

use super::super::error::{Gr00tError, Result};
use super::{EmbodimentConfig, Group, Norm};

/// GR00T's per-group normalisation of the state and the action (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Normalizer {
    /// `norm(x) = (x − state_offset) · state_inv_scale`, per raw state dimension (a
    /// degenerate min/max dimension has `inv_scale = 0`: it maps to 0; a zero-std one has
    /// offset 0 and `inv_scale = 1`).
    state_offset: Vec<f32>,
    state_inv_scale: Vec<f32>,
    /// Clip the normalised state to `[-1, 1]` (min/max and percentile groups).
    state_clip: Vec<bool>,
    /// The state groups in order: `(first raw dimension, width, sin/cos encoded)`.
    state_groups: Vec<(usize, usize, bool)>,
    /// `raw = scale · clip(x) + offset`, per action dimension.
    action_scale: Vec<f32>,
    action_offset: Vec<f32>,
    /// Clip the model's action to `[-1, 1]` before denormalising (min/max and percentile).
    action_clip: Vec<bool>,
    /// A degenerate min/max (or percentile) action dimension: normalises to 0.
    action_zero: Vec<bool>,
}

/// The groups' affine maps, per dimension: `(offset, scale, clip, to_zero)` with
/// `norm = (x − offset)/scale` and `raw = scale·norm + offset`; `to_zero` marks a degenerate
/// min/max dimension, which normalises to 0.
type Affine = (Vec<f32>, Vec<f32>, Vec<bool>, Vec<bool>);

type StatsFile = BTreeMap<String, BTreeMap<String, BTreeMap<String, BTreeMap<String, Vec<f64>>>>>;

impl Normalizer {
    /// The identity (no statistics).
    pub fn identity(state_dim: usize, action_dim: usize) -> Self {
        Normalizer {
            state_offset: vec![0.0; state_dim],
            state_inv_scale: vec![1.0; state_dim],
            state_clip: vec![false; state_dim],
            state_groups: vec![(0, state_dim, false)],
            action_scale: vec![1.0; action_dim],
            action_offset: vec![0.0; action_dim],
            action_clip: vec![false; action_dim],
            action_zero: vec![false; action_dim],
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
        let affine = |modality: &str, groups: &[Group]| -> Result<Affine> {
            let (mut off, mut scale, mut clip, mut zero) =
                (Vec::new(), Vec::new(), Vec::new(), Vec::new());
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
                            // numpy's isclose(max, min): such a dimension normalises to 0.
                            zero.push((h - l).abs() <= 1e-8 + 1e-5 * l.abs());
                            off.push(((l + h) / 2.0) as f32);
                            scale.push(((h - l) / 2.0) as f32);
                            clip.push(true);
                        }
                    }
                    Norm::MeanStd => {
                        let (mean, std) = (get("mean")?, get("std")?);
                        for (m, sd) in mean.iter().zip(&std) {
                            // GR00T passes a zero-std dimension through unchanged.
                            let (o, sc) = if *sd == 0.0 { (0.0, 1.0) } else { (*m, *sd) };
                            off.push(o as f32);
                            scale.push(sc as f32);
                            clip.push(false);
                            zero.push(false);
                        }
                    }
                    Norm::None | Norm::SinCos => {
                        for _ in 0..g.dim {
                            off.push(0.0);
                            scale.push(1.0);
                            clip.push(false);
                            zero.push(false);
                        }
                    }
                }
            }
            Ok((off, scale, clip, zero))
        };
        let (so, ss, sc, sz) = affine("state", &cfg.state)?;
        let (ao, ascale, aclip, azero) = affine("action", &cfg.action)?;
        let mut state_groups = Vec::with_capacity(cfg.state.len());
        let mut first = 0;
        for g in &cfg.state {
            state_groups.push((first, g.dim, g.norm == Norm::SinCos));
            first += g.dim;
        }
        Ok(Normalizer {
            state_offset: so,
            state_inv_scale: ss
                .iter()
                .zip(&sz)
                .map(|(&s, &zero)| if zero { 0.0 } else { 1.0 / s })
                .collect(),
            state_clip: sc,
            state_groups,
            action_scale: ascale,
            action_offset: ao,
            action_clip: aclip,
            action_zero: azero,
        })
    }

    /// Raw state width (what the robot reports).
    pub fn state_dim(&self) -> usize {
        self.state_offset.len()
    }

    /// State width as the model sees it (sin/cos groups count twice).
    pub fn encoded_state_dim(&self) -> usize {
        self.state_groups
            .iter()
            .map(|&(_, w, sc)| if sc { 2 * w } else { w })
            .sum()
    }

    /// Normalise one raw state vector (`state_dim` values) into `out`
    /// (`encoded_state_dim` values), group by group.
    pub fn normalize_state(&self, raw: &[f32], out: &mut [f32]) {
        debug_assert!(raw.len() >= self.state_dim() && out.len() >= self.encoded_state_dim());
        let mut o = 0;
        for &(first, width, sin_cos) in &self.state_groups {
            let x = &raw[first..first + width];
            if sin_cos {
                for (k, v) in x.iter().enumerate() {
                    out[o + k] = v.sin();
                    out[o + width + k] = v.cos();
                }
                o += 2 * width;
                continue;
            }
            for (k, v) in x.iter().enumerate() {
                let i = first + k;
                let n = (v - self.state_offset[i]) * self.state_inv_scale[i];
                out[o + k] = if self.state_clip[i] {
                    n.clamp(-1.0, 1.0)
                } else {
                    n
                };
            }
            o += width;
        }
    }

    /// Normalise one raw action vector in place, as GR00T's processor does for training
    /// targets: `(x − offset)/scale`, clipped to `[-1, 1]` for the min/max and percentile
    /// groups; a degenerate min/max dimension maps to 0. [`Self::denormalize_action`] inverts
    /// it inside the clip range.
    pub fn normalize_action(&self, a: &mut [f32]) {
        for (i, x) in a.iter_mut().enumerate() {
            if self.action_zero[i] {
                *x = 0.0;
                continue;
            }
            let n = (*x - self.action_offset[i]) / self.action_scale[i];
            *x = if self.action_clip[i] {
                n.clamp(-1.0, 1.0)
            } else {
                n
            };
        }
    }

    /// Denormalise one action vector in place (what the runtime's output map does).
    pub fn denormalize_action(&self, a: &mut [f32]) {
        for (i, x) in a.iter_mut().enumerate() {
            let v = if self.action_clip[i] {
                x.clamp(-1.0, 1.0)
            } else {
                *x
            };
            *x = self.action_scale[i] * v + self.action_offset[i];
        }
    }

    /// The runtime's output map that turns model actions into absolute joint targets.
    pub fn action_output_map(&self) -> pir2_runtime::OutputMap {
        pir2_runtime::OutputMap {
            scale: self.action_scale.clone(),
            offset: self.action_offset.clone(),
            clip: self.action_clip.clone(),
        }
    }
}
